// Simulation settings (the `simulation:` map), building a simulator from a model, and settling.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/solver/cholmod_solver.h"

using namespace breast_sim::core;
namespace fs = std::filesystem;

namespace {

std::string writeYaml(const std::string& name, const std::string& text) {
  const fs::path p = fs::temp_directory_path() / ("breast_sim_test_simulation_" + name + ".yaml");
  std::ofstream(p) << text;
  return p.string();
}

std::string errorOf(const std::string& yaml) {
  try {
    loadSimulationSettings(writeYaml("bad", yaml));
  } catch (const std::exception& e) {
    return e.what();
  }
  return "(no error)";
}

const std::string kPhantomCase = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml";

}  // namespace

TEST(SimulationSettings, DefaultsWithoutASimulationMap) {
  const SimulationSettings s = loadSimulationSettings(writeYaml("none", "phantom: {}\n"));
  EXPECT_EQ(s.solver.kind, SolverSettings::Kind::kMultigrid);
  EXPECT_DOUBLE_EQ(s.dynamics.time_step_s, 0.033);
  EXPECT_DOUBLE_EQ(s.material.youngs_modulus_pa, 2000.0);
  EXPECT_EQ(s.fixed_node_set, "chest_wall");
  EXPECT_TRUE(s.stiffening);
  EXPECT_EQ(s.volume_term, CorotatedTetFem::VolumeTerm::kDeterminant);
  EXPECT_TRUE(s.sliding);
}

