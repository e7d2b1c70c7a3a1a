// Von Mises stiffening with time-step reversal: the α controller, the reversal loop on a
// case that inverts, the undo history, the settle criterion, explicit Euler and the trimmed
// stability grid.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <iostream>
#include <memory>
#include <string>

#include <omp.h>

#include <Eigen/Geometry>

#include "breast_sim/core/fem/anp_tet_fem.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/material/explicit_euler.h"
#include "breast_sim/core/material/stability_map.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/solver/cholmod_solver.h"

using namespace breast_sim::core;

namespace {

constexpr double kPi = 3.14159265358979323846;

// The meshes here are tiny: one thread is faster than two (no spinning, no barriers), above all on
// a shared machine.
[[maybe_unused]] const int kOneThread = (omp_set_num_threads(1), 1);

// The phantom's hard case at ~1000 elements: prone rest shape, chest wall fixed, supine gravity.
const StabilityLoadCase& tinyPhantom() {
  static const StabilityLoadCase load = makePhantomLoadCase(defaultPhantomCasePath(), 1000);
  return load;
}

template <class F>
void expectThrowsNaming(F f, const std::string& name) {
  try {
    f();
    ADD_FAILURE() << "no exception for " << name;
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find(name), std::string::npos) << e.what();
  }
}

struct PhantomSim {
  std::unique_ptr<DynamicSimulator> sim;
  std::unique_ptr<StiffeningSimulation> stiff;
};

// E = 600 Pa, ν = 0.48: co-rotated FEM with fixed E pushes elements through each other here.
PhantomSim makePhantomSim(double dt, const StiffeningParams& p, double E = 600.0) {
  const StabilityLoadCase& load = tinyPhantom();
  ElasticMaterial mat;
  mat.youngs_modulus_pa = E;
  mat.poisson_ratio = 0.48;
  DynamicsParams dyn;
  dyn.time_step_s = dt;
  PhantomSim s;
  s.sim = std::make_unique<DynamicSimulator>(load.mesh, std::make_unique<CorotatedTetFem>(load.mesh, mat), mat, dyn,
                                             std::make_unique<CholmodSolver>(CholmodOptions{1}));
  s.stiff = std::make_unique<StiffeningSimulation>(*s.sim, load.mesh, p);
  s.stiff->fixNodes(load.fixed_nodes);
  s.stiff->setGravity(load.gravity_mps2);
  return s;
}

// A 2×2×2 block of tetrahedra, 2 cm on a side, of 2 kPa tissue at ν 0.48, and its top corner node.
struct SmallBlock {
  TetMesh m = makeBoxMesh({2, 2, 2}, {0.02, 0.02, 0.02});
  ElasticMaterial mat;
  int corner = -1;
  SmallBlock() {
    mat.youngs_modulus_pa = 2000.0;
    mat.poisson_ratio = 0.48;
    for (int n = 0; n < m.numNodes(); ++n)
      if ((m.nodes().row(n).array() > 0.019).all()) corner = n;
  }
};

// The smallest volume ratio J = V / V0 over the elements of m displaced by u.
double minVolumeRatio(const TetMesh& m, const Eigen::VectorXd& u) {
  const Eigen::VectorXd V0 = m.tetVolumes();
  double jmin = 1e9;
  for (int e = 0; e < m.numTets(); ++e) {
    Eigen::Vector3d x[4];
    for (int i = 0; i < 4; ++i)
      x[i] = (m.nodes().row(m.tets()(e, i)) + u.segment<3>(3 * m.tets()(e, i)).transpose()).transpose();
    jmin = std::min(jmin, (x[1] - x[0]).dot((x[2] - x[0]).cross(x[3] - x[0])) / 6.0 / V0[e]);
  }
  return jmin;
}

}  // namespace

TEST(AlphaController, InvalidParametersThrowNamingTheField) {
  auto with = [](auto change) {
    AlphaControllerParams p;
    change(p);
    return p;
  };
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.decrease_factor = 1.0; })); }, "decrease_factor");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.increase_factor = 1.0; })); }, "increase_factor");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.min_alpha_per_pa = 0.0; })); }, "min_alpha_per_pa");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.initial_alpha_per_pa = 1e9; })); }, "initial_alpha_per_pa");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.rate_halving = 1.0; })); }, "rate_halving");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.min_rate = 0.5; })); }, "min_rate");
  expectThrowsNaming([&] { AlphaController(with([](auto& p) { p.reversal_growth = 0.5; })); }, "reversal_growth");
  {
    AlphaController c;
    AlphaControllerParams bad;
    bad.reversal_growth = 0.5;
    expectThrowsNaming([&] { c.setParams(bad); }, "reversal_growth");
    EXPECT_EQ(c.params().reversal_growth, 1.0);  // the old parameters stay
  }
  StiffeningParams sp;
  sp.max_reversals_per_step = 0;
  expectThrowsNaming([&] { sp.validate(); }, "max_reversals_per_step");
  sp = {};
  sp.history_size = 0;
  expectThrowsNaming([&] { sp.validate(); }, "history_size");
  sp = {};
  sp.gravity_direction_tolerance_deg = 200;
  expectThrowsNaming([&] { sp.validate(); }, "gravity_direction_tolerance_deg");
  sp = {};
  sp.settle.max_speed_mps = -1;
  expectThrowsNaming([&] { sp.validate(); }, "max_speed_mps");
  StabilityRun run;
  run.poisson_ratio = 0.5;
  expectThrowsNaming([&] { run.validate(); }, "poisson_ratio");
  DivergenceLimits lim;
  lim.max_displacement_m = 0;
  expectThrowsNaming([&] { lim.validate(); }, "max_displacement_m");
  expectThrowsNaming([&] { makePhantomLoadCase(defaultPhantomCasePath(), 0); }, "target_elements");
  expectThrowsNaming([&] { parseStabilityMethod("implicit"); }, "implicit");
}

