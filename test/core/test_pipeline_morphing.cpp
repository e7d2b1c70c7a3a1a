// The pipeline's morphing stage: the zero-distance target, the pull onto a reachable target, the
// implicit pull against the forces alone, the step's move measures (pulled vertices' 95th
// percentile, off the wall band) and the stop rules that use them, with the volume condition.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <fstream>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_fixtures.h"

using namespace breast_sim::core;
using namespace breast_sim::core::test_fixtures;

TEST(Pipeline, AZeroDistanceTargetLeavesTheModelUnchanged) {
  // No gravity and the model's own skin as the target: every pulled vertex is on the target, no
  // force is ever added, and the model does not move.
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.simulation.gravity_mps2 = 0.0;
  s.morphing.target = "";
  ProneToSupinePipeline pipe(p.c, p.m, s);
  EXPECT_NEAR(pipe.supineGravityLoad().norm(), 0.0, 1e-12);
  TargetSurface own;
  own.vertices_m = p.m.mesh.nodes();
  own.triangles = skinTriangles(p.m.mesh, p.m.mesh.nodeSet(node_sets::kSkin));
  pipe.setTarget(own);
  // A bad frame (no points) is refused and the last good target stays.
  EXPECT_THROW(pipe.setTarget(TargetSurface{}), std::invalid_argument);
  ASSERT_TRUE(pipe.hasTarget());
  EXPECT_EQ(pipe.target().vertices_m.rows(), own.vertices_m.rows());
  pipe.setTarget(own);  // the same target again: an in-place rebuild
  for (int k = 0; k < 10; ++k) {
    const IterationReport it = pipe.iterate();
    EXPECT_TRUE(it.advanced);
    EXPECT_LT(it.surface_mean_m, 1e-6);
    EXPECT_TRUE(it.alpha_held);  // within tolerance from the start
  }
  EXPECT_LT(maxNodalNorm(pipe.simulator().state().displacement_m), 1e-7);
  const PipelineMetrics m = pipe.metrics();
  EXPECT_LT(m.surface.model_to_target.max_m, 1e-6);
  EXPECT_EQ(m.inverted_elements, 0);
  EXPECT_NEAR(m.volume_change_percent, 0.0, 1e-6);
}

TEST(Pipeline, TrackingModeSwitchesTheStiffeningToTrackingFrames) {
  // A tracking frame is a small move about a settled state: the stiffening driver's tracking frames
  // (local reversals, one element update per step; their behaviour is tested in test_stiffening)
  // are on while tracking, and the stages go back to the seed's rules.
  const SmallPhantom& p = phantom();
  ProneToSupinePipeline pipe(p.c, p.m, PipelineSettings{});
  EXPECT_FALSE(pipe.stiffening().tracking());
  pipe.setTrackingMode(true);
  EXPECT_TRUE(pipe.trackingMode());
  EXPECT_TRUE(pipe.stiffening().tracking());
  pipe.setTrackingMode(false);
  EXPECT_FALSE(pipe.stiffening().tracking());
}

