#pragma once
/// @file input_checks.h
/// Checks the node applies to a message before it acts on it (pure functions, times in seconds), and
/// a throttle for its warnings. Each check returns "" when the input is acceptable, else the reason,
/// naming the value and the limit.
///
/// Why: one patient pose with a flipped orientation, or one stamped an hour ahead, used to turn the
/// model (and gravity) by 180° or, re-broadcast on tf, made every tf2 listener drop the transforms
/// that followed it.

#include <map>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

namespace breast_sim::ros_interface {

/// How far a message stamp may lie from the receiver's clock (tracking/max_future_stamp_s,
/// tracking/max_stamp_age_s).
struct StampLimits {
  double max_future_s = 0.5;  ///< a stamp further ahead of the clock is refused [s]
  double max_age_s = 2.0;     ///< a stamp further behind the clock is refused [s]
};

/// `what` ("cloud", "patient pose") at `stamp_s` received when the clock reads `now_s` [s]. A stamp of
/// 0 (unset) is refused; with `now_s` = 0 (a simulated clock that has not started) only that is
/// checked.
std::string checkStamp(double stamp_s, double now_s, const StampLimits& limits, const std::string& what);

/// How far the patient pose may move between two poses (gravity/max_pose_jump_m, _deg, _window_s).
struct PoseJumpLimits {
  double max_jump_m = 0.02;     ///< translation [m]
  double max_jump_deg = 5.0;    ///< rotation [deg]
  /// Only a pose within this time of the last accepted one is compared with it [s]: after a longer
  /// gap (a reposition, a tracker that lost the patient) the new pose is taken as it is.
  double window_s = 0.5;
};

/// A pose at `stamp_s` against the last accepted one at `previous_stamp_s` [s].
std::string checkPoseJump(const Eigen::Isometry3d& previous, double previous_stamp_s, const Eigen::Isometry3d& pose,
                          double stamp_s, const PoseJumpLimits& limits);

/// The accepted patient poses of the last seconds, for the pose at a cloud's stamp. Interpolates
/// (linear translation, slerp rotation) only between two poses at most `max_gap_s` apart: across a
/// longer gap (a tracker that lost the patient) nothing is known in between, where tf2::BufferCore
/// would interpolate across any gap within its cache.
class PoseHistory {
 public:
  explicit PoseHistory(double span_s = 10.0) : span_s_(span_s) {}
  /// Adds a pose at `stamp_s` [s]; one at a stamp already held replaces it; poses older than the
  /// newest by more than the span are forgotten.
  void add(double stamp_s, const Eigen::Isometry3d& pose);
  void clear() { poses_.clear(); }
  bool empty() const { return poses_.empty(); }
  double newestStamp() const { return poses_.empty() ? 0.0 : poses_.back().first; }
  const Eigen::Isometry3d& newest() const { return poses_.back().second; }
  /// The pose at `stamp_s`: interpolated between its neighbours when they are at most `max_gap_s`
  /// apart, else the nearest pose when it is within `max_age_s` of the stamp; false without either.
  bool at(double stamp_s, double max_gap_s, double max_age_s, Eigen::Isometry3d* pose) const;

 private:
  double span_s_;
  std::vector<std::pair<double, Eigen::Isometry3d>> poses_;  ///< by increasing stamp
};

/// One warning per key and period: a stream of the same bad input is logged once per period, each
/// distinct kind of bad input (its key) on its own.
class KeyedThrottle {
 public:
  explicit KeyedThrottle(double period_s = 5.0) : period_s_(period_s) {}
  /// Whether a warning of `key` may be logged at `now_s` [s] (monotonic); records it when so.
  bool allow(const std::string& key, double now_s);
  /// How many warnings of `key` were held back since it was last allowed.
  long suppressed(const std::string& key) const;
  void setPeriod(double period_s) { period_s_ = period_s; }

 private:
  struct Entry {
    double last_s = 0;
    long suppressed = 0;
  };
  double period_s_;
  std::map<std::string, Entry> entries_;
};

}  // namespace breast_sim::ros_interface