TEST(AlphaController, DecreasesOnAcceptIncreasesOnReversalWithinBounds) {
  AlphaControllerParams p;
  p.initial_alpha_per_pa = 1e-2;
  p.min_alpha_per_pa = 1e-3;
  p.max_alpha_per_pa = 5e-2;
  AlphaController c(p);
  c.onAccepted();
  EXPECT_DOUBLE_EQ(c.alpha(), 1e-2 * p.decrease_factor);
  c.onReversed(1);
  EXPECT_DOUBLE_EQ(c.alpha(), 1e-2 * p.decrease_factor * p.increase_factor);
  for (int i = 0; i < 10; ++i) c.onReversed(i + 1);
  EXPECT_DOUBLE_EQ(c.alpha(), p.max_alpha_per_pa);
  for (int i = 0; i < 100; ++i) c.onAccepted();
  EXPECT_DOUBLE_EQ(c.alpha(), p.min_alpha_per_pa);
  c.restart();
  EXPECT_DOUBLE_EQ(c.alpha(), p.initial_alpha_per_pa);
  EXPECT_EQ(c.phase(), AlphaController::Phase::kSearch);
}

TEST(AlphaController, RepeatedReversalsOfOneStepGrowGeometricallyWithReversalGrowth) {
  // Without growth (the default) every repeated reversal doubles α; with growth 2 the k-th multiplies
  // by 2 · 2^(k−1), so four reversals of one step raise α by 2·4·8·16 = 1024 (default: 16). The first
  // reversal of a step and accepted steps are unchanged.
  AlphaControllerParams p;
  p.initial_alpha_per_pa = 1e-7;
  AlphaController plain(p);
  p.reversal_growth = 2.0;
  AlphaController grown(p);
  for (int attempt = 1; attempt <= 4; ++attempt) {
    plain.onReversed(attempt);
    grown.onReversed(attempt);
  }
  EXPECT_NEAR(plain.alpha(), 1e-7 * 16, 1e-18);
  EXPECT_NEAR(grown.alpha(), 1e-7 * 1024, 1e-16);
  grown.onAccepted();
  EXPECT_NEAR(grown.alpha(), 1e-7 * 1024 * p.decrease_factor, 1e-16);
  grown.onReversed(1);  // a new step's first reversal: × increase_factor only
  EXPECT_NEAR(grown.alpha(), 1e-7 * 1024 * p.decrease_factor * 2, 1e-16);
  for (int attempt = 2; attempt < 40; ++attempt) grown.onReversed(attempt);
  EXPECT_DOUBLE_EQ(grown.alpha(), p.max_alpha_per_pa);  // still capped
}

// In the settling phase the second reversal of one step raises α by twice the settling increment,
// and only a third one by the search phase's factor: not ×2 at once (which the settling descent,
// × (1 − ρ) per step, takes hundreds of steps to undo).
TEST(AlphaController, InTheSettlingPhaseASecondReversalOfAStepTakesTwiceTheSettlingIncrement) {
  AlphaControllerParams p;
  p.initial_alpha_per_pa = 1e-3;
  AlphaController c(p);
  // Decrease, increase, decrease: an oscillation, and the settling phase.
  c.onAccepted();
  c.onReversed(1);
  c.onAccepted();
  ASSERT_EQ(c.phase(), AlphaController::Phase::kSettling);
  const double k = (p.increase_factor - 1.0) / (1.0 - p.decrease_factor);
  // Deep in settling: more oscillations halve ρ down to its floor.
  for (int i = 0; i < 20; ++i) {
    c.onReversed(1);
    c.onAccepted();
  }
  const double rho = c.rate();
  ASSERT_DOUBLE_EQ(rho, p.min_rate);
  const double alpha = c.alpha();
  c.onReversed(1);
  EXPECT_NEAR(c.alpha(), alpha * (1 + k * rho), 1e-12 * alpha);
  c.onReversed(2);
  EXPECT_NEAR(c.alpha(), alpha * (1 + k * rho) * (1 + 2 * k * rho), 1e-12 * alpha);  // ×1.01 here, not ×2
  c.onReversed(3);
  EXPECT_NEAR(c.alpha(), alpha * (1 + k * rho) * (1 + 2 * k * rho) * p.increase_factor, 1e-12 * alpha);
  EXPECT_EQ(c.phase(), AlphaController::Phase::kSettling);
}

// A step inverts whenever α < α*: the controller must oscillate first, detect it, and settle just
// above α* (the search phase alone would keep jumping by ×2 / ×0.8).
TEST(AlphaController, OscillationDetectionSettlesAlpha) {
  const double alpha_star = 1.234e-3;
  AlphaController c;  // the default preset, from 1e-2
  std::vector<double> trace;
  for (int step = 0; step < 400; ++step) {
    int attempt = 0;
    while (c.alpha() < alpha_star) c.onReversed(++attempt);  // the step reverts until α is enough
    ASSERT_LE(attempt, 10);
    c.onAccepted();
    trace.push_back(c.alpha());
  }
  EXPECT_EQ(c.phase(), AlphaController::Phase::kSettling);
  EXPECT_GE(c.oscillations(), 3);
  double lo = 1e9, hi = 0;
  for (size_t i = trace.size() - 100; i < trace.size(); ++i) lo = std::min(lo, trace[i]), hi = std::max(hi, trace[i]);
  // Settled: the last 100 steps stay within 2 % and within 5 % above the threshold.
  EXPECT_LT((hi - lo) / lo, 0.02) << lo << " " << hi;
  EXPECT_GE(lo, alpha_star * (1 - c.rate()));
  EXPECT_LT(hi, 1.05 * alpha_star);
}

