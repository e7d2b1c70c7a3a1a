// The combined prone-to-supine pipeline: settings, the zero-distance target, snapshots, the Figure-2
// loop's bookkeeping (no forces after a step that could not advance, α held within tolerance).
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

using namespace breast_sim::core;
namespace fs = std::filesystem;

namespace {

const std::string kConfigDir = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/";
const std::string kPhantomCase = kConfigDir + "phantom_default.yaml";

struct SmallPhantom {
  ModelCase c;
  SimulationModel m;
  explicit SmallPhantom(int elements = 2000) {
    c = loadModelCase(kPhantomCase);
    c.meshing.target_elements = elements;
    m = buildSimulationModel(c);
  }
};

const SmallPhantom& phantom() {
  static const SmallPhantom p;
  return p;
}

std::string writeTemp(const std::string& name, const std::string& text) {
  const fs::path p = fs::temp_directory_path() / name;
  std::ofstream(p) << text;
  return p.string();
}

/// The error loadPipelineSettings gives for a case file of this text ("no error" if none).
std::string message(const std::string& text) {
  try {
    loadPipelineSettings(writeTemp("breast_sim_pipeline_bad.yaml", text));
  } catch (const std::runtime_error& e) {
    return std::string(e.what());
  }
  return std::string("no error");
}

}  // namespace

TEST(PipelineSettings, ReadsSlidingAndMorphingMapsWithTheirUnits) {
  const std::string f = writeTemp("breast_sim_pipeline_settings.yaml",
                                  "simulation: {sliding: true}\n"
                                  "sliding: {max_slide_mm: 12, gaussian_limit: false, static_friction: 0.1, kinetic_friction: 0.05}\n"
                                  "morphing: {target: surfaces/t.stl, target_unit_mm: 1, gain_pa_per_mm: 30, tolerance_mean_mm: 0.4,\n"
                                  "           tolerance_p95_mm: 1.2, time_step_s: 0.05, max_steps: 77, voxel_size_mm: 0.8}\n");
  const PipelineSettings s = loadPipelineSettings(f);
  EXPECT_TRUE(s.simulation.sliding);
  EXPECT_DOUBLE_EQ(s.sliding.max_slide_m, 0.012);
  EXPECT_FALSE(s.sliding.gaussian_limit);
  EXPECT_DOUBLE_EQ(s.sliding.static_friction, 0.1);
  EXPECT_EQ(s.morphing.target, (fs::path(f).parent_path() / "surfaces/t.stl").string());  // relative to the case file
  EXPECT_DOUBLE_EQ(s.morphing.target_length_unit_m, 1e-3);
  EXPECT_DOUBLE_EQ(s.morphing.forces.gain_pa_per_m, 3e4);
  EXPECT_DOUBLE_EQ(s.morphing.tolerance_mean_m, 4e-4);
  EXPECT_DOUBLE_EQ(s.morphing.tolerance_p95_m, 1.2e-3);
  EXPECT_DOUBLE_EQ(s.morphing.time_step_s, 0.05);
  EXPECT_EQ(s.morphing.max_steps, 77);
  EXPECT_DOUBLE_EQ(s.morphing.field.voxel_size_m, 8e-4);
}

TEST(PipelineSettings, ReadsTheStageStepKeysWithTheirUnits) {
  const std::string f = writeTemp("breast_sim_pipeline_steps.yaml",
                                  "sliding: {time_step_s: 0.5, alpha_restart: initial, settle_increment_tolerance_mm: 0.05,\n"
                                  "          settle_increment_measure: off_wall}\n"
                                  "morphing: {spring_pa_per_mm: 700, increment_measure: all_max, alpha_reversal_growth: 1.5,\n"
                                  "           volume_tolerance_percent: 0.4}\n");
  const PipelineSettings s = loadPipelineSettings(f);
  EXPECT_DOUBLE_EQ(s.sliding_stage.time_step_s, 0.5);
  EXPECT_EQ(s.sliding_stage.alpha_restart, SlidingStageSettings::AlphaRestart::kInitial);
  EXPECT_DOUBLE_EQ(s.sliding_stage.increment_tolerance_m, 5e-5);
  EXPECT_DOUBLE_EQ(s.morphing.forces.spring_pa_per_m, 7e5);
  EXPECT_EQ(s.morphing.increment_measure, MorphingStageSettings::IncrementMeasure::kAllMax);
  EXPECT_DOUBLE_EQ(s.morphing.alpha_reversal_growth, 1.5);
  EXPECT_EQ(s.sliding_stage.increment_measure, SlidingStageSettings::IncrementMeasure::kOffWall);
  EXPECT_DOUBLE_EQ(s.morphing.volume_tolerance_percent, 0.4);
  EXPECT_EQ(loadPipelineSettings(writeTemp("breast_sim_pipeline_steps3.yaml", "morphing: {increment_measure: off_wall}\n"))
                .morphing.increment_measure,
            MorphingStageSettings::IncrementMeasure::kOffWall);
  const PipelineSettings t = loadPipelineSettings(writeTemp("breast_sim_pipeline_steps2.yaml",
                                                            "sliding: {alpha_restart: current}\nmorphing: {increment_measure: pulled_p95}\n"));
  EXPECT_EQ(t.sliding_stage.alpha_restart, SlidingStageSettings::AlphaRestart::kCurrent);
  EXPECT_EQ(t.morphing.increment_measure, MorphingStageSettings::IncrementMeasure::kPulledP95);
}

TEST(PipelineSettings, BadKeysAndValuesAreNamed) {
  EXPECT_NE(message("morphing: {gain: 3}\n").find("gain"), std::string::npos);
  EXPECT_NE(message("morphing: {tolerance_p95_mm: -1}\n").find("morphing.tolerance_p95_mm"), std::string::npos);
  EXPECT_NE(message("sliding: {max_slide_mm: [1, 2]}\n").find("sliding.max_slide_mm"), std::string::npos);
  EXPECT_NE(message("simulation: {sliding: true, stiffening: false}\n").find("needs 'stiffening: true'"), std::string::npos);
  EXPECT_NE(message("sliding: {alpha_restart: never}\n").find("sliding.alpha_restart"), std::string::npos);
  EXPECT_NE(message("sliding: {time_step_s: -1}\n").find("sliding.time_step_s"), std::string::npos);
  EXPECT_NE(message("sliding: {settle_increment_tolerance_mm: -1}\n").find("sliding.settle_increment_tolerance_mm"), std::string::npos);
  EXPECT_NE(message("morphing: {spring_pa_per_mm: -5}\n").find("morphing.spring_pa_per_mm"), std::string::npos);
  EXPECT_NE(message("morphing: {alpha_reversal_growth: 0.5}\n").find("morphing.alpha_reversal_growth"), std::string::npos);
  EXPECT_NE(message("morphing: {increment_measure: some}\n").find("morphing.increment_measure"), std::string::npos);
  EXPECT_NE(message("morphing: {volume_tolerance_percent: -1}\n").find("morphing.volume_tolerance_percent"), std::string::npos);
  EXPECT_NE(message("sliding: {settle_increment_measure: max}\n").find("sliding.settle_increment_measure"), std::string::npos);
}

