#pragma once
/// @file breast_sim_node.h
/// The breast_sim navigation node: loads a case (an MRI case is segmented first), precomputes the
/// prone-to-supine deformation on a worker thread, then follows the skin surface a tracker sees and
/// publishes the deformed mesh, the lesions (messages, markers, tf2 frames), sliding vectors, its
/// state and diagnostics; on request it writes the simulated supine MRI of an MRI case to a file.
///
/// Threads: ROS callbacks run on an AsyncSpinner and never compute; one worker runs the long jobs
/// (case loading, precomputation) one at a time; one tracking thread processes the newest cloud (older
/// ones are dropped, so the node never falls behind its tracker). The pipeline is guarded by one mutex;
/// services that need it refuse with a reason while a long job runs.
///
/// Tracking is guarded (tracking_monitor.h): the lesions carry whether the node vouches for them, and
/// every cloud and pose is checked before it acts (input_checks.h). Every parameter is documented with
/// its unit in config/node.yaml (node_params.h).
///
/// Files: cases are read only inside ~data_folder, states written and read only inside
/// ~state_folder (confined_folder.h). The node checkpoints its state there after each
/// precomputation, after a loaded state and every checkpoint/period_s while tracking, and on start
/// resumes from the newest checkpoint of its case (node_checkpoint.h), so that a node restarted
/// after a crash tracks again without a precomputation.
///
/// The class is implemented in src/ros_interface: breast_sim_node.cpp (set-up), _jobs, _services,
/// _tracking, _poses, _publishing and _checkpoints (breast_sim_node_*.cpp), one file per group below.

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include <actionlib/server/action_server.h>
#include <geometry_msgs/PoseStamped.h>
#include <ros/ros.h>
#include <sensor_msgs/PointCloud2.h>
#include <std_srvs/Trigger.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_broadcaster.h>
#include <tf2_ros/transform_listener.h>

#include <breast_sim/LoadCase.h>
#include <breast_sim/NodeState.h>
#include <breast_sim/PrecomputeAction.h>
#include <breast_sim/StartPrecomputation.h>
#include <breast_sim/StateFile.h>
#include <breast_sim/WriteSupineMri.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/lesion_uncertainty.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/confined_folder.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/input_checks.h"
#include "breast_sim/ros_interface/node_params.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracking_monitor.h"