// A state saved after the whole run (wall sliding, morphing forces) loads into a fresh pipeline of
// the same case, as a respawned node resumes its checkpoint: the morphing forces belong to the
// vertices pulled once the state's wall is attached (its nodes free), not to those of the fresh
// model with its wall still fixed.
TEST(Pipeline, AWholeRunsStateLoadsIntoAFreshPipeline) {
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.morphing.max_steps = 30;  // the state need not be converged
  ProneToSupinePipeline run(p.c, p.m, s);
  run.run();
  ASSERT_GT(run.state().morphing_forces_n.rows(), 0);
  const std::string file = (std::filesystem::temp_directory_path() / "breast_sim_whole_run.state").string();
  run.saveState(file);

  ProneToSupinePipeline fresh(p.c, p.m, s);
  // Morphing forces that fit no model, or are not finite, are refused before any part of the state
  // applies, though the fresh pipeline has no morphing forces to compare with yet: its wall stays
  // fixed and its displacements zero.
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const std::pair<const char*, std::function<void(PipelineState&)>> spoiled[] = {
      {"this model pulls", [](PipelineState& t) { t.morphing_forces_n.conservativeResize(t.morphing_forces_n.rows() - 1, 3); }},
      {"morphing forces that are not finite", [&](PipelineState& t) { t.morphing_forces_n(0, 1) = nan; }},
      {"displacements that are not finite", [&](PipelineState& t) { t.simulation.displacement_m[4] = nan; }},
      {"sliding targets that are not finite", [&](PipelineState& t) { t.sliding_targets_m(2, 0) = nan; }},
  };
  const std::vector<char> constrained_before = fresh.simulator().constrainedDofs();
  for (const auto& [says, spoil] : spoiled) {
    SCOPED_TRACE(says);
    PipelineState bad = run.state();
    spoil(bad);
    try {
      fresh.restore(bad);
      ADD_FAILURE() << "restored";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(says), std::string::npos) << e.what();
    }
    EXPECT_EQ(fresh.simulator().state().displacement_m.norm(), 0.0);
    EXPECT_EQ(fresh.state().sliding_targets_m.rows(), 0) << "the state's wall was attached";
    EXPECT_EQ(fresh.state().morphing_forces_n.rows(), 0);
    EXPECT_EQ(fresh.simulator().constrainedDofs(), constrained_before);
  }
  fresh.loadState(file);
  EXPECT_EQ(fresh.simulator().state().displacement_m, run.simulator().state().displacement_m);
  EXPECT_EQ(fresh.state().morphing_forces_n, run.state().morphing_forces_n);
  EXPECT_EQ(fresh.lesionPositions(), run.lesionPositions());
  // A state from before the morphing drops the forces accumulated since: none are reported or
  // applied, as before the first morphing step.
  PipelineState before_morphing = fresh.state();
  before_morphing.morphing_forces_n.resize(0, 3);
  fresh.restore(before_morphing);
  EXPECT_EQ(fresh.state().morphing_forces_n.rows(), 0);
  EXPECT_EQ(fresh.morphing(), nullptr);
  EXPECT_EQ(fresh.simulator().externalForces().norm(), 0.0);
  std::filesystem::remove(file);
}

// With the explicit (seed 2.4) sliding the wall's nodes stay constrained (moving targets): a fresh
// pipeline restoring a state with morphing forces pulls the same vertices as the run it came from,
// and a spoiled one is refused before its wall is attached.
TEST(Pipeline, AnExplicitSlidingRunsStateLoadsIntoAFreshPipeline) {
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.sliding_method = PipelineSettings::SlidingMethod::kExplicit;
  s.simulation.settle.max_steps = 40;  // the states need not be settled
  s.morphing.max_steps = 5;
  ProneToSupinePipeline run(p.c, p.m, s);
  run.run();
  const PipelineState state = run.state();
  ASSERT_GT(state.morphing_forces_n.rows(), 0);
  ASSERT_GT(state.sliding_targets_m.rows(), 0);
  ProneToSupinePipeline fresh(p.c, p.m, s);
  const std::vector<char> constrained_before = fresh.simulator().constrainedDofs();
  PipelineState bad = state;
  bad.morphing_forces_n.conservativeResize(bad.morphing_forces_n.rows() - 1, 3);
  EXPECT_THROW(fresh.restore(bad), std::invalid_argument);
  EXPECT_EQ(fresh.simulator().constrainedDofs(), constrained_before);
  EXPECT_EQ(fresh.simulator().state().displacement_m.norm(), 0.0);
  fresh.restore(state);
  ASSERT_TRUE(fresh.morphing() && run.morphing());
  EXPECT_EQ(fresh.morphing()->vertices(), run.morphing()->vertices());
  EXPECT_EQ(fresh.state().morphing_forces_n, state.morphing_forces_n);
  EXPECT_EQ(fresh.simulator().constrainedDofs(), run.simulator().constrainedDofs());
}

TEST(Pipeline, MorphingPullsTheSkinOntoAReachableTarget) {
  // The model's own skin stretched 8 % anteriorly away from the fixed wall (y = 0 stays, so the
  // base needs no sliding): the pulled vertices reach the tolerance, no element inverts.
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.simulation.gravity_mps2 = 0.0;
  s.morphing.target = "";
  s.morphing.max_steps = 200;  // converges in 40-90 steps on the meshes seen (meshing varies run to run)
  ProneToSupinePipeline pipe(p.c, p.m, s);
  TargetSurface stretched;
  stretched.vertices_m = p.m.mesh.nodes();
  stretched.vertices_m.col(1) *= 1.08;
  stretched.triangles = skinTriangles(p.m.mesh, p.m.mesh.nodeSet(node_sets::kSkin));
  pipe.setTarget(stretched);
  const StageReport r = pipe.runMorphing();
  const PipelineMetrics m = pipe.metrics();
  // The distances reach the tolerance; the stage's stop criterion (also no node moving more than
  // 0.1 mm per step) is not asserted: on some meshes a few nodes keep moving.
  SCOPED_TRACE("after " + std::to_string(r.steps) + " steps");
  EXPECT_LT(r.surface_mean_m, s.morphing.tolerance_mean_m);
  EXPECT_LT(r.surface_p95_m, s.morphing.tolerance_p95_m);
  // The whole skin, constrained rim nodes included, exactly: close too.
  EXPECT_LT(m.surface.model_to_target.mean_m, 2 * s.morphing.tolerance_mean_m);
  EXPECT_EQ(m.inverted_elements, 0);
  EXPECT_GT(m.max_displacement_m, 3e-3);  // the nipple moved ~5.6 mm
}