TEST(Settle, CriterionMeasuresSpeedAndResidualOverFreeNodes) {
  const Eigen::VectorXd m = Eigen::VectorXd::Constant(2, 0.5);
  const Eigen::Vector3d g(0, -10, 0);
  Eigen::VectorXd f_el(6), v = Eigen::VectorXd::Zero(6);
  f_el << 0, 5, 0, 0, 5, 0;  // balances m g on both nodes
  std::vector<char> fixed = {0, 0};
  SettleCriterion crit;
  SettleCheck c = evaluateSettle(crit, v, f_el, Eigen::VectorXd(), m, g, fixed);
  EXPECT_TRUE(c.below);
  EXPECT_NEAR(c.relative_residual, 0.0, 1e-15);
  v[4] = 0.01;  // 1 cm/s
  c = evaluateSettle(crit, v, f_el, Eigen::VectorXd(), m, g, fixed);
  EXPECT_FALSE(c.below);
  EXPECT_DOUBLE_EQ(c.max_speed_mps, 0.01);
  fixed[1] = 1;  // a fixed node is left out
  f_el[4] = 100;
  c = evaluateSettle(crit, v, f_el, Eigen::VectorXd(), m, g, fixed);
  EXPECT_TRUE(c.below);
  f_el[1] = 4.0;  // 20 % unbalanced
  c = evaluateSettle(crit, v, f_el, Eigen::VectorXd(), m, g, fixed);
  EXPECT_NEAR(c.relative_residual, 0.2, 1e-12);
  EXPECT_FALSE(c.below);
}

// The phantom under supine gravity at E = 600 Pa: co-rotated FEM with fixed E inverts elements;
// the full method reverts those steps, raises α and never keeps an inverted element.
TEST(Stiffening, ReversesWhenElementsInvertAndMovesAlpha) {
  StiffeningParams fixed_e;
  fixed_e.update_moduli = false;
  PhantomSim weak = makePhantomSim(0.1, fixed_e);
  for (int i = 0; i < 20; ++i) weak.stiff->step();
  EXPECT_GT(weak.stiff->stats().inverted_elements, 0) << "the weak method should fail in this case";

  PhantomSim full = makePhantomSim(0.1, StiffeningParams{});
  long reversed_calls = 0;
  long released_reversals = 0;
  for (int i = 0; i < 40; ++i) {
    const double before = full.stiff->alpha();
    const bool releasing = full.stiff->stats().releasing;
    const StiffeningStepResult r = full.stiff->step();
    ASSERT_TRUE(r.advanced) << "step " << i;
    EXPECT_EQ(r.inverted_elements, 0);
    if (releasing) {
      // The release: α halves after every accepted step, past the controller's floor; a reversal
      // stiffens only the inverting elements (a local α), the global α does not grow.
      EXPECT_DOUBLE_EQ(r.alpha_per_pa, 0.5 * before) << "step " << i;
      if (r.reversals > 0) {
        ++released_reversals;
        EXPECT_GT(full.stiff->stats().locally_stiffened_elements, 0) << "step " << i;
      }
    } else if (r.reversals > 0) {
      ++reversed_calls;
      EXPECT_GT(r.alpha_per_pa, before) << "α must grow over a reversed step";
    } else {
      EXPECT_LT(r.alpha_per_pa, before) << "α must shrink after a good step";
    }
  }
  const RunStats s = full.stiff->stats();
  EXPECT_GT(reversed_calls, 0);
  EXPECT_EQ(s.reversed_steps > 0, true);
  EXPECT_GT(s.reversal_fraction, 0.0);
  EXPECT_LT(s.reversal_fraction, 0.5);
  EXPECT_EQ(s.inverted_elements, 0);
  EXPECT_FALSE(s.nan);
  EXPECT_EQ(s.steps, 40);
  EXPECT_GT(s.max_displacement_m, 5e-3);  // it did deform (mm scale)
  EXPECT_GT(s.max_modulus_factor, 1.0);
  std::cout << "phantom 1k, E 600 Pa, dt 0.1 s: " << s.steps << " steps, " << s.reversed_steps << " reversed ("
            << 100 * s.reversal_fraction << " %; " << released_reversals << " in the release, "
            << s.locally_stiffened_elements << " elements stiffened locally), final alpha " << s.final_alpha_per_pa
            << " 1/Pa, max |u| " << 1e3 * s.max_displacement_m << " mm, dV " << s.volume_change_percent << " %\n";
}

namespace {

// Settles `s` with its driver (at most max_steps accepted steps); returns whether it settled.
bool settleDriver(PhantomSim& s, int max_steps) {
  for (int calls = 0; calls < 2 * max_steps && s.stiff->stats().steps < max_steps; ++calls) {
    const StiffeningStepResult r = s.stiff->step();
    if (r.advanced && s.stiff->settled()) return true;
  }
  return false;
}

double maxNodalDistance(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  double m = 0.0;
  for (Eigen::Index n = 0; n < a.size() / 3; ++n) m = std::max(m, (a.segment<3>(3 * n) - b.segment<3>(3 * n)).norm());
  return m;
}

}  // namespace

