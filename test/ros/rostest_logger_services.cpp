// Integration test of the node's logger services (test/ros/logger_services.test), the calls
// rqt_logger_level makes: ~get_loggers answers every time (rosconsole's own answer deletes log4cxx's
// loggers, see include/breast_sim/ros_interface/logger_services.h) with the node's loggers and their
// levels, ~set_logger_level changes a level twice, and the node stays up and keeps logging to /rosout.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <ros/ros.h>
#include <rosgraph_msgs/Log.h>
#include <roscpp/GetLoggers.h>
#include <roscpp/SetLoggerLevel.h>

#include <breast_sim/LoadCase.h>
#include <breast_sim/NodeState.h>

#include "wait_until.h"

namespace {

using Clock = std::chrono::steady_clock;
constexpr const char* kNode = "/breast_sim";
constexpr const char* kPackageLogger = "ros.breast_sim";  // ROS_* macros of the package log here

std::mutex m;
breast_sim::NodeState::ConstPtr state;
std::vector<rosgraph_msgs::Log> node_log;  // the node's messages on /rosout

void onState(const breast_sim::NodeState::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(m);
  state = msg;
}

void onRosout(const rosgraph_msgs::Log::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(m);
  if (msg->name == kNode) node_log.push_back(*msg);
}

template <class F>
bool waitUntil(F&& condition, double timeout_s) {
  return breast_sim::test_fixtures::waitUntil(m, std::forward<F>(condition), timeout_s);
}

std::string service(const char* name) { return std::string(kNode) + "/" + name; }

/// The node's loggers (name -> level), or a failure if the call did not go through.
::testing::AssertionResult getLoggers(std::vector<roscpp::Logger>* loggers) {
  roscpp::GetLoggers srv;
  if (!ros::service::call(service("get_loggers"), srv))
    return ::testing::AssertionFailure() << service("get_loggers") << " did not answer";
  *loggers = srv.response.loggers;
  return ::testing::AssertionSuccess();
}

std::string levelOf(const std::vector<roscpp::Logger>& loggers, const std::string& name) {
  for (const auto& l : loggers)
    if (l.name == name) return l.level;
  return "";
}

bool nodeIsRegistered() {
  std::vector<std::string> nodes;
  return ros::master::getNodes(nodes) && std::find(nodes.begin(), nodes.end(), kNode) != nodes.end();
}

}  // namespace

TEST(LoggerServices, NodeStartsWithItsLoggerServices) {
  for (const char* s : {"get_loggers", "set_logger_level", "load_case"})
    ASSERT_TRUE(ros::service::waitForService(service(s), ros::Duration(30.0))) << s;
  ASSERT_TRUE(waitUntil([] { return state && state->model_loaded; }, 40.0)) << "the node loaded no model";
}

TEST(LoggerServices, GetLoggersAnswersEveryTimeWithTheSameLoggers) {
  // The package's logger exists from the node's first ROS_* message (at the latest, the one that
  // reports the loaded case, right after the state says so).
  std::vector<roscpp::Logger> first;
  const auto t0 = Clock::now();
  do {
    ASSERT_TRUE(getLoggers(&first));
  } while (levelOf(first, kPackageLogger).empty() && std::chrono::duration<double>(Clock::now() - t0).count() < 10.0);
  for (const char* name : {"ros", "ros.roscpp", kPackageLogger})
    EXPECT_FALSE(levelOf(first, name).empty()) << name << " is not listed";
  EXPECT_TRUE(std::is_sorted(first.begin(), first.end(), [](const auto& a, const auto& b) { return a.name < b.name; }));
  for (const auto& l : first)
    EXPECT_TRUE(l.level == "debug" || l.level == "info" || l.level == "warn" || l.level == "error" ||
                l.level == "fatal") << l.name << ": " << l.level;
  EXPECT_EQ(levelOf(first, kPackageLogger), "info");
  for (int call = 2; call <= 5; ++call) {
    std::vector<roscpp::Logger> again;
    ASSERT_TRUE(getLoggers(&again)) << "call " << call;
    for (const auto& l : first) EXPECT_EQ(levelOf(again, l.name), l.level) << l.name << ", call " << call;
  }
  EXPECT_TRUE(nodeIsRegistered());
}

TEST(LoggerServices, SetLoggerLevelTwiceIsSeenByGetLoggers) {
  for (const char* level : {"debug", "info"}) {
    roscpp::SetLoggerLevel set;
    set.request.logger = kPackageLogger;
    set.request.level = level;
    ASSERT_TRUE(ros::service::call(service("set_logger_level"), set)) << level;
    std::vector<roscpp::Logger> loggers;
    ASSERT_TRUE(getLoggers(&loggers)) << "after setting " << level;
    EXPECT_EQ(levelOf(loggers, kPackageLogger), level);
  }
}

TEST(LoggerServices, NodeStillAnswersAndLogsAfterwards) {
  // A refused case is answered and warned about on /rosout (logging goes through the loggers that
  // ~get_loggers listed).
  ros::NodeHandle pnh("~");
  breast_sim::LoadCase load;
  ASSERT_TRUE(pnh.getParam("bad_case_file", load.request.case_file));
  ASSERT_TRUE(ros::service::call(service("load_case"), load));
  EXPECT_FALSE(load.response.success);
  EXPECT_TRUE(waitUntil([] {
    return std::any_of(node_log.begin(), node_log.end(), [](const rosgraph_msgs::Log& msg) {
      return msg.level == rosgraph_msgs::Log::WARN && msg.msg.find("keeping the previous model") != std::string::npos;
    });
  }, 10.0)) << "the node's warning did not reach /rosout";
  std::vector<roscpp::Logger> loggers;
  EXPECT_TRUE(getLoggers(&loggers));
  EXPECT_TRUE(nodeIsRegistered());
  std::lock_guard<std::mutex> l(m);
  ASSERT_TRUE(state);
  EXPECT_TRUE(state->model_loaded);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "logger_services_test");
  ros::NodeHandle nh;
  ros::Subscriber s1 = nh.subscribe("/breast_sim/state", 10, onState);
  ros::Subscriber s2 = nh.subscribe("/rosout", 100, onRosout);
  ros::AsyncSpinner spinner(1);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