TEST(SimulationSettings, ReadsEveryKeyWithItsUnit) {
  const SimulationSettings s = loadSimulationSettings(writeYaml("all", R"(
simulation:
  youngs_modulus_pa: 3000
  poisson_ratio: 0.45
  density_kg_per_m3: 950
  time_step_s: 0.01
  mass_damping_per_s: 2
  stiffness_damping_s: 0.05
  solver: cholmod
  solver_relative_tolerance: 1e-6
  solver_max_iterations: 50
  multigrid_smoother: gauss-seidel
  multigrid_smoothing_steps: 2
  multigrid_coarse_update_interval: 3
  multigrid_coarse_update_adaptive: true
  multigrid_coarse_update_cost_iterations: 7.5
  multigrid_max_coarsest_elements: 500
  fixed_node_set: z_min
  gravity_mps2: 9.80665
  settle_time_step_s: 0.5
  settle_increment_tolerance_mm: 0.002
  settle_max_steps: 77
  stiffening: false
  volume_term: determinant
  sliding: true
)"));
  EXPECT_DOUBLE_EQ(s.material.youngs_modulus_pa, 3000);
  EXPECT_DOUBLE_EQ(s.material.poisson_ratio, 0.45);
  EXPECT_DOUBLE_EQ(s.material.density_kg_per_m3, 950);
  EXPECT_DOUBLE_EQ(s.dynamics.time_step_s, 0.01);
  EXPECT_DOUBLE_EQ(s.dynamics.mass_damping_per_s, 2);
  EXPECT_DOUBLE_EQ(s.dynamics.stiffness_damping_s, 0.05);
  EXPECT_EQ(s.solver.kind, SolverSettings::Kind::kCholmod);
  EXPECT_DOUBLE_EQ(s.solver.relative_tolerance, 1e-6);
  EXPECT_EQ(s.solver.max_iterations, 50);
  EXPECT_EQ(s.solver.multigrid.smoother, MultigridOptions::Smoother::kGaussSeidel);
  EXPECT_EQ(s.solver.multigrid.pre_smoothing_steps, 2);
  EXPECT_EQ(s.solver.multigrid.post_smoothing_steps, 2);
  EXPECT_EQ(s.solver.multigrid.coarse_update_interval, 3);
  EXPECT_TRUE(s.solver.multigrid.coarse_update_adaptive);
  EXPECT_DOUBLE_EQ(s.solver.multigrid.coarse_update_cost_iterations, 7.5);
  EXPECT_EQ(s.solver.coarsening.max_coarsest_elements, 500);
  EXPECT_EQ(s.fixed_node_set, "z_min");
  EXPECT_DOUBLE_EQ(s.gravity_mps2, 9.80665);
  EXPECT_DOUBLE_EQ(s.settle.time_step_s, 0.5);
  EXPECT_DOUBLE_EQ(s.settle.increment_tolerance_m, 2e-6);
  EXPECT_EQ(s.settle.max_steps, 77);
  EXPECT_FALSE(s.stiffening);
  EXPECT_EQ(s.volume_term, CorotatedTetFem::VolumeTerm::kDeterminant);
  EXPECT_TRUE(s.sliding);
}

TEST(SimulationSettings, ReadsTheElementFormulationAndTheChebyshevSmoother) {
  const SimulationSettings s = loadSimulationSettings(writeYaml("anp", R"(
simulation:
  element: anp
  anp_element_volume_fraction: 0.1
  anp_inversion_barrier: 0.5
  anp_inversion_barrier_stiffness: 30
  multigrid_smoother: chebyshev
  multigrid_chebyshev_ratio: 20
)"));
  EXPECT_EQ(s.element, SimulationSettings::Element::kAnpTet);
  EXPECT_DOUBLE_EQ(s.anp_element_volume_fraction, 0.1);
  EXPECT_DOUBLE_EQ(s.anp_inversion_barrier, 0.5);
  EXPECT_DOUBLE_EQ(s.anp_inversion_barrier_stiffness, 30);
  EXPECT_DOUBLE_EQ(SimulationSettings{}.anp_inversion_barrier_stiffness, 100);
  EXPECT_EQ(s.solver.multigrid.smoother, MultigridOptions::Smoother::kChebyshev);
  EXPECT_DOUBLE_EQ(s.solver.multigrid.chebyshev_ratio, 20);
  EXPECT_EQ(SimulationSettings{}.element, SimulationSettings::Element::kAnpTet);  // the accurate element by default
  EXPECT_DOUBLE_EQ(SimulationSettings{}.anp_inversion_barrier, 0.3);
  EXPECT_NE(errorOf("simulation: {element: c3d10}").find("expected one of anp, linear, got 'c3d10'"), std::string::npos)
      << errorOf("simulation: {element: c3d10}");
  EXPECT_NE(errorOf("simulation: {anp_inversion_barrier: 1}").find("anp_inversion_barrier"), std::string::npos);
  EXPECT_NE(errorOf("simulation: {anp_element_volume_fraction: -0.1}").find("anp_element_volume_fraction"),
            std::string::npos);
  EXPECT_NE(errorOf("simulation: {multigrid_smoother: sor}").find("chebyshev"), std::string::npos);
  EXPECT_NE(errorOf("simulation: {multigrid_coarse_update_cost_iterations: 0}").find("multigrid_coarse_update_cost_iterations"),
            std::string::npos)
      << errorOf("simulation: {multigrid_coarse_update_cost_iterations: 0}");
  EXPECT_NE(errorOf("simulation: {multigrid_coarse_update_adaptive: 2}").find("multigrid_coarse_update_adaptive"),
            std::string::npos)
      << errorOf("simulation: {multigrid_coarse_update_adaptive: 2}");
}

TEST(SimulationSettings, BadValuesNameTheKeyAndTheAcceptedRange) {
  EXPECT_NE(errorOf("simulation: {poisson_ratio: 0.5}").find("'simulation.poisson_ratio': expected a value in (-1, 0.5)"),
            std::string::npos)
      << errorOf("simulation: {poisson_ratio: 0.5}");
  EXPECT_NE(errorOf("simulation: {solver: lu}").find("expected one of aggregation, cholmod, jacobi-pcg, multigrid, got 'lu'"),
            std::string::npos);
  EXPECT_NE(errorOf("simulation: {time_stepp_s: 0.1}").find("'simulation.time_stepp_s': unknown key"), std::string::npos);
  EXPECT_NE(errorOf("simulation: {youngs_modulus_pa: -2}").find("Pa"), std::string::npos);
  EXPECT_NE(errorOf("simulation: {settle_max_steps: 1.5}").find("whole number"), std::string::npos);
}

TEST(SimulationSettings, AMissingFixedNodeSetIsNamedWithTheSetsThereAre) {
  const ModelCase c = [] {
    ModelCase m = loadModelCase(kPhantomCase);
    m.meshing.target_elements = 3000;
    return m;
  }();
  const SimulationModel model = buildSimulationModel(c);
  SimulationSettings s;
  s.solver.kind = SolverSettings::Kind::kCholmod;
  s.fixed_node_set = "ribs";
  try {
    buildSimulator(c, model, s);
    FAIL() << "no error for a missing node set";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("'ribs' is not a node set of the model (it has: chest_wall"), std::string::npos)
        << e.what();
  }
}

// Settling a cantilever box: the result is the static equilibrium (elastic forces balance gravity
// on every free node), the velocity is zero and the time step is restored.
TEST(Settle, ReachesStaticEquilibriumWithLongStepsAndRestoresTheTimeStep) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 20e3;
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  SettleOptions o;
  o.time_step_s = 0.5;
  o.increment_tolerance_m = 1e-9;
  int calls = 0;
  const SettleResult r = settle(sim, o, [&](int step, double) { EXPECT_EQ(step, ++calls); });
  ASSERT_TRUE(r.settled);
  EXPECT_EQ(calls, r.steps);
  EXPECT_LT(r.steps, 40);  // long steps: nearly Newton steps of the static problem
  EXPECT_DOUBLE_EQ(sim.params().time_step_s, 0.033);
  EXPECT_EQ(sim.state().velocity_mps.cwiseAbs().maxCoeff(), 0.0);
  EXPECT_GT(r.max_displacement_m, 1e-3);
  const Eigen::VectorXd& f = sim.elasticForces();
  std::vector<char> fixed(m.numNodes(), 0);
  for (int n : m.nodeSet("x_min")) fixed[n] = 1;
  double worst = 0, weight = 0;
  for (int n = 0; n < m.numNodes(); ++n) {
    const double g = sim.lumpedMass()[n] * 9.81;
    weight = std::max(weight, g);
    if (!fixed[n]) worst = std::max(worst, std::abs(f[3 * n + 2] - g) + std::abs(f[3 * n]) + std::abs(f[3 * n + 1]));
  }
  EXPECT_LT(worst, 1e-5 * weight);
}

