// BreastSimNode's patient pose and transforms: ~patient_pose is checked (stamp, value, frame,
// jump) and kept with its history; a cloud is put into the model frame, and gravity into the model
// frame, at the cloud's time from those poses or from tf2.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <cmath>
#include <limits>
#include <sstream>

#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;

void BreastSimNode::poseCb(const geometry_msgs::PoseStampedConstPtr& msg) {
  const std::string stamp_why =
      checkStamp(msg->header.stamp.toSec(), ros::Time::now().toSec(), params_.stamps, "~patient_pose");
  if (!stamp_why.empty()) {
    warn("pose stamp", "breast_sim: ~patient_pose refused: " + stamp_why + "; gravity and transforms keep their last values");
    return;
  }
  Eigen::Isometry3d t;
  try {
    t = isometryFromPose(msg->pose);  // refuses non-finite values and quaternions not of unit length
  } catch (const std::exception& ex) {
    warn("pose value", std::string("breast_sim: ~patient_pose refused: ") + ex.what() +
                           "; gravity and transforms keep their last values");
    return;
  }
  if (msg->header.frame_id.empty() || msg->header.frame_id == params_.frame_id) {
    warn("pose frame", "breast_sim: ~patient_pose must give the pose of '" + params_.frame_id +
                           "' in another frame (header.frame_id = '" + msg->header.frame_id +
                           "'); refused, gravity and transforms keep their last values");
    return;
  }
  geometry_msgs::TransformStamped ts;
  ts.header = msg->header;
  ts.child_frame_id = params_.frame_id;
  ts.transform = transformFromIsometry(t);
  const double stamp = msg->header.stamp.toSec();
  bool broadcast = false;
  {
    std::lock_guard<std::mutex> lock(pose_mutex_);
    // Time went back (a bag played again, a simulator restarted), or another frame: the kept poses
    // are of another run.
    if (pose_ && (msg->header.stamp + ros::Duration(1.0) < pose_->header.stamp ||
                  msg->header.frame_id != pose_->header.frame_id)) {
      pose_history_.clear();
      pose_.reset();
      last_pose_tf_stamp_ = ros::Time();
      time_went_back_ = true;  // publishModel forgets its newest lesion stamp too
    }
    // A jump is measured from the last accepted pose, or, without one close in time, from the pose
    // tf2 has for the model frame (another source of the same pose: they must agree).
    Eigen::Isometry3d reference;
    double reference_stamp = 0;
    bool have_reference = false;
    if (pose_ && std::abs(stamp - pose_->header.stamp.toSec()) <= params_.pose_jump.window_s) {
      reference = pose_accepted_;
      reference_stamp = pose_->header.stamp.toSec();
      have_reference = true;
    } else {
      for (const ros::Time& at : {msg->header.stamp, ros::Time(0)}) {
        if (!tf_buffer_.canTransform(msg->header.frame_id, params_.frame_id, at)) continue;
        const geometry_msgs::TransformStamped tf = tf_buffer_.lookupTransform(msg->header.frame_id, params_.frame_id, at);
        reference = isometryFromTransform(tf.transform);
        reference_stamp = tf.header.stamp.isZero() ? stamp : tf.header.stamp.toSec();
        have_reference = true;
        break;
      }
    }
    if (have_reference) {
      const std::string jump = checkPoseJump(reference, reference_stamp, t, stamp, params_.pose_jump);
      if (!jump.empty()) {
        warn("pose jump", "breast_sim: ~patient_pose refused: " + jump + "; gravity and transforms keep their last values");
        return;
      }
    }
    pose_history_.add(stamp, t);
    if (!pose_ || msg->header.stamp >= pose_->header.stamp) {
      pose_ = msg;
      pose_accepted_ = t;
    }
    // Every tf2 listener drops data older than what it has: broadcast only newer stamps.
    if (params_.publish_pose_tf && msg->header.stamp > last_pose_tf_stamp_) {
      last_pose_tf_stamp_ = msg->header.stamp;
      broadcast = true;
    }
  }
  if (broadcast) tf_broadcaster_.sendTransform(ts);
}

