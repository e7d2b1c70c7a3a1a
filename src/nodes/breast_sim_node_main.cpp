// The breast_sim navigation node (see include/breast_sim/ros_interface/breast_sim_node.h).
#include <ros/ros.h>

#include "breast_sim/ros_interface/breast_sim_node.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "breast_sim");
  try {
    breast_sim::ros_interface::BreastSimNode node(ros::NodeHandle(), ros::NodeHandle("~"));
    node.initialize();
    ros::AsyncSpinner spinner(4);  // services, clouds, poses and the action answer while jobs run
    spinner.start();
    ros::waitForShutdown();
  } catch (const std::exception& e) {
    ROS_FATAL_STREAM("breast_sim: " << e.what());
    return 2;
  }
  return 0;
}