// A load that inverts nothing (E 2 kPa, the J − 1 volume term): the stiffened run settles where the
// base material does. The seed's own stop (speed and residual alone) ends with α high, on the
// equilibrium of a stiffer material.
TEST(Stiffening, SettlesAtTheBaseMaterialsEquilibriumUnderALoadThatInvertsNothing) {
  const StabilityLoadCase& load = tinyPhantom();
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 2000.0;
  mat.poisson_ratio = 0.48;
  DynamicsParams dyn;
  dyn.time_step_s = 0.33;
  auto make = [&](const StiffeningParams& p) {
    auto fem = std::make_unique<CorotatedTetFem>(load.mesh, mat);
    fem->setVolumeTerm(CorotatedTetFem::VolumeTerm::kDeterminant);
    PhantomSim s;
    s.sim = std::make_unique<DynamicSimulator>(load.mesh, std::move(fem), mat, dyn,
                                               std::make_unique<CholmodSolver>(CholmodOptions{1}));
    s.stiff = std::make_unique<StiffeningSimulation>(*s.sim, load.mesh, p);
    s.stiff->fixNodes(load.fixed_nodes);
    s.stiff->setGravity(load.gravity_mps2);
    return s;
  };
  // The base material's equilibrium: E fixed, settled far past the criterion (increments < 1e-9 m).
  StiffeningParams base_p;
  base_p.update_moduli = false;
  PhantomSim base = make(base_p);
  Eigen::VectorXd prev = base.sim->state().displacement_m;
  for (int i = 0; i < 400; ++i) {
    base.stiff->step();
    const double inc = maxNodalDistance(base.sim->state().displacement_m, prev);
    prev = base.sim->state().displacement_m;
    if (inc < 1e-9) break;
  }
  ASSERT_EQ(base.stiff->stats().inverted_elements, 0) << "the load must invert nothing";
  const Eigen::VectorXd u0 = base.sim->state().displacement_m;
  const double u_max = maxNodalNorm(u0);
  ASSERT_GT(u_max, 5e-3);

  PhantomSim stiff = make(StiffeningParams{});
  ASSERT_TRUE(settleDriver(stiff, 400));
  const RunStats st = stiff.stiff->stats();
  EXPECT_LE(st.max_modulus_excess, StiffeningParams{}.settle.max_modulus_excess);
  EXPECT_EQ(st.inverted_elements, 0);
  // Stated distance: δ = 1e-3 of the largest displacement (δ bounds the linearised distance in the
  // energy norm; the 1 mm/s, 1e-2 residual stop adds to it).
  const double d = maxNodalDistance(stiff.sim->state().displacement_m, u0);
  EXPECT_LT(d, StiffeningParams{}.settle.max_modulus_excess * u_max) << "stiffened " << 1e3 * d << " mm from the base material's equilibrium";

  // The seed's stop alone would have ended on a stiffer material: this case exercises the release.
  PhantomSim seed = make(StiffeningParams{});
  StiffeningStepResult r;
  int shape_run = 0;
  for (int i = 0; i < 400 && shape_run < StiffeningParams{}.settle.consecutive_steps; ++i) {
    r = seed.stiff->step();
    if (r.advanced) shape_run = r.settle.below ? shape_run + 1 : 0;
  }
  const double d_seed = maxNodalDistance(seed.sim->state().displacement_m, u0);
  EXPECT_GT(d_seed, 5.0 * d) << "speed and residual alone stop " << 1e3 * d_seed << " mm from it, at α "
                            << r.alpha_per_pa << " /Pa";
  std::cout << "phantom 1k, E 2 kPa, J - 1: base equilibrium max |u| " << 1e3 * u_max << " mm; settled with stiffening "
            << 1e3 * d << " mm from it (" << st.steps << " steps, excess " << st.max_modulus_excess
            << "); speed and residual alone: " << 1e3 * d_seed << " mm (alpha " << r.alpha_per_pa << " /Pa)\n";
}

TEST(Stiffening, AStepThatWouldCollapseAnElementIsShortened) {
  // A 2×2×2 block of average-nodal-pressure tetrahedra (barrier J_b 0.3, so collapsed below 0.1),
  // bottom fixed, a top corner pulled by 0.109 N for one 0.33 s step: the plain step leaves an
  // element at J ≈ 0.06 (not inverted); with stiffening the step is shortened to the fraction that
  // keeps every element at J ≥ 0.1 + kStepKeep (1 − 0.1) (they start at rest, J = 1), with no
  // reversal. The co-rotated tetrahedra have no collapsed ratio: their steps are never shortened.
  const SmallBlock b;
  ASSERT_GE(b.corner, 0);
  const TetMesh& m = b.m;
  double jmin[2];
  StiffeningStepResult r;
  for (int stiffened = 0; stiffened < 2; ++stiffened) {
    auto anp = std::make_unique<AnpTetFem>(m, b.mat);
    anp->setInversionBarrier(0.3);
    EXPECT_DOUBLE_EQ(anp->collapsedVolumeRatio(), 0.1);
    DynamicsParams dp;
    dp.time_step_s = 0.33;
    DynamicSimulator sim(m, std::move(anp), b.mat, dp, std::make_unique<CholmodSolver>());
    sim.fixNodes(m.nodeSet("z_min"));
    Points f(1, 3);
    f << -0.109, -0.109, -0.109;
    sim.addNodalForces({b.corner}, f);
    if (stiffened) {
      StiffeningParams p;
      p.alpha.initial_alpha_per_pa = 1e-7;
      StiffeningSimulation stiff(sim, m, p);
      r = stiff.step();
      EXPECT_EQ(stiff.stats().shortened_steps, 1);
    } else {
      sim.step();
    }
    jmin[stiffened] = minVolumeRatio(m, sim.state().displacement_m);
  }
  EXPECT_GT(jmin[0], 0.0);
  EXPECT_LT(jmin[0], 0.1);
  EXPECT_TRUE(r.advanced);
  EXPECT_EQ(r.reversals, 0);
  EXPECT_GE(r.step_fraction, StiffeningSimulation::kMinStepFraction);
  EXPECT_LT(r.step_fraction, 1.0);
  EXPECT_GE(jmin[1], 0.1 + StiffeningSimulation::kStepKeep * 0.9 - 1e-9);
  EXPECT_LT(jmin[1], 0.1 + StiffeningSimulation::kStepKeep * 0.9 + 0.01);  // shortened to the bound, not further
  EXPECT_EQ(CorotatedTetFem(m, b.mat).collapsedVolumeRatio(), 0.0);
}

