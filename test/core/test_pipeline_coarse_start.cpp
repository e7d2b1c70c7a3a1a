// Nested iteration (coarse_start): a pipeline's state carried to another mesh of the same case
// (startFrom), the phantom started on a coarse mesh, its settings, and cancelling either model.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_fixtures.h"

using namespace breast_sim::core;
using namespace breast_sim::core::test_fixtures;

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
  // The next steps are those of `a` itself: restore() and startFrom() resync the stiffening driver
  // (StiffeningSimulation::resync), so the next moduli come from the carried state's stress, not
  // from the state before (at rest for a new pipeline: 3–28 µm off here).
  for (int k = 0; k < 3; ++k) {
    a.iterate();
    b.iterate();
    EXPECT_LT((b.simulator().state().displacement_m - a.simulator().state().displacement_m).cwiseAbs().maxCoeff(), 1e-12)
        << "step " << k;
  }
}

TEST(CoarseStart, WithUnloadedRestShapesTheModelsMeetInTheProneShape) {
  // Each model's rest shape is its own X0, and a stiffer coarse model sags less: the two X0 differ.
  // A material point is where the prone shape has it, so the state carried between two models of one
  // mesh whose X0 differ (moduli 2 and 4 kPa) puts every node where the other model has it.
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.simulation.reference_state = SimulationSettings::ReferenceState::kUnloaded;
  s.simulation.sliding = false;
  s.morphing.enabled = false;
  PipelineSettings stiffer = s;
  stiffer.simulation.material.youngs_modulus_pa *= 2.0;
  ProneToSupinePipeline soft(p.c, p.m, s), stiff(p.c, p.m, stiffer);
  ASSERT_TRUE(soft.unloadedState().converged && stiff.unloadedState().converged);
  const double x0_gap = (soft.model().mesh.nodes() - stiff.model().mesh.nodes()).rowwise().norm().maxCoeff();
  ASSERT_TRUE(stiff.runGravity().converged);
  soft.startFrom(stiff);
  const double gap = (soft.positions() - stiff.positions()).rowwise().norm().maxCoeff();
  std::printf("[ measure  ] X0 of 2 and 4 kPa up to %.2f mm apart; carried positions %.2e mm apart\n", 1e3 * x0_gap,
              1e3 * gap);
  ASSERT_GT(x0_gap, 1e-3);  // else the check below could not tell the shapes apart
  EXPECT_LT(gap, 1e-12);
  EXPECT_LT((soft.displacement() - stiff.displacement()).cwiseAbs().maxCoeff(), 1e-12);  // both from prone
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
  // The J − 1 element: ANP's state carried over from this coarse model inverts a few rim elements,
  // which recover within 7 fine steps (ElementsInvertedOnArrivalRecover); a cancel before that would
  // leave them, and the state checks below ask for none.
  s.simulation.element = SimulationSettings::Element::kLinearTet;
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

// A coarse model of 40 % of the elements: ANP's state carried over inverts a few rim elements of
// this model. The stiffened steps let an element that arrived inverted recover (never one invert),
// so the count only falls and the run ends with none.
TEST(CoarseStart, ElementsInvertedOnArrivalRecover) {
  const SmallPhantom& p = phantom();
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  ASSERT_EQ(s.simulation.element, SimulationSettings::Element::kAnpTet);
  s.coarse_start.elements = 900;
  ProneToSupinePipeline pipe(p.c, p.m, s);
  ASSERT_TRUE(pipe.coarse());
  pipe.runGravity();
  std::vector<int> inverted;  // after each fine morphing step
  pipe.runMorphing([&](const PipelineProgress&) {
    if (&pipe.running() == &pipe) inverted.push_back(pipe.metrics().inverted_elements);
  });
  std::printf("[ measure  ] %d elements from %d: inverted after the first fine steps", p.m.mesh.numTets(),
              pipe.coarse()->model().mesh.numTets());
  for (size_t i = 0; i < std::min<size_t>(inverted.size(), 10); ++i) std::printf(" %d", inverted[i]);
  std::printf("\n");
  ASSERT_FALSE(inverted.empty());
  EXPECT_GT(inverted.front(), 0) << "the carried-over state inverts no element: the test covers nothing";
  for (size_t i = 1; i < inverted.size(); ++i) EXPECT_LE(inverted[i], inverted[i - 1]) << "fine step " << i + 1;
  EXPECT_EQ(pipe.metrics().inverted_elements, 0);
}