TEST(Pipeline, TheImplicitPullReachesTheToleranceInFewerStepsThanTheForcesAlone) {
  // The same reachable target as above, morphed by the seed's accumulated forces alone (the slow
  // reference: MorphingOptions' gain of 20 Pa/mm, 0.1 s steps, α doubling per reversal) and with the
  // implicit pull (augmented Lagrangian: a spring of 100 Pa/mm to the target point solved with the
  // step, the accumulated force updated with the same gain). Counted: accepted steps until the pulled
  // vertices' mean and p95 distances first meet the tolerances. The forces alone end within tolerance
  // without an inverted element; the pull has no inverted element when it first meets the tolerance.
  // Not asserted: the pull's stop criterion and where it ends. On this mesh a few vertices keep moving
  // by more than 0.1 mm per step where their nearest target point jumps, so the pull runs on to the
  // step limit and its final state follows the path: solver changes at round-off level moved its
  // final mean between 0.28 and 4.4 mm (while it met the tolerance at step 10 each time). Why the
  // pull is off by default.
  const SmallPhantom& p = phantom();
  TargetSurface stretched;
  stretched.vertices_m = p.m.mesh.nodes();
  stretched.vertices_m.col(1) *= 1.08;
  stretched.triangles = skinTriangles(p.m.mesh, p.m.mesh.nodeSet(node_sets::kSkin));
  auto run = [&](bool pull, Points* x, StageReport* r) {
    PipelineSettings s;
    s.simulation.sliding = false;  // the wall held: the two pulls are compared on the same constraints
    s.simulation.gravity_mps2 = 0.0;
    s.morphing.target = "";
    s.morphing.max_steps = 120;
    s.morphing.time_step_s = 0.1;
    if (pull) {
      s.morphing.forces.spring_pa_per_m = 1e5;
      s.morphing.forces.gain_pa_per_m = 1e5;
    } else {  // the seed's forces alone: MorphingOptions' defaults, reversal growth 1
      s.morphing.forces = MorphingOptions{};
      ASSERT_EQ(s.morphing.forces.spring_pa_per_m, 0.0);
      s.morphing.alpha_reversal_growth = 1.0;
    }
    ProneToSupinePipeline pipe(p.c, p.m, s);
    pipe.setTarget(stretched);
    int to_tolerance = -1;
    size_t inverted_at_tolerance = 0;
    *r = pipe.runMorphing([&](const PipelineProgress& pr) {
      if (to_tolerance < 0 && pr.surface_mean_m <= s.morphing.tolerance_mean_m && pr.surface_p95_m <= s.morphing.tolerance_p95_m) {
        to_tolerance = pr.step;
        inverted_at_tolerance = invertedTets(p.m.mesh.tets(), pipe.positions()).size();
        *x = pipe.positions();
      }
    });
    r->steps = to_tolerance;  // reused below: steps until the tolerance was first met
    EXPECT_EQ(inverted_at_tolerance, 0u) << (pull ? "pull" : "forces alone");
    if (pull) {
      EXPECT_FALSE(pipe.simulator().springNodes().empty());  // the springs were set
      std::printf("[ measure  ] implicit pull at its step limit: mean %.3f mm, p95 %.3f mm, %d inverted\n",
                  1e3 * r->surface_mean_m, 1e3 * r->surface_p95_m, pipe.metrics().inverted_elements);
    } else {
      *x = pipe.positions();
      EXPECT_EQ(pipe.metrics().inverted_elements, 0);
      EXPECT_LT(r->surface_mean_m, s.morphing.tolerance_mean_m);
      EXPECT_LT(r->surface_p95_m, s.morphing.tolerance_p95_m);
    }
  };
  Points x_forces, x_pull;
  StageReport r_forces, r_pull;
  run(false, &x_forces, &r_forces);
  run(true, &x_pull, &r_pull);
  ASSERT_GT(r_forces.steps, 0);
  ASSERT_GT(r_pull.steps, 0);
  std::printf("[ measure  ] %d tets, stretched target, steps to the tolerance: forces alone %d (%ld reversed, final mean %.3f "
              "mm), implicit pull %d (%ld reversed, final mean %.3f mm); largest node difference (forces at the end, pull "
              "where it met the tolerance) %.3f mm\n",
              p.m.mesh.numTets(), r_forces.steps, r_forces.reversed_steps, 1e3 * r_forces.surface_mean_m, r_pull.steps,
              r_pull.reversed_steps, 1e3 * r_pull.surface_mean_m, 1e3 * (x_pull - x_forces).rowwise().norm().maxCoeff());
  EXPECT_LE(2 * r_pull.steps, r_forces.steps);
  // Where the pull first meets the tolerance, it has the shape the forces reach (within the p95 tolerance).
  EXPECT_LT((x_pull - x_forces).rowwise().norm().maxCoeff(), 1.5e-3);
}

