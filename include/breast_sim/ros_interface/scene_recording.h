#pragma once
/// @file scene_recording.h
/// A recorded tracking scene, written as a rosbag, for testing the navigation node against inputs it
/// was not designed around: two sensors of their own (an organized depth camera fixed above the
/// table and a hand-held scanner that sweeps over the breast), a hand that hovers over the skin, a
/// torso around the breast, the patient's pose on tf only, malformed and mis-stamped messages at
/// known times, and a deliberate drift at the end. The sensor models are ray casters written here
/// (pinhole cameras against the skin triangles, a torso plane and an ellipsoidal hand); nothing of
/// tracker_simulation.h is used. Deterministic for a given seed.
///
/// Units: metres, seconds, radians where not said otherwise (REP 103). Frames (REP 105):
///  - `world` (SceneOptions::world_frame): gravity along −z. The model frame (`breast_model`, LPS)
///    lies supine: the model's gravity direction (SceneOptions::gravity_in_model, the one the skin
///    was computed under) is world −z at the mean table roll, the model's z (superior) is along
///    world x (the table), and the table rolls about world x by roll_amplitude_deg · sin(2πt/T).
///  - `depth_camera_optical` (camera_frame): fixed in world (/tf_static); optical convention (z
///    forward, x right, y down); placed camera_distance_m anterior of the skin's centre at the mean
///    roll, looking posterior (model +y), image x along model +x.
///  - `handheld_scanner` (scanner_frame): dynamic /tf (world → scanner); optical convention; it
///    sweeps laterally and cranio-caudally over the breast at scanner_distance_m, aimed at the skin's
///    centre.
///
/// What is in the bag (all stamps on the scene's clock, t = start_s + offset; "at t" means header
/// stamp t; a good cloud is written at its stamp plus sensor_latency_s, as a driver publishes it
/// after the exposure; tf and the bad messages are written at their stamps, the mis-stamped ones at
/// the time their stamp misstates):
///  - /tf_static (latched): world → camera_frame, once at start_s.
///  - /tf: world → model_frame every 1/tf_rate_hz for the whole scene; world → scanner_frame at the
///    same times from scanner_start − 0.2 s to scanner_end + 0.2 s.
///  - cloud_topic (sensor_msgs/PointCloud2), from both sensors:
///    * depth camera in camera_frame: organized (height × width), fields x, y, z (FLOAT32, offsets
///      0, 4, 8) and rgb (FLOAT32 holding packed 8-bit colour, offset 16), point_step 32 (padding as
///      OpenNI / RealSense drivers lay it out), is_dense false, NaN x/y/z for pixels that hit
///      nothing within camera_max_range_m; depth noise N(0, depth_noise_m) along the optical axis;
///      at camera_rate_hz from camera_start, at burst_rate_hz during the burst.
///    * hand-held scanner in scanner_frame: unorganized (height 1), fields x, y, z (FLOAT64, offsets
///      0, 8, 16) and intensity (FLOAT32, offset 24), point_step 32, is_dense true; scanner_points
///      rays at random pixels of its image (those that hit nothing are left out); noise
///      N(0, scanner_noise_m) along the ray; at scanner_rate_hz for scanner_duration_s.
///    What the rays hit: the skin (the given triangles, slid by the drift), the torso (the plane of
///    the skin's rim, perpendicular to model y, from torso_half_width_m towards model −x to 0.7 of
///    it towards +x of the skin's centre, so that one side of the image looks past the patient's
///    side and sees nothing, and torso_half_length_m either way along the body, beyond the image
///    border), and, in depth-camera
///    frames during the hand's segment, the hand: an ellipsoid of semi-axes hand_semi_axes_m
///    (lateral, along the skin normal, cranio-caudal) whose near side hovers hand_gap_min_m to
///    hand_gap_max_m in front of the skin while it crosses the breast.
///  - pose_topic (geometry_msgs/PoseStamped of model_frame in world): only bad poses (below). A
///    node must take the patient's pose from tf.
///  - Bad inputs (SceneBadInput), each kind in bursts of bad_burst_size messages bad_burst_spacing_s
///    apart, at the offsets of SceneOptions::bad_bursts (the sensors are quiet around each bad
///    cloud, see there): a nearly zero quaternion (w 1e-5, x y z 0),
///    the true pose turned 180° about the model's x axis, the true pose stamped an hour ahead; depth
///    clouds stamped an hour ahead, stamped 10 s in the past, truncated to half their data, all NaN,
///    and one in an unknown frame (unknown_frame).
///  - The drift: from drift_start, the skin the depth camera sees is slid along model +x (along the
///    chest wall) by drift_m, ramped in linearly over drift_ramp_s, then held to the end. The torso
///    does not move. The hand-held scanner has stopped by then.