TEST(PipelineSettings, ReadsTheAlphaControllerPresetOfTheStiffeningMap) {
  const std::string f = writeTemp("breast_sim_pipeline_alpha.yaml",
                                  "stiffening: {initial_alpha_per_pa: 3e-3, min_alpha_per_pa: 1e-8, max_alpha_per_pa: 100,\n"
                                  "             decrease_factor: 0.6, increase_factor: 3, reversal_growth: 1.5, rate_halving: 0.25,\n"
                                  "             min_rate: 0.01, max_reversals_per_step: 7, settle_max_speed_mm_per_s: 0.5,\n"
                                  "             settle_max_relative_residual: 0.02, settle_consecutive_steps: 2}\n");
  const PipelineSettings s = loadPipelineSettings(f);
  const AlphaControllerParams& a = s.stiffening.alpha;
  EXPECT_DOUBLE_EQ(a.initial_alpha_per_pa, 3e-3);
  EXPECT_DOUBLE_EQ(a.min_alpha_per_pa, 1e-8);
  EXPECT_DOUBLE_EQ(a.max_alpha_per_pa, 100);
  EXPECT_DOUBLE_EQ(a.decrease_factor, 0.6);
  EXPECT_DOUBLE_EQ(a.increase_factor, 3);
  EXPECT_DOUBLE_EQ(a.reversal_growth, 1.5);
  EXPECT_DOUBLE_EQ(a.rate_halving, 0.25);
  EXPECT_DOUBLE_EQ(a.min_rate, 0.01);
  EXPECT_EQ(s.stiffening.max_reversals_per_step, 7);
  EXPECT_DOUBLE_EQ(s.stiffening.settle.max_speed_mps, 5e-4);
  EXPECT_DOUBLE_EQ(s.stiffening.settle.max_relative_residual, 0.02);
  EXPECT_EQ(s.stiffening.settle.consecutive_steps, 2);
  // The pipeline's controller runs with the preset: α starts at the initial value and falls by the
  // decrease factor after an accepted step.
  const SmallPhantom& p = phantom();
  PipelineSettings t = s;
  t.morphing.enabled = false;
  t.simulation.sliding = false;
  ProneToSupinePipeline pipe(p.c, p.m, t);
  EXPECT_DOUBLE_EQ(pipe.stiffening().controller().alpha(), 3e-3);
  EXPECT_DOUBLE_EQ(pipe.stiffening().controller().params().decrease_factor, 0.6);
  EXPECT_EQ(pipe.stiffening().params().max_reversals_per_step, 7);
}

TEST(PipelineSettings, BadAlphaControllerKeysNameTheKeyTheValueAndTheRange) {
  auto expectNames = [&](const std::string& text, const std::vector<std::string>& parts) {
    const std::string m = message(text);
    for (const std::string& part : parts) EXPECT_NE(m.find(part), std::string::npos) << text << " -> " << m;
  };
  expectNames("stiffening: {decrease_factor: 1.2}\n", {"stiffening.decrease_factor", "1.2", "(0, 1)"});
  expectNames("stiffening: {decrease_factor: 0}\n", {"stiffening.decrease_factor", "(0, 1)"});
  expectNames("stiffening: {increase_factor: 1}\n", {"stiffening.increase_factor", "(1, "});
  expectNames("stiffening: {rate_halving: 1}\n", {"stiffening.rate_halving", "(0, 1)"});
  expectNames("stiffening: {reversal_growth: 0.5}\n", {"stiffening.reversal_growth", "0.5", "[1, 100]"});
  expectNames("stiffening: {min_alpha_per_pa: -1}\n", {"stiffening.min_alpha_per_pa", "-1", "1/Pa"});
  expectNames("stiffening: {decrease_factor: 0.9, min_rate: 0.2}\n", {"stiffening.min_rate", "0.2", "decrease_factor"});
  expectNames("stiffening: {max_alpha_per_pa: 1, initial_alpha_per_pa: 5}\n", {"stiffening.initial_alpha_per_pa", "5"});
  expectNames("stiffening: {max_reversals_per_step: 0}\n", {"stiffening.max_reversals_per_step"});
  expectNames("stiffening: {settle_max_speed_mm_per_s: 0}\n", {"stiffening.settle_max_speed_mm_per_s", "mm/s"});
  expectNames("stiffening: {decrease_factor: fast}\n", {"stiffening.decrease_factor", "fast"});
  expectNames("stiffening: {decrease: 0.5}\n", {"decrease", "stiffening"});
  // A key given against the default of another: the default initial α (1e-2 /Pa) below a raised floor.
  expectNames("stiffening: {min_alpha_per_pa: 0.1}\n", {"stiffening", "initial_alpha_per_pa", "0.01"});
}