TEST(Settle, GivesUpAfterMaxStepsAndSaysSo) {
  const TetMesh m = makeBoxMesh({4, 2, 2}, {0.04, 0.02, 0.02});
  ElasticMaterial mat;
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  SettleOptions o;
  o.max_steps = 3;
  const SettleResult r = settle(sim, o);
  EXPECT_FALSE(r.settled);
  EXPECT_EQ(r.steps, 3);
  EXPECT_GT(r.last_increment_m, o.increment_tolerance_m);
  EXPECT_NE(sim.state().velocity_mps.cwiseAbs().maxCoeff(), 0.0);  // not at rest: left as it is
  o.increment_tolerance_m = 0;
  EXPECT_THROW(settle(sim, o), std::invalid_argument);
}

// The phantom at 4k elements under supine gravity, and the state CHOLMOD (exact solves) settles it
// to: the reference of the iterative solvers below, built once.
struct SolverComparison {
  ModelCase c;
  SimulationModel model;
  SimulationSettings s;
  Eigen::VectorXd exact_u;
  /// Settles the phantom with `kind` from rest; the displacement [m] (#3N).
  Eigen::VectorXd settleWith(SolverSettings::Kind kind, int* multigrid_levels = nullptr) const {
    SimulationSettings with = s;
    with.solver.kind = kind;
    SimulatorBuild b = buildSimulator(c, model, with);
    if (multigrid_levels) *multigrid_levels = b.multigrid_levels;
    const SettleResult r = settle(*b.simulator, with.settle);
    EXPECT_TRUE(r.settled) << SolverSettings::kindName(kind);
    return b.simulator->state().displacement_m;
  }
};

