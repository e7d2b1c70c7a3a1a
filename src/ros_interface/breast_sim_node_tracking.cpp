// BreastSimNode's tracking: ~surface_points hands the newest cloud to the tracking thread, which
// checks it, puts it into the model frame, tracks it under the monitor and publishes the result;
// a cloud refused on the way counts toward the monitor's refusals.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <algorithm>

#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;
using node_util::seconds;

void BreastSimNode::cloudCb(const sensor_msgs::PointCloud2ConstPtr& msg) {
  {
    std::lock_guard<std::mutex> lock(cloud_mutex_);
    if (pending_cloud_) {
      std::lock_guard<std::mutex> sl(stats_mutex_);
      ++window_.dropped;  // the tracking thread had not taken the previous one: newest wins
    }
    pending_cloud_ = msg;
    pending_received_ = Clock::now();
  }
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    ++window_.clouds;
  }
  cloud_cv_.notify_one();
}

void BreastSimNode::restartTracking() {
  guard_.stop();
  last_lesion_tf_stamp_ = ros::Time();
}

void BreastSimNode::countRejected(const std::string& reason) {
  std::lock_guard<std::mutex> sl(stats_mutex_);
  ++window_.rejected;
  ++total_rejected_;
  last_reject_ = reason;
}

void BreastSimNode::rejectFrame(const std::string& reason) {
  countRejected(reason);
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_ || !engine_->precomputed) return;
  const bool was_valid = guard_.valid();
  guard_.refused(reason);
  if (was_valid && !guard_.valid()) {
    // The lesions last published were valid; say at once that they no longer are.
    publishModel(*engine_, ros::Time::now(), false, false, guard_.reason());
    setState(breast_sim::NodeState::DEGRADED, guard_.reason() + "; the model keeps its last good state and the "
             "lesions are not valid until tracking recovers");
  }
}

void BreastSimNode::trackingLoop() {
  while (true) {
    sensor_msgs::PointCloud2ConstPtr msg;
    Clock::time_point received;
    {
      std::unique_lock<std::mutex> lock(cloud_mutex_);
      cloud_cv_.wait(lock, [this] { return stop_ || pending_cloud_; });
      if (stop_) return;
      msg = pending_cloud_;
      received = pending_received_;
      pending_cloud_.reset();
    }
    try {
      processCloud(msg, received);
    } catch (const std::exception& ex) {
      // Nothing a cloud holds may stop the node: report and go on with the next one.
      warn("cloud exception", std::string("breast_sim: a cloud could not be tracked: ") + ex.what() +
                                  "; the model keeps its last good state, the next cloud is tried");
      rejectFrame(ex.what());
    }
  }
}