TEST(Pipeline, AnImageCaseCannotMorphToThePhantomTarget) {
  SmallPhantom p(1500);
  p.c.phantom.reset();  // the same model, as if it came from an image
  PipelineSettings s;
  {
    ProneToSupinePipeline automatic(p.c, p.m, s);  // the default "auto": no target for an image
    EXPECT_FALSE(automatic.hasTarget());
  }
  s.morphing.target = "phantom";
  try {
    ProneToSupinePipeline pipe(p.c, p.m, s);
    FAIL() << "an image case was given the phantom's target";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("morphing target 'phantom' needs the software phantom"), std::string::npos) << e.what();
  }
}

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
  // 0.1 mm per step) is not asserted: on some meshes a few nodes keep moving (open, issue 7).
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
  // reference: gain 20 Pa/mm, 0.1 s steps, the settings before issue 7's step work) and with the
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
    s.simulation.gravity_mps2 = 0.0;
    s.morphing.target = "";
    s.morphing.max_steps = 120;
    s.morphing.time_step_s = 0.1;
    if (pull) {
      s.morphing.forces.spring_pa_per_m = 1e5;
      s.morphing.forces.gain_pa_per_m = 1e5;
    } else {  // the seed's forces alone, as before issue 7's step work
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

TEST(Pipeline, TheSlidingStageUsesItsOwnTimeStepAndSettleTolerance) {
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.morphing.enabled = false;
  s.sliding_stage.time_step_s = 0.1;
  s.sliding_stage.increment_tolerance_m = 0.05e-3;
  ProneToSupinePipeline pipe(p.c, p.m, s);
  std::vector<double> dts;
  std::vector<double> increments;
  pipe.runGravity([&](const PipelineProgress& pr) {
    if (pr.stage != PipelineStage::kSliding) return;
    dts.push_back(pipe.simulator().params().time_step_s);
    increments.push_back(pr.increment_m);
  });
  ASSERT_TRUE(pipe.slidingReport().converged);
  ASSERT_GE(increments.size(), 3u);
  for (double dt : dts) EXPECT_DOUBLE_EQ(dt, 0.1);
  // Settled: the last three increments within the stage's own tolerance, an earlier one above it
  // (else the tolerance was never tested).
  for (size_t k = increments.size() - 3; k < increments.size(); ++k) EXPECT_LE(increments[k], 0.05e-3);
  EXPECT_GT(*std::max_element(increments.begin(), increments.end()), 0.05e-3);
}

TEST(Pipeline, TheSlidingStageSearchesAlphaFromWhereTheFixedWallSettleLeftIt) {
  // alpha_restart current: releasing the wall starts the new α search at the gravity stage's final α
  // (the first sliding step then has at most 2× it, one reversal), not at the initial 1e-2 /Pa, which
  // is ×0.8 per step ~50 steps above the floor and stiffens the tissue again (kInitial, the reference:
  // its first sliding step has α ≥ 0.8 · 1e-2 /Pa). The wall slides and the stage settles either way.
  const SmallPhantom& p = phantom();
  for (auto restart : {SlidingStageSettings::AlphaRestart::kCurrent, SlidingStageSettings::AlphaRestart::kInitial}) {
    PipelineSettings s = loadPipelineSettings(kPhantomCase);
    s.morphing.enabled = false;
    s.sliding_stage.alpha_restart = restart;
    ProneToSupinePipeline pipe(p.c, p.m, s);
    double first_sliding_alpha = -1;
    pipe.runGravity([&](const PipelineProgress& pr) {
      if (pr.stage == PipelineStage::kSliding && first_sliding_alpha < 0) first_sliding_alpha = pr.alpha_per_pa;
    });
    const double gravity_alpha = pipe.gravityReport().final_alpha_per_pa;
    const StageReport& sl = pipe.slidingReport();
    std::printf("[ measure  ] alpha restart %s: gravity ends at alpha %.3g /Pa (%d steps), first sliding step %.3g /Pa, "
                "sliding %d steps (%ld reversed)\n",
                restart == SlidingStageSettings::AlphaRestart::kCurrent ? "current" : "initial", gravity_alpha,
                pipe.gravityReport().steps, first_sliding_alpha, sl.steps, sl.reversed_steps);
    ASSERT_TRUE(pipe.gravityReport().converged);
    EXPECT_TRUE(sl.converged);
    EXPECT_EQ(pipe.metrics().inverted_elements, 0);
    ASSERT_LT(gravity_alpha, 1e-3);  // else the two cases could not be told apart
    if (restart == SlidingStageSettings::AlphaRestart::kCurrent)
      EXPECT_LE(first_sliding_alpha, 2.0 * gravity_alpha);
    else
      EXPECT_GE(first_sliding_alpha, 0.8 * StiffeningParams{}.alpha.initial_alpha_per_pa * (1 - 1e-12));
  }
}

TEST(Pipeline, GravityStageSettlesAndTheSnapshotRestoresExactly) {
  const SmallPhantom& p = phantom();
  PipelineSettings s;
  s.morphing.enabled = false;
  ProneToSupinePipeline pipe(p.c, p.m, s);
  const StageReport g = pipe.runGravity();
  EXPECT_TRUE(g.converged);
  EXPECT_EQ(pipe.metrics().inverted_elements, 0);
  // The lesions moved with the tissue, posteriorly (supine gravity pushes towards the wall, +y).
  const Points l0 = p.m.lesion_embedding.positions(p.m.mesh.nodes()), l1 = pipe.lesionPositions();
  for (Eigen::Index i = 0; i < l0.rows(); ++i) EXPECT_GT(l1(i, 1) - l0(i, 1), 1e-3) << "lesion " << i;

  const fs::path file = fs::temp_directory_path() / "breast_sim_pipeline_state.bin";
  pipe.saveState(file.string());
  const PipelineState saved = pipe.state();
  pipe.setGravityLoad(Eigen::Vector3d(5, 0, 0));
  pipe.stiffening().step();
  ASSERT_GT((pipe.simulator().state().displacement_m - saved.simulation.displacement_m).norm(), 0.0);
  pipe.loadState(file.string());
  EXPECT_EQ(pipe.simulator().state().displacement_m, saved.simulation.displacement_m);
  EXPECT_EQ(pipe.simulator().state().velocity_mps, saved.simulation.velocity_mps);
  EXPECT_EQ(pipe.modulusFactors(), saved.modulus_factors);
  EXPECT_EQ(pipe.stiffening().controller().alpha(), saved.alpha.alpha_per_pa);
  // The gravity load comes back with the state (it was the supine load), from the file and from
  // memory; without it a state loaded after a table tilt would go on under the tilted load.
  EXPECT_EQ(saved.gravity_load_mps2, pipe.supineGravityLoad());
  EXPECT_EQ(pipe.gravityLoad(), saved.gravity_load_mps2);
  pipe.setGravityLoad(Eigen::Vector3d(5, 0, 0));
  pipe.restore(saved);
  EXPECT_EQ(pipe.gravityLoad(), saved.gravity_load_mps2);
  // A file of the format before (no gravity load at its end) loads under the supine load.
  {
    PipelineState tilted = saved;
    tilted.gravity_load_mps2 = Eigen::Vector3d(1, 2, 3);
    pipe.restore(tilted);
    pipe.saveState(file.string());
    fs::resize_file(file, fs::file_size(file) - sizeof(std::int64_t) - 3 * sizeof(double));
    pipe.loadState(file.string());
    EXPECT_EQ(pipe.gravityLoad(), pipe.supineGravityLoad());
    EXPECT_EQ(pipe.simulator().state().displacement_m, saved.simulation.displacement_m);
    // A gravity load that is not finite is refused, naming it, and the state is kept.
    tilted.gravity_load_mps2.x() = std::numeric_limits<double>::quiet_NaN();
    tilted.simulation.displacement_m.setZero();
    try {
      pipe.restore(tilted);
      FAIL();
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("gravity load"), std::string::npos) << e.what();
    }
    EXPECT_EQ(pipe.simulator().state().displacement_m, saved.simulation.displacement_m);
    EXPECT_EQ(pipe.gravityLoad(), pipe.supineGravityLoad());
    pipe.saveState(file.string());  // the state file again, for the checks below
  }

  // A snapshot of another model is refused by name and leaves the state alone.
  SmallPhantom other(1000);
  PipelineSettings so;
  so.morphing.enabled = false;
  ProneToSupinePipeline pipe2(other.c, other.m, so);
  try {
    pipe2.loadState(file.string());
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("load the same case with the same meshing"), std::string::npos) << e.what();
  }
  EXPECT_EQ(pipe2.simulator().state().displacement_m.norm(), 0.0);
  // So is one of a mesh of the same size whose nodes differ (here one node moved by 1 µm; in practice
  // another numbering of the nodes).
  SimulationModel moved = p.m;
  Points x = p.m.mesh.nodes();
  x(0, 0) += 1e-6;
  moved.mesh = TetMesh(x, p.m.mesh.tets(), p.m.mesh.regionLabels());
  for (const auto& [name, set] : p.m.mesh.nodeSets()) moved.mesh.setNodeSet(name, set);
  ProneToSupinePipeline pipe3(p.c, moved, so);
  try {
    pipe3.loadState(file.string());
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("same size but other nodes"), std::string::npos) << e.what();
  }
  EXPECT_EQ(pipe3.simulator().state().displacement_m.norm(), 0.0);
  std::ofstream(file) << "not a state";
  EXPECT_THROW(pipe.loadState(file.string()), std::runtime_error);
}