bool BreastSimNode::lookup(const std::string& target, const std::string& source, const ros::Time& stamp,
                           Eigen::Isometry3d* t, std::string* why) {
  std::string err;
  const auto deadline = Clock::now() + std::chrono::duration<double>(params_.tf_wait_s);
  while (true) {
    err.clear();  // tf2 appends its reason to the string on every failed call
    if (tf_buffer_.canTransform(target, source, stamp, &err)) {
      *t = isometryFromTransform(tf_buffer_.lookupTransform(target, source, stamp).transform);
      return true;
    }
    if (Clock::now() >= deadline) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  // Not at the cloud's time: the newest transform, if recent enough (or static).
  std::string err0;
  if (tf_buffer_.canTransform(target, source, ros::Time(0), &err0)) {
    const geometry_msgs::TransformStamped latest = tf_buffer_.lookupTransform(target, source, ros::Time(0));
    const double age = std::abs((stamp - latest.header.stamp).toSec());
    if (latest.header.stamp.isZero() || age <= params_.max_transform_age_s) {
      *t = isometryFromTransform(latest.transform);
      return true;
    }
    std::ostringstream s;
    s << "stale transform '" << source << "' -> '" << target << "': the newest is " << age
      << " s away from the cloud's stamp (tracking/max_transform_age_s = " << params_.max_transform_age_s << " s)";
    *why = s.str();
    return false;
  }
  *why = "no transform '" + source + "' -> '" + target + "' (" + (err.empty() ? err0 : err) + ")";
  return false;
}

bool BreastSimNode::cloudTransform(const std::string& frame, const ros::Time& stamp, Eigen::Isometry3d* t,
                                   std::string* why) {
  if (frame.empty()) {
    *why = "the cloud has no header.frame_id";
    return false;
  }
  if (frame == params_.frame_id) {
    *t = Eigen::Isometry3d::Identity();
    return true;
  }
  Eigen::Isometry3d pose_frame_from_model;
  std::string pose_frame;
  if (poseAt(stamp, params_.max_transform_age_s, &pose_frame_from_model, &pose_frame)) {
    const Eigen::Isometry3d model_from_pose_frame = pose_frame_from_model.inverse();
    if (frame == pose_frame) {
      *t = model_from_pose_frame;
      return true;
    }
    Eigen::Isometry3d pose_from_cloud;
    if (lookup(pose_frame, frame, stamp, &pose_from_cloud, why)) {
      *t = model_from_pose_frame * pose_from_cloud;
      return true;
    }
    return false;
  }
  return lookup(params_.frame_id, frame, stamp, t, why);
}

bool BreastSimNode::poseAt(const ros::Time& stamp, double max_age_s, Eigen::Isometry3d* frame_from_model,
                           std::string* frame) {
  std::lock_guard<std::mutex> lock(pose_mutex_);
  if (!pose_) return false;
  *frame = pose_->header.frame_id;
  // Between two poses at most twice the allowed age apart, else the nearest within the age.
  return pose_history_.at(stamp.toSec(), 2 * params_.max_transform_age_s, max_age_s, frame_from_model);
}

bool BreastSimNode::gravityRotation(const ros::Time& stamp, Eigen::Matrix3d* r) {
  if (!params_.follow_patient_pose) return false;
  Eigen::Isometry3d pose_frame_from_model;
  std::string pose_frame;
  // A pose of any age: the newest known table orientation is the best guess of gravity.
  if (poseAt(stamp, std::numeric_limits<double>::infinity(), &pose_frame_from_model, &pose_frame)) {
    const Eigen::Matrix3d model_from_pose = pose_frame_from_model.linear().transpose();
    if (pose_frame == params_.gravity_frame) {
      *r = model_from_pose;
      return true;
    }
    for (const ros::Time& at : {stamp, ros::Time(0)})  // at the cloud's time, else the newest
      if (tf_buffer_.canTransform(pose_frame, params_.gravity_frame, at)) {
        *r = model_from_pose *
             isometryFromTransform(tf_buffer_.lookupTransform(pose_frame, params_.gravity_frame, at).transform).linear();
        return true;
      }
  }
  for (const ros::Time& at : {stamp, ros::Time(0)})
    if (tf_buffer_.canTransform(params_.frame_id, params_.gravity_frame, at)) {
      *r = isometryFromTransform(tf_buffer_.lookupTransform(params_.frame_id, params_.gravity_frame, at).transform).linear();
      return true;
    }
  return false;
}

void BreastSimNode::applyGravity(Engine& e, const ros::Time& stamp) {
  Eigen::Matrix3d r;
  if (!gravityRotation(stamp, &r)) return;  // no pose and no tf: the precomputed (case) gravity stays
  const Eigen::Vector3d load = gravityLoad(r, e.settings.simulation.gravity_mps2, e.prone_gravity_mps2);
  if (gravityLoadChanged(load, e.gravity_load_mps2, params_.gravity_update_threshold_deg, e.settings.simulation.gravity_mps2)) {
    e.pipeline->setGravityLoad(load);
    e.gravity_load_mps2 = load;
  }
}

}  // namespace breast_sim::ros_interface