const SolverComparison& solverComparison() {
  static const SolverComparison f = [] {
    SolverComparison f;
    f.c = loadModelCase(kPhantomCase);
    f.c.meshing.target_elements = 4000;
    f.model = buildSimulationModel(f.c);
    f.s.dynamics.gravity_mps2 = f.c.phantom->gravity_supine_mps2;
    f.s.settle.time_step_s = 0.33;
    f.s.settle.increment_tolerance_m = 1e-7;
    f.exact_u = f.settleWith(SolverSettings::Kind::kCholmod);
    return f;
  }();
  return f;
}

// The multigrid solver at its loose per-step tolerance settles to the same state as CHOLMOD: the
// inexact solves only change the path.
TEST(Settle, MultigridWithLooseStepToleranceReachesTheCholmodEquilibrium) {
  const SolverComparison& f = solverComparison();
  int levels = 0;
  const Eigen::VectorXd u = f.settleWith(SolverSettings::Kind::kMultigrid, &levels);
  EXPECT_GE(levels, 2);
  const double scale = maxNodalNorm(f.exact_u);
  EXPECT_GT(scale, 3e-3);
  EXPECT_LT(maxNodalNorm(u - f.exact_u), 1e-3 * scale);
}

// Smoothed aggregation needs no coarse meshes and reaches the same equilibrium as CHOLMOD.
TEST(Settle, AggregationMultigridReachesTheCholmodEquilibrium) {
  const SolverComparison& f = solverComparison();
  const Eigen::VectorXd u = f.settleWith(SolverSettings::Kind::kAggregation);
  const double scale = maxNodalNorm(f.exact_u);
  EXPECT_GT(scale, 3e-3);
  EXPECT_LT(maxNodalNorm(u - f.exact_u), 1e-3 * scale);
}

// A mesh not meshed from an image (no coarse meshes for the geometric multigrid): the error says
// what to choose instead, and that choice builds and settles.
TEST(SimulationSettings, AMeshWithoutAnImageNamesTheSolversThatNeedNoCoarseMeshes) {
  SimulationModel model;
  model.mesh = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  const ModelCase c;
  SimulationSettings s;
  s.fixed_node_set = "x_min";
  s.material.youngs_modulus_pa = 20e3;
  s.dynamics.gravity_mps2 = {0, 0, -9.81};
  try {
    buildSimulator(c, model, s);
    FAIL() << "the geometric multigrid was built without coarse meshes";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("choose the solver 'aggregation'"), std::string::npos) << e.what();
  }
  s.solver.kind = SolverSettings::Kind::kAggregation;
  SimulatorBuild b = buildSimulator(c, model, s);
  EXPECT_TRUE(settle(*b.simulator, s.settle).settled);
  EXPECT_GT(maxNodalNorm(b.simulator->state().displacement_m), 1e-4);
}

// The constraint reactions balance the loads: at rest, their sum is minus the total weight, and
// they are zero at free DOFs.
TEST(DynamicSimulator, ConstraintForcesBalanceTheWeightAtRest) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 20e3;
  DynamicsParams p;
  p.gravity_mps2 = {0.5, -1.0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  SettleOptions o;
  o.time_step_s = 0.5;
  o.increment_tolerance_m = 1e-10;
  ASSERT_TRUE(settle(sim, o).settled);
  sim.step();  // a step from rest: reactions of the equilibrium
  const Eigen::VectorXd& r = sim.constraintForces();
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (int n = 0; n < m.numNodes(); ++n) sum += r.segment<3>(3 * n);
  const double weight = sim.lumpedMass().sum();
  EXPECT_LT((sum + weight * p.gravity_mps2).norm(), 1e-6 * weight * 9.81) << sum.transpose();
  for (int d = 0; d < 3 * m.numNodes(); ++d)
    if (!sim.constrainedDofs()[d]) EXPECT_EQ(r[d], 0.0);
  // The external forces are what addNodalForces accumulated.
  sim.addNodalForces({5}, Points::Constant(1, 3, 0.25));
  sim.addNodalForces({5}, Points::Constant(1, 3, 0.25));
  EXPECT_DOUBLE_EQ(sim.externalForces()[15], 0.5);
}

