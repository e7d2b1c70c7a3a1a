// Checks of message stamps and poses before the node acts on them, and the warnings' throttle (see input_checks.h).
#include "breast_sim/ros_interface/input_checks.h"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace breast_sim::ros_interface {

std::string checkStamp(double stamp_s, double now_s, const StampLimits& limits, const std::string& what) {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(3);
  if (!std::isfinite(stamp_s) || stamp_s <= 0) {
    s << what << " has no stamp (header.stamp = " << stamp_s << " s); stamp it with the time it was measured";
    return s.str();
  }
  if (now_s <= 0) return "";
  if (stamp_s - now_s > limits.max_future_s) {
    s << what << " stamped " << stamp_s - now_s << " s ahead of the clock (limit " << limits.max_future_s
      << " s, tracking/max_future_stamp_s); check the sender's clock";
    return s.str();
  }
  if (now_s - stamp_s > limits.max_age_s) {
    s << what << " stamped " << now_s - stamp_s << " s behind the clock (limit " << limits.max_age_s
      << " s, tracking/max_stamp_age_s); a stale measurement or a sender's clock that lags";
    return s.str();
  }
  return "";
}

std::string checkPoseJump(const Eigen::Isometry3d& previous, double previous_stamp_s, const Eigen::Isometry3d& pose,
                          double stamp_s, const PoseJumpLimits& limits) {
  if (std::abs(stamp_s - previous_stamp_s) > limits.window_s) return "";
  const double move = (pose.translation() - previous.translation()).norm();
  const double turn = Eigen::AngleAxisd(previous.linear().transpose() * pose.linear()).angle() * 180.0 / M_PI;
  if (move <= limits.max_jump_m && turn <= limits.max_jump_deg) return "";
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(2);
  s << "patient pose jumped " << 1e3 * move << " mm / " << turn << " deg in " << std::abs(stamp_s - previous_stamp_s)
    << " s (limits " << 1e3 * limits.max_jump_m << " mm / " << limits.max_jump_deg << " deg within " << limits.window_s
    << " s, gravity/max_pose_jump_m, gravity/max_pose_jump_deg)";
  return s.str();
}

void PoseHistory::add(double stamp_s, const Eigen::Isometry3d& pose) {
  auto it = std::lower_bound(poses_.begin(), poses_.end(), stamp_s,
                             [](const std::pair<double, Eigen::Isometry3d>& p, double s) { return p.first < s; });
  if (it != poses_.end() && it->first == stamp_s) it->second = pose;
  else poses_.insert(it, {stamp_s, pose});
  const double oldest = poses_.back().first - span_s_;
  size_t drop = 0;
  while (drop < poses_.size() && poses_[drop].first < oldest) ++drop;
  poses_.erase(poses_.begin(), poses_.begin() + static_cast<std::ptrdiff_t>(drop));
}

bool PoseHistory::at(double stamp_s, double max_gap_s, double max_age_s, Eigen::Isometry3d* pose) const {
  if (poses_.empty()) return false;
  auto after = std::lower_bound(poses_.begin(), poses_.end(), stamp_s,
                                [](const std::pair<double, Eigen::Isometry3d>& p, double s) { return p.first < s; });
  if (after != poses_.end() && after->first == stamp_s) {
    *pose = after->second;
    return true;
  }
  if (after != poses_.begin() && after != poses_.end()) {
    const auto before = after - 1;
    const double gap = after->first - before->first;
    if (gap <= max_gap_s) {
      const double w = (stamp_s - before->first) / gap;
      const Eigen::Quaterniond qa(before->second.linear()), qb(after->second.linear());
      *pose = Eigen::Isometry3d::Identity();
      pose->linear() = qa.slerp(w, qb).toRotationMatrix();
      pose->translation() = (1 - w) * before->second.translation() + w * after->second.translation();
      return true;
    }
  }
  // The nearest pose, if close enough in time.
  const auto nearest = (after == poses_.end()) ? poses_.end() - 1
                       : (after == poses_.begin()) ? after
                       : (stamp_s - (after - 1)->first <= after->first - stamp_s ? after - 1 : after);
  if (std::abs(nearest->first - stamp_s) > max_age_s) return false;
  *pose = nearest->second;
  return true;
}

bool KeyedThrottle::allow(const std::string& key, double now_s) {
  auto it = entries_.find(key);
  if (it == entries_.end()) {
    entries_[key] = Entry{now_s, 0};
    return true;
  }
  if (now_s - it->second.last_s >= period_s_) {
    it->second.last_s = now_s;
    it->second.suppressed = 0;
    return true;
  }
  ++it->second.suppressed;
  return false;
}

long KeyedThrottle::suppressed(const std::string& key) const {
  const auto it = entries_.find(key);
  return it == entries_.end() ? 0 : it->second.suppressed;
}

}  // namespace breast_sim::ros_interface