TEST(Stiffening, AnElementInvalidAtTheStartHoldsTheStepBackOnlyIfItLosesVolume) {
  // A 2×2×2 block of average-nodal-pressure tetrahedra (barrier J_b 0.3), bottom fixed, starts from
  // a state with its top corner pushed through the block's diagonal (elements inverted), as a state
  // interpolated from a coarser model can. Unloaded, a 2 ms step raises the inverted elements'
  // volume ratios part of the way (−0.25 to about −0.2): it is taken, with no reversal, and says how
  // many elements were recovering. Pushed on further by 200 N, the trials lower them: they are
  // reverted as any step that leaves an element invalid.
  const SmallBlock b;
  ASSERT_GE(b.corner, 0);
  const TetMesh& m = b.m;
  SimulationState start;
  start.displacement_m = Eigen::VectorXd::Zero(3 * m.numNodes());
  start.velocity_mps = Eigen::VectorXd::Zero(3 * m.numNodes());
  start.displacement_m.segment<3>(3 * b.corner) = Eigen::Vector3d::Constant(-0.0125);
  const double j_start = minVolumeRatio(m, start.displacement_m);
  ASSERT_LT(j_start, 0.0);
  ASSERT_GT(j_start, -1.0);
  for (int pushed = 0; pushed < 2; ++pushed) {
    auto anp = std::make_unique<AnpTetFem>(m, b.mat);
    anp->setInversionBarrier(0.3);
    DynamicsParams dp;
    dp.time_step_s = 0.002;
    dp.gravity_mps2 = Eigen::Vector3d::Zero();
    DynamicSimulator sim(m, std::move(anp), b.mat, dp, std::make_unique<CholmodSolver>());
    sim.fixNodes(m.nodeSet("z_min"));
    if (pushed) {
      Points f(1, 3);
      f << -200.0, -200.0, -200.0;
      sim.addNodalForces({b.corner}, f);
    }
    sim.restore(start);
    StiffeningParams p;
    p.alpha.initial_alpha_per_pa = 1e-7;
    p.max_reversals_per_step = 3;
    StiffeningSimulation stiff(sim, m, p);
    const StiffeningStepResult r = stiff.step();
    if (!pushed) {
      EXPECT_TRUE(r.advanced);
      EXPECT_EQ(r.reversals, 0);
      EXPECT_GE(r.recovering_elements, 1);
      EXPECT_GT(minVolumeRatio(m, sim.state().displacement_m), j_start);
    } else {
      EXPECT_GE(r.reversals, 1);
      EXPECT_EQ(r.recovering_elements, 0);
    }
  }
}

// admissibleStepFraction against a dense scan of every element's volume ratio along the step.
TEST(Stiffening, AdmissibleStepFractionIsTheFirstCrossingOfTheBound) {
  const TetMesh m = makeBoxMesh({3, 3, 3}, {0.03, 0.03, 0.03});
  const Eigen::VectorXd V0 = m.tetVolumes();
  auto ratio = [&](const Eigen::VectorXd& u, int e) {
    Eigen::Vector3d x[4];
    for (int i = 0; i < 4; ++i)
      x[i] = (m.nodes().row(m.tets()(e, i)) + u.segment<3>(3 * m.tets()(e, i)).transpose()).transpose();
    return (x[1] - x[0]).dot((x[2] - x[0]).cross(x[3] - x[0])) / 6.0 / V0[e];
  };
  const double jc = 0.1, keep = 0.25;
  int shortened = 0, whole = 0;
  for (int seed = 1; seed <= 20; ++seed) {
    std::srand(static_cast<unsigned>(seed));
    const Eigen::VectorXd u0 = 4e-4 * Eigen::VectorXd::Random(3 * m.numNodes());
    const Eigen::VectorXd u1 = u0 + (seed % 4 == 0 ? 5e-4 : 6e-3) * Eigen::VectorXd::Random(3 * m.numNodes());
    const double s = admissibleStepFraction(m, u0, u1, jc, keep);
    ASSERT_GE(s, 0.0);
    ASSERT_LE(s, 1.0);
    // Slow reference: 4000 samples of t in [0, 1] per element, from the start to the first sample
    // below the element's bound.
    double first = 1.0;
    for (int e = 0; e < m.numTets(); ++e) {
      const double j0 = ratio(u0, e);
      if (!(j0 > jc)) continue;
      const double bound = jc + keep * (j0 - jc);
      for (int i = 1; i <= 4000; ++i) {
        const double t = i / 4000.0;
        if (ratio(u0 + t * (u1 - u0), e) < bound) {
          first = std::min(first, t);
          break;
        }
      }
      // Every element keeps its bound up to s.
      for (int i = 0; i <= 200; ++i) EXPECT_GE(ratio(u0 + (s * i / 200.0) * (u1 - u0), e), bound - 1e-9) << seed << " " << e;
    }
    if (first == 1.0) EXPECT_EQ(s, 1.0) << seed;
    else EXPECT_NEAR(s, first, 1.0 / 4000.0) << seed;  // the first crossing, to the scan's resolution
    (s < 1.0 ? shortened : whole) += 1;
  }
  EXPECT_GE(shortened, 5);  // both kinds of step were drawn
  EXPECT_GE(whole, 1);
  Eigen::VectorXd u = Eigen::VectorXd::Zero(3 * m.numNodes());
  EXPECT_EQ(admissibleStepFraction(m, u, u, jc, keep), 1.0);
  EXPECT_THROW(admissibleStepFraction(m, u, u.head(3), jc, keep), std::invalid_argument);
  EXPECT_THROW(admissibleStepFraction(m, u, u, -0.1, keep), std::invalid_argument);
  EXPECT_THROW(admissibleStepFraction(m, u, u, jc, 1.0), std::invalid_argument);
}