namespace breast_sim::ros_interface {

class BreastSimNode {
 public:
  BreastSimNode(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~BreastSimNode();
  /// Reads parameters, advertises, starts the tracking thread and loads the configured case.
  void initialize();

 private:
  /// A loaded case with its model, pipeline and what the node derives from them.
  struct Engine {
    std::string case_file;
    std::unique_ptr<core::ModelCase> model_case;
    std::unique_ptr<core::SimulationModel> model;
    core::PipelineSettings settings;
    std::unique_ptr<core::ProneToSupinePipeline> pipeline;
    DisplaySurface display;
    std::vector<int> wall_nodes;
    Eigen::Vector3d prone_gravity_mps2 = Eigen::Vector3d::Zero();
    Eigen::Vector3d gravity_load_mps2 = Eigen::Vector3d::Zero();
    bool precomputed = false;
    /// The lesions' confidence regions of the last precomputation (`uncertainty:` enabled), one per
    /// lesion; empty when none was computed (or it failed, was cancelled, or a state was loaded).
    std::vector<core::LesionRegion> regions;
    std::string region_status = "not computed";  ///< why there are no regions, or how they were made
    /// caseFingerprint of the case as loaded; 0 when it could not be made (then no checkpoints).
    std::uint64_t fingerprint = 0;
    /// How many multigrid levels were read from ~state_folder instead of meshed (buildPipeline); 0
    /// when they were meshed.
    int levels_read = 0;
  };
  using PrecomputeServer = actionlib::ActionServer<breast_sim::PrecomputeAction>;

  // Long jobs (breast_sim_node_jobs.cpp).
  /// `stage` is called with each loading stage ("reading", "segmentation" for an MRI case, "meshing",
  /// "setup") as it starts.
  std::unique_ptr<Engine> buildEngine(const std::string& case_file, int target_elements,
                                      const std::function<void(const std::string&)>& stage) const;
  bool startJob(std::function<void()> job, std::string* why);
  void loadCaseJob(const std::string& case_file, int target_elements, std::string* message, bool* ok);
  void precomputeJob(bool gravity_only, std::optional<PrecomputeServer::GoalHandle> goal);
  /// The ensemble of the engine's `uncertainty:` after a precomputation; sets e.regions and
  /// e.region_status and returns a line for the job's message.
  std::string lesionRegionsJob(Engine& e);
  void resetJob();
  /// The state a job ends in, published by the worker once the node is free for the next job.
  void endJob(uint8_t state, const std::string& message);

  // Services and action (breast_sim_node_services.cpp).
  bool loadCaseSrv(breast_sim::LoadCase::Request& req, breast_sim::LoadCase::Response& res);
  bool startPrecomputationSrv(breast_sim::StartPrecomputation::Request& req,
                              breast_sim::StartPrecomputation::Response& res);
  bool cancelSrv(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool resetSrv(std_srvs::Trigger::Request& req, std_srvs::Trigger::Response& res);
  bool saveStateSrv(breast_sim::StateFile::Request& req, breast_sim::StateFile::Response& res);
  bool loadStateSrv(breast_sim::StateFile::Request& req, breast_sim::StateFile::Response& res);
  /// The simulated supine MRI of the current state to a name in ~output_folder (output_folder_'s
  /// rules): resampled outside the engine's lock (the tracking thread goes on), written atomically,
  /// never over a file unless asked.
  bool writeSupineMriSrv(breast_sim::WriteSupineMri::Request& req, breast_sim::WriteSupineMri::Response& res);
  void goalCb(PrecomputeServer::GoalHandle goal);
  void cancelGoalCb(PrecomputeServer::GoalHandle goal);
  /// After the pipeline loaded a state from `file`: the engine is precomputed, tracking restarts
  /// from it, ~state and the model say so (under engine_mutex_).
  void adoptLoadedState(Engine& e, const std::string& file);

  // Checkpoints (breast_sim_node_checkpoints.cpp); all under engine_mutex_.
  /// Sets e.fingerprint (caseFingerprint); on failure 0, with a warning that no checkpoints are kept.
  void fingerprintEngine(Engine& e) const;
  /// Builds e.pipeline (after fingerprintEngine) with the multigrid's coarse levels kept in
  /// ~state_folder for e's fingerprint when they are there and nest; else meshes them and keeps them
  /// there for a restart. A level file that does not read or fit is a warning, not an error.
  void buildPipeline(Engine& e) const;
  /// Writes the engine's state to its checkpoint in ~state_folder, replacing the last one
  /// atomically; false (with a warning) when it cannot.
  bool writeCheckpoint(Engine& e, const char* after);
  /// Loads the newest checkpoint of the engine's case (an older one when the newest does not load);
  /// true when one was loaded.
  bool resumeFromCheckpoint(Engine& e);
  /// Removes the engine's checkpoint (a reset: the node must not come back precomputed).
  void forgetCheckpoint(Engine& e);

  // Tracking (breast_sim_node_tracking.cpp).
  void cloudCb(const sensor_msgs::PointCloud2ConstPtr& msg);
  void trackingLoop();
  void processCloud(const sensor_msgs::PointCloud2ConstPtr& msg, std::chrono::steady_clock::time_point received);
  /// A cloud refused before it reached the tracker (counts toward the monitor's refusals).
  void rejectFrame(const std::string& reason);
  /// The statistics of a refused cloud (diagnostics).
  void countRejected(const std::string& reason);
  /// Forget the tracking reference (a new model or state); the next cloud starts from the model's state.
  void restartTracking();

  // The patient pose, transforms and gravity (breast_sim_node_poses.cpp).
  void poseCb(const geometry_msgs::PoseStampedConstPtr& msg);
  /// model ← cloud frame at `stamp`; false with the reason when unknown or stale.
  bool cloudTransform(const std::string& frame, const ros::Time& stamp, Eigen::Isometry3d* t, std::string* why);
  bool lookup(const std::string& target, const std::string& source, const ros::Time& stamp, Eigen::Isometry3d* t,
              std::string* why);
  /// The patient pose at `stamp` (the model's pose in *frame): interpolated between the accepted poses
  /// around it (at most 2 max_transform_age_s apart), else the nearest within max_age_s [s] of
  /// `stamp`. False without such a pose.
  bool poseAt(const ros::Time& stamp, double max_age_s, Eigen::Isometry3d* frame_from_model, std::string* frame);
  /// Rotation of gravity-frame vectors into the model frame at `stamp` (the cloud's), if known.
  bool gravityRotation(const ros::Time& stamp, Eigen::Matrix3d* r);
  void applyGravity(Engine& e, const ros::Time& stamp);

  // Publishing, state and diagnostics (breast_sim_node_publishing.cpp).
  /// Mesh, lesions (marked `valid` with `status`, with the engine's regions), their tf frames (only
  /// valid ones, only newer stamps), and at the marker rate the markers.
  void publishModel(Engine& e, const ros::Time& stamp, bool force_all, bool valid, const std::string& status);
  void setState(uint8_t state, const std::string& message, bool force = true);
  void publishDiagnostics(const ros::WallTimerEvent&);
  /// Keyed, throttled warning (tracking/warn_throttle_s per key).
  void warn(const std::string& key, const std::string& text);

  ros::NodeHandle nh_, pnh_;
  NodeParams params_;
  std::unique_ptr<ConfinedFolder> data_folder_, state_folder_, output_folder_;
  std::chrono::steady_clock::time_point last_checkpoint_;  ///< under engine_mutex_
  ros::Publisher mesh_pub_, lesions_pub_, lesion_markers_pub_, surface_pub_, sliding_pub_, state_pub_, diag_pub_;
  ros::Subscriber cloud_sub_, pose_sub_;
  std::vector<ros::ServiceServer> services_;
  std::unique_ptr<PrecomputeServer> action_;
  ros::WallTimer diag_timer_;
  tf2_ros::Buffer tf_buffer_;
  std::unique_ptr<tf2_ros::TransformListener> tf_listener_;
  tf2_ros::TransformBroadcaster tf_broadcaster_;

  std::mutex engine_mutex_;
  std::unique_ptr<Engine> engine_;

  // The long-job worker.
  std::mutex job_mutex_;
  std::thread worker_;
  std::atomic<bool> busy_{false};
  std::atomic<bool> cancel_{false};
  std::mutex goal_mutex_;
  std::optional<PrecomputeServer::GoalHandle> goal_;

  // The newest cloud, handed to the tracking thread.
  std::mutex cloud_mutex_;
  std::condition_variable cloud_cv_;
  sensor_msgs::PointCloud2ConstPtr pending_cloud_;
  std::chrono::steady_clock::time_point pending_received_;
  bool stop_ = false;
  std::thread tracking_thread_;
  GuardedTracker guard_;  ///< used under engine_mutex_

  std::mutex pose_mutex_;
  geometry_msgs::PoseStampedConstPtr pose_;  ///< the newest
  /// The poses of the last seconds, so that a cloud is put into the model frame, and gravity taken,
  /// at the cloud's time: a node that lags behind the stream would otherwise use a pose up to
  /// max_transform_age_s newer than the cloud (breathing, a table that moves).
  PoseHistory pose_history_{10.0};
  Eigen::Isometry3d pose_accepted_ = Eigen::Isometry3d::Identity();  ///< the newest accepted pose
  ros::Time last_pose_tf_stamp_;    ///< newest ~patient_pose broadcast on tf (under pose_mutex_)
  ros::Time last_lesion_tf_stamp_;  ///< newest lesion frames broadcast (under engine_mutex_)
  std::atomic<bool> time_went_back_{false};

  std::mutex warn_mutex_;
  KeyedThrottle throttle_;

  // State and statistics.
  std::mutex state_mutex_;
  breast_sim::NodeState state_;
  std::optional<std::pair<uint8_t, std::string>> job_end_;  ///< under state_mutex_
  std::chrono::steady_clock::time_point last_progress_pub_, last_marker_pub_, last_mesh_pub_, last_quality_;
  std::mutex stats_mutex_;
  struct Window {
    int clouds = 0, tracked = 0, rejected = 0, dropped = 0;
    double latency_sum_s = 0, latency_max_s = 0, step_sum_s = 0, field_sum_s = 0, icp_sum_s = 0, filter_sum_s = 0;
    size_t points_in = 0, points_used = 0;
  } window_;
  std::chrono::steady_clock::time_point window_start_;
  long total_tracked_ = 0, total_rejected_ = 0;
  long total_taken_back_ = 0;
  int inverted_elements_ = 0;
  bool lesions_valid_ = false;
  std::string lesion_status_ = "no model";
  std::string region_status_ = "not computed";
  FrameQuality quality_;
  double surface_mean_m_ = -1, surface_p95_m_ = -1, alpha_ = 0, icp_rms_m_ = -1;
  int skin_seen_ = 0, skin_held_ = 0;
  std::chrono::steady_clock::time_point last_tracked_;
  std::string last_reject_;
};

}  // namespace breast_sim::ros_interface
