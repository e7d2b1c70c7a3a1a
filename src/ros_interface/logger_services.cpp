#include "breast_sim/ros_interface/logger_services.h"

#include <algorithm>
#include <stdexcept>
#include <string>

#include <log4cxx/level.h>
#include <log4cxx/logger.h>
#include <log4cxx/logmanager.h>
#include <ros/names.h>
#include <ros/service_manager.h>
#include <roscpp/GetLoggers.h>

namespace breast_sim::ros_interface {
namespace {

/// roscpp's level names, for a log4cxx level (thresholds, so that trace, all and off have one too).
const char* levelName(int log4cxx_level) {
  if (log4cxx_level >= log4cxx::Level::FATAL_INT) return "fatal";
  if (log4cxx_level >= log4cxx::Level::ERROR_INT) return "error";
  if (log4cxx_level >= log4cxx::Level::WARN_INT) return "warn";
  if (log4cxx_level >= log4cxx::Level::INFO_INT) return "info";
  return "debug";
}

bool answerGetLoggers(roscpp::GetLoggers::Request&, roscpp::GetLoggers::Response& res) {
  // LogManager::getCurrentLoggers() shares the hierarchy with LogManager, which keeps owning it
  // (rosconsole's get_loggers deletes it: see logger_services.h).
  for (const log4cxx::LoggerPtr& logger : log4cxx::LogManager::getCurrentLoggers()) {
    roscpp::Logger entry;
    logger->getName(entry.name);
    entry.level = levelName(logger->getEffectiveLevel()->toInt());
    res.loggers.push_back(std::move(entry));
  }
  std::sort(res.loggers.begin(), res.loggers.end(),
            [](const roscpp::Logger& a, const roscpp::Logger& b) { return a.name < b.name; });
  return true;
}

}  // namespace

LoggerServices::LoggerServices(const ros::NodeHandle& nh) : spinner_(1, &queue_) {
  // The name roscpp advertised (ros::start(), ros/init.cpp), remappings applied the same way.
  const std::string name = ros::names::resolve("~get_loggers");
  ros::ServiceManager::instance()->unadvertiseService(name);  // false only if roscpp had none
  ros::AdvertiseServiceOptions ops;
  ops.init<roscpp::GetLoggers::Request, roscpp::GetLoggers::Response>(name, &answerGetLoggers);
  ops.callback_queue = &queue_;
  get_loggers_ = ros::NodeHandle(nh).advertiseService(ops);
  if (!get_loggers_)
    throw std::runtime_error("cannot advertise " + name + " (is it advertised already in this process?)");
  spinner_.start();
}

}  // namespace breast_sim::ros_interface