TEST(Pipeline, ThePulledVerticesIncrementIsTheirNinetyFifthPercentileMove) {
  // IterationReport::pulled_increment_p95_m against a brute-force percentile of the pulled vertices'
  // moves over each Figure-2 iteration, and never above the largest move of any node; the morphing
  // stage's reversal growth is its own (the controller's preset is back after the stage).
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.simulation.gravity_mps2 = 0.0;
  s.morphing.target = "";
  s.morphing.max_steps = 5;
  s.morphing.alpha_reversal_growth = 3.0;
  ProneToSupinePipeline pipe(p.c, p.m, s);
  TargetSurface stretched;
  stretched.vertices_m = p.m.mesh.nodes();
  stretched.vertices_m.col(1) *= 1.08;
  stretched.triangles = skinTriangles(p.m.mesh, p.m.mesh.nodeSet(node_sets::kSkin));
  pipe.setTarget(stretched);
  pipe.runMorphing();
  EXPECT_EQ(pipe.stiffening().controller().params().reversal_growth, AlphaControllerParams{}.reversal_growth);
  for (int k = 0; k < 4; ++k) {
    const Eigen::VectorXd before = pipe.simulator().state().displacement_m;
    const IterationReport it = pipe.iterate();
    const Eigen::VectorXd& after = pipe.simulator().state().displacement_m;
    std::vector<double> moves;
    for (int v : pipe.morphing()->vertices()) moves.push_back((after.segment<3>(3 * v) - before.segment<3>(3 * v)).norm());
    std::sort(moves.begin(), moves.end());
    const size_t rank = static_cast<size_t>(std::ceil(0.95 * static_cast<double>(moves.size())));  // ⌈0.95 n⌉-th smallest
    EXPECT_NEAR(it.pulled_increment_p95_m, moves[rank - 1], 1e-15) << "iteration " << k;
    EXPECT_LE(it.pulled_increment_p95_m, it.increment_m);
    EXPECT_GT(it.pulled_increment_p95_m, 0.0);
  }
}

namespace {
/// Largest move of a node off the wall band and the ⌈0.95 n⌉-th smallest move of the band's nodes, brute force.
void offWallMoves(const Eigen::VectorXd& before, const Eigen::VectorXd& after, const std::vector<int>& wall_nodes,
                  double* off_wall_max, double* wall_p95) {
  std::vector<char> wall(before.size() / 3, 0);
  for (int n : wall_nodes) wall[static_cast<size_t>(n)] = 1;
  std::vector<double> moves;
  *off_wall_max = 0;
  for (Eigen::Index n = 0; n < before.size() / 3; ++n) {
    const double d = (after.segment<3>(3 * n) - before.segment<3>(3 * n)).norm();
    if (wall[static_cast<size_t>(n)]) moves.push_back(d);
    else *off_wall_max = std::max(*off_wall_max, d);
  }
  std::sort(moves.begin(), moves.end());
  *wall_p95 = moves.empty() ? 0.0 : moves[static_cast<size_t>(std::ceil(0.95 * static_cast<double>(moves.size()))) - 1];
}
}  // namespace

