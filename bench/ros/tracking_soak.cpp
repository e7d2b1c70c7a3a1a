// Memory of a running breast_sim node over a long tracking run (scripts/soak_tracking.sh starts the
// master and the node, then this client):
//   tracking_soak --pid PID [--minutes M] [--rate HZ] [--points N] [--resets K] [--warmup-min W]
//                 [--sample-s S] [--json FILE]
// It first resets and precomputes the node K times (~reset, ~start_precomputation), then publishes
// the phantom tracker's clouds (TrackerSimulation, in the `tracker` frame with its patient pose on
// ~patient_pose and /tf_static world -> tracker) at HZ for M minutes, and samples the node's
// resident memory (VmRSS of /proc/PID/status) every S seconds. Prints the samples, the growth over
// the resets, and the spread after the warm-up (W minutes): the figure the node is held to (flat
// within ±5 MB). Wall time; the node runs with its defaults (config/node.yaml).
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <thread>

#include <geometry_msgs/PoseStamped.h>
#include <nlohmann/json.hpp>
#include <ros/package.h>
#include <ros/ros.h>
#include <sensor_msgs/PointCloud2.h>
#include <std_srvs/Trigger.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include <breast_sim/NodeState.h>
#include <breast_sim/StartPrecomputation.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

using namespace breast_sim;