void BreastSimNode::processCloud(const sensor_msgs::PointCloud2ConstPtr& msg, Clock::time_point received) {
  if (busy_) {
    ROS_INFO_STREAM_THROTTLE(params_.warn_throttle_s,
                             "breast_sim: a job (loading, precomputing, reset) runs; clouds are ignored until it ends");
    return;
  }
  // 0. When it was measured: a future stamp would be re-broadcast with the lesion frames and break
  // every tf2 listener; a stale one no longer shows the patient.
  const std::string stamp_why = checkStamp(msg->header.stamp.toSec(), ros::Time::now().toSec(), params_.stamps, "cloud");
  if (!stamp_why.empty()) {
    warn("cloud stamp", "breast_sim: cloud on ~surface_points refused: " + stamp_why + "; the model keeps its last state");
    rejectFrame(stamp_why);
    return;
  }
  // 1. Points, in the cloud's frame.
  CloudPoints cp;
  try {
    cp = pointsFromCloud(*msg, params_.max_cloud_points);
  } catch (const std::invalid_argument& ex) {
    warn("cloud malformed", std::string("breast_sim: malformed cloud on ~surface_points: ") + ex.what() +
                                "; it is dropped and the model keeps its last state");
    rejectFrame(ex.what());
    return;
  }
  if (cp.total == 0) {
    warn("cloud empty", "breast_sim: empty cloud on ~surface_points; it is dropped and the model keeps its last state");
    rejectFrame("empty cloud");
    return;
  }
  if (cp.stride > 1)
    warn("cloud large", "breast_sim: cloud of " + std::to_string(cp.total) + " points, more than tracking/max_cloud_points = " +
                            std::to_string(params_.max_cloud_points) + "; every " + std::to_string(cp.stride) +
                            "th point is used");
  if (cp.non_finite > 0 && cp.points_m.rows() < params_.tracker.min_points) {
    warn("cloud non-finite", "breast_sim: " + std::to_string(cp.non_finite) + " of " + std::to_string(cp.total) +
                                 " cloud points are NaN/inf, too few remain; the cloud is dropped and the model keeps "
                                 "its last state");
    rejectFrame("cloud of non-finite points");
    return;
  }
  // (Finite points among NaN padding, as an organized depth image has them, are tracked as they are.)
  // 2. Into the model frame.
  Eigen::Isometry3d model_from_cloud;
  std::string why;
  if (!cloudTransform(msg->header.frame_id, msg->header.stamp, &model_from_cloud, &why)) {
    warn("cloud transform " + msg->header.frame_id,
         "breast_sim: cloud in frame '" + msg->header.frame_id + "' cannot be put into '" + params_.frame_id + "': " + why +
             "; it is dropped and the model keeps its last state");
    rejectFrame(why);
    return;
  }
  const core::Points cloud = transformPoints(model_from_cloud, cp.points_m);

  // 3. Track, guarded by the monitor.
  std::unique_lock<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    ROS_WARN_STREAM_THROTTLE(params_.warn_throttle_s, "breast_sim: no model is loaded; clouds are ignored until a case loads (~load_case)");
    return;
  }
  Engine& e = *engine_;
  if (params_.require_precomputation && !e.precomputed) {
    ROS_WARN_STREAM_THROTTLE(params_.warn_throttle_s, "breast_sim: the model is not precomputed; clouds are ignored until "
                             "~start_precomputation (or ~load_state) has run");
    return;
  }
  applyGravity(e, msg->header.stamp);
  const bool was_valid = guard_.valid();
  const GuardedFrame f = guard_.frame(*e.pipeline, cloud);
  e.gravity_load_mps2 = e.pipeline->gravityLoad();  // a frame taken back restores the load it had
  if (!f.track.tracked) {
    lock.unlock();
    warn("cloud refused", "breast_sim: cloud refused: " + f.track.reason + "; the model keeps its last state");
    countRejected(f.track.reason);
    if (was_valid && !f.valid) {
      std::lock_guard<std::mutex> relock(engine_mutex_);
      if (engine_) publishModel(*engine_, ros::Time::now(), false, false, f.status);
      setState(breast_sim::NodeState::DEGRADED, f.status + "; the model keeps its last good state and the lesions are "
               "not valid until tracking recovers");
    }
    return;
  }
  if (f.restored)
    warn("monitor " + std::to_string(static_cast<int>(f.verdict.recovery)),
         "breast_sim: tracking frame past a limit: " + f.verdict.reason + "; " +
             (f.verdict.recovery == Recovery::kReference ? "the model is back at its precomputed state"
                                                          : "the frame was taken back") +
             ", the lesions are not valid until " + std::to_string(params_.monitor.recover_frames) +
             " good frames in a row");
  // 4. Publish (header stamp = the cloud's, so consumers can match them).
  publishModel(e, msg->header.stamp, false, f.valid, f.status);
  const double latency = seconds(Clock::now() - received);
  // A frame the monitor vouches for is a state to resume from (after the latency is taken: the
  // lesions are out before the checkpoint is written).
  if (f.valid && params_.checkpoint_period_s > 0 && seconds(Clock::now() - last_checkpoint_) >= params_.checkpoint_period_s)
    writeCheckpoint(e, "tracking");
  const auto now = Clock::now();
  inverted_elements_ = f.quality.inverted_elements;
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    ++window_.tracked;
    ++total_tracked_;
    if (f.restored) ++total_taken_back_;
    window_.latency_sum_s += latency;
    window_.latency_max_s = std::max(window_.latency_max_s, latency);
    window_.step_sum_s += f.track.iterate_s;
    window_.field_sum_s += f.track.field_s;
    window_.icp_sum_s += f.track.icp_s;
    window_.filter_sum_s += f.track.filter_s;
    window_.points_in += f.track.points_in;
    window_.points_used += f.track.points_used;
    surface_mean_m_ = f.track.seen_mean_m;
    surface_p95_m_ = f.track.seen_p95_m;
    alpha_ = f.track.last.alpha_per_pa;
    icp_rms_m_ = f.track.icp_rms_m;
    skin_seen_ = f.track.skin_seen;
    skin_held_ = f.track.skin_held;
    quality_ = f.quality;
    lesions_valid_ = f.valid;
    lesion_status_ = f.status;
    last_tracked_ = now;
  }
  lock.unlock();
  if (f.valid) setState(breast_sim::NodeState::TRACKING, "tracking: " + f.status, false);
  else setState(breast_sim::NodeState::DEGRADED, f.status + "; the lesions are not valid", false);
}

}  // namespace breast_sim::ros_interface