TEST(Pipeline, TheOffWallMeasuresAndTheVolumeConditionStopTheStagesAsStated) {
  // sliding.settle_increment_measure off_wall: the sliding stage settles when the largest move off the
  // wall and the wall nodes' 95th-percentile move are within the tolerance for 3 steps (checked by brute
  // force on the last three steps; the largest move of all nodes may then be above it). morphing
  // off_wall + volume_tolerance_percent: the stage ends within tolerance and within the volume bound,
  // and each iteration reports the two moves as a brute-force count gives them.
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ASSERT_TRUE(s.simulation.sliding);
  s.sliding_stage.increment_measure = SlidingStageSettings::IncrementMeasure::kOffWall;
  s.sliding_stage.increment_tolerance_m = 0.05e-3;
  s.morphing.increment_measure = MorphingStageSettings::IncrementMeasure::kOffWall;
  s.morphing.volume_tolerance_percent = 0.5;
  ProneToSupinePipeline pipe(p.c, p.m, s);
  ASSERT_NE(pipe.wallSlip(), nullptr);
  // The band: the wall nodes and every node of an element touching one (brute force here).
  std::vector<int> wall;
  {
    std::vector<char> on(static_cast<size_t>(p.m.mesh.numNodes()), 0), band(on.size(), 0);
    for (int n : pipe.wallSlip()->nodes()) on[static_cast<size_t>(n)] = 1;
    for (int t = 0; t < p.m.mesh.numTets(); ++t)
      for (int i = 0; i < 4; ++i)
        if (on[static_cast<size_t>(p.m.mesh.tets()(t, i))])
          for (int j = 0; j < 4; ++j) band[static_cast<size_t>(p.m.mesh.tets()(t, j))] = 1;
    for (int n = 0; n < p.m.mesh.numNodes(); ++n)
      if (band[static_cast<size_t>(n)]) wall.push_back(n);
  }
  EXPECT_EQ(pipe.wallBandNodes(), wall);
  EXPECT_GT(wall.size(), pipe.wallSlip()->nodes().size());
  Eigen::VectorXd previous = pipe.simulator().state().displacement_m;
  std::vector<std::array<double, 3>> sliding_moves;  // off-wall max, wall p95, all max
  pipe.runGravity([&](const PipelineProgress& pr) {
    const Eigen::VectorXd& u = pipe.simulator().state().displacement_m;
    if (pr.stage == PipelineStage::kSliding) {
      double off = 0, wp95 = 0;
      offWallMoves(previous, u, wall, &off, &wp95);
      sliding_moves.push_back({off, wp95, pr.increment_m});
    }
    previous = u;
  });
  const StageReport& sl = pipe.slidingReport();
  ASSERT_TRUE(sl.converged);
  ASSERT_GE(sliding_moves.size(), 3u);
  for (size_t k = sliding_moves.size() - 3; k < sliding_moves.size(); ++k) {
    EXPECT_LE(sliding_moves[k][0], 0.05e-3) << "step " << k + 1;
    EXPECT_LE(sliding_moves[k][1], 0.05e-3) << "step " << k + 1;
  }
  const StageReport mo = pipe.runMorphing();
  const PipelineMetrics m = pipe.metrics();
  std::printf("[ measure  ] %d tets, off_wall measures: sliding %d steps, morphing %d steps (%ld reversed), volume %.3f %%, "
              "pulled mean %.3f / p95 %.3f mm, inverted %d\n",
              p.m.mesh.numTets(), sl.steps, mo.steps, mo.reversed_steps, m.volume_change_percent, 1e3 * mo.surface_mean_m,
              1e3 * mo.surface_p95_m, m.inverted_elements);
  EXPECT_TRUE(mo.converged);
  EXPECT_LE(std::abs(mo.volume_change_percent), 0.5);
  EXPECT_NEAR(mo.volume_change_percent, m.volume_change_percent, 1e-9);
  EXPECT_EQ(m.inverted_elements, 0);
  for (int k = 0; k < 3; ++k) {
    const Eigen::VectorXd before = pipe.simulator().state().displacement_m;
    const IterationReport it = pipe.iterate();
    double off = 0, wp95 = 0;
    offWallMoves(before, pipe.simulator().state().displacement_m, wall, &off, &wp95);
    EXPECT_NEAR(it.off_wall_increment_m, off, 1e-15) << "iteration " << k;
    EXPECT_NEAR(it.wall_increment_p95_m, wp95, 1e-15) << "iteration " << k;
    EXPECT_LE(it.off_wall_increment_m, it.increment_m);
    EXPECT_GT(it.wall_increment_p95_m, 0.0);  // the wall slides with the morphing
  }
}
