#pragma once
/// @file node_params.h
/// The parameters of the breast_sim navigation node (breast_sim_node.h), read from its private
/// namespace. config/node.yaml documents each with its unit and default.

#include <cstddef>
#include <string>

#include <ros/node_handle.h>

#include "breast_sim/ros_interface/input_checks.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracking_monitor.h"

namespace breast_sim::ros_interface {

/// Parameters of the node (config/node.yaml documents each with unit and default).
struct NodeParams {
  /// Case files (case_file, settings_file, ~load_case) are read only inside it; default: the package's folder.
  std::string data_folder;
  /// ~save_state, ~load_state and the checkpoints, only inside it; default: $ROS_HOME/breast_sim/states.
  std::string state_folder;
  /// While tracking, a checkpoint at most this often [s] (after a frame with valid lesions); 0 = off.
  double checkpoint_period_s = 2.0;
  std::string case_file;              ///< relative to data_folder, or absolute inside it
  int target_elements = 0;
  std::string settings_file;          ///< "" = the case file's simulation/sliding/morphing maps; as case_file
  double field_voxel_size_m = 0.003;  ///< [m]; 0 = the settings' morphing.voxel_size_mm
  std::string frame_id = "breast_model";
  /// Where ~write_supine_mri writes (absolute); "" at start = $ROS_HOME/breast_sim (~/.ros/breast_sim).
  std::string output_folder;
  bool precompute_on_start = false;
  // gravity
  std::string gravity_frame = "world";
  bool follow_patient_pose = true;
  double gravity_update_threshold_deg = 0.5;
  bool publish_pose_tf = true;
  PoseJumpLimits pose_jump;
  // tracking
  TrackerOptions tracker;
  MonitorLimits monitor;              ///< monitor.refused_frames = tracking/degraded_after_rejected
  StampLimits stamps;
  size_t max_cloud_points = 300000;
  double max_transform_age_s = 0.5;
  double tf_wait_s = 0.05;
  bool require_precomputation = true;
  double tracking_timeout_s = 2.0;
  // publishing
  double mesh_rate_hz = 0.0;          ///< 0 = every tracked frame
  double marker_rate_hz = 10.0;
  int marker_max_triangles = 4000;
  bool publish_lesion_tf = true;
  std::string lesion_frame_prefix = "lesion_";
  double sliding_arrow_scale = 1.0;
  double sliding_min_length_m = 1e-4;
  int sliding_max_arrows = 300;
  double diagnostics_period_s = 1.0;
  double progress_rate_hz = 5.0;
  double warn_throttle_s = 5.0;

  /// Reads every parameter from the private namespace (missing keys keep the defaults above).
  /// @throws std::invalid_argument naming the parameter for a value out of range.
  static NodeParams fromRos(const ros::NodeHandle& pnh);
};

}  // namespace breast_sim::ros_interface
