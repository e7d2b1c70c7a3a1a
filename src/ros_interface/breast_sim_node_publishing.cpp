// What BreastSimNode publishes: the model (mesh, lesions, their tf frames, markers, sliding
// vectors), its state on ~state, the diagnostics on /diagnostics, and its throttled warnings.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <algorithm>
#include <sstream>

#include <diagnostic_msgs/DiagnosticArray.h>

#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;
using node_util::seconds;

namespace {

const char* stateName(uint8_t s) {
  switch (s) {
    case breast_sim::NodeState::IDLE: return "idle";
    case breast_sim::NodeState::LOADING: return "loading";
    case breast_sim::NodeState::PRECOMPUTING: return "precomputing";
    case breast_sim::NodeState::TRACKING: return "tracking";
    case breast_sim::NodeState::DEGRADED: return "degraded";
  }
  return "unknown";
}

}  // namespace

void BreastSimNode::publishModel(Engine& e, const ros::Time& stamp, bool force_all, bool valid,
                                 const std::string& status) {
  const auto now = Clock::now();
  const core::Points x = e.pipeline->positions();
  const core::Points lesions = e.model->lesion_embedding.positions(x);
  if (force_all || params_.mesh_rate_hz <= 0 || seconds(now - last_mesh_pub_) >= 1.0 / params_.mesh_rate_hz) {
    last_mesh_pub_ = now;
    mesh_pub_.publish(toMessage(e.model->mesh, x - e.model->mesh.nodes(), params_.frame_id, stamp));
  }
  const std::vector<core::LesionRegion>* regions = e.regions.empty() ? nullptr : &e.regions;
  lesions_pub_.publish(lesionsMessage(e.model->lesions, lesions, params_.frame_id, stamp, valid, status, regions));
  if (time_went_back_.exchange(false)) last_lesion_tf_stamp_ = ros::Time();
  // Frames only for lesions the node vouches for, and only newer stamps (a tf2 listener drops a
  // frame older than the newest it holds and warns about one at the same stamp).
  if (params_.publish_lesion_tf && valid && !e.model->lesions.empty() && stamp > last_lesion_tf_stamp_) {
    last_lesion_tf_stamp_ = stamp;
    tf_broadcaster_.sendTransform(lesionTransforms(e.model->lesions, lesions, params_.frame_id,
                                                   params_.lesion_frame_prefix, stamp));
  }
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    lesions_valid_ = valid;
    lesion_status_ = status;
    region_status_ = e.region_status;
  }
  if (force_all || seconds(now - last_marker_pub_) >= 1.0 / params_.marker_rate_hz) {
    last_marker_pub_ = now;
    surface_pub_.publish(surfaceMarker(e.display, x, params_.frame_id, stamp));
    lesion_markers_pub_.publish(lesionMarkers(e.model->lesions, lesions, params_.frame_id, stamp, regions));
    if (e.pipeline->sliding())
      sliding_pub_.publish(slidingMarkers(x, e.pipeline->slidingVectors(), e.wall_nodes, params_.sliding_arrow_scale,
                                          params_.sliding_min_length_m, params_.sliding_max_arrows, params_.frame_id,
                                          stamp));
    else if (force_all)
      sliding_pub_.publish(slidingMarkers(x, core::Points::Zero(x.rows(), 3), {}, 1.0, 1.0, 0, params_.frame_id, stamp));
  }
}

void BreastSimNode::setState(uint8_t state, const std::string& message, bool force) {
  std::lock_guard<std::mutex> sl(state_mutex_);
  const bool changed = state_.state != state || state_.state_name.empty();
  state_.state = state;
  state_.state_name = stateName(state);
  state_.message = message;
  const auto now = Clock::now();
  // Tracking updates come per frame: republish on a change or at the progress rate.
  if (force || changed || seconds(now - last_progress_pub_) >= 1.0 / params_.progress_rate_hz) {
    if (!force) last_progress_pub_ = now;
    state_.header.stamp = ros::Time::now();
    state_pub_.publish(state_);
  }
}