TEST(PipelineSettings, TheDocumentedDefaultsOfTheCaseFileAreTheCodeDefaults) {
  // config/phantom_default.yaml lists every sliding and morphing key with its default: reading it
  // must give exactly the defaults of the structs (so the file cannot drift from the code).
  const PipelineSettings file = loadPipelineSettings(kPhantomCase), code;
  const SlidingSettings &a = file.sliding, &b = code.sliding;
  EXPECT_DOUBLE_EQ(a.field.sigma_m, b.field.sigma_m);
  EXPECT_DOUBLE_EQ(a.mobility_m_per_pa_s, b.mobility_m_per_pa_s);
  EXPECT_DOUBLE_EQ(a.static_friction, b.static_friction);
  EXPECT_DOUBLE_EQ(a.kinetic_friction, b.kinetic_friction);
  EXPECT_DOUBLE_EQ(a.static_threshold_pa, b.static_threshold_pa);
  EXPECT_DOUBLE_EQ(a.inertia, b.inertia);
  EXPECT_DOUBLE_EQ(a.max_step_m, b.max_step_m);
  EXPECT_DOUBLE_EQ(a.max_slide_m, b.max_slide_m);
  EXPECT_EQ(a.thickness_limit, b.thickness_limit);
  EXPECT_EQ(a.gaussian_limit, b.gaussian_limit);
  EXPECT_DOUBLE_EQ(a.gaussian_amplitude, b.gaussian_amplitude);
  EXPECT_DOUBLE_EQ(a.gaussian_sigma_m, b.gaussian_sigma_m);
  EXPECT_DOUBLE_EQ(a.gaussian_sigma_fraction, b.gaussian_sigma_fraction);
  EXPECT_EQ(file.sliding_method, code.sliding_method);
  const WallSlipSettings &w = file.wall_slip, &v = code.wall_slip;
  EXPECT_DOUBLE_EQ(w.normal_stiffness_pa_per_m, v.normal_stiffness_pa_per_m);
  EXPECT_DOUBLE_EQ(w.friction_stiffness_pa_per_m, v.friction_stiffness_pa_per_m);
  EXPECT_DOUBLE_EQ(w.tether_stiffness_pa_per_m, v.tether_stiffness_pa_per_m);
  EXPECT_DOUBLE_EQ(w.stick_speed_mps, v.stick_speed_mps);
  EXPECT_EQ(w.contact, v.contact);
  EXPECT_DOUBLE_EQ(w.contact_gap_m, v.contact_gap_m);
  const MorphingStageSettings &m = file.morphing, &n = code.morphing;
  EXPECT_EQ(m.enabled, n.enabled);
  EXPECT_EQ(m.target, n.target);
  EXPECT_DOUBLE_EQ(m.target_length_unit_m, n.target_length_unit_m);
  EXPECT_DOUBLE_EQ(m.forces.gain_pa_per_m, n.forces.gain_pa_per_m);
  EXPECT_DOUBLE_EQ(m.forces.max_traction_pa, n.forces.max_traction_pa);
  EXPECT_DOUBLE_EQ(m.forces.max_distance_m, n.forces.max_distance_m);
  EXPECT_EQ(m.forces.skip_constrained, n.forces.skip_constrained);
  EXPECT_DOUBLE_EQ(m.field.voxel_size_m, n.field.voxel_size_m);
  EXPECT_EQ(m.field.max_voxels_per_axis, n.field.max_voxels_per_axis);
  EXPECT_DOUBLE_EQ(m.time_step_s, n.time_step_s);
  EXPECT_DOUBLE_EQ(m.tolerance_mean_m, n.tolerance_mean_m);
  EXPECT_DOUBLE_EQ(m.tolerance_p95_m, n.tolerance_p95_m);
  EXPECT_DOUBLE_EQ(m.increment_tolerance_m, n.increment_tolerance_m);
  EXPECT_EQ(m.increment_measure, n.increment_measure);
  EXPECT_DOUBLE_EQ(m.alpha_reversal_growth, n.alpha_reversal_growth);
  EXPECT_DOUBLE_EQ(m.forces.spring_pa_per_m, n.forces.spring_pa_per_m);
  EXPECT_EQ(m.max_steps, n.max_steps);
  EXPECT_DOUBLE_EQ(m.max_step_move_m, n.max_step_move_m);
  EXPECT_DOUBLE_EQ(m.max_step_volume_change_percent, n.max_step_volume_change_percent);
  EXPECT_DOUBLE_EQ(file.sliding_stage.time_step_s, code.sliding_stage.time_step_s);
  EXPECT_EQ(file.sliding_stage.alpha_restart, code.sliding_stage.alpha_restart);
  EXPECT_DOUBLE_EQ(file.sliding_stage.increment_tolerance_m, code.sliding_stage.increment_tolerance_m);
  EXPECT_EQ(file.sliding_stage.increment_measure, code.sliding_stage.increment_measure);
  // The one documented exception ("Here: 0.5"): the phantom's target has the prone volume, so its case
  // file adds the volume condition, which the code leaves off (a measured surface need not enclose it).
  EXPECT_DOUBLE_EQ(m.volume_tolerance_percent, 0.5);
  EXPECT_DOUBLE_EQ(n.volume_tolerance_percent, 0.0);
  EXPECT_EQ(file.coarse_start.elements, code.coarse_start.elements);
  EXPECT_DOUBLE_EQ(file.coarse_start.snap_tolerance_m, code.coarse_start.snap_tolerance_m);
  const AlphaControllerParams &fa = file.stiffening.alpha, &ca = code.stiffening.alpha;
  EXPECT_DOUBLE_EQ(fa.initial_alpha_per_pa, ca.initial_alpha_per_pa);
  EXPECT_DOUBLE_EQ(fa.min_alpha_per_pa, ca.min_alpha_per_pa);
  EXPECT_DOUBLE_EQ(fa.max_alpha_per_pa, ca.max_alpha_per_pa);
  EXPECT_DOUBLE_EQ(fa.decrease_factor, ca.decrease_factor);
  EXPECT_DOUBLE_EQ(fa.increase_factor, ca.increase_factor);
  EXPECT_DOUBLE_EQ(fa.reversal_growth, ca.reversal_growth);
  EXPECT_DOUBLE_EQ(fa.rate_halving, ca.rate_halving);
  EXPECT_DOUBLE_EQ(fa.min_rate, ca.min_rate);
  EXPECT_EQ(file.stiffening.max_reversals_per_step, code.stiffening.max_reversals_per_step);
  EXPECT_DOUBLE_EQ(file.stiffening.settle.max_speed_mps, code.stiffening.settle.max_speed_mps);
  EXPECT_DOUBLE_EQ(file.stiffening.settle.max_relative_residual, code.stiffening.settle.max_relative_residual);
  EXPECT_EQ(file.stiffening.settle.consecutive_steps, code.stiffening.settle.consecutive_steps);
}

