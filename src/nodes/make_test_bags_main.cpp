// Writes the recorded tracker bag of the tests and the demo from the phantom, reproducibly:
//   make_test_bags [--case FILE] [--out BAG] [--seconds S] [--cloud-rate HZ] [--pose-rate HZ]
//                  [--points N] [--noise-mm MM] [--seed N] [--start S]
// Topics: /tf_static (world → tracker), /tracker/patient_pose (geometry_msgs/PoseStamped of the model
// frame in world), /tracker/surface_points (sensor_msgs/PointCloud2 in the tracker frame). See
// ros_interface/tracker_simulation.h for the motion and noise model.
#include <cstdlib>
#include <iostream>
#include <string>

#include <geometry_msgs/PoseStamped.h>
#include <boost/make_shared.hpp>
#include <rosbag/bag.h>
#include <ros/package.h>
#include <ros/time.h>
#include <tf2_msgs/TFMessage.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

using namespace breast_sim;

int main(int argc, char** argv) {
  ros::Time::init();
  std::string case_file, out = "tracking_phantom.bag", frame = "breast_model";
  double seconds = 10.0, cloud_rate = 10.0, pose_rate = 20.0, start = 100.0;
  ros_interface::TrackerSimulationOptions o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::cerr << a << " needs a value\n";
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--case") case_file = next();
    else if (a == "--out") out = next();
    else if (a == "--seconds") seconds = std::stod(next());
    else if (a == "--cloud-rate") cloud_rate = std::stod(next());
    else if (a == "--pose-rate") pose_rate = std::stod(next());
    else if (a == "--points") o.points = std::stoi(next());
    else if (a == "--noise-mm") o.noise_m = 1e-3 * std::stod(next());
    else if (a == "--seed") o.seed = static_cast<unsigned>(std::stoul(next()));
    else if (a == "--start") start = std::stod(next());
    else if (a == "--frame") frame = next();
    else {
      std::cerr << "usage: make_test_bags [--case FILE] [--out BAG] [--seconds S] [--cloud-rate HZ] [--pose-rate HZ]"
                   " [--points N] [--noise-mm MM] [--seed N] [--start S] [--frame MODEL_FRAME]\n";
      return a == "--help" ? 0 : 2;
    }
  }
  if (case_file.empty()) case_file = ros::package::getPath("breast_sim") + "/config/phantom_default.yaml";
  try {
    const core::ModelCase c = core::loadModelCase(case_file);
    ros_interface::TrackerSimulation sim(c, o);
    rosbag::Bag bag(out, rosbag::bagmode::Write);
    bag.setCompression(rosbag::compression::BZ2);
    const ros::Time t0(start);
    tf2_msgs::TFMessage statics;
    geometry_msgs::TransformStamped ts;
    ts.header.stamp = t0;
    ts.header.frame_id = "world";
    ts.child_frame_id = "tracker";
    ts.transform = ros_interface::transformFromIsometry(sim.worldFromTracker());
    statics.transforms.push_back(ts);
    // Latched, as tf2's static broadcaster does: `rosbag play` then keeps it for subscribers that
    // connect after the first message (otherwise a node slow to connect under load never gets the
    // tracker frame and drops every cloud).
    auto latched = boost::make_shared<ros::M_string>();
    (*latched)["latching"] = "1";
    (*latched)["callerid"] = "/make_test_bags";
    bag.write("/tf_static", t0, statics, latched);
    const int poses = static_cast<int>(seconds * pose_rate), clouds = static_cast<int>(seconds * cloud_rate);
    int p = 0, k = 0;
    while (p < poses || k < clouds) {
      const double tp = p / pose_rate, tc = k / cloud_rate;
      if (p < poses && (k >= clouds || tp <= tc)) {
        geometry_msgs::PoseStamped pose;
        pose.header.stamp = t0 + ros::Duration(tp);
        pose.header.frame_id = "world";
        pose.pose = ros_interface::poseFromIsometry(sim.worldFromModel(tp));
        bag.write("/tracker/patient_pose", pose.header.stamp, pose);
        ++p;
      } else {
        const ros::Time stamp = t0 + ros::Duration(tc);
        bag.write("/tracker/surface_points", stamp, ros_interface::cloudToMessage(sim.cloudInTracker(tc), "tracker", stamp));
        ++k;
      }
    }
    bag.close();
    std::cout << "wrote " << out << ": " << clouds << " clouds of " << o.points << " points at " << cloud_rate << " Hz, "
              << poses << " poses at " << pose_rate << " Hz, " << seconds << " s from t = " << start << " s\n";
  } catch (const std::exception& e) {
    std::cerr << "make_test_bags: " << e.what() << "\n";
    return 2;
  }
  return 0;
}