#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/model_case.h"

namespace breast_sim::ros_interface {

/// The kinds of bad input a scene holds.
enum class SceneBadKind {
  kPoseNearZeroQuaternion,  ///< pose_topic: orientation (w 1e-5, 0, 0, 0)
  kPoseFlipped,             ///< pose_topic: the true pose turned 180° about the model's x axis
  kPoseFuture,              ///< pose_topic: the true pose stamped bad_future_s ahead
  kCloudFuture,             ///< cloud_topic: a depth cloud stamped bad_future_s ahead
  kCloudPast,               ///< cloud_topic: a depth cloud stamped bad_past_s behind
  kCloudTruncated,          ///< cloud_topic: a depth cloud with half its data
  kCloudAllNan,             ///< cloud_topic: a depth cloud whose every point is NaN
  kCloudUnknownFrame,       ///< cloud_topic: a depth cloud in unknown_frame
};
constexpr int kSceneBadKinds = 8;
/// A short name of the kind ("pose near-zero quaternion", ...).
const char* sceneBadKindName(SceneBadKind kind);

/// One burst of a bad input: bad_burst_size messages from offset_s on [s after start_s].
struct SceneBadBurst {
  SceneBadKind kind;
  double offset_s;
};

struct SceneOptions {
  unsigned seed = 1;
  double start_s = 100.0;     ///< scene clock at its first message [s]
  double duration_s = 21.0;   ///< [s]
  double sensor_latency_s = 0.03;  ///< a cloud is written this long after its stamp [s]
  std::string world_frame = "world", model_frame = "breast_model", camera_frame = "depth_camera_optical",
              scanner_frame = "handheld_scanner", unknown_frame = "unregistered_camera_optical";
  std::string cloud_topic = "/scene/surface_points", pose_topic = "/scene/patient_pose";
  /// Gravity's direction in the model frame under which the skin was computed (any length > 0).
  Eigen::Vector3d gravity_in_model{0.0, 1.0, 0.0};
  Eigen::Vector3d table_origin_m{0.3, 0.0, 0.8};  ///< the model origin in world [m]
  // Patient pose on tf.
  double tf_rate_hz = 50.0;
  double roll_amplitude_deg = 1.0, roll_period_s = 12.0;
  // Depth camera.
  int camera_width = 128, camera_height = 96;
  double camera_hfov_deg = 34.0;        ///< horizontal field of view; square pixels
  double camera_distance_m = 0.45;      ///< from the skin's centre, anterior
  double camera_max_range_m = 1.0;      ///< farther returns are NaN
  double camera_start_s = 0.5, camera_rate_hz = 15.0;
  double burst_start_s = 10.0, burst_duration_s = 1.0, burst_rate_hz = 60.0;
  double depth_noise_m = 0.5e-3;
  // Torso: the rim's plane around the breast [m], about the skin's centre.
  bool with_torso = true;
  double torso_half_width_m = 0.16, torso_half_length_m = 0.25;
  // Hand (depth camera only).
  bool with_hand = true;
  double hand_start_s = 4.0, hand_end_s = 7.0;
  Eigen::Vector3d hand_semi_axes_m{0.045, 0.015, 0.030};
  double hand_gap_min_m = 0.040, hand_gap_max_m = 0.060;
  // Hand-held scanner.
  double scanner_start_s = 1.0, scanner_duration_s = 8.0, scanner_rate_hz = 10.0;
  int scanner_points = 3000;
  double scanner_hfov_deg = 30.0, scanner_distance_m = 0.25, scanner_noise_m = 0.3e-3;
  double scanner_sweep_m = 0.04;        ///< lateral sweep amplitude [m] (cranio-caudal: 0.75 of it)
  // Drift.
  double drift_start_s = 15.0, drift_ramp_s = 1.0, drift_m = 0.020;
  // Bad inputs.
  int bad_burst_size = 3;
  double bad_burst_spacing_s = 0.2;
  double bad_future_s = 3600.0, bad_past_s = 10.0;
  double bad_quiet_before_s = 0.07, bad_quiet_after_s = 0.12;
  /// Offsets chosen so that no two bursts whose warnings a node might throttle under one key (the
  /// future and the past cloud stamps) start within 3.5 s of each other. Around each bad cloud
  /// both sensors leave out their clouds stamped from bad_quiet_before_s before it to
  /// bad_quiet_after_s after it, so that a node that keeps only the newest cloud gets to see it.
  std::vector<SceneBadBurst> bad_bursts = {
      {SceneBadKind::kCloudFuture, 1.6},  {SceneBadKind::kPoseNearZeroQuaternion, 2.0},
      {SceneBadKind::kCloudTruncated, 2.6}, {SceneBadKind::kPoseFuture, 3.0},
      {SceneBadKind::kCloudAllNan, 3.6},  {SceneBadKind::kCloudPast, 5.1},
      {SceneBadKind::kPoseFlipped, 6.0},  {SceneBadKind::kCloudUnknownFrame, 6.6},
      {SceneBadKind::kCloudFuture, 8.6},  {SceneBadKind::kPoseNearZeroQuaternion, 9.0},
      {SceneBadKind::kCloudTruncated, 9.6}, {SceneBadKind::kCloudAllNan, 11.3},
      {SceneBadKind::kCloudPast, 12.1},   {SceneBadKind::kPoseFuture, 12.5},
      {SceneBadKind::kPoseFlipped, 13.0}, {SceneBadKind::kCloudUnknownFrame, 13.6},
  };
  /// @throws std::invalid_argument naming the option for a value out of range.
  void validate() const;
};

/// One good cloud of the scene.
struct SceneCloud {
  double stamp_s;          ///< header stamp [s]
  bool depth_camera;       ///< false: the hand-held scanner
  bool hand;               ///< the hand is in view (depth camera)
  double drift_m;          ///< how far the skin is slid at this stamp [m]
  int points;              ///< finite points
};

/// One bad message of the scene.
struct SceneBadInput {
  SceneBadKind kind;
  double time_s;           ///< when it is written (played) [s]
  double stamp_s;          ///< its header stamp [s]
  std::string topic;
};

/// A named interval of the scene [s, scene clock].
struct SceneSegment {
  std::string name;
  double begin_s, end_s;
};

/// What a scene holds and when: the test's key to the bag.
struct SceneDescription {
  double start_s = 0, end_s = 0;
  double drift_begin_s = 0, drift_full_s = 0, drift_end_s = 0, drift_m = 0;
  std::vector<SceneSegment> segments;  ///< camera, burst, hand, scanner, drift ramp, drift held
  std::vector<SceneCloud> clouds;      ///< the good clouds, by stamp
  std::vector<SceneBadInput> bad_inputs;
  std::vector<SceneBadBurst> bad_bursts;  ///< absolute times (start_s + offset)
  /// How many bursts of `kind` the scene holds.
  int bursts(SceneBadKind kind) const;
  /// A YAML text of the description (segments, bad inputs, cloud counts).
  std::string toYaml() const;
};

/// Gravity's direction in the model frame under which a case's supine skin is computed: the
/// phantom's tilted supine gravity, otherwise the opposite of its prone direction (unit vector).
Eigen::Vector3d supineGravityDirection(const core::ModelCase& model_case);

/// Writes the scene of the supine skin to `bag_path` (overwritten) and describes it.
/// @param skin_positions_m  #N×3 node positions [m] in the model frame (the supine state)
/// @param skin_triangles    #T×3 indices into them, oriented outward (core::skinTriangles)
/// @throws std::invalid_argument for empty or out-of-range input or invalid options;
///         rosbag::BagException when the bag cannot be written.
SceneDescription writeSceneBag(const std::string& bag_path, const core::Points& skin_positions_m,
                               const core::Triangles& skin_triangles, const SceneOptions& options = {});

}  // namespace breast_sim::ros_interface