// Issue 7's targets in a reduced size: the phantom (~4.8k elements) with the settings of its case
// file (stiffening, J − 1 term, implicit sliding on the wall) reaches its supine target: skin → target
// mean ≤ 0.5 mm and p95 ≤ 1.5 mm, volume within 1 %, no inverted element. Then a state with the
// wall's stick points saved and restored gives the same next step.
TEST(Pipeline, PhantomWithSlidingReachesItsSupineTargetAndItsStateRestores) {
  SmallPhantom p(4000);
  const PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ASSERT_TRUE(s.simulation.sliding);
  ASSERT_EQ(s.sliding_method, PipelineSettings::SlidingMethod::kImplicit);
  ProneToSupinePipeline pipe(p.c, p.m, s);
  pipe.run();
  const StageReport& sl = pipe.slidingReport();
  const StageReport& mo = pipe.morphingReport();
  const PipelineMetrics m = pipe.metrics();
  std::printf("[ measure  ] %d tets: sliding %d steps (%ld reversed, largest slide %.1f mm), morphing %d steps (%ld reversed, "
              "converged %d); skin->target mean %.3f / p95 %.3f mm, target->skin mean %.2f / p95 %.2f mm, volume %.2f %%, "
              "inverted %d\n",
              p.m.mesh.numTets(), sl.steps, sl.reversed_steps, 1e3 * sl.max_slide_m, mo.steps, mo.reversed_steps, mo.converged,
              1e3 * m.surface.model_to_target.mean_m, 1e3 * m.surface.model_to_target.p95_m,
              1e3 * m.surface.target_to_model.mean_m, 1e3 * m.surface.target_to_model.p95_m, m.volume_change_percent,
              m.inverted_elements);
  EXPECT_TRUE(sl.converged);
  EXPECT_TRUE(mo.converged);
  EXPECT_GT(sl.max_slide_m, 5e-3);  // the wall did slide
  EXPECT_LE(m.surface.model_to_target.mean_m, 0.5e-3);
  EXPECT_LE(m.surface.model_to_target.p95_m, 1.5e-3);
  EXPECT_LT(std::abs(m.volume_change_percent), 1.0);
  EXPECT_EQ(m.inverted_elements, 0);

  const PipelineState saved = pipe.state();
  ASSERT_EQ(saved.sliding_targets_m.rows(), static_cast<Eigen::Index>(pipe.wallSlip()->nodes().size()));
  pipe.iterate();
  const Eigen::VectorXd after_one = pipe.simulator().state().displacement_m;
  pipe.iterate();
  pipe.restore(saved);
  EXPECT_EQ(pipe.wallSlip()->stickPoints(), saved.sliding_targets_m);
  pipe.iterate();
  // Equal up to the iterative solve (the multigrid's coarse operators are renewed every 4th step,
  // a phase the state does not carry): measured 3 nm, and 128 nm when the stage's stop fell so that
  // the two steps sit on either side of a renewal; a lost slip state gave 50 µm.
  EXPECT_LT((pipe.simulator().state().displacement_m - after_one).cwiseAbs().maxCoeff(), 1e-6);
}

// --- Cancelling: a stage that is cancelled cancels the run, and the stages after it do not run. ---

namespace {

/// Where a run is cancelled: the progress callback sets the flag once `step` steps of `stage` are
/// accepted. `fine`: only for the fine model's steps (with coarse_start, the coarse one reports first).
struct CancelAt {
  PipelineStage stage;
  int step;
  bool fine = false;
};

std::string describe(const CancelAt& at) {
  return std::string("cancelled at ") + (at.fine ? "fine " : "") + stageName(at.stage) + " step " + std::to_string(at.step);
}

PipelineProgressFn cancelAt(const ProneToSupinePipeline& pipe, CancelAt at, std::atomic<bool>& cancel) {
  return [&pipe, at, &cancel](const PipelineProgress& pr) {
    if (pr.stage == at.stage && pr.step >= at.step && (!at.fine || &pipe.running() == &pipe)) cancel = true;
  };
}

/// What a stopped run leaves must be usable: finite positions, no inverted element, metrics, and a
/// snapshot that restores to itself.
void expectAConsistentState(ProneToSupinePipeline& pipe) {
  EXPECT_TRUE(pipe.positions().allFinite());
  const PipelineMetrics m = pipe.metrics();
  EXPECT_EQ(m.inverted_elements, 0);
  EXPECT_TRUE(std::isfinite(m.volume_change_percent));
  const PipelineState s = pipe.state();
  pipe.restore(s);
  const PipelineState t = pipe.state();
  EXPECT_EQ(t.simulation.displacement_m, s.simulation.displacement_m);
  EXPECT_EQ(t.simulation.velocity_mps, s.simulation.velocity_mps);
  EXPECT_EQ(t.modulus_factors, s.modulus_factors);
  EXPECT_EQ(t.alpha.alpha_per_pa, s.alpha.alpha_per_pa);
  EXPECT_EQ(t.sliding_targets_m, s.sliding_targets_m);
  EXPECT_EQ(t.sliding_slip_directions, s.sliding_slip_directions);
  EXPECT_EQ(t.morphing_forces_n, s.morphing_forces_n);
  EXPECT_EQ(t.gravity_load_mps2, s.gravity_load_mps2);
}

/// With the flag cleared, run() goes through every stage to the end.
void expectARunCompletes(ProneToSupinePipeline& pipe, std::atomic<bool>& cancel) {
  cancel = false;
  pipe.run({}, &cancel);
  EXPECT_EQ(pipe.stage(), PipelineStage::kDone);
  for (const StageReport* r : {&pipe.gravityReport(), &pipe.slidingReport(), &pipe.morphingReport()}) {
    EXPECT_TRUE(r->ran);
    EXPECT_FALSE(r->cancelled);
  }
  EXPECT_GT(pipe.morphingReport().steps, 0);
  EXPECT_GE(pipe.morphingReport().surface_mean_m, 0.0);
  EXPECT_TRUE(invertedTets(pipe.model().mesh.tets(), pipe.positions()).empty());
}

}  // namespace