namespace {
DynamicSimulator cantileverSim(const TetMesh& m, const DynamicsParams& p, bool corotated = true) {
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 20e3;
  auto fem = std::make_unique<CorotatedTetFem>(m, mat);
  fem->setCorotated(corotated);
  return DynamicSimulator(m, std::move(fem), mat, p, std::make_unique<CholmodSolver>());
}
}  // namespace

TEST(DynamicSimulator, NodeSpringsCarryTheWeightAndStiffOnesActLikeAFixedWall) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  DynamicsParams p;
  p.gravity_mps2 = {0.5, -1.0, -9.81};
  SettleOptions o;
  o.time_step_s = 0.5;
  o.increment_tolerance_m = 1e-11;
  const std::vector<int>& wall = m.nodeSet("x_min");
  // Reference: the x_min face fixed (Dirichlet).
  DynamicSimulator fixed = cantileverSim(m, p);
  fixed.fixNodes(wall);
  ASSERT_TRUE(settle(fixed, o).settled);
  // The same face on very stiff isotropic springs anchored at rest: the same equilibrium, reached
  // with long steps (implicit springs: 1e7 N/m per node at dt 0.5 s would explode explicitly).
  DynamicSimulator sprung = cantileverSim(m, p);
  const double k = 1e7;  // [N/m]
  std::vector<Eigen::Matrix3d> ks(wall.size(), k * Eigen::Matrix3d::Identity());
  Points anchors(static_cast<Eigen::Index>(wall.size()), 3);
  for (size_t i = 0; i < wall.size(); ++i) anchors.row(static_cast<Eigen::Index>(i)) = m.nodes().row(wall[i]);
  sprung.setNodeSprings(wall, ks, anchors);
  ASSERT_TRUE(settle(sprung, o).settled);
  const double tip = fixed.state().displacement_m.cwiseAbs().maxCoeff();
  EXPECT_GT(tip, 1e-4);
  EXPECT_LT((sprung.state().displacement_m - fixed.state().displacement_m).cwiseAbs().maxCoeff(), 1e-3 * tip);
  // At rest the springs carry the whole weight: Σ f_spring = −m g.
  const Eigen::VectorXd f = sprung.currentSpringForces();
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (int n = 0; n < m.numNodes(); ++n) sum += f.segment<3>(3 * n);
  const double weight = sprung.lumpedMass().sum();
  EXPECT_LT((sum + weight * p.gravity_mps2).norm(), 1e-5 * weight * 9.81) << sum.transpose();
  // A spring along z only (a frictionless floor under the face): the face slides freely in x and y
  // under the sideways gravity, so the body keeps accelerating sideways instead of settling.
  DynamicSimulator floor = cantileverSim(m, p);
  Eigen::Matrix3d kz = Eigen::Matrix3d::Zero();
  kz(2, 2) = k;
  std::vector<Eigen::Matrix3d> kzs(wall.size(), kz);
  floor.setNodeSprings(wall, kzs, anchors);
  for (int s = 0; s < 10; ++s) floor.step();
  double max_z = 0;
  for (int n : wall) max_z = std::max(max_z, std::abs(floor.state().displacement_m[3 * n + 2]));
  const double t = floor.state().time_s;
  // Free sliding under g_x = 0.5 m/s² moves the face by about g_x t²/2 (less the mass damping).
  EXPECT_GT(floor.state().displacement_m[3 * wall[0]], 0.5 * (0.5 * p.gravity_mps2.x() * t * t));
  EXPECT_LT(max_z, 1e-4);  // but it stayed on the floor
}

