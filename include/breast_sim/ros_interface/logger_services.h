#pragma once
/// @file logger_services.h
/// The node's `~get_loggers` service (roscpp/GetLoggers, what rqt_logger_level and
/// `rosservice call <node>/get_loggers` use), served without rosconsole's log4cxx backend.
///
/// roscpp advertises `~get_loggers` and `~set_logger_level` for every node. Its `~get_loggers` calls
/// ros::console::get_loggers, and Debian's rosconsole (librosconsole3d 1.14.3 on log4cxx 1.0) takes
/// ownership there of log4cxx's logger hierarchy: log4cxx 1.0's Logger::getLoggerRepository() returns
/// a raw pointer to the hierarchy that LogManager owns, and rosconsole wraps it in a shared_ptr of its
/// own, which deletes the hierarchy when the call returns. After one call the process logs nothing more
/// and holds dangling loggers; the next call reads the freed hierarchy and the process dies (SIGSEGV
/// in log4cxx::LogManager::getLoggerLS). So nothing in this process may call ros::console::get_loggers.
/// `~set_logger_level` goes through Logger::getLogger and setLevel only, and is safe: it stays
/// roscpp's. rosout, a process of its own built on the same libraries, dies on its second
/// `get_loggers` (roscore respawns it); this node keeps running and logging meanwhile.

#include <ros/callback_queue.h>
#include <ros/node_handle.h>
#include <ros/service_server.h>
#include <ros/spinner.h>

namespace breast_sim::ros_interface {

/// The node's `~get_loggers` while it lives. Construction withdraws roscpp's `~get_loggers` and
/// advertises one with the same name, type and answer: every logger that log4cxx knows (the root
/// logger excepted, as in roscpp), sorted by name, each with its effective level as "debug", "info",
/// "warn", "error" or "fatal" (log4cxx's trace and all read as "debug", off as "fatal"). Its own
/// callback queue and thread serve it, as roscpp's internal queue serves roscpp's, so it answers
/// while the node is busy (loading a case, or every spinner thread in a callback).
/// Construct it as soon as the first NodeHandle exists (that starts the node and roscpp's
/// `~get_loggers` with it) and before anything slow, so that the faulty service is up for
/// milliseconds only. One per process.
class LoggerServices {
 public:
  /// @throws std::runtime_error if the service cannot be advertised (e.g. one is already up).
  explicit LoggerServices(const ros::NodeHandle& nh);
  LoggerServices(const LoggerServices&) = delete;
  LoggerServices& operator=(const LoggerServices&) = delete;

 private:
  ros::CallbackQueue queue_;
  ros::AsyncSpinner spinner_;
  ros::ServiceServer get_loggers_;  // declared last: withdrawn before its thread stops
};

}  // namespace breast_sim::ros_interface