// Where the base material inverts elements at its equilibrium (E 600 Pa here), the release keeps just
// those elements stiffer: the rest of the model settles to within δ of its base material.
TEST(Stiffening, ReleaseStiffensOnlyTheElementsThatWouldInvert) {
  PhantomSim full = makePhantomSim(0.33, StiffeningParams{});
  ASSERT_TRUE(settleDriver(full, 400));
  const RunStats st = full.stiff->stats();
  EXPECT_EQ(st.inverted_elements, 0);
  EXPECT_LE(st.max_modulus_excess, StiffeningParams{}.settle.max_modulus_excess);
  EXPECT_GT(st.locally_stiffened_elements, 0);
  EXPECT_LT(st.locally_stiffened_volume_percent, 5.0);
  EXPECT_LT(st.final_alpha_per_pa, 1e-5);
  std::cout << "phantom 1k, E 600 Pa: settled in " << st.steps << " steps, " << st.locally_stiffened_elements
            << " elements (" << st.locally_stiffened_volume_percent << " % of the volume) stiffened locally, alpha "
            << st.final_alpha_per_pa << " /Pa\n";
}

// Tracking frames: a reverted step stiffens only the elements that would invert, and the global α
// never grows; the same run with global reversals raises α for them.
TEST(Stiffening, TrackingFramesStiffenOnlyTheElementsThatWouldInvertAndHoldTheGlobalAlpha) {
  PhantomSim local = makePhantomSim(0.1, StiffeningParams{});
  local.stiff->setTracking(true);
  PhantomSim global = makePhantomSim(0.1, StiffeningParams{});
  long local_reversed_calls = 0, global_raised = 0;
  for (int i = 0; i < 40; ++i) {
    const double before = local.stiff->alpha();
    const StiffeningStepResult r = local.stiff->step();
    ASSERT_TRUE(r.advanced) << "step " << i;
    EXPECT_EQ(r.inverted_elements, 0) << "step " << i;
    EXPECT_LE(r.alpha_per_pa, before) << "step " << i << ": a reversal must not raise the global alpha";
    if (r.reversals > 0) {
      ++local_reversed_calls;
      EXPECT_GT(local.stiff->stats().locally_stiffened_elements, 0) << "step " << i;
    }
    const double global_before = global.stiff->alpha();
    if (global.stiff->step().alpha_per_pa > global_before) ++global_raised;
  }
  const RunStats s = local.stiff->stats();
  EXPECT_GT(local_reversed_calls, 0) << "the load must invert elements for the test to mean anything";
  EXPECT_GT(global_raised, 0) << "global reversals raise alpha on the same load";
  EXPECT_EQ(s.inverted_elements, 0);
  EXPECT_LT(s.locally_stiffened_volume_percent, 5.0);
  std::cout << "phantom 1k, E 600 Pa, dt 0.1 s, tracking frames: " << s.reversed_steps << " reversed in "
            << local_reversed_calls << " steps, " << s.locally_stiffened_elements << " elements ("
            << s.locally_stiffened_volume_percent << " % of the volume) stiffened locally, alpha "
            << s.final_alpha_per_pa << " /Pa (global reversals raised alpha in " << global_raised << " steps)\n";
}