TEST(DynamicSimulator, NodeSpringForceMatchesItsStiffnessAndBadSpringsAreRefused) {
  const TetMesh m = makeBoxMesh({2, 1, 1}, {0.02, 0.01, 0.01});
  DynamicSimulator sim = cantileverSim(m, DynamicsParams{});
  Eigen::Matrix3d k;
  k << 3, 1, 0, 1, 2, 0.5, 0, 0.5, 4;
  Points a(1, 3);
  a << 0.001, -0.002, 0.003;
  sim.setNodeSprings({1}, {k}, a);
  // f = −K (x − a), and its derivative is −K: finite differences in the displacement.
  SimulationState s = sim.state();
  const Eigen::Vector3d x = m.nodes().row(1).transpose();
  EXPECT_LT((sim.currentSpringForces().segment<3>(3) + k * (x - a.row(0).transpose())).norm(), 1e-15);
  const double h = 1e-6;
  for (int c = 0; c < 3; ++c) {
    SimulationState plus = s;
    plus.displacement_m[3 + c] += h;
    sim.restore(plus);
    const Eigen::Vector3d fp = sim.currentSpringForces().segment<3>(3);
    plus.displacement_m[3 + c] -= 2 * h;
    sim.restore(plus);
    const Eigen::Vector3d fm = sim.currentSpringForces().segment<3>(3);
    EXPECT_LT(((fp - fm) / (2 * h) + k.col(c)).norm(), 1e-8);
  }
  auto err = [&](const std::vector<int>& n, const std::vector<Eigen::Matrix3d>& ks, const Points& an) {
    try {
      sim.setNodeSprings(n, ks, an);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("(no error)");
  };
  Eigen::Matrix3d skew = k;
  skew(0, 1) = 7;
  EXPECT_NE(err({1}, {skew}, a).find("node 1"), std::string::npos);
  EXPECT_NE(err({99}, {k}, a).find("node 99"), std::string::npos);
  EXPECT_NE(err({1, 1}, {k, k}, Points::Zero(2, 3)).find("twice"), std::string::npos);
  EXPECT_NE(err({1}, {k, k}, a).find("one of each"), std::string::npos);
  // The refused calls left the last good springs in place.
  EXPECT_EQ(sim.springNodes(), std::vector<int>{1});
  sim.clearNodeSprings();
  EXPECT_TRUE(sim.springNodes().empty());
}

// Matrix reuse (setMatrixReuse) against assembling every step. With linear (not co-rotated)
// elements the matrix is the same at every state, so a reused one must give the very bits of a
// fresh assembly: this checks the right-hand side of the reusing steps (forces, springs with moving
// anchors, moving target constraints, eliminated columns) and the reactions.
TEST(DynamicSimulator, AReusedMatrixGivesTheAssembledStepsBitsWhenTheMatrixIsConstant) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  DynamicsParams p;
  p.gravity_mps2 = {0.5, -1.0, -9.81};
  DynamicSimulator reusing = cantileverSim(m, p, false), assembling = cantileverSim(m, p, false);
  for (DynamicSimulator* sim : {&reusing, &assembling}) sim->fixNodes(m.nodeSet("x_min"));
  reusing.setMatrixReuse(3);
  const std::vector<int>& tip = m.nodeSet("x_max");
  std::vector<int> sprung = {tip[0], tip[1]};
  std::vector<Eigen::Matrix3d> ks(2, 50.0 * Eigen::Matrix3d::Identity());
  std::vector<bool> reused;
  for (int s = 0; s < 7; ++s) {
    // Targets and anchors move every step; the constrained DOFs and the spring stiffness stay.
    Points targets = Points::Constant(static_cast<Eigen::Index>(tip.size()) - 2, 3, 1e-4 * s);
    std::vector<int> moved(tip.begin() + 2, tip.end());
    Points anchors(2, 3);
    for (int i = 0; i < 2; ++i) anchors.row(i) = m.nodes().row(sprung[i]) + Eigen::RowVector3d(0, 0, -1e-4 * s);
    for (DynamicSimulator* sim : {&reusing, &assembling}) {
      sim->setNodeTargets(moved, targets);
      sim->setNodeSprings(sprung, ks, anchors);
    }
    reused.push_back(reusing.step().matrix_reused);
    EXPECT_FALSE(assembling.step().matrix_reused);
    ASSERT_EQ(reusing.state().displacement_m, assembling.state().displacement_m) << "step " << s;
    ASSERT_EQ(reusing.constraintForces(), assembling.constraintForces()) << "step " << s;
  }
  EXPECT_EQ(reused, (std::vector<bool>{false, true, true, false, true, true, false}));
  // Another reuse setting starts with an assembly (it records what the reusing steps compare with).
  reusing.setMatrixReuse(2);
  EXPECT_FALSE(reusing.step().matrix_reused);
  EXPECT_TRUE(reusing.step().matrix_reused);
  EXPECT_THROW(reusing.setMatrixReuse(0), std::invalid_argument);
}