TEST(Pipeline, CancelDuringSlidingCancelsTheRunAndMorphingDoesNotStart) {
  // The navigation node's sequence: runGravity, then runMorphing unless the returned report says
  // cancelled. A cancel in the sliding stage (after the fixed-wall settle converged) must say so.
  const SmallPhantom& p = phantom();
  const PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ASSERT_TRUE(s.simulation.sliding);
  for (int at : {1, 5}) {
    SCOPED_TRACE("cancelled at sliding step " + std::to_string(at));
    ProneToSupinePipeline pipe(p.c, p.m, s);
    std::atomic<bool> cancel{false};
    const StageReport g = pipe.runGravity(cancelAt(pipe, {PipelineStage::kSliding, at}, cancel), &cancel);
    EXPECT_TRUE(g.cancelled);
    EXPECT_TRUE(pipe.gravityReport().converged);  // the fixed-wall settle itself ran to its end
    EXPECT_TRUE(pipe.slidingReport().cancelled);
    EXPECT_EQ(pipe.slidingReport().steps, at);
    if (!g.cancelled) pipe.runMorphing({}, &cancel);
    EXPECT_FALSE(pipe.morphingReport().ran);
    // Asked anyway, the morphing stage stops before its first step and reports the distances where it stands.
    const StageReport m = pipe.runMorphing({}, &cancel);
    EXPECT_TRUE(m.cancelled);
    EXPECT_EQ(m.steps, 0);
    EXPECT_FALSE(m.converged);
    EXPECT_GT(m.surface_mean_m, 0.0);
    EXPECT_GE(m.surface_p95_m, m.surface_mean_m);
    expectAConsistentState(pipe);
    expectARunCompletes(pipe, cancel);
  }
}

TEST(Pipeline, ACancelInAnyStageCancelsTheRunAndTheStagesAfterItDoNotRun) {
  const SmallPhantom& p = phantom();
  const PipelineSettings s = loadPipelineSettings(kPhantomCase);
  for (const CancelAt at : {CancelAt{PipelineStage::kGravity, 1}, CancelAt{PipelineStage::kGravity, 5},
                            CancelAt{PipelineStage::kSliding, 1}, CancelAt{PipelineStage::kSliding, 5},
                            CancelAt{PipelineStage::kMorphing, 1}, CancelAt{PipelineStage::kMorphing, 5}}) {
    SCOPED_TRACE(describe(at));
    ProneToSupinePipeline pipe(p.c, p.m, s);
    std::atomic<bool> cancel{false};
    pipe.run(cancelAt(pipe, at, cancel), &cancel);
    EXPECT_NE(pipe.stage(), PipelineStage::kDone);
    const StageReport &g = pipe.gravityReport(), &sl = pipe.slidingReport(), &mo = pipe.morphingReport();
    const StageReport& stopped = at.stage == PipelineStage::kGravity ? g : at.stage == PipelineStage::kSliding ? sl : mo;
    EXPECT_TRUE(stopped.ran);
    EXPECT_TRUE(stopped.cancelled);
    EXPECT_EQ(stopped.steps, at.step);
    if (at.stage == PipelineStage::kGravity) {
      EXPECT_FALSE(sl.ran);
      EXPECT_EQ(sl.steps, 0);
    } else {
      EXPECT_TRUE(g.converged);
      EXPECT_FALSE(g.cancelled);
    }
    if (at.stage != PipelineStage::kMorphing) {
      EXPECT_FALSE(mo.ran);
      EXPECT_EQ(mo.steps, 0);
    } else {
      EXPECT_TRUE(sl.converged);
      EXPECT_GE(mo.surface_mean_m, 0.0);  // measured where it stopped
    }
    expectAConsistentState(pipe);
    expectARunCompletes(pipe, cancel);
  }
}

TEST(Pipeline, RunMorphingWithTheCancelFlagAlreadySetReturnsCancelledBeforeItsFirstStep) {
  // Straight after construction: no morphing step has ever run (no force generator yet).
  const SmallPhantom& p = phantom();
  const PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ProneToSupinePipeline pipe(p.c, p.m, s);
  const std::atomic<bool> cancel{true};
  const StageReport m = pipe.runMorphing({}, &cancel);
  EXPECT_TRUE(m.ran);
  EXPECT_TRUE(m.cancelled);
  EXPECT_EQ(m.steps, 0);
  EXPECT_TRUE(pipe.morphingReport().cancelled);
  EXPECT_GT(m.surface_mean_m, 0.0);  // the rest shape is not the supine target
  EXPECT_EQ(pipe.simulator().state().displacement_m.norm(), 0.0);
  EXPECT_NE(pipe.stage(), PipelineStage::kDone);
  // So does run(): the first stage stops before its first step, nothing after it runs.
  pipe.run({}, &cancel);
  EXPECT_TRUE(pipe.gravityReport().cancelled);
  EXPECT_EQ(pipe.gravityReport().steps, 0);
  EXPECT_FALSE(pipe.slidingReport().ran);
  EXPECT_NE(pipe.stage(), PipelineStage::kDone);
  expectAConsistentState(pipe);
}

// --- Nested iteration (coarse_start): a pipeline's state carried to another mesh of the same case. ---

