#pragma once
// Test fixture of the rostests on simulated time (navigation, scene): until a bag's player takes the
// clock over (rosbag play --clock), the client drives /clock itself, from 1 s at a tenth of wall speed
// (below the bags' start), because ROS timers (the action server's status, the node's) need a
// running clock.
#include <atomic>
#include <chrono>
#include <thread>

#include <ros/ros.h>
#include <rosgraph_msgs/Clock.h>

namespace breast_sim::test_fixtures {

class SimulatedClock {
 public:
  explicit SimulatedClock(ros::NodeHandle& nh) : pub_(nh.advertise<rosgraph_msgs::Clock>("/clock", 10)) {
    thread_ = std::thread([this] {
      const auto t0 = std::chrono::steady_clock::now();
      while (ros::ok() && run_) {
        rosgraph_msgs::Clock c;
        c.clock = ros::Time(1.0 + 0.1 * std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
        pub_.publish(c);
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      }
    });
  }
  ~SimulatedClock() { stop(); }
  /// Stops driving the clock (a player takes over); waits for the driver to end.
  void stop() {
    run_ = false;
    if (thread_.joinable() && thread_.get_id() != std::this_thread::get_id()) thread_.join();
  }

 private:
  ros::Publisher pub_;
  std::atomic<bool> run_{true};
  std::thread thread_;
};

}  // namespace breast_sim::test_fixtures