namespace {
// The cantilever block (its x_min face fixed) settled hanging under gravity, in two simulators at
// the same state: one to reuse its matrix, one that assembles every step.
struct HangingBlock {
  TetMesh mesh = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  DynamicsParams params = [] {
    DynamicsParams p;
    p.gravity_mps2 = {0.5, -1.0, -9.81};
    return p;
  }();
  DynamicSimulator reusing = cantileverSim(mesh, params), assembling = cantileverSim(mesh, params);
  bool settled = false;
  HangingBlock() {
    for (DynamicSimulator* sim : {&reusing, &assembling}) sim->fixNodes(mesh.nodeSet("x_min"));
    SettleOptions o;
    o.increment_tolerance_m = 1e-9;
    settled = settle(assembling, o).settled;
    reusing.restore(assembling.state());
  }
};
}  // namespace

// With co-rotated elements a reused matrix lags the rotations: close to the assembled step, not
// equal. Whatever else enters the matrix makes the next step assemble: then both give the same bits
// from the same state.
TEST(DynamicSimulator, AReusedMatrixLagsOnlyTheRotationsAndAnyOtherChangeAssemblesAgain) {
  HangingBlock b;
  ASSERT_TRUE(b.settled);
  const TetMesh& m = b.mesh;
  DynamicSimulator &reusing = b.reusing, &assembling = b.assembling;
  // Hanging at rest, then a tenth more weight: the motion of the next steps is a fraction of the
  // sag, as a tracking frame's is of the supine deformation.
  const Eigen::VectorXd hanging = assembling.state().displacement_m;
  for (DynamicSimulator* sim : {&reusing, &assembling}) sim->setGravity(1.1 * b.params.gravity_mps2);
  reusing.setMatrixReuse(100);
  int reused = 0;
  for (int s = 0; s < 12; ++s) {
    reused += reusing.step().matrix_reused;
    assembling.step();
  }
  // The first step assembles, and so may one whose move more than doubled as the motion starts.
  EXPECT_GE(reused, 9);
  const Eigen::VectorXd& ur = reusing.state().displacement_m;
  const Eigen::VectorXd& ua = assembling.state().displacement_m;
  const double sag = hanging.cwiseAbs().maxCoeff(), moved = (ua - hanging).cwiseAbs().maxCoeff();
  EXPECT_GT(sag, 5e-3);
  EXPECT_GT(moved, 0.02 * sag);
  std::printf("sag %.3f mm, moved %.3f mm over 12 steps, reused against assembled %.2e mm\n", 1e3 * sag, 1e3 * moved,
              1e3 * (ur - ua).cwiseAbs().maxCoeff());
  EXPECT_GT((ur - ua).cwiseAbs().maxCoeff(), 1e-9 * moved);  // the reused matrix lags
  EXPECT_LT((ur - ua).cwiseAbs().maxCoeff(), 0.005 * moved);

  // Each change below, made to both from the same state: the reusing one assembles, the same bits.
  const std::vector<int>& tip = m.nodeSet("x_max");
  const std::vector<std::pair<std::string, std::function<void(DynamicSimulator&)>>> changes = {
      {"restore", [](DynamicSimulator&) {}},
      {"time step", [](DynamicSimulator& s) {
         DynamicsParams q = s.params();
         q.time_step_s = 0.05;
         s.setParams(q);
       }},
      {"damping", [](DynamicSimulator& s) {
         DynamicsParams q = s.params();
         q.stiffness_damping_s = 0.03;
         s.setParams(q);
       }},
      {"springs", [&](DynamicSimulator& s) {
         s.setNodeSprings({tip[0]}, {30.0 * Eigen::Matrix3d::Identity()}, m.nodes().row(tip[0]));
       }},
      {"spring stiffness", [&](DynamicSimulator& s) {
         s.setNodeSprings({tip[0]}, {60.0 * Eigen::Matrix3d::Identity()}, m.nodes().row(tip[0]));
       }},
      {"no springs", [](DynamicSimulator& s) { s.clearNodeSprings(); }},
      {"constraints", [&](DynamicSimulator& s) { s.fixNodes({tip[1]}); }},
  };
  for (const auto& [name, change] : changes) {
    // The reusing one assembled at its last step: without the change it would reuse now.
    assembling.restore(reusing.state());
    change(reusing);
    change(assembling);
    if (name == "restore") reusing.restore(reusing.state());
    EXPECT_FALSE(reusing.step().matrix_reused) << name;
    assembling.step();
    EXPECT_EQ(reusing.state().displacement_m, assembling.state().displacement_m) << name;
  }
  // Anchors do not enter the matrix, and a spring block that changed by a little of what holds its
  // node lags as the rotations do: reused. A change of the spring's own size is a change.
  const Eigen::Matrix3d k = 30.0 * Eigen::Matrix3d::Identity();
  reusing.setNodeSprings({tip[0]}, {k}, m.nodes().row(tip[0]));
  EXPECT_FALSE(reusing.step().matrix_reused);
  reusing.setNodeSprings({tip[0]}, {k}, m.nodes().row(tip[0]) + Eigen::RowVector3d(0, 0, 1e-3));
  EXPECT_TRUE(reusing.step().matrix_reused);
  reusing.setNodeSprings({tip[0]}, {1.001 * k}, m.nodes().row(tip[0]));
  EXPECT_TRUE(reusing.step().matrix_reused);
  reusing.setNodeSprings({tip[0]}, {10.0 * k}, m.nodes().row(tip[0]));
  EXPECT_FALSE(reusing.step().matrix_reused);
}

