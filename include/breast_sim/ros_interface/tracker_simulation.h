#pragma once
/// @file tracker_simulation.h
/// A simulated surgical tracker for the phantom, for the recorded test bags, the rviz demo and the
/// latency benchmark: the supine target skin as a tracked surface scanner sees it (the anterior part,
/// area-uniform samples, Gaussian noise, a share of stray outliers, a small breathing motion) and the
/// patient's pose on a table that tilts slowly. Deterministic for a given seed.
///
/// Frames (REP 103/105): `world` is gravity-aligned (z up); the model frame (prone image patient
/// space, LPS) lies supine on the table: model y (posterior) points down, model z (superior) along
/// world x; the table rolls about its long axis by tilt(t), which in the model frame gives gravity
/// g·(sin tilt, cos tilt, 0), the phantom's supine gravity at the mean tilt. The scanner frame
/// `tracker` hangs above the table looking down.

#include <random>
#include <vector>
#include <string>

#include <Eigen/Geometry>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracking_monitor.h"

namespace breast_sim::ros_interface {

struct TrackerSimulationOptions {
  int points = 2500;                 ///< points per cloud (before noise outliers are added)
  double noise_m = 0.5e-3;           ///< isotropic Gaussian noise σ [m]
  double outlier_fraction = 0.01;    ///< share of points replaced by stray returns near the breast
  double breathing_amplitude_m = 1e-3;  ///< anterior skin motion at the apex [m], zero at the wall
  double breathing_period_s = 4.0;
  double tilt_amplitude_deg = 2.0;   ///< table roll around the mean tilt [deg]
  double tilt_period_s = 8.0;
  double sway_amplitude_m = 2e-3;    ///< vertical table motion [m]
  double sway_period_s = 5.0;
  unsigned seed = 1;
};

class TrackerSimulation {
 public:
  /// @param model_case a phantom case (its supine surface and gravity tilt are used)
  /// @throws std::invalid_argument when the case is not the software phantom.
  TrackerSimulation(const core::ModelCase& model_case, const TrackerSimulationOptions& options = {});

  /// Pose of the model frame in `world` at time t [s].
  Eigen::Isometry3d worldFromModel(double t_s) const;
  /// Pose of the scanner frame `tracker` in `world` (fixed).
  Eigen::Isometry3d worldFromTracker() const;
  /// The cloud at time t in the model frame [m] (noise and outliers drawn from the generator).
  core::Points cloudInModel(double t_s);
  /// The same cloud in the scanner frame [m].
  core::Points cloudInTracker(double t_s);
  /// The cloud as a node gets it from a recording (make_test_bags): in the scanner frame in single
  /// precision (PointCloud2 FLOAT32), put into the model frame with the pose at time t [m]. Offline
  /// references of the node use it: tracking can tell the ~10 nm of the rounding apart.
  core::Points cloudAsRecordedInModel(double t_s);
  /// The visible (anterior-facing) supine skin triangles that are sampled.
  const core::TargetSurface& visibleSkin() const { return skin_; }

 private:
  TrackerSimulationOptions options_;
  core::TargetSurface skin_;
  std::vector<double> cumulative_area_;
  double depth_m_ = 0.0;  // anterior extent of the supine skin (−y) [m]
  double mean_tilt_rad_ = 0.0;
  Eigen::AlignedBox3d box_;
  std::mt19937 rng_;
};

/// Scans of a given skin surface, as a scanner above a supine patient sees it: the skin triangles
/// facing anterior (−y in the model frame, normal within 78° of it) sampled uniformly by area, with
/// Gaussian noise; breathing lifts the anterior skin (zero at the wall, full at the apex). For tests
/// and studies whose truth is the skin itself (tracking the model's own precomputed skin).
class SkinScanner {
 public:
  /// @param positions_m  #N×3 node positions [m]; @param triangles  skin triangles (outward) into them
  /// @throws std::invalid_argument when no triangle faces anterior.
  SkinScanner(const core::Points& positions_m, const core::Triangles& triangles, unsigned seed = 1);
  /// `points` samples [m], the anterior skin lifted by `breath_m` at the apex, the whole scan moved by
  /// `shift_m`, noise of σ `noise_m`.
  core::Points scan(int points, double breath_m, const Eigen::Vector3d& shift_m, double noise_m);

 private:
  core::Points x_;
  std::vector<Eigen::Vector3i> triangles_;
  std::vector<double> cumulative_area_;
  double depth_m_ = 0.0;
  std::mt19937 rng_;
};

/// What an offline tracking run of a recording did.
struct OfflineTrackingRun {
  std::vector<core::Points> lesions_m;  ///< after each cloud [m] (after a skipped one, those before it)
  std::vector<char> valid;              ///< per cloud: the monitor vouched for the lesions after it
  int reverted_frames = 0;              ///< tracked clouds whose step reverted at least once
  int reversals = 0;                    ///< time-step reversals in all
  int taken_back = 0;                   ///< frames the monitor took back
};

/// The clouds of a recording (make_test_bags: TrackerSimulation with `sim`'s options, `clouds` clouds
/// at `cloud_rate_hz` from t = 0) tracked offline as the node tracks them, without ROS in between:
/// from the state `start`, for each cloud k with tracked[k] the gravity load of the table's pose at
/// the cloud's time (gravityLoadChanged, `gravity_update_threshold_deg`), then the GuardedTracker
/// with `options` and `limits` on the cloud as recorded (cloudAsRecordedInModel). Every cloud is drawn, tracked
/// or not: the noise comes from one random stream. The navigation rostest's reference and
/// bench_tracking_drops.
/// @throws std::invalid_argument when `tracked` does not hold `clouds` entries.
OfflineTrackingRun trackRecordingOffline(core::ProneToSupinePipeline& pipeline, const core::PipelineState& start,
                                         const core::ModelCase& model_case, const TrackerOptions& options,
                                         const MonitorLimits& limits, double gravity_update_threshold_deg, int clouds,
                                         double cloud_rate_hz, const std::vector<bool>& tracked,
                                         const TrackerSimulationOptions& sim = {});

}  // namespace breast_sim::ros_interface
