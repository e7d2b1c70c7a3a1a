// The tracking monitor (tracking_monitor.h) and the node's input checks (input_checks.h).
#include <gtest/gtest.h>

#include <cmath>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/input_checks.h"
#include "breast_sim/ros_interface/tracker_simulation.h"
#include "breast_sim/ros_interface/tracking_monitor.h"
#include "rest_phantom.h"

using namespace breast_sim;
using ros_interface::FrameQuality;
using ros_interface::MonitorLimits;
using ros_interface::Recovery;

namespace {

FrameQuality goodFrame() {
  FrameQuality q;
  q.seen_mean_m = 0.0005;
  q.seen_p95_m = 0.0015;
  q.seen_fraction = 0.8;
  q.wall_drift_m = 0.001;
  q.rigid_drift_m = 0.0005;
  q.lesion_offset_m = 0.002;
  q.lesion_jump_m = 0.0002;
  return q;
}

}  // namespace

TEST(TrackingMonitor, EachLimitTripsWithItsRecovery) {
  const MonitorLimits l;
  EXPECT_TRUE(ros_interface::judgeFrame(goodFrame(), l).good);
  struct Case {
    const char* name;
    void (*spoil)(FrameQuality&);
    Recovery recovery;
    const char* says;
  };
  const Case cases[] = {
      {"inverted", [](FrameQuality& q) { q.inverted_elements = 2; }, Recovery::kLastGood, "inverted"},
      {"seen share", [](FrameQuality& q) { q.seen_fraction = 0.1; }, Recovery::kLastGood, "covers"},
      {"seen mean", [](FrameQuality& q) { q.seen_mean_m = 0.0025; }, Recovery::kLastGood, "seen skin"},
      {"seen p95", [](FrameQuality& q) { q.seen_p95_m = 0.007; }, Recovery::kLastGood, "seen skin"},
      {"nothing seen", [](FrameQuality& q) { q.seen_mean_m = -1; }, Recovery::kLastGood, "seen skin"},
      {"lesion jump", [](FrameQuality& q) { q.lesion_jump_m = 0.004; }, Recovery::kLastGood, "in one frame"},
      {"stiffened", [](FrameQuality& q) { q.stiffening = 0.5; }, Recovery::kLastGood, "stiffer"},
      {"wall drift", [](FrameQuality& q) { q.wall_drift_m = 0.006; }, Recovery::kReference, "chest wall"},
      {"model drift", [](FrameQuality& q) { q.rigid_drift_m = 0.006; }, Recovery::kReference, "drifted"},
      {"lesion offset", [](FrameQuality& q) { q.lesion_offset_m = 0.016; }, Recovery::kReference, "precompute again"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    FrameQuality q = goodFrame();
    c.spoil(q);
    const auto v = ros_interface::judgeFrame(q, l);
    EXPECT_FALSE(v.good);
    EXPECT_EQ(v.recovery, c.recovery);
    EXPECT_NE(v.reason.find(c.says), std::string::npos) << v.reason;
  }
  // Scaled limits (the recovery rule): a frame at 60 % of a limit passes at 1, not at 0.5.
  FrameQuality q = goodFrame();
  q.rigid_drift_m = 0.6 * l.max_rigid_drift_m;
  EXPECT_TRUE(ros_interface::judgeFrame(q, l).good);
  EXPECT_FALSE(ros_interface::judgeFrame(q, l, 0.5).good);
}

TEST(TrackingMonitor, LimitsOutOfRangeNameTheParameter) {
  MonitorLimits l;
  l.max_wall_drift_m = 0;
  try {
    l.validate();
    ADD_FAILURE() << "accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("tracking/monitor/max_wall_drift_m"), std::string::npos) << e.what();
  }
  l = MonitorLimits();
  l.recover_fraction = 0;
  EXPECT_THROW(l.validate(), std::invalid_argument);
}

namespace {

/// The rest phantom (rest_phantom.h) and one pipeline on it.
struct Scene : test_fixtures::RestPhantom {
  std::unique_ptr<core::ProneToSupinePipeline> pipeline_owner = pipeline();
  core::ProneToSupinePipeline* const pipeline_ptr = pipeline_owner.get();
  Scene() : test_fixtures::RestPhantom(3) {}
  core::Points scan(int k, double slide_m = 0) { return RestPhantom::scan(k, 3000, slide_m); }
  double lesionErrorMm() const { return RestPhantom::lesionErrorMm(*pipeline_ptr); }
};

}  // namespace

TEST(GuardedTracker, OwnSkinStaysValidAScanSlidAlongTheWallTurnsItInvalidAndItRecovers) {
  Scene s;
  ros_interface::TrackerOptions to;
  to.icp.enabled = false;  // the monitor alone must catch the slide (ICP would refuse the scans)
  ros_interface::GuardedTracker g(to);
  g.start(*s.pipeline_ptr);
  // 1. The skin as it is: valid throughout, nothing taken back, lesions within 1 mm.
  double worst = 0;
  for (int k = 0; k < 40; ++k) {
    const auto f = g.frame(*s.pipeline_ptr, s.scan(k));
    ASSERT_TRUE(f.track.tracked) << f.track.reason;
    EXPECT_TRUE(f.valid) << "frame " << k << ": " << f.status;
    EXPECT_FALSE(f.restored) << f.verdict.reason;
    worst = std::max(worst, s.lesionErrorMm());
  }
  std::printf("[ measure  ] own skin, 40 frames: lesions within %.3f mm of rest\n", worst);
  EXPECT_LT(worst, 1.0);
  // 2. The scan slid 20 mm laterally along the wall over 10 frames: invalid within 12 frames of the
  // start and for as long as the scan stays slid; the model never leaves the reference by more than
  // the limits let it.
  int first_invalid = -1;
  const MonitorLimits limits;
  for (int k = 0; k < 40; ++k) {
    const double slide = 0.02 * std::min(1.0, (k + 1) / 10.0);
    const auto f = g.frame(*s.pipeline_ptr, s.scan(40 + k, slide));
    if (!f.valid && first_invalid < 0) first_invalid = k;
    if (first_invalid >= 0) {
      EXPECT_FALSE(f.valid) << "frame " << k << " of the slid scans: " << f.status;
    }
    const core::Points x = s.pipeline_ptr->positions();
    EXPECT_LT((x.colwise().mean() - s.model.mesh.nodes().colwise().mean()).norm(), limits.max_rigid_drift_m + 1e-9);
  }
  std::printf("[ measure  ] scan slid 20 mm: lesions invalid %d frames after the slide began; reason: %s\n", first_invalid,
              g.reason().c_str());
  ASSERT_GE(first_invalid, 0);
  EXPECT_LE(first_invalid, 12);
  // 3. Back to the true skin: valid again after at least recover_frames good frames.
  int valid_after = -1;
  for (int k = 0; k < 40 && valid_after < 0; ++k)
    if (g.frame(*s.pipeline_ptr, s.scan(80 + k)).valid) valid_after = k + 1;
  std::printf("[ measure  ] back on the true skin: valid after %d frames\n", valid_after);
  EXPECT_GE(valid_after, limits.recover_frames);
  EXPECT_LE(valid_after, 30);
  EXPECT_LT(s.lesionErrorMm(), 1.0);
}

TEST(GuardedTracker, AFrameTakenBackLeavesTheLastGoodStateBitForBit) {
  Scene s;
  MonitorLimits l;
  l.max_lesion_jump_m = 1e-9;  // every step moves the lesions more than this: every frame is taken back
  ros_interface::GuardedTracker g(ros_interface::TrackerOptions{}, l);
  g.start(*s.pipeline_ptr);
  const core::PipelineState before = s.pipeline_ptr->state();
  for (int k = 0; k < 3; ++k) {
    const auto f = g.frame(*s.pipeline_ptr, s.scan(k));
    ASSERT_TRUE(f.track.tracked) << f.track.reason;
    EXPECT_TRUE(f.restored);
    EXPECT_EQ(f.verdict.recovery, Recovery::kLastGood);
    EXPECT_FALSE(f.valid);
    EXPECT_EQ(s.pipeline_ptr->state().simulation.displacement_m, before.simulation.displacement_m);
    EXPECT_EQ(s.pipeline_ptr->state().morphing_forces_n, before.morphing_forces_n);
  }
}

TEST(GuardedTracker, AFrameOnAStiffenedMaterialIsTakenBack) {
  // A frame whose step ran with a raised global alpha moved the lesions of a breast stiffer than the
  // tissue: taken back to the last good frame, whose alpha comes back with it.
  Scene s;
  ros_interface::GuardedTracker g;
  g.start(*s.pipeline_ptr);
  ASSERT_TRUE(g.frame(*s.pipeline_ptr, s.scan(0)).valid);
  const double alpha = s.pipeline_ptr->stiffening().alpha();
  s.pipeline_ptr->stiffening().controller().restart(1.0);  // [1/Pa]: E_r = 1 + s_VM / Pa
  const auto f = g.frame(*s.pipeline_ptr, s.scan(1));
  ASSERT_TRUE(f.track.tracked) << f.track.reason;
  EXPECT_GT(f.quality.stiffening, g.limits().max_stiffening);
  EXPECT_TRUE(f.restored);
  EXPECT_EQ(f.verdict.recovery, Recovery::kLastGood);
  EXPECT_NE(f.verdict.reason.find("stiffer"), std::string::npos) << f.verdict.reason;
  EXPECT_FALSE(f.valid);
  EXPECT_EQ(s.pipeline_ptr->stiffening().alpha(), alpha);
  std::printf("[ measure  ] a frame with alpha 1 /Pa: %s\n", f.verdict.reason.c_str());
}

TEST(GuardedTracker, FramesThatKeepFailingTheLastGoodFrameGoBackToTheReference) {
  // A last good frame that no cloud fits (here: scans slid 40 mm, which cover too little of the
  // skin) is given up after recover_frames take-backs in a row: the model goes back to the
  // precomputed state instead of being taken back to that frame for ever.
  Scene s;
  ros_interface::TrackerOptions to;
  to.icp.enabled = false;  // ICP would refuse the slid scans before the monitor sees them
  ros_interface::GuardedTracker g(to);
  g.start(*s.pipeline_ptr);
  const core::PipelineState reference = s.pipeline_ptr->state();
  for (int k = 0; k < 10; ++k) ASSERT_TRUE(g.frame(*s.pipeline_ptr, s.scan(k)).valid);
  const Eigen::VectorXd last_good = s.pipeline_ptr->state().simulation.displacement_m;
  ASSERT_NE(last_good, reference.simulation.displacement_m);
  for (int k = 0; k < g.limits().recover_frames; ++k) {
    const auto f = g.frame(*s.pipeline_ptr, s.scan(10 + k, 0.04));
    ASSERT_TRUE(f.track.tracked) << f.track.reason;
    const bool last = k + 1 == g.limits().recover_frames;
    EXPECT_EQ(f.verdict.recovery, last ? Recovery::kReference : Recovery::kLastGood) << f.verdict.reason;
    EXPECT_TRUE(f.restored);
    EXPECT_EQ(s.pipeline_ptr->state().simulation.displacement_m, last ? reference.simulation.displacement_m : last_good)
        << "take-back " << k + 1;
    if (last) EXPECT_NE(g.reason().find("did not fit the last good frame"), std::string::npos) << g.reason();
  }
}

// A frame taken back is taken back whole: local α's a rejected step added (here set by hand after
// the last good frame) go with it.
TEST(GuardedTracker, AFrameTakenBackTakesItsLocalAlphasBack) {
  Scene s;
  ros_interface::TrackerOptions to;
  to.icp.enabled = false;
  ros_interface::GuardedTracker g(to);
  g.start(*s.pipeline_ptr);
  for (int k = 0; k < 3; ++k) ASSERT_TRUE(g.frame(*s.pipeline_ptr, s.scan(k)).valid);
  const Eigen::VectorXd good = s.pipeline_ptr->stiffening().elementAlpha();
  Eigen::VectorXd added = good;
  added[0] += 1e-3;
  s.pipeline_ptr->stiffening().setElementAlpha(added);
  const auto f = g.frame(*s.pipeline_ptr, s.scan(3, 0.04));  // slid 40 mm: too little skin seen
  ASSERT_TRUE(f.restored) << f.verdict.reason;
  ASSERT_EQ(f.verdict.recovery, Recovery::kLastGood);
  EXPECT_EQ(s.pipeline_ptr->stiffening().elementAlpha(), good);
}

TEST(GuardedTracker, RefusedCloudsInARowMakeTheLesionsInvalidUntilAFrameIsTracked) {
  Scene s;
  ros_interface::GuardedTracker g;
  g.start(*s.pipeline_ptr);
  ASSERT_TRUE(g.frame(*s.pipeline_ptr, s.scan(0)).valid);
  for (int k = 0; k < g.limits().refused_frames - 1; ++k) g.refused("malformed");
  EXPECT_TRUE(g.valid());
  const auto empty = g.frame(*s.pipeline_ptr, core::Points(0, 3));  // refused by the tracker: too few points
  EXPECT_FALSE(empty.track.tracked);
  EXPECT_FALSE(g.valid());
  EXPECT_NE(g.reason().find("in a row refused"), std::string::npos) << g.reason();
  EXPECT_TRUE(g.frame(*s.pipeline_ptr, s.scan(1)).valid);
}

TEST(InputChecks, StampsInTheFutureOrTooOldAreRefused) {
  const ros_interface::StampLimits l;  // 0.5 s ahead, 2 s behind
  EXPECT_EQ(ros_interface::checkStamp(100.0, 100.2, l, "cloud"), "");
  EXPECT_EQ(ros_interface::checkStamp(100.4, 100.0, l, "cloud"), "");
  const std::string ahead = ros_interface::checkStamp(3700.0, 100.0, l, "cloud");
  EXPECT_NE(ahead.find("3600.000 s ahead"), std::string::npos) << ahead;
  EXPECT_NE(ros_interface::checkStamp(97.0, 100.0, l, "~patient_pose").find("behind"), std::string::npos);
  EXPECT_NE(ros_interface::checkStamp(0.0, 100.0, l, "cloud").find("no stamp"), std::string::npos);
  EXPECT_EQ(ros_interface::checkStamp(3700.0, 0.0, l, "cloud"), "");  // a simulated clock not started yet
}

TEST(InputChecks, APoseThatJumpsWithinTheWindowIsRefused) {
  const ros_interface::PoseJumpLimits l;  // 20 mm, 5°, within 0.5 s
  Eigen::Isometry3d a = Eigen::Isometry3d::Identity(), b = a;
  b.translation() << 0.005, 0, 0;
  EXPECT_EQ(ros_interface::checkPoseJump(a, 10.0, b, 10.05, l), "");
  b.translation() << 0.03, 0, 0;
  EXPECT_NE(ros_interface::checkPoseJump(a, 10.0, b, 10.05, l).find("jumped 30.00 mm"), std::string::npos);
  EXPECT_EQ(ros_interface::checkPoseJump(a, 10.0, b, 11.0, l), "");  // after a gap: a reposition
  b = a;
  b.linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();  // the 180° flip
  EXPECT_NE(ros_interface::checkPoseJump(a, 10.0, b, 10.05, l).find("180.00 deg"), std::string::npos);
}

TEST(InputChecks, TheThrottleLetsEachKindOfWarningThroughOncePerPeriod) {
  ros_interface::KeyedThrottle t(5.0);
  EXPECT_TRUE(t.allow("cloud stamp", 0.0));
  EXPECT_TRUE(t.allow("pose jump", 0.1));  // another kind: not held back by the first
  for (int i = 0; i < 100; ++i) EXPECT_FALSE(t.allow("cloud stamp", 0.2 + 0.01 * i));
  EXPECT_EQ(t.suppressed("cloud stamp"), 100);
  EXPECT_TRUE(t.allow("cloud stamp", 5.1));
  EXPECT_EQ(t.suppressed("cloud stamp"), 0);
}

TEST(InputChecks, PoseHistoryInterpolatesOnlyAcrossShortGaps) {
  ros_interface::PoseHistory h(10.0);
  Eigen::Isometry3d a = Eigen::Isometry3d::Identity(), b = a, c = a;
  b.translation() << 0.01, 0, 0;
  b.linear() = Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  c.translation() << 0.05, 0, 0;
  h.add(10.0, a);
  h.add(10.1, b);
  h.add(17.0, c);  // after a 6.9 s gap
  Eigen::Isometry3d p;
  ASSERT_TRUE(h.at(10.05, 1.0, 0.5, &p));  // between two poses 0.1 s apart: interpolated
  EXPECT_NEAR(p.translation().x(), 0.005, 1e-12);
  EXPECT_NEAR(Eigen::AngleAxisd(p.linear()).angle(), 0.1, 1e-9);
  ASSERT_TRUE(h.at(10.3, 1.0, 0.5, &p));  // across the long gap: the nearest, 0.2 s away
  EXPECT_TRUE(p.isApprox(b, 1e-12));
  EXPECT_FALSE(h.at(13.5, 1.0, 0.5, &p));  // nothing within 0.5 s, and the gap is not bridged
  ASSERT_TRUE(h.at(17.0, 1.0, 0.5, &p));
  EXPECT_TRUE(p.isApprox(c, 1e-12));
  h.add(25.0, a);  // the span: poses older than 15 s are forgotten
  EXPECT_FALSE(h.at(10.0, 1.0, 0.5, &p));
  EXPECT_EQ(h.newestStamp(), 25.0);
}