// Tracking frames: a step that its local α's cannot keep valid (here every element is held at
// max_modulus_factor 1.2, too soft for the load) is given up after kTrackingReversals solves
// (not max_reversals_per_step), with the state left where the step began.
TEST(Stiffening, ATrackingStepTheLocalAlphasCannotFixIsGivenUpAfterAFewSolves) {
  StiffeningParams p;
  p.max_modulus_factor = 1.2;
  PhantomSim tracked = makePhantomSim(0.1, p);
  tracked.stiff->setTracking(true);
  ASSERT_GT(p.max_reversals_per_step, StiffeningSimulation::kTrackingReversals);
  int given_up = 0;
  for (int i = 0; i < 40 && given_up == 0; ++i) {
    const Eigen::VectorXd start = tracked.sim->state().displacement_m;
    const StiffeningStepResult r = tracked.stiff->step();
    EXPECT_LE(r.reversals, StiffeningSimulation::kTrackingReversals) << "step " << i;
    if (!r.advanced) {
      ++given_up;
      EXPECT_TRUE(r.reversal_limit_hit);
      EXPECT_EQ(r.reversals, StiffeningSimulation::kTrackingReversals);
      EXPECT_EQ((tracked.sim->state().displacement_m - start).cwiseAbs().maxCoeff(), 0.0) << "left where it began";
      EXPECT_EQ(r.inverted_elements, 0);
      EXPECT_GT(tracked.stiff->stats().locally_stiffened_elements, 0);
    }
  }
  EXPECT_GT(given_up, 0) << "the load must defeat the capped moduli for the test to mean anything";
  // The doublings go on in later frames, up to the controller's ceiling and no further (unbounded,
  // they reached 1e77 /Pa in 100 frames and inf in 356).
  for (int i = 0; i < 20; ++i) tracked.stiff->step();
  const Eigen::VectorXd& local = tracked.stiff->elementAlpha();
  ASSERT_TRUE(local.allFinite());
  EXPECT_EQ(local.maxCoeff(), p.alpha.max_alpha_per_pa);
}

// Tracking frames take the next step's moduli from the stress at the start of the step (no second
// element update at its end); switching tracking off brings the stress up to the current state.
TEST(Stiffening, TrackingFramesTakeTheStressAtTheStepsStartAndCatchUpWhenSwitchedOff) {
  PhantomSim s = makePhantomSim(0.1, StiffeningParams{}, 2000.0);
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(s.stiff->step().advanced);
  s.stiff->setTracking(true);
  const auto stressNow = [&s]() -> Eigen::VectorXd {
    s.sim->elasticForces();
    return s.sim->elements().vonMisesStress().cwiseQuotient(s.sim->elements().modulusFactors());
  };
  for (int i = 0; i < 3; ++i) {
    const Eigen::VectorXd at_start = stressNow();
    const StiffeningStepResult r = s.stiff->step();
    ASSERT_TRUE(r.advanced);
    ASSERT_EQ(r.reversals, 0);
    EXPECT_LT((s.stiff->baseStress() - at_start).cwiseAbs().maxCoeff(), 1e-9 * at_start.cwiseAbs().maxCoeff()) << "step " << i;
    EXPECT_FALSE(r.settle.below);  // not evaluated in tracking frames
  }
  const Eigen::VectorXd lagging = s.stiff->baseStress();
  const Eigen::VectorXd now = stressNow();
  EXPECT_GT((lagging - now).cwiseAbs().maxCoeff(), 1e-6 * now.cwiseAbs().maxCoeff()) << "the model must still move";
  s.stiff->setTracking(false);
  EXPECT_LT((s.stiff->baseStress() - now).cwiseAbs().maxCoeff(), 1e-9 * now.cwiseAbs().maxCoeff());
}

TEST(Stiffening, HistoryRestoresExactlyAndReplaysBitwise) {
  StiffeningParams p;
  p.history_size = 4;
  PhantomSim a = makePhantomSim(0.1, p);
  for (int i = 0; i < 7; ++i) a.stiff->step();
  ASSERT_EQ(a.stiff->historySize(), 4);  // round-robin: only the newest 4 kept
  const StiffeningSimulation::HistoryEntry older = a.stiff->history(2);
  const StiffeningSimulation::HistoryEntry next = a.stiff->history(1);  // what the step after `older` gave
  a.stiff->revertTo(2);
  EXPECT_EQ(a.stiff->historySize(), 2);
  const SimulationState& s = a.sim->state();
  ASSERT_EQ(s.displacement_m.size(), older.state.displacement_m.size());
  EXPECT_EQ(0, std::memcmp(s.displacement_m.data(), older.state.displacement_m.data(), sizeof(double) * s.displacement_m.size()));
  EXPECT_EQ(0, std::memcmp(s.velocity_mps.data(), older.state.velocity_mps.data(), sizeof(double) * s.velocity_mps.size()));
  EXPECT_EQ(s.time_s, older.state.time_s);
  EXPECT_EQ(s.step, older.state.step);
  const Eigen::VectorXd& er = a.sim->elements().modulusFactors();
  EXPECT_EQ(0, std::memcmp(er.data(), older.modulus_factors.data(), sizeof(double) * er.size()));
  EXPECT_EQ(a.stiff->controller().alpha(), older.controller.alpha_per_pa);
  // Continuing from the restored state takes exactly the step it took the first time.
  a.stiff->step();
  const SimulationState& s2 = a.sim->state();
  EXPECT_EQ(0, std::memcmp(s2.displacement_m.data(), next.state.displacement_m.data(), sizeof(double) * s2.displacement_m.size()));
  EXPECT_EQ(a.stiff->controller().alpha(), next.controller.alpha_per_pa);
  EXPECT_THROW(a.stiff->revertTo(5), std::out_of_range);
}

