// The node's parameters, read from its private namespace and checked (node_params.h).
#include "breast_sim/ros_interface/node_params.h"

#include <cstdlib>
#include <stdexcept>

#include <ros/package.h>

namespace breast_sim::ros_interface {

namespace {

template <typename T>
T param(const ros::NodeHandle& pnh, const std::string& name, const T& fallback) {
  T v;
  return pnh.getParam(name, v) ? v : fallback;
}

void require(bool ok, const std::string& name, const std::string& what) {
  if (!ok) throw std::invalid_argument("parameter ~" + name + ": " + what);
}

/// $ROS_HOME/`sub`, ROS_HOME defaulting to ~/.ros as roslaunch's does.
std::string rosHomeFolder(const std::string& sub) {
  const char* ros_home = std::getenv("ROS_HOME");
  const char* home = std::getenv("HOME");
  const std::string base = ros_home && *ros_home ? ros_home : std::string(home && *home ? home : "/tmp") + "/.ros";
  return base + "/" + sub;
}

}  // namespace

NodeParams NodeParams::fromRos(const ros::NodeHandle& pnh) {
  NodeParams p;
  p.data_folder = param<std::string>(pnh, "data_folder", ros::package::getPath("breast_sim"));
  p.state_folder = param<std::string>(pnh, "state_folder", rosHomeFolder("breast_sim/states"));
  p.checkpoint_period_s = param(pnh, "checkpoint/period_s", p.checkpoint_period_s);
  p.case_file = param<std::string>(pnh, "case_file", "config/phantom_default.yaml");
  p.target_elements = param(pnh, "target_elements", p.target_elements);
  p.settings_file = param(pnh, "settings_file", p.settings_file);
  p.field_voxel_size_m = param(pnh, "field_voxel_size_m", p.field_voxel_size_m);
  p.frame_id = param(pnh, "frame_id", p.frame_id);
  p.output_folder = param(pnh, "output_folder", p.output_folder);
  if (p.output_folder.empty()) p.output_folder = rosHomeFolder("breast_sim");
  p.precompute_on_start = param(pnh, "precompute_on_start", p.precompute_on_start);
  p.gravity_frame = param(pnh, "gravity/frame", p.gravity_frame);
  p.follow_patient_pose = param(pnh, "gravity/follow_patient_pose", p.follow_patient_pose);
  p.gravity_update_threshold_deg = param(pnh, "gravity/update_threshold_deg", p.gravity_update_threshold_deg);
  p.publish_pose_tf = param(pnh, "gravity/publish_pose_tf", p.publish_pose_tf);
  p.pose_jump.max_jump_m = param(pnh, "gravity/max_pose_jump_m", p.pose_jump.max_jump_m);
  p.pose_jump.max_jump_deg = param(pnh, "gravity/max_pose_jump_deg", p.pose_jump.max_jump_deg);
  p.pose_jump.window_s = param(pnh, "gravity/pose_jump_window_s", p.pose_jump.window_s);
  TrackerOptions& t = p.tracker;
  t.filter.voxel_leaf_m = param(pnh, "tracking/voxel_leaf_m", t.filter.voxel_leaf_m);
  t.filter.remove_outliers = param(pnh, "tracking/remove_outliers", t.filter.remove_outliers);
  t.filter.outlier_neighbours = param(pnh, "tracking/outlier_neighbours", t.filter.outlier_neighbours);
  t.filter.outlier_stddev = param(pnh, "tracking/outlier_stddev", t.filter.outlier_stddev);
  t.icp.enabled = param(pnh, "tracking/icp/enabled", t.icp.enabled);
  t.icp.max_iterations = param(pnh, "tracking/icp/max_iterations", t.icp.max_iterations);
  t.icp.max_points = param(pnh, "tracking/icp/max_points", t.icp.max_points);
  t.icp.max_correspondence_m = param(pnh, "tracking/icp/max_correspondence_m", t.icp.max_correspondence_m);
  t.icp.max_translation_m = param(pnh, "tracking/icp/max_translation_m", t.icp.max_translation_m);
  t.icp.max_rotation_deg = param(pnh, "tracking/icp/max_rotation_deg", t.icp.max_rotation_deg);
  t.icp.max_rms_m = param(pnh, "tracking/icp/max_rms_m", t.icp.max_rms_m);
  t.icp.min_inlier_fraction = param(pnh, "tracking/icp/min_inlier_fraction", t.icp.min_inlier_fraction);
  t.max_point_distance_m = param(pnh, "tracking/max_point_distance_m", t.max_point_distance_m);
  t.iterations_per_frame = param(pnh, "tracking/iterations_per_frame", t.iterations_per_frame);
  t.solver_relative_tolerance = param(pnh, "tracking/solver_relative_tolerance", t.solver_relative_tolerance);
  t.min_points = param(pnh, "tracking/min_points", t.min_points);
  t.hold_unseen_skin_m = param(pnh, "tracking/hold_unseen_skin_m", t.hold_unseen_skin_m);
  p.max_cloud_points = static_cast<size_t>(param(pnh, "tracking/max_cloud_points", static_cast<int>(p.max_cloud_points)));
  p.max_transform_age_s = param(pnh, "tracking/max_transform_age_s", p.max_transform_age_s);
  p.tf_wait_s = param(pnh, "tracking/tf_wait_s", p.tf_wait_s);
  p.require_precomputation = param(pnh, "tracking/require_precomputation", p.require_precomputation);
  MonitorLimits& m = p.monitor;
  m.refused_frames = param(pnh, "tracking/degraded_after_rejected", m.refused_frames);
  m.max_seen_mean_m = param(pnh, "tracking/monitor/max_seen_mean_m", m.max_seen_mean_m);
  m.max_seen_p95_m = param(pnh, "tracking/monitor/max_seen_p95_m", m.max_seen_p95_m);
  m.min_seen_fraction = param(pnh, "tracking/monitor/min_seen_fraction", m.min_seen_fraction);
  m.max_wall_drift_m = param(pnh, "tracking/monitor/max_wall_drift_m", m.max_wall_drift_m);
  m.max_rigid_drift_m = param(pnh, "tracking/monitor/max_rigid_drift_m", m.max_rigid_drift_m);
  m.max_lesion_offset_m = param(pnh, "tracking/monitor/max_lesion_offset_m", m.max_lesion_offset_m);
  m.max_lesion_jump_m = param(pnh, "tracking/monitor/max_lesion_jump_m", m.max_lesion_jump_m);
  m.max_stiffening = param(pnh, "tracking/monitor/max_stiffening", m.max_stiffening);
  m.recover_frames = param(pnh, "tracking/monitor/recover_frames", m.recover_frames);
  m.recover_fraction = param(pnh, "tracking/monitor/recover_fraction", m.recover_fraction);
  p.stamps.max_future_s = param(pnh, "tracking/max_future_stamp_s", p.stamps.max_future_s);
  p.stamps.max_age_s = param(pnh, "tracking/max_stamp_age_s", p.stamps.max_age_s);
  p.tracking_timeout_s = param(pnh, "tracking/timeout_s", p.tracking_timeout_s);
  p.mesh_rate_hz = param(pnh, "publish/mesh_rate_hz", p.mesh_rate_hz);
  p.marker_rate_hz = param(pnh, "publish/marker_rate_hz", p.marker_rate_hz);
  p.marker_max_triangles = param(pnh, "publish/marker_max_triangles", p.marker_max_triangles);
  p.publish_lesion_tf = param(pnh, "publish/lesion_tf", p.publish_lesion_tf);
  p.lesion_frame_prefix = param(pnh, "publish/lesion_frame_prefix", p.lesion_frame_prefix);
  p.sliding_arrow_scale = param(pnh, "publish/sliding_arrow_scale", p.sliding_arrow_scale);
  p.sliding_min_length_m = param(pnh, "publish/sliding_min_length_m", p.sliding_min_length_m);
  p.sliding_max_arrows = param(pnh, "publish/sliding_max_arrows", p.sliding_max_arrows);
  p.diagnostics_period_s = param(pnh, "publish/diagnostics_period_s", p.diagnostics_period_s);
  p.progress_rate_hz = param(pnh, "publish/progress_rate_hz", p.progress_rate_hz);
  p.warn_throttle_s = param(pnh, "warn_throttle_s", p.warn_throttle_s);

  require(!p.data_folder.empty(), "data_folder", "must not be empty (a folder holding the case files)");
  require(!p.state_folder.empty(), "state_folder", "must not be empty (a folder for state files and checkpoints)");
  require(p.checkpoint_period_s >= 0, "checkpoint/period_s", "must be ≥ 0 s (0 = no checkpoints while tracking)");
  require(p.target_elements >= 0, "target_elements", "must be ≥ 0 (0 keeps the case's meshing.target_elements)");
  require(p.field_voxel_size_m >= 0 && p.field_voxel_size_m < 0.1, "field_voxel_size_m", "must be in [0, 0.1) m");
  require(!p.frame_id.empty(), "frame_id", "must not be empty");
  require(p.output_folder.front() == '/', "output_folder",
          "must be an absolute path (or \"\" for $ROS_HOME/breast_sim), got '" + p.output_folder + "'");
  require(t.filter.voxel_leaf_m >= 0 && t.filter.voxel_leaf_m < 0.1, "tracking/voxel_leaf_m", "must be in [0, 0.1) m");
  require(t.filter.outlier_neighbours >= 1, "tracking/outlier_neighbours", "must be ≥ 1");
  require(t.filter.outlier_stddev > 0, "tracking/outlier_stddev", "must be > 0");
  require(t.icp.max_iterations >= 1, "tracking/icp/max_iterations", "must be ≥ 1");
  require(t.icp.max_correspondence_m > 0, "tracking/icp/max_correspondence_m", "must be > 0 m");
  require(t.icp.max_rms_m > 0, "tracking/icp/max_rms_m", "must be > 0 m");
  require(t.icp.min_inlier_fraction >= 0 && t.icp.min_inlier_fraction <= 1, "tracking/icp/min_inlier_fraction",
          "must be in [0, 1]");
  require(t.max_point_distance_m >= 0, "tracking/max_point_distance_m", "must be ≥ 0 m (0 = keep every point)");
  require(p.stamps.max_future_s > 0, "tracking/max_future_stamp_s", "must be > 0 s");
  require(p.stamps.max_age_s > 0, "tracking/max_stamp_age_s", "must be > 0 s");
  require(p.pose_jump.max_jump_m > 0, "gravity/max_pose_jump_m", "must be > 0 m");
  require(p.pose_jump.max_jump_deg > 0, "gravity/max_pose_jump_deg", "must be > 0 deg");
  require(p.pose_jump.window_s >= 0, "gravity/pose_jump_window_s", "must be ≥ 0 s");
  m.validate();
  require(t.iterations_per_frame >= 1 && t.iterations_per_frame <= 100, "tracking/iterations_per_frame", "must be in [1, 100]");
  require(t.solver_relative_tolerance >= 0 && t.solver_relative_tolerance < 1, "tracking/solver_relative_tolerance",
          "must be in [0, 1) (0 = the case's simulation.solver_relative_tolerance)");
  require(t.min_points >= 10, "tracking/min_points", "must be ≥ 10");
  require(t.hold_unseen_skin_m >= 0, "tracking/hold_unseen_skin_m", "must be ≥ 0 m (0 = off)");
  require(p.max_cloud_points >= 1000, "tracking/max_cloud_points", "must be ≥ 1000");
  require(p.max_transform_age_s > 0, "tracking/max_transform_age_s", "must be > 0 s");
  require(p.tf_wait_s >= 0 && p.tf_wait_s <= 1.0, "tracking/tf_wait_s", "must be in [0, 1] s");
  require(p.mesh_rate_hz >= 0, "publish/mesh_rate_hz", "must be ≥ 0 Hz (0 = every frame)");
  require(p.marker_rate_hz > 0, "publish/marker_rate_hz", "must be > 0 Hz");
  require(p.diagnostics_period_s > 0, "publish/diagnostics_period_s", "must be > 0 s");
  require(p.progress_rate_hz > 0, "publish/progress_rate_hz", "must be > 0 Hz");
  require(p.warn_throttle_s >= 0, "warn_throttle_s", "must be ≥ 0 s");
  return p;
}

}  // namespace breast_sim::ros_interface
