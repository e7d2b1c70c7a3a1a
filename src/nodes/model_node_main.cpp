#include <ros/ros.h>

#include "breast_sim/ros_interface/model_node.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "breast_sim");
  breast_sim::ros_interface::ModelNode node(ros::NodeHandle(), ros::NodeHandle("~"));
  node.initialize();
  ros::AsyncSpinner spinner(2);  // services keep answering while a model builds
  spinner.start();
  ros::waitForShutdown();
  return 0;
}