void BreastSimNode::publishDiagnostics(const ros::WallTimerEvent&) {
  Window w;
  double window_s;
  long total_tracked, total_rejected;
  double mean_m, p95_m, alpha, icp_rms;
  Clock::time_point last_tracked;
  std::string last_reject, lesion_status, region_status;
  FrameQuality quality;
  bool lesions_valid;
  long taken_back;
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    quality = quality_;
    lesions_valid = lesions_valid_;
    lesion_status = lesion_status_;
    region_status = region_status_;
    taken_back = total_taken_back_;
    w = window_;
    window_ = Window();
    const auto now = Clock::now();
    window_s = std::max(1e-9, seconds(now - window_start_));
    window_start_ = now;
    total_tracked = total_tracked_;
    total_rejected = total_rejected_;
    mean_m = surface_mean_m_;
    p95_m = surface_p95_m_;
    alpha = alpha_;
    icp_rms = icp_rms_m_;
    last_tracked = last_tracked_;
    last_reject = last_reject_;
  }
  // No clouds for a while: back to idle.
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    // (A degraded state stays: its reason must stay visible until tracking recovers.)
    if (state_.state == breast_sim::NodeState::TRACKING && w.clouds == 0 &&
        seconds(Clock::now() - last_tracked) > params_.tracking_timeout_s) {
      state_.state = breast_sim::NodeState::IDLE;
      state_.state_name = stateName(state_.state);
      state_.message = "no surface cloud for " + std::to_string(params_.tracking_timeout_s) +
                       " s; the model holds its last state and tracking resumes with the next cloud";
      state_.header.stamp = ros::Time::now();
      state_pub_.publish(state_);
    }
  }
  breast_sim::NodeState st;
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    st = state_;
  }
  diagnostic_msgs::DiagnosticStatus s;
  s.name = ros::this_node::getName() + ": navigation";
  s.hardware_id = st.case_name.empty() ? "breast_sim" : st.case_name;
  // ERROR: the node cannot vouch for its lesions; WARN: tracking, but clouds were refused or a frame
  // taken back in this window.
  s.level = st.state == breast_sim::NodeState::DEGRADED ? diagnostic_msgs::DiagnosticStatus::ERROR
            : (st.state == breast_sim::NodeState::TRACKING && w.rejected > 0) ? diagnostic_msgs::DiagnosticStatus::WARN
                                                                             : diagnostic_msgs::DiagnosticStatus::OK;
  if (!st.model_loaded && st.state != breast_sim::NodeState::LOADING) s.level = diagnostic_msgs::DiagnosticStatus::ERROR;
  s.message = st.state_name + ": " + st.message;
  auto kv = [&s](const std::string& k, const std::string& v) {
    diagnostic_msgs::KeyValue x;
    x.key = k;
    x.value = v;
    s.values.push_back(x);
  };
  auto num = [](double v, int precision = 3) {
    std::ostringstream o;
    o.setf(std::ios::fixed);
    o.precision(precision);
    o << v;
    return o.str();
  };
  const double n = std::max(1, w.tracked);
  kv("state", st.state_name);
  kv("lesions valid", lesions_valid ? "true" : "false");
  kv("lesion status", lesion_status);
  kv("lesion regions", region_status);
  kv("precomputed", st.precomputed ? "true" : "false");
  kv("cloud rate in [Hz]", num(w.clouds / window_s, 2));
  kv("tracked rate [Hz]", num(w.tracked / window_s, 2));
  kv("clouds dropped (newest wins) in window", std::to_string(w.dropped));
  kv("clouds rejected in window", std::to_string(w.rejected));
  kv("clouds tracked total", std::to_string(total_tracked));
  kv("clouds rejected total", std::to_string(total_rejected));
  kv("last rejection", last_reject);
  kv("latency mean [ms]", w.tracked ? num(1e3 * w.latency_sum_s / n, 2) : "-");
  kv("latency max [ms]", w.tracked ? num(1e3 * w.latency_max_s, 2) : "-");
  kv("step time mean [ms]", w.tracked ? num(1e3 * w.step_sum_s / n, 2) : "-");
  kv("field build mean [ms]", w.tracked ? num(1e3 * w.field_sum_s / n, 2) : "-");
  kv("icp mean [ms]", w.tracked ? num(1e3 * w.icp_sum_s / n, 2) : "-");
  kv("cloud filter mean [ms]", w.tracked ? num(1e3 * w.filter_sum_s / n, 2) : "-");
  kv("points in mean", w.tracked ? num(w.points_in / n, 0) : "-");
  kv("points used mean", w.tracked ? num(w.points_used / n, 0) : "-");
  kv("inverted elements", std::to_string(inverted_elements_));
  // The seen skin's distance to the last tracked cloud before its step (along the skin normal).
  kv("seen skin to cloud mean [mm]", mean_m >= 0 ? num(1e3 * mean_m) : "-");
  kv("seen skin to cloud p95 [mm]", p95_m >= 0 ? num(1e3 * p95_m) : "-");
  kv("seen skin share", num(quality.seen_fraction, 3));
  kv("chest wall drift from precomputed [mm]", num(1e3 * quality.wall_drift_m));
  kv("model drift from precomputed [mm]", num(1e3 * quality.rigid_drift_m));
  kv("lesion offset from precomputed [mm]", num(1e3 * quality.lesion_offset_m));
  kv("lesion move in the last frame [mm]", num(1e3 * quality.lesion_jump_m));
  kv("frames taken back total", std::to_string(taken_back));
  kv("icp rms [mm]", icp_rms >= 0 ? num(1e3 * icp_rms) : "-");
  kv("skin vertices seen / held", std::to_string(skin_seen_) + " / " + std::to_string(skin_held_));
  kv("alpha [1/Pa]", num(alpha, 6));
  diagnostic_msgs::DiagnosticArray a;
  a.header.stamp = ros::Time::now();
  a.status.push_back(s);
  diag_pub_.publish(a);
}

void BreastSimNode::warn(const std::string& key, const std::string& text) {
  long suppressed;
  {
    std::lock_guard<std::mutex> lock(warn_mutex_);
    suppressed = throttle_.suppressed(key);
    if (!throttle_.allow(key, ros::WallTime::now().toSec())) return;
  }
  if (suppressed > 0) ROS_WARN_STREAM(text << " (" << suppressed << " more like it in the last " << params_.warn_throttle_s << " s)");
  else ROS_WARN_STREAM(text);
}

}  // namespace breast_sim::ros_interface
