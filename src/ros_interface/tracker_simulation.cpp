// A simulated tracker for the phantom (see tracker_simulation.h).
#include "breast_sim/ros_interface/tracker_simulation.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "breast_sim/core/model/phantom.h"
#include "breast_sim/ros_interface/conversions.h"

namespace breast_sim::ros_interface {

TrackerSimulation::TrackerSimulation(const core::ModelCase& model_case, const TrackerSimulationOptions& options)
    : options_(options), rng_(options.seed) {
  if (!model_case.phantom)
    throw std::invalid_argument("TrackerSimulation: case '" + model_case.name + "' is not the software phantom");
  const core::TargetSurface all = core::skinTarget(model_case.phantom->supine_surface);
  mean_tilt_rad_ = model_case.phantom->params.supine_gravity_tilt_rad;
  // What a scanner above the supine patient sees: triangles facing anterior (−y in the model).
  std::vector<Eigen::Vector3i> tris;
  for (Eigen::Index t = 0; t < all.triangles.rows(); ++t) {
    const Eigen::Vector3d a = all.vertices_m.row(all.triangles(t, 0)), b = all.vertices_m.row(all.triangles(t, 1)),
                          c = all.vertices_m.row(all.triangles(t, 2));
    const Eigen::Vector3d n = (b - a).cross(c - a);
    if (n.norm() > 0 && n.normalized().dot(Eigen::Vector3d(0, -1, 0)) > 0.2) {
      tris.push_back(all.triangles.row(t).transpose());
      cumulative_area_.push_back((cumulative_area_.empty() ? 0.0 : cumulative_area_.back()) + 0.5 * n.norm());
    }
  }
  if (tris.empty()) throw std::invalid_argument("TrackerSimulation: no anterior-facing supine skin");
  skin_.vertices_m = all.vertices_m;
  skin_.triangles.resize(static_cast<Eigen::Index>(tris.size()), 3);
  for (size_t i = 0; i < tris.size(); ++i) skin_.triangles.row(static_cast<Eigen::Index>(i)) = tris[i].transpose();
  for (Eigen::Index i = 0; i < all.vertices_m.rows(); ++i) {
    box_.extend(all.vertices_m.row(i).transpose());
    depth_m_ = std::max(depth_m_, -all.vertices_m(i, 1));
  }
}

Eigen::Isometry3d TrackerSimulation::worldFromModel(double t) const {
  Eigen::Matrix3d base;
  base.col(0) = Eigen::Vector3d(0, -1, 0);  // model x (left)      → world −y
  base.col(1) = Eigen::Vector3d(0, 0, -1);  // model y (posterior) → down
  base.col(2) = Eigen::Vector3d(1, 0, 0);   // model z (superior)  → along the table
  const double tilt = mean_tilt_rad_ + options_.tilt_amplitude_deg * M_PI / 180.0 * std::sin(2 * M_PI * t / options_.tilt_period_s);
  Eigen::Isometry3d w = Eigen::Isometry3d::Identity();
  // Rolling the model by +tilt about its z axis puts gravity at g·(sin tilt, cos tilt, 0) in the model.
  w.linear() = base * Eigen::AngleAxisd(tilt, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  w.translation() = Eigen::Vector3d(0.3, 0.0, 0.8 + options_.sway_amplitude_m * std::sin(2 * M_PI * t / options_.sway_period_s));
  return w;
}

Eigen::Isometry3d TrackerSimulation::worldFromTracker() const {
  Eigen::Isometry3d w = Eigen::Isometry3d::Identity();
  w.linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();  // looking down
  w.translation() = Eigen::Vector3d(0.3, 0.0, 1.5);
  return w;
}

core::Points TrackerSimulation::cloudInModel(double t) {
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, options_.noise_m);
  const double breath = options_.breathing_amplitude_m * std::sin(2 * M_PI * t / options_.breathing_period_s);
  core::Points p(options_.points, 3);
  const double total = cumulative_area_.back();
  for (int i = 0; i < options_.points; ++i) {
    if (u01(rng_) < options_.outlier_fraction) {
      // A stray return: anywhere in the breast's box grown by 3 cm.
      const Eigen::Vector3d lo = box_.min() - Eigen::Vector3d::Constant(0.03);
      const Eigen::Vector3d hi = box_.max() + Eigen::Vector3d::Constant(0.03);
      for (int k = 0; k < 3; ++k) p(i, k) = lo[k] + u01(rng_) * (hi[k] - lo[k]);
      continue;
    }
    const double a = u01(rng_) * total;
    const auto it = std::lower_bound(cumulative_area_.begin(), cumulative_area_.end(), a);
    const Eigen::Index t_idx = std::min<Eigen::Index>(it - cumulative_area_.begin(), skin_.triangles.rows() - 1);
    double r1 = u01(rng_), r2 = u01(rng_);
    if (r1 + r2 > 1) {
      r1 = 1 - r1;
      r2 = 1 - r2;
    }
    const Eigen::Vector3d A = skin_.vertices_m.row(skin_.triangles(t_idx, 0)), B = skin_.vertices_m.row(skin_.triangles(t_idx, 1)),
                          C = skin_.vertices_m.row(skin_.triangles(t_idx, 2));
    Eigen::Vector3d x = A + r1 * (B - A) + r2 * (C - A);
    x.y() -= breath * std::clamp(-x.y() / depth_m_, 0.0, 1.0);  // anterior, growing towards the apex
    for (int k = 0; k < 3; ++k) p(i, k) = x[k] + noise(rng_);
  }
  return p;
}

core::Points TrackerSimulation::cloudInTracker(double t) {
  const core::Points m = cloudInModel(t);
  const Eigen::Isometry3d tracker_from_model = worldFromTracker().inverse() * worldFromModel(t);
  core::Points out(m.rows(), 3);
  for (Eigen::Index i = 0; i < m.rows(); ++i) out.row(i) = (tracker_from_model * Eigen::Vector3d(m.row(i))).transpose();
  return out;
}

core::Points TrackerSimulation::cloudAsRecordedInModel(double t) {
  core::Points cloud = cloudInTracker(t).cast<float>().cast<double>();
  const Eigen::Isometry3d model_from_tracker = worldFromModel(t).inverse() * worldFromTracker();
  for (Eigen::Index i = 0; i < cloud.rows(); ++i)
    cloud.row(i) = (model_from_tracker * Eigen::Vector3d(cloud.row(i).transpose())).transpose();
  return cloud;
}

SkinScanner::SkinScanner(const core::Points& x, const core::Triangles& tris, unsigned seed) : x_(x), rng_(seed) {
  for (Eigen::Index t = 0; t < tris.rows(); ++t) {
    const Eigen::Vector3d a = x.row(tris(t, 0)), b = x.row(tris(t, 1)), c = x.row(tris(t, 2));
    const Eigen::Vector3d n = (b - a).cross(c - a);
    if (n.norm() > 0 && n.normalized().dot(Eigen::Vector3d(0, -1, 0)) > 0.2) {
      triangles_.push_back(tris.row(t).transpose());
      cumulative_area_.push_back((cumulative_area_.empty() ? 0.0 : cumulative_area_.back()) + 0.5 * n.norm());
    }
  }
  if (triangles_.empty()) throw std::invalid_argument("SkinScanner: no skin triangle faces anterior (-y)");
  for (Eigen::Index i = 0; i < x.rows(); ++i) depth_m_ = std::max(depth_m_, -x(i, 1));
}

core::Points SkinScanner::scan(int points, double breath_m, const Eigen::Vector3d& shift_m, double noise_m) {
  std::uniform_real_distribution<double> u01(0, 1);
  std::normal_distribution<double> noise(0, noise_m);
  core::Points cloud(points, 3);
  for (int i = 0; i < points; ++i) {
    const double a = u01(rng_) * cumulative_area_.back();
    const size_t t = std::min<size_t>(
        std::lower_bound(cumulative_area_.begin(), cumulative_area_.end(), a) - cumulative_area_.begin(), triangles_.size() - 1);
    double r1 = u01(rng_), r2 = u01(rng_);
    if (r1 + r2 > 1) {
      r1 = 1 - r1;
      r2 = 1 - r2;
    }
    const Eigen::Vector3d A = x_.row(triangles_[t][0]), B = x_.row(triangles_[t][1]), C = x_.row(triangles_[t][2]);
    Eigen::Vector3d p = A + r1 * (B - A) + r2 * (C - A);
    if (depth_m_ > 0) p.y() -= breath_m * std::clamp(-p.y() / depth_m_, 0.0, 1.0);
    p += shift_m;
    for (int d = 0; d < 3; ++d) cloud(i, d) = p[d] + noise(rng_);
  }
  return cloud;
}

OfflineTrackingRun trackRecordingOffline(core::ProneToSupinePipeline& p, const core::PipelineState& start,
                                         const core::ModelCase& model_case, const TrackerOptions& options,
                                         const MonitorLimits& limits, double gravity_update_threshold_deg, int clouds,
                                         double cloud_rate_hz, const std::vector<bool>& tracked,
                                         const TrackerSimulationOptions& sim_options) {
  if (tracked.size() != static_cast<size_t>(std::max(clouds, 0)))
    throw std::invalid_argument("trackRecordingOffline: " + std::to_string(tracked.size()) + " tracked flags for " +
                                std::to_string(clouds) + " clouds; give one per cloud");
  p.restore(start);
  GuardedTracker tracker(options, limits);
  tracker.start(p);
  TrackerSimulation sim(model_case, sim_options);
  const double g = p.settings().simulation.gravity_mps2;
  const Eigen::Vector3d prone = g * model_case.prone_gravity_direction.normalized();
  Eigen::Vector3d current = p.gravityLoad();  // the start state's, as the node's after load_state
  OfflineTrackingRun run;
  for (int k = 0; k < clouds; ++k) {
    const double t = k / cloud_rate_hz;
    const core::Points cloud = sim.cloudAsRecordedInModel(t);
    if (tracked[static_cast<size_t>(k)]) {
      const Eigen::Vector3d load = gravityLoad(sim.worldFromModel(t).linear().transpose(), g, prone);
      if (gravityLoadChanged(load, current, gravity_update_threshold_deg, g)) {
        p.setGravityLoad(load);
        current = load;
      }
      const GuardedFrame f = tracker.frame(p, cloud);
      current = p.gravityLoad();  // a frame taken back restores the load it had, as in the node
      run.reversals += f.track.reversals;
      run.reverted_frames += f.track.reversals > 0;
      run.taken_back += f.restored;
    }
    run.lesions_m.push_back(p.lesionPositions());
    run.valid.push_back(tracker.valid());
  }
  return run;
}

}  // namespace breast_sim::ros_interface
