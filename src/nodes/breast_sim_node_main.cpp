// The breast_sim navigation node (see include/breast_sim/ros_interface/breast_sim_node.h).
#include <ros/ros.h>

#include "breast_sim/ros_interface/breast_sim_node.h"
#include "breast_sim/ros_interface/logger_services.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "breast_sim");
  try {
    const ros::NodeHandle nh, pnh("~");
    // roscpp's ~get_loggers deletes log4cxx's loggers (logger_services.h): replaced before anything slow.
    const breast_sim::ros_interface::LoggerServices logger_services(pnh);
    breast_sim::ros_interface::BreastSimNode node(nh, pnh);
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