TEST(Stiffening, GravityDirectionChangeRestartsTheAlphaSearch) {
  PhantomSim a = makePhantomSim(0.1, StiffeningParams{}, 2000.0);
  for (int i = 0; i < 5; ++i) a.stiff->step();
  const double alpha = a.stiff->controller().alpha();
  ASSERT_LT(alpha, a.stiff->params().alpha.initial_alpha_per_pa);
  const Eigen::Vector3d g = a.sim->params().gravity_mps2;
  const Eigen::Vector3d g_small = Eigen::AngleAxisd(2.0 * kPi / 180.0, Eigen::Vector3d::UnitZ()) * g;  // 2° < 5°
  EXPECT_FALSE(a.stiff->setGravity(g_small));
  EXPECT_EQ(a.stiff->controller().alpha(), alpha);
  const Eigen::Vector3d g_turned = Eigen::AngleAxisd(kPi / 2, Eigen::Vector3d::UnitZ()) * g;
  EXPECT_TRUE(a.stiff->setGravity(g_turned));
  EXPECT_EQ(a.stiff->controller().alpha(), a.stiff->params().alpha.initial_alpha_per_pa);
  EXPECT_EQ(a.sim->params().gravity_mps2, g_turned);
}

// Nodes fixed on the simulator itself (not through the driver) are left out of the settle
// residual too: a clamped box under gravity settles whichever way it was clamped, in the same steps.
TEST(Stiffening, SettlesWithNodesFixedOnTheSimulatorDirectly) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 20e3;
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  p.time_step_s = 0.1;
  long steps[2];
  for (int direct = 0; direct < 2; ++direct) {
    DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<CholmodSolver>());
    StiffeningSimulation stiff(sim, m);
    if (direct) sim.fixNodes(m.nodeSet("x_min"));
    else stiff.fixNodes(m.nodeSet("x_min"));
    for (int i = 0; i < 200 && !stiff.settled(); ++i) stiff.step();
    EXPECT_TRUE(stiff.settled()) << (direct ? "fixed on the simulator" : "fixed through the driver");
    steps[direct] = stiff.stats().steps;
  }
  EXPECT_EQ(steps[0], steps[1]);
}

// Explicit Euler: stable below its critical time step (there it reaches the implicit method's
// static solution), blows up cleanly above it.
TEST(ExplicitEuler, StableForTinyStepsAndStopsCleanlyWhenItBlowsUp) {
  const TetMesh box = makeBoxMesh({4, 2, 2}, {0.04, 0.02, 0.02});
  ElasticMaterial mat;
  mat.poisson_ratio = 0.3;
  DynamicsParams dyn;
  dyn.gravity_mps2 = Eigen::Vector3d(0, 0, -9.81);
  dyn.mass_damping_per_s = 5.0;      // settles within the 3 s simulated
  dyn.stiffness_damping_s = 0.002;   // explicit stability needs α_K ω_max² dt < 2
  const std::vector<int>& clamp = box.nodeSet("x_min");

  dyn.time_step_s = 0.01;
  DynamicSimulator imp(box, std::make_unique<CorotatedTetFem>(box, mat), mat, dyn, std::make_unique<CholmodSolver>());
  imp.fixNodes(clamp);
  for (int i = 0; i < 300; ++i) imp.step();

  dyn.time_step_s = 5e-4;
  ExplicitEulerSimulator exp(box, std::make_unique<CorotatedTetFem>(box, mat), mat, dyn);
  exp.fixNodes(clamp);
  for (int i = 0; i < 6000; ++i) ASSERT_TRUE(exp.step()) << "step " << i;
  const double umax = imp.state().displacement_m.cwiseAbs().maxCoeff();
  ASSERT_GT(umax, 1e-3);
  EXPECT_LT((exp.state().displacement_m - imp.state().displacement_m).cwiseAbs().maxCoeff(), 0.02 * umax);

  dyn.time_step_s = 0.033;
  ExplicitEulerSimulator blow(box, std::make_unique<CorotatedTetFem>(box, mat), mat, dyn);
  blow.fixNodes(clamp);
  int steps = 0;
  while (blow.step() && steps < 1000) ++steps;
  EXPECT_TRUE(blow.diverged());
  EXPECT_LT(steps, 1000);
  EXPECT_FALSE(blow.step());  // stays stopped
}

// The trimmed grid on the tiny phantom: the full method never ends inverted or NaN; explicit Euler
// blows up and co-rotated FEM with fixed E inverts at 600 Pa.
TEST(StabilityMap, TrimmedGridFullMethodNeverInvertsWeakerMethodsFail) {
  const StabilityLoadCase& load = tinyPhantom();
  int full_runs = 0;
  for (StabilityRun r : stabilityGrid(true)) {
    if (r.method != StabilityMethod::kFullMethod && r.method != StabilityMethod::kExplicitEuler) continue;
    if (r.method == StabilityMethod::kExplicitEuler && r.poisson_ratio != 0.48) continue;
    r.youngs_modulus_pa = 600.0;  // harder than the grid's 1 kPa, so the tiny mesh inverts too
    const StabilityResult res = runStability(load, r);
    SCOPED_TRACE(std::string(methodName(r.method)) + " nu " + std::to_string(r.poisson_ratio) + " dt " +
                 std::to_string(r.time_step_s) + ": " + res.outcome + " " + res.reason);
    if (r.method == StabilityMethod::kFullMethod) {
      ++full_runs;
      EXPECT_EQ(res.stats.inverted_elements, 0);
      EXPECT_FALSE(res.stats.nan);
      EXPECT_TRUE(res.outcome == "settled" || res.outcome == "not_settled");
    } else {
      EXPECT_TRUE(res.outcome == "exploded" || res.outcome == "nan");
    }
  }
  EXPECT_EQ(full_runs, 7);
  StabilityRun weak;
  weak.method = StabilityMethod::kCorotatedFixed;
  weak.youngs_modulus_pa = 600.0;
  weak.time_step_s = 0.33;
  const StabilityResult res = runStability(load, weak);
  EXPECT_EQ(res.outcome, "inverted") << res.reason;
}