TEST(CoarseStart, FromTheSameModelTheStateIsCarriedOverExactly) {
  // Two pipelines on one mesh: every carried quantity must come back as it was (nodes are vertices of
  // their own elements, centroids inside them, each pulled vertex its own nearest coarse vertex).
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.simulation.solver.kind = SolverSettings::Kind::kCholmod;  // exact solves: the next steps can be compared exactly
  ProneToSupinePipeline a(p.c, p.m, s), b(p.c, p.m, s);
  a.runGravity();
  for (int k = 0; k < 5; ++k) a.iterate();
  ASSERT_TRUE(a.wallSlip() && a.morphing());
  b.startFrom(a);
  const SimulationState &sa = a.simulator().state(), &sb = b.simulator().state();
  EXPECT_LT((sb.displacement_m - sa.displacement_m).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_LT((sb.velocity_mps - sa.velocity_mps).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_EQ(b.modulusFactors(), a.modulusFactors());
  EXPECT_EQ(b.stiffening().controller().alpha(), a.stiffening().controller().alpha());
  EXPECT_EQ(b.simulator().params().gravity_mps2, a.simulator().params().gravity_mps2);
  // The wall nodes keep their friction state: stick points and slip directions.
  ASSERT_EQ(b.wallSlip()->nodes(), a.wallSlip()->nodes());
  EXPECT_LT((b.wallSlip()->stickPoints() - a.wallSlip()->stickPoints()).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_EQ(b.wallSlip()->slipDirections(), a.wallSlip()->slipDirections());
  ASSERT_GT(a.wallSlip()->slipDirections().rowwise().norm().maxCoeff(), 0.0) << "no wall node slips: a weak check";
  // The morphing forces: each vertex's own traction (force / area · the same area).
  ASSERT_TRUE(b.morphing());
  ASSERT_EQ(b.morphing()->vertices(), a.morphing()->vertices());
  const Points &fa = a.morphing()->accumulatedForces(), &fb = b.morphing()->accumulatedForces();
  ASSERT_GT(fa.norm(), 0.0);
  EXPECT_LT((fb - fa).cwiseAbs().maxCoeff(), 1e-12 * fa.cwiseAbs().maxCoeff());
  // The next steps are those of `a` itself. (Before StiffeningSimulation::resync, a restored pipeline
  // took its next moduli from the stress of the state before the restore, at rest for a new one:
  // 3–28 µm off here, with restore() as with startFrom().)
  for (int k = 0; k < 3; ++k) {
    a.iterate();
    b.iterate();
    EXPECT_LT((b.simulator().state().displacement_m - a.simulator().state().displacement_m).cwiseAbs().maxCoeff(), 1e-12)
        << "step " << k;
  }
}

TEST(CoarseStart, AnAffineDisplacementIsCarriedExactlyToAnotherMeshAndTheForcesKeepTheirTotal) {
  const SmallPhantom& coarse = phantom();  // 2000 elements
  const SmallPhantom fine(5000);
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ProneToSupinePipeline a(coarse.c, coarse.m, s), b(fine.c, fine.m, s);
  a.runGravity();
  for (int k = 0; k < 3; ++k) a.iterate();
  // Replace the coarse displacement by an affine field (the forces and the rest stay).
  PipelineState st = a.state();
  Eigen::Matrix3d A;
  A << 0.01, -0.02, 0.005, 0.03, 0.0, -0.01, 0.002, 0.015, -0.02;
  const Eigen::Vector3d t(1e-3, -2e-3, 0.5e-3);
  for (int n = 0; n < coarse.m.mesh.numNodes(); ++n)
    st.simulation.displacement_m.segment<3>(3 * n) = A * coarse.m.mesh.nodes().row(n).transpose() + t;
  a.restore(st);
  b.startFrom(a);
  // Exact at the fine nodes inside the coarse mesh; the ones outside take the value at the closest
  // point of the coarse surface (how far off that is depends on the distance, checked loosely).
  const PointEmbedding where(coarse.m.mesh, fine.m.mesh.nodes(), {}, 5e-3);
  const Eigen::VectorXd& u = b.simulator().state().displacement_m;
  int inside = 0;
  for (int n = 0; n < fine.m.mesh.numNodes(); ++n) {
    const Eigen::Vector3d expected = A * fine.m.mesh.nodes().row(n).transpose() + t;
    const double err = (u.segment<3>(3 * n) - expected).norm();
    const double outside = where.points()[static_cast<size_t>(n)].outside_distance_m;
    if (outside == 0.0) {
      ++inside;
      EXPECT_LT(err, 1e-12) << "node " << n;
    } else {
      EXPECT_LT(err, 0.05 * outside + 1e-12) << "node " << n << ", " << outside * 1e3 << " mm outside";  // ‖A‖ ≈ 0.04
    }
  }
  EXPECT_GT(inside, fine.m.mesh.numNodes() / 2);
  // The morphing tractions keep their total force within a few per cent (the two skins' areas differ
  // by their facet approximation).
  ASSERT_TRUE(b.morphing());
  const Eigen::RowVector3d fa = a.morphing()->accumulatedForces().colwise().sum();
  const Eigen::RowVector3d fb = b.morphing()->accumulatedForces().colwise().sum();
  ASSERT_GT(fa.norm(), 0.0);
  EXPECT_LT((fb - fa).norm(), 0.05 * fa.norm()) << "coarse " << fa << " N, fine " << fb << " N";
  // Pipelines that differ in sliding are refused, and the one asked stays as it was.
  PipelineSettings off = s;
  off.simulation.sliding = false;
  ProneToSupinePipeline c(fine.c, fine.m, off);
  EXPECT_THROW(c.startFrom(a), std::invalid_argument);
  EXPECT_EQ(c.simulator().state().displacement_m.norm(), 0.0);
}

TEST(CoarseStart, ThePhantomStartedOnACoarseMeshMeetsTheTargetsWithFewerFineSolves) {
  SmallPhantom p(4000);
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ProneToSupinePipeline single(p.c, p.m, s);
  single.run();
  s.coarse_start.elements = 1500;
  ProneToSupinePipeline nested(p.c, p.m, s);
  ASSERT_TRUE(nested.coarse());
  const int coarse_elements = nested.coarse()->model().mesh.numTets();
  EXPECT_LT(coarse_elements, p.m.mesh.numTets() / 2);
  nested.run();
  const StageReport &g = nested.gravityReport(), &mo = nested.morphingReport();
  const PipelineMetrics m = nested.metrics();
  const StageReport &g1 = single.gravityReport(), &s1 = single.slidingReport(), &m1 = single.morphingReport();
  const long single_solves = g1.steps + g1.reversed_steps + s1.steps + s1.reversed_steps + m1.steps + m1.reversed_steps;
  double lesion_shift = 0;
  const Points l1 = single.lesionPositions(), l2 = nested.lesionPositions();
  for (Eigen::Index i = 0; i < l1.rows(); ++i) lesion_shift = std::max(lesion_shift, (l2.row(i) - l1.row(i)).norm());
  std::printf("[ measure  ] %d tets from %d: %d coarse gravity, %d coarse sliding, %d coarse + %d fine morphing steps "
              "(single-level: %ld solves on the fine mesh); skin->target mean %.3f / p95 %.3f mm, volume %.2f %%, inverted %d, "
              "lesions %.2f mm from the single-level run\n",
              p.m.mesh.numTets(), coarse_elements, g.steps, nested.slidingReport().steps, mo.coarse_steps, mo.steps,
              single_solves, 1e3 * m.surface.model_to_target.mean_m, 1e3 * m.surface.model_to_target.p95_m,
              m.volume_change_percent, m.inverted_elements, 1e3 * lesion_shift);
  auto expectTargets = [&](const ProneToSupinePipeline& run) {
    const StageReport& r = run.morphingReport();
    const PipelineMetrics mm = run.metrics();
    EXPECT_EQ(run.gravityReport().elements, coarse_elements);
    EXPECT_EQ(r.elements, p.m.mesh.numTets());
    EXPECT_EQ(r.coarse_elements, coarse_elements);
    EXPECT_GT(r.coarse_steps, 0);
    EXPECT_TRUE(r.converged);
    EXPECT_LE(mm.surface.model_to_target.mean_m, 0.5e-3);
    EXPECT_LE(mm.surface.model_to_target.p95_m, 1.5e-3);
    EXPECT_LT(std::abs(mm.volume_change_percent), 1.0);
    EXPECT_EQ(mm.inverted_elements, 0);
    EXPECT_LT(r.steps + r.reversed_steps, single_solves / 2);
  };
  expectTargets(nested);

  // config/phantom_fast.yaml (base: the phantom case; α decrease 0.6, morphing stopped on the pulled
  // skin's moves) started on the same coarse size meets the same targets.
  PipelineSettings fs = loadPipelineSettings(kConfigDir + "phantom_fast.yaml");
  ASSERT_EQ(fs.morphing.increment_measure, MorphingStageSettings::IncrementMeasure::kPulledP95);
  fs.coarse_start.elements = 1500;
  ProneToSupinePipeline fast(p.c, p.m, fs);
  fast.run();
  const PipelineMetrics fm = fast.metrics();
  const StageReport& fmo = fast.morphingReport();
  std::printf("[ measure  ] %d tets from %d with the fast settings: %d coarse gravity, %d coarse sliding, %d coarse + %d fine "
              "morphing steps; skin->target mean %.3f / p95 %.3f mm, volume %.2f %%, inverted %d\n",
              p.m.mesh.numTets(), coarse_elements, fast.gravityReport().steps, fast.slidingReport().steps, fmo.coarse_steps,
              fmo.steps, 1e3 * fm.surface.model_to_target.mean_m, 1e3 * fm.surface.model_to_target.p95_m,
              fm.volume_change_percent, fm.inverted_elements);
  expectTargets(fast);
}

TEST(CoarseStart, SettingsAreReadAndCheckedByName) {
  const std::string f = writeTemp("breast_sim_coarse_start.yaml", "coarse_start:\n  elements: 5000\n  snap_tolerance_mm: 3\n");
  const PipelineSettings s = loadPipelineSettings(f);
  EXPECT_EQ(s.coarse_start.elements, 5000);
  EXPECT_DOUBLE_EQ(s.coarse_start.snap_tolerance_m, 3e-3);
  EXPECT_EQ(PipelineSettings{}.coarse_start.elements, 0);  // off by default
  EXPECT_NE(message("coarse_start:\n  elements: -1\n").find("coarse_start.elements"), std::string::npos);
  EXPECT_NE(message("coarse_start:\n  snap_tolerance_mm: 0\n").find("coarse_start.snap_tolerance_mm"), std::string::npos);
  EXPECT_NE(message("coarse_start:\n  elemnts: 10\n").find("elemnts"), std::string::npos);

  // A coarse target not at most half the model's elements: the model runs alone.
  const SmallPhantom& p = phantom();
  PipelineSettings big;
  big.coarse_start.elements = p.m.mesh.numTets() / 2 + 1;
  EXPECT_EQ(ProneToSupinePipeline(p.c, p.m, big).coarse(), nullptr);
  big.coarse_start.elements = p.m.mesh.numTets() / 2;
  EXPECT_NE(ProneToSupinePipeline(p.c, p.m, big).coarse(), nullptr);
  // Without the morphing stage (or a target) the model runs alone: it settles in that stage.
  big.morphing.enabled = false;
  EXPECT_EQ(ProneToSupinePipeline(p.c, p.m, big).coarse(), nullptr);
  big.morphing.enabled = true;
  big.morphing.target = "";
  EXPECT_EQ(ProneToSupinePipeline(p.c, p.m, big).coarse(), nullptr);
}

TEST(CoarseStart, ACancelInAnyStageOfTheCoarseOrTheFineModelCancelsTheRun) {
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.coarse_start.elements = 900;
  for (const CancelAt at : {CancelAt{PipelineStage::kGravity, 1}, CancelAt{PipelineStage::kSliding, 1},
                            CancelAt{PipelineStage::kSliding, 5}, CancelAt{PipelineStage::kMorphing, 1},
                            CancelAt{PipelineStage::kMorphing, 5}, CancelAt{PipelineStage::kMorphing, 1, true}}) {
    SCOPED_TRACE(describe(at));
    ProneToSupinePipeline pipe(p.c, p.m, s);
    ASSERT_TRUE(pipe.coarse());
    std::atomic<bool> cancel{false};
    // The node's sequence: runGravity, then runMorphing unless the returned report says cancelled.
    const StageReport g = pipe.runGravity(cancelAt(pipe, at, cancel), &cancel);
    EXPECT_EQ(g.cancelled, at.stage != PipelineStage::kMorphing);
    if (!g.cancelled) {
      const StageReport m = pipe.runMorphing(cancelAt(pipe, at, cancel), &cancel);
      EXPECT_TRUE(m.cancelled);
      EXPECT_EQ(pipe.coarse()->morphingReport().cancelled, !at.fine);
      EXPECT_EQ(at.fine ? m.steps : m.coarse_steps, at.step);
      if (at.fine) {
        EXPECT_GT(m.coarse_steps, 0);  // the coarse model morphed first
      } else {
        EXPECT_EQ(m.steps, 0);  // the fine model did not start
      }
    } else {
      const StageReport& stopped = at.stage == PipelineStage::kGravity ? pipe.gravityReport() : pipe.slidingReport();
      EXPECT_TRUE(stopped.cancelled);
      EXPECT_EQ(stopped.steps, at.step);
      EXPECT_EQ(pipe.slidingReport().ran, at.stage == PipelineStage::kSliding);
      EXPECT_FALSE(pipe.morphingReport().ran);
      // The fine model never took the coarse one's unfinished state.
      EXPECT_EQ(pipe.simulator().state().displacement_m.norm(), 0.0);
      // Asked anyway, the morphing stage stops before its first step, on either model.
      const StageReport m = pipe.runMorphing({}, &cancel);
      EXPECT_TRUE(m.cancelled);
      EXPECT_EQ(m.steps + m.coarse_steps, 0);
    }
    expectAConsistentState(pipe);
    expectARunCompletes(pipe, cancel);
    EXPECT_GT(pipe.morphingReport().coarse_steps, 0);
  }
}
