// The breast_sim navigation node: wiring only (see breast_sim_node.h); the science is in the core.
// This file constructs the node, advertises its interfaces and starts its threads; the jobs,
// services, tracking, poses and publishing are in the breast_sim_node_*.cpp files beside it.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <diagnostic_msgs/DiagnosticArray.h>

#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;

BreastSimNode::BreastSimNode(ros::NodeHandle nh, ros::NodeHandle pnh)
    : nh_(nh), pnh_(pnh), tf_buffer_(ros::Duration(30.0)) {}

BreastSimNode::~BreastSimNode() {
  cancel_ = true;
  {
    std::lock_guard<std::mutex> lock(cloud_mutex_);
    stop_ = true;
  }
  cloud_cv_.notify_all();
  if (tracking_thread_.joinable()) tracking_thread_.join();
  std::lock_guard<std::mutex> lock(job_mutex_);
  if (worker_.joinable()) worker_.join();
}

void BreastSimNode::initialize() {
  params_ = NodeParams::fromRos(pnh_);
  data_folder_ = std::make_unique<ConfinedFolder>(params_.data_folder, "~data_folder", false);
  state_folder_ = std::make_unique<ConfinedFolder>(params_.state_folder, "~state_folder", true);
  output_folder_ = std::make_unique<ConfinedFolder>(params_.output_folder, "~output_folder", true);
  if (!params_.settings_file.empty()) params_.settings_file = data_folder_->existingFile(params_.settings_file);
  guard_ = GuardedTracker(params_.tracker, params_.monitor);
  throttle_.setPeriod(params_.warn_throttle_s);
  tf_listener_ = std::make_unique<tf2_ros::TransformListener>(tf_buffer_, nh_);
  mesh_pub_ = pnh_.advertise<breast_sim::TetrahedralMesh>("deformed_mesh", 1, /*latch=*/true);
  lesions_pub_ = pnh_.advertise<breast_sim::LesionArray>("lesions", 1, /*latch=*/true);
  lesion_markers_pub_ = pnh_.advertise<visualization_msgs::MarkerArray>("lesion_markers", 1, true);
  surface_pub_ = pnh_.advertise<visualization_msgs::Marker>("surface_marker", 1, true);
  sliding_pub_ = pnh_.advertise<visualization_msgs::MarkerArray>("sliding_vectors", 1, true);
  state_pub_ = pnh_.advertise<breast_sim::NodeState>("state", 1, true);
  diag_pub_ = nh_.advertise<diagnostic_msgs::DiagnosticArray>("/diagnostics", 10);
  services_.push_back(pnh_.advertiseService("load_case", &BreastSimNode::loadCaseSrv, this));
  services_.push_back(pnh_.advertiseService("start_precomputation", &BreastSimNode::startPrecomputationSrv, this));
  services_.push_back(pnh_.advertiseService("cancel_precomputation", &BreastSimNode::cancelSrv, this));
  services_.push_back(pnh_.advertiseService("reset", &BreastSimNode::resetSrv, this));
  services_.push_back(pnh_.advertiseService("save_state", &BreastSimNode::saveStateSrv, this));
  services_.push_back(pnh_.advertiseService("load_state", &BreastSimNode::loadStateSrv, this));
  services_.push_back(pnh_.advertiseService("write_supine_mri", &BreastSimNode::writeSupineMriSrv, this));
  action_ = std::make_unique<PrecomputeServer>(
      pnh_, "precompute", [this](PrecomputeServer::GoalHandle g) { goalCb(g); },
      [this](PrecomputeServer::GoalHandle g) { cancelGoalCb(g); }, false);
  action_->start();
  cloud_sub_ = pnh_.subscribe("surface_points", 2, &BreastSimNode::cloudCb, this);
  pose_sub_ = pnh_.subscribe("patient_pose", 10, &BreastSimNode::poseCb, this);
  window_start_ = Clock::now();
  diag_timer_ = nh_.createWallTimer(ros::WallDuration(params_.diagnostics_period_s), &BreastSimNode::publishDiagnostics, this);
  tracking_thread_ = std::thread([this] { trackingLoop(); });

  // The first case loads on the worker; the node answers at once.
  const std::string case_file = params_.case_file;
  const int target = params_.target_elements;
  const bool precompute = params_.precompute_on_start;
  std::string why;
  startJob([this, case_file, target, precompute] {
    std::string message;
    bool ok = false;
    try {
      loadCaseJob(data_folder_->existingFile(case_file), target, &message, &ok);
    } catch (const ConfinementError& ex) {
      message = std::string("cannot load case_file: ") + ex.what();
      endJob(breast_sim::NodeState::IDLE, message + "; no model loaded");
    }
    if (!ok) {
      ROS_ERROR_STREAM("breast_sim: " << message << "; no model until a case loads (~load_case)");
      return;
    }
    // A node restarted after a crash goes on from where it was, without precomputing.
    {
      std::lock_guard<std::mutex> lock(engine_mutex_);
      if (engine_ && resumeFromCheckpoint(*engine_)) return;
    }
    if (precompute) precomputeJob(false, std::nullopt);
  }, &why);
}

}  // namespace breast_sim::ros_interface