// A reusing step whose largest node move more than doubles the last step's is solved again with an
// assembled matrix (a lagged linearisation can let a mode grow): a sudden push on a hanging block.
TEST(DynamicSimulator, AReusingStepWhoseMoveMoreThanDoublesIsSolvedAgainAssembled) {
  HangingBlock b;
  ASSERT_TRUE(b.settled);
  const TetMesh& m = b.mesh;
  DynamicSimulator &reusing = b.reusing, &assembling = b.assembling;
  reusing.setMatrixReuse(100);
  EXPECT_FALSE(reusing.step().matrix_reused);
  EXPECT_TRUE(reusing.step().matrix_reused);  // at rest: it hardly moves
  assembling.restore(reusing.state());
  const int tip = m.nodeSet("x_max")[0];
  for (DynamicSimulator* sim : {&reusing, &assembling}) sim->addNodalForces({tip}, Points::Constant(1, 3, 0.01));
  const StepTotals before = reusing.totals();
  const long calls = before.steps;
  EXPECT_FALSE(reusing.step().matrix_reused);
  EXPECT_EQ(reusing.totals().steps, calls + 2);  // the discarded solve counts as a step() call
  EXPECT_EQ(reusing.totals().resolved_assembled, before.resolved_assembled + 1);
  EXPECT_EQ(reusing.totals().reused_matrix, before.reused_matrix);  // neither call ended reusing
  assembling.step();
  EXPECT_EQ(reusing.state().displacement_m, assembling.state().displacement_m);
}
