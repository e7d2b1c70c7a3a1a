// The breast_sim navigation node (see include/breast_sim/ros_interface/breast_sim_node.h).
#include <cstdlib>

#include <ros/ros.h>

#include "breast_sim/ros_interface/breast_sim_node.h"
#include "breast_sim/ros_interface/logger_services.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "breast_sim");
  // libgomp reads its wait policy before main(); all the node can do is say so (docs/benchmarks.md, "Threads").
  if (!std::getenv("OMP_WAIT_POLICY") && !std::getenv("GOMP_SPINCOUNT"))
    ROS_WARN("breast_sim: OMP_WAIT_POLICY is not set, so OpenMP threads spin while they wait; a simulation step "
             "then gets 10-100x slower whenever another process holds a core. Start the node with "
             "OMP_WAIT_POLICY=passive (launch/breast_sim.launch sets it).");
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