namespace {

double rssMb(int pid) {
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(f, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;  // kB
  return -1;
}

breast_sim::NodeState::ConstPtr g_state;
std::mutex g_mutex;

void onState(const breast_sim::NodeState::ConstPtr& m) {
  std::lock_guard<std::mutex> l(g_mutex);
  g_state = m;
}

bool waitFor(const std::function<bool(const breast_sim::NodeState&)>& ok, double timeout_s) {
  const ros::WallTime t0 = ros::WallTime::now();
  while ((ros::WallTime::now() - t0).toSec() < timeout_s && ros::ok()) {
    {
      std::lock_guard<std::mutex> l(g_mutex);
      if (g_state && ok(*g_state)) return true;
    }
    ros::WallDuration(0.05).sleep();
  }
  return false;
}

}  // namespace

int main(int argc, char** argv) {
  ros::init(argc, argv, "tracking_soak", ros::init_options::AnonymousName);
  int pid = -1, points = 10000, resets = 8;
  double minutes = 30, rate = 30, warmup_min = 2, sample_s = 30;
  std::string json_path, node = "/breast_sim";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string { return i + 1 < argc ? argv[++i] : ""; };
    if (a == "--pid") pid = std::stoi(next());
    else if (a == "--minutes") minutes = std::stod(next());
    else if (a == "--rate") rate = std::stod(next());
    else if (a == "--points") points = std::stoi(next());
    else if (a == "--resets") resets = std::stoi(next());
    else if (a == "--warmup-min") warmup_min = std::stod(next());
    else if (a == "--sample-s") sample_s = std::stod(next());
    else if (a == "--node") node = next();
    else if (a == "--json") json_path = next();
    else {
      std::cerr << "tracking_soak: unknown option '" << a << "'\n";
      return 2;
    }
  }
  if (pid <= 0 || rssMb(pid) < 0) {
    std::cerr << "tracking_soak: --pid must name the running node's process\n";
    return 2;
  }
  ros::NodeHandle nh;
  ros::Subscriber st = nh.subscribe(node + "/state", 10, onState);
  ros::Publisher clouds = nh.advertise<sensor_msgs::PointCloud2>(node + "/surface_points", 2);
  ros::Publisher poses = nh.advertise<geometry_msgs::PoseStamped>(node + "/patient_pose", 10);
  ros::AsyncSpinner spinner(1);
  spinner.start();
  nlohmann::json out = {{"rate_hz", rate}, {"points", points}, {"minutes", minutes}, {"resets", nlohmann::json::array()},
                        {"samples", nlohmann::json::array()}};
  if (!waitFor([](const breast_sim::NodeState& s) { return s.model_loaded && s.state == breast_sim::NodeState::IDLE; }, 600)) {
    std::cerr << "tracking_soak: the node did not load its case\n";
    return 1;
  }
  const auto idleAnd = [](bool precomputed) {
    return [precomputed](const breast_sim::NodeState& s) { return s.state == breast_sim::NodeState::IDLE && s.precomputed == precomputed; };
  };
  // 1. Resets and precomputations.
  std::cout << "tracking_soak: node pid " << pid << ", RSS " << std::fixed << std::setprecision(1) << rssMb(pid)
            << " MB after loading\n  reset+precompute  RSS [MB]  ~reset answered in [ms]\n";
  for (int r = 0; r <= resets; ++r) {
    double answer_ms = 0;
    if (r > 0) {
      std_srvs::Trigger reset;
      const ros::WallTime t0 = ros::WallTime::now();
      if (!ros::service::call(node + "/reset", reset) || !reset.response.success) {
        std::cerr << "tracking_soak: ~reset failed: " << reset.response.message << "\n";
        return 1;
      }
      answer_ms = 1e3 * (ros::WallTime::now() - t0).toSec();
      if (!waitFor(idleAnd(false), 300)) {
        std::cerr << "tracking_soak: the reset did not finish\n";
        return 1;
      }
    }
    breast_sim::StartPrecomputation start;
    if (!ros::service::call(node + "/start_precomputation", start) || !start.response.accepted) {
      std::cerr << "tracking_soak: precomputation refused: " << start.response.message << "\n";
      return 1;
    }
    ros::WallDuration(0.5).sleep();
    if (!waitFor(idleAnd(true), 900)) {
      std::cerr << "tracking_soak: the precomputation did not finish\n";
      return 1;
    }
    const double rss = rssMb(pid);
    std::cout << "  " << std::setw(16) << r << std::setw(10) << rss << std::setw(24) << answer_ms << "\n";
    out["resets"].push_back({{"cycle", r}, {"rss_mb", rss}, {"reset_answer_ms", answer_ms}});
  }
  // 2. Tracking at `rate` for `minutes`.
  const core::ModelCase c = core::loadModelCase(ros::package::getPath("breast_sim") + "/config/phantom_default.yaml");
  ros_interface::TrackerSimulationOptions so;
  so.points = points;
  ros_interface::TrackerSimulation sim(c, so);
  tf2_ros::StaticTransformBroadcaster statics;
  geometry_msgs::TransformStamped ts;
  ts.header.stamp = ros::Time::now();
  ts.header.frame_id = "world";
  ts.child_frame_id = "tracker";
  ts.transform = ros_interface::transformFromIsometry(sim.worldFromTracker());
  statics.sendTransform(ts);
  ros::WallDuration(0.5).sleep();
  std::cout << "  minute  RSS [MB]  state\n";
  const ros::WallTime t0 = ros::WallTime::now();
  ros::WallTime next_sample = t0;
  std::vector<double> after_warmup;
  long sent = 0;
  for (ros::WallRate loop(rate); ros::ok(); loop.sleep()) {
    const double t = (ros::WallTime::now() - t0).toSec();
    if (t > 60 * minutes) break;
    const ros::Time stamp = ros::Time::now();
    geometry_msgs::PoseStamped pose;
    pose.header.stamp = stamp;
    pose.header.frame_id = "world";
    pose.pose = ros_interface::poseFromIsometry(sim.worldFromModel(t));
    poses.publish(pose);
    clouds.publish(ros_interface::cloudToMessage(sim.cloudInTracker(t), "tracker", stamp));
    ++sent;
    if (ros::WallTime::now() >= next_sample) {
      next_sample += ros::WallDuration(sample_s);
      const double rss = rssMb(pid);
      std::string state;
      {
        std::lock_guard<std::mutex> l(g_mutex);
        state = g_state ? g_state->state_name : "?";
      }
      std::cout << "  " << std::setw(6) << std::setprecision(1) << t / 60 << std::setw(10) << rss << "  " << state << "\n";
      out["samples"].push_back({{"minute", t / 60}, {"rss_mb", rss}, {"state", state}});
      if (t >= 60 * warmup_min) after_warmup.push_back(rss);
    }
  }
  const double first = out["resets"].front()["rss_mb"], last_reset = out["resets"].back()["rss_mb"];
  std::cout << "  resets: RSS " << first << " -> " << last_reset << " MB over " << resets << " reset+precompute cycles\n";
  if (!after_warmup.empty()) {
    const auto [lo, hi] = std::minmax_element(after_warmup.begin(), after_warmup.end());
    std::cout << "  tracking: " << sent << " clouds; after " << warmup_min << " min of warm-up RSS " << after_warmup.front()
              << " -> " << after_warmup.back() << " MB, range " << *lo << " - " << *hi << " MB (spread " << *hi - *lo
              << " MB)\n";
    out["after_warmup"] = {{"first_mb", after_warmup.front()}, {"last_mb", after_warmup.back()}, {"min_mb", *lo},
                           {"max_mb", *hi}, {"spread_mb", *hi - *lo}, {"clouds", sent}};
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
