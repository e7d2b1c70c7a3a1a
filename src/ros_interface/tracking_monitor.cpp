// The tracking-quality monitor and the tracker it guards (see tracking_monitor.h).
#include "breast_sim/ros_interface/tracking_monitor.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/mesh/tet_quality.h"

namespace breast_sim::ros_interface {

namespace {

std::string mm(double m) {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(2);
  s << 1e3 * m << " mm";
  return s.str();
}

double maxRowDistance(const core::Points& a, const core::Points& b) {
  return a.rows() == 0 || a.rows() != b.rows() ? 0.0 : (a - b).rowwise().norm().maxCoeff();
}

}  // namespace

void MonitorLimits::validate() const {
  auto positive = [](double v, const char* name) {
    if (!(v > 0) || !std::isfinite(v))
      throw std::invalid_argument(std::string("parameter ~tracking/monitor/") + name + " = " + std::to_string(v) +
                                  ": must be a finite value > 0");
  };
  positive(max_seen_mean_m, "max_seen_mean_m");
  positive(max_seen_p95_m, "max_seen_p95_m");
  positive(max_wall_drift_m, "max_wall_drift_m");
  positive(max_rigid_drift_m, "max_rigid_drift_m");
  positive(max_lesion_offset_m, "max_lesion_offset_m");
  positive(max_lesion_jump_m, "max_lesion_jump_m");
  positive(max_stiffening, "max_stiffening");
  if (!(recover_fraction > 0 && recover_fraction <= 1))
    throw std::invalid_argument("parameter ~tracking/monitor/recover_fraction = " + std::to_string(recover_fraction) +
                                ": must be in (0, 1]");
  if (!(min_seen_fraction >= 0 && min_seen_fraction <= 1))
    throw std::invalid_argument("parameter ~tracking/monitor/min_seen_fraction = " + std::to_string(min_seen_fraction) +
                                ": must be in [0, 1]");
  if (recover_frames < 1 || recover_frames > 1000)
    throw std::invalid_argument("parameter ~tracking/monitor/recover_frames = " + std::to_string(recover_frames) +
                                ": must be in [1, 1000]");
  if (refused_frames < 1 || refused_frames > 1000)
    throw std::invalid_argument("parameter ~tracking/degraded_after_rejected = " + std::to_string(refused_frames) +
                                ": must be in [1, 1000]");
}

Verdict judgeFrame(const FrameQuality& q, const MonitorLimits& limits, double scale) {
  MonitorLimits l = limits;
  for (double* x : {&l.max_seen_mean_m, &l.max_seen_p95_m, &l.max_wall_drift_m, &l.max_rigid_drift_m,
                    &l.max_lesion_offset_m, &l.max_lesion_jump_m, &l.max_stiffening})
    *x *= scale;
  Verdict v;
  auto fail = [&v](Recovery r, const std::string& why) {
    v.good = false;
    v.recovery = r;
    v.reason = why;
    return v;
  };
  // Per frame: the step or the cloud is wrong; the last good frame is the best state.
  if (q.inverted_elements > 0) return fail(Recovery::kLastGood, std::to_string(q.inverted_elements) + " inverted elements");
  if (q.seen_fraction < l.min_seen_fraction) {
    std::ostringstream s;
    s.precision(3);
    s << "the cloud covers " << 100 * q.seen_fraction << " % of the skin, less than " << 100 * l.min_seen_fraction
      << " % (tracking/monitor/min_seen_fraction)";
    return fail(Recovery::kLastGood, s.str());
  }
  if (!(q.seen_mean_m >= 0) || q.seen_mean_m > l.max_seen_mean_m || q.seen_p95_m > l.max_seen_p95_m)
    return fail(Recovery::kLastGood, "seen skin " + mm(q.seen_mean_m) + " mean / " + mm(q.seen_p95_m) +
                                         " p95 from the cloud (limits " + mm(l.max_seen_mean_m) + " / " +
                                         mm(l.max_seen_p95_m) + ")");
  if (q.lesion_jump_m > l.max_lesion_jump_m)
    return fail(Recovery::kLastGood, "a lesion moved " + mm(q.lesion_jump_m) + " in one frame (limit " +
                                         mm(l.max_lesion_jump_m) + ")");
  if (q.stiffening > l.max_stiffening) {
    std::ostringstream s;
    s.precision(3);
    s << "the global stiffening rose: the material is up to " << 100 * q.stiffening
      << " % stiffer than the precomputed state's (limit " << 100 * l.max_stiffening << " %, tracking/monitor/max_stiffening)";
    return fail(Recovery::kLastGood, s.str());
  }
  // Against the reference: the model has drifted; the last good frame has too.
  if (q.wall_drift_m > l.max_wall_drift_m)
    return fail(Recovery::kReference, "the chest wall moved " + mm(q.wall_drift_m) + " from the precomputed state (limit " +
                                          mm(l.max_wall_drift_m) + ")");
  if (q.rigid_drift_m > l.max_rigid_drift_m)
    return fail(Recovery::kReference, "the model drifted " + mm(q.rigid_drift_m) + " from the precomputed state (limit " +
                                          mm(l.max_rigid_drift_m) + ")");
  if (q.lesion_offset_m > l.max_lesion_offset_m)
    return fail(Recovery::kReference, "a lesion is " + mm(q.lesion_offset_m) +
                                          " from its precomputed position (limit " + mm(l.max_lesion_offset_m) +
                                          "): precompute again for this posture");
  return v;
}

GuardedTracker::GuardedTracker(const TrackerOptions& tracker, const MonitorLimits& limits)
    : tracker_(tracker), limits_(limits) {
  limits_.validate();
}

void GuardedTracker::start(const core::ProneToSupinePipeline& p) {
  tracker_.reset();
  p.copyState(reference_);
  p.copyState(last_good_);
  reference_positions_ = p.positions();
  reference_mean_ = reference_positions_.colwise().mean();
  reference_lesions_ = p.lesionPositions();
  // The larger of the α in use and the controller's: a release in progress at the start uses a
  // smaller one, and the first restore (resync) ends it.
  reference_alpha_ = std::max(p.stiffening().alpha(), p.stiffening().controller().alpha());
  last_good_lesions_ = reference_lesions_;
  const core::TetMesh& mesh = p.model().mesh;
  wall_nodes_ = mesh.hasNodeSet(core::node_sets::kChestWall) ? mesh.nodeSet(core::node_sets::kChestWall) : std::vector<int>();
  started_ = true;
  trusted_ = true;
  good_in_row_ = refused_in_row_ = taken_back_in_row_ = 0;
  reason_.clear();
}

void GuardedTracker::stop() {
  started_ = false;
  tracker_.reset();
}

void GuardedTracker::refused(const std::string& reason) {
  ++refused_in_row_;
  if (refused_in_row_ >= limits_.refused_frames)
    reason_ = std::to_string(refused_in_row_) + " clouds in a row refused, last: " + reason;
}

GuardedFrame GuardedTracker::frame(core::ProneToSupinePipeline& p, const core::Points& cloud_m) {
  if (!started_) start(p);
  GuardedFrame f;
  f.track = tracker_.track(p, cloud_m);
  if (!f.track.tracked) {
    refused(f.track.reason);
    f.valid = valid();
    f.status = valid() ? f.track.reason : reason_;
    return f;
  }
  refused_in_row_ = 0;
  const core::Points x = p.positions();
  FrameQuality& q = f.quality;
  q.seen_mean_m = f.track.seen_mean_m;
  q.seen_p95_m = f.track.seen_p95_m;
  const int skin = f.track.skin_seen + f.track.skin_held;
  q.seen_fraction = skin > 0 ? static_cast<double>(f.track.skin_seen) / skin : 0.0;
  for (int n : wall_nodes_) q.wall_drift_m = std::max(q.wall_drift_m, (x.row(n) - reference_positions_.row(n)).norm());
  q.rigid_drift_m = (x.colwise().mean() - reference_mean_).norm();
  const core::Points lesions = p.model().lesion_embedding.positions(x);
  q.lesion_offset_m = maxRowDistance(lesions, reference_lesions_);
  q.lesion_jump_m = maxRowDistance(lesions, last_good_lesions_);
  q.inverted_elements = static_cast<int>(core::invertedTets(p.model().mesh.tets(), x, 0.0).size());
  const core::StiffeningSimulation& stiffening = p.stiffening();
  if (stiffening.alpha() > reference_alpha_ && stiffening.baseStress().size() > 0)
    q.stiffening = (stiffening.alpha() - reference_alpha_) * stiffening.baseStress().maxCoeff();
  f.verdict = judgeFrame(q, limits_);
  std::string recovering;
  if (f.verdict.good) {
    if (trusted_) {
      ++good_in_row_;
    } else {
      const Verdict strict = judgeFrame(q, limits_, limits_.recover_fraction);
      good_in_row_ = strict.good ? good_in_row_ + 1 : 0;
      if (!strict.good) recovering = "; not yet within " + std::to_string(limits_.recover_fraction).substr(0, 4) +
                                     " of the limits: " + strict.reason;
      if (good_in_row_ >= limits_.recover_frames) {
        trusted_ = true;
        reason_.clear();
      }
    }
    p.copyState(last_good_);
    last_good_lesions_ = lesions;
    taken_back_in_row_ = 0;
  } else {
    trusted_ = false;
    good_in_row_ = 0;
    reason_ = f.verdict.reason;
    const bool give_up_last_good = f.verdict.recovery == Recovery::kLastGood && ++taken_back_in_row_ >= limits_.recover_frames;
    if (f.verdict.recovery == Recovery::kReference || give_up_last_good) {
      p.restore(reference_);
      last_good_ = reference_;
      last_good_lesions_ = reference_lesions_;
      tracker_.reset();
      if (give_up_last_good) {
        f.verdict.recovery = Recovery::kReference;  // what was restored
        reason_ += "; " + std::to_string(taken_back_in_row_) + " frames in a row did not fit the last good frame";
      }
      reason_ += "; back to the precomputed state";
      taken_back_in_row_ = 0;
    } else {
      p.restore(last_good_);
      reason_ += "; the frame was taken back";
    }
    f.restored = true;
  }
  f.valid = valid();
  if (f.valid) {
    std::ostringstream s;
    s << "seen skin " << mm(q.seen_mean_m) << " mean / " << mm(q.seen_p95_m) << " p95, lesions " << mm(q.lesion_offset_m)
      << " from precomputed";
    f.status = s.str();
  } else {
    f.status = reason_;
    if (f.verdict.good)
      f.status += " (recovering: " + std::to_string(good_in_row_) + " of " + std::to_string(limits_.recover_frames) +
                  " good frames" + recovering + ")";
  }
  return f;
}

}  // namespace breast_sim::ros_interface
