// recoverUnloadedShape: a known rest shape loaded by gravity is recovered from its loaded shape, with
// and without stiffening; a load too large for the material ends without converging and says why;
// bad input throws naming the value; no gravity gives the loaded shape back.
#include <gtest/gtest.h>

#include <omp.h>

#include <cmath>
#include <functional>
#include <limits>
#include <stdexcept>
#include <string>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/fem/unloaded_state.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/case_file.h"
#include "breast_sim/core/pipeline/lesion_uncertainty.h"

using namespace breast_sim::core;

namespace {

// The meshes here are small: one thread is faster than two on a shared machine.
[[maybe_unused]] const int kOneThread = (omp_set_num_threads(1), 1);

const Eigen::Vector3d kGravity(0.0, 0.0, -9.81);

// A 4 cm cube of 2 kPa tissue held at its x_min face: under gravity along −z it bends and hangs
// (about 1 cm at the free edge), like a breast off the chest wall.
const TetMesh& cube() {
  static const TetMesh m = [] {
    TetMesh b = makeBoxMesh({5, 5, 5}, {0.04, 0.04, 0.04});
    b.setNodeSet("chest_wall", b.nodeSet("x_min"));
    return b;
  }();
  return m;
}

SimulationSettings settings(bool stiffening, double youngs_modulus_pa = 2000.0) {
  SimulationSettings s;
  s.material.youngs_modulus_pa = youngs_modulus_pa;
  s.material.poisson_ratio = 0.48;
  s.solver.kind = SolverSettings::Kind::kCholmod;
  s.solver.cholmod.blas_threads = 1;
  s.stiffening = stiffening;
  s.sliding = false;
  return s;
}

// The rest shape X0 loaded by gravity, settled tighter than the recovery's tolerance.
const TetMesh& loadedCube() {
  static const TetMesh m = [] {
    SimulationSettings s = settings(false);
    s.dynamics.gravity_mps2 = kGravity;
    SimulatorBuild b = buildSimulator(cube(), s);
    SettleOptions o = s.settle;
    o.increment_tolerance_m = 1e-7;
    const SettleResult r = settle(*b.simulator, o);
    if (!r.settled) throw std::runtime_error("the cube did not settle");
    return withNodes(cube(), cube().nodes() + b.simulator->displacement());
  }();
  return m;
}

void expectRecovered(const UnloadedStateResult& r, const UnloadedStateOptions& o) {
  ASSERT_TRUE(r.converged) << r.failure;
  EXPECT_EQ(r.failure, "");
  EXPECT_LE(r.max_residual_m, o.tolerance_m);
  EXPECT_EQ(static_cast<int>(r.history.size()), r.iterations);
  EXPECT_EQ(r.inverted_elements, 0);
  ASSERT_EQ(r.unloaded_nodes_m.rows(), cube().numNodes());
  const Eigen::VectorXd d = (r.unloaded_nodes_m - cube().nodes()).rowwise().norm();
  const double sag = (loadedCube().nodes() - cube().nodes()).rowwise().norm().maxCoeff();
  EXPECT_GT(sag, 5e-3);  // the load is not a small one
  EXPECT_LT(d.mean(), 0.3e-3) << "max " << d.maxCoeff() << " m";
  EXPECT_LT(d.maxCoeff(), 0.5e-3);
  // The held face stays where it is.
  for (int i : cube().nodeSet("chest_wall"))
    EXPECT_EQ((r.unloaded_nodes_m.row(i) - loadedCube().nodes().row(i)).norm(), 0.0);
  // The re-loaded shape is the loaded one.
  ASSERT_EQ(r.reloaded_nodes_m.rows(), cube().numNodes());
  EXPECT_LE((r.reloaded_nodes_m - loadedCube().nodes()).rowwise().norm().maxCoeff(), o.tolerance_m);
  std::printf("    sag %.2f mm; %d iterations, %.3f s; |X0 - known| mean %.4f mm, max %.4f mm; residual max %.2e m, "
              "mean %.2e m\n",
              sag * 1e3, r.iterations, r.seconds, d.mean() * 1e3, d.maxCoeff() * 1e3, r.max_residual_m, r.mean_residual_m);
}

std::string invalidArgumentOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "no std::invalid_argument";
}

}  // namespace

TEST(UnloadedState, RecoversTheKnownRestShape) {
  const UnloadedStateOptions o;
  const UnloadedStateResult r = recoverUnloadedShape(loadedCube(), settings(false), kGravity, o);
  expectRecovered(r, o);
  EXPECT_LE(r.iterations, 12);
  // Each loading settles from the last one's displacement: the later ones are short.
  EXPECT_LT(r.history.back().settle_steps, r.history.front().settle_steps);
}

// On the multigrid: its level meshes the loaded (sagged) shape, from which the rest shape lies up to
// 22 mm away, farther than a level's snap tolerance (its mean boundary edge, 8 mm): every loading
// takes the loaded shape's prolongations (a hierarchy on X0's own nodes would be refused).
TEST(UnloadedState, RecoversTheKnownRestShapeOnTheMultigridOfTheLoadedShape) {
  UnloadedStateOptions o;
  o.coarse_meshes = {loadedCube()};
  SimulationSettings mg = settings(false);
  mg.solver.kind = SolverSettings::Kind::kMultigrid;
  const UnloadedStateResult r = recoverUnloadedShape(loadedCube(), mg, kGravity, o);
  expectRecovered(r, o);
  EXPECT_LE(r.iterations, 12);
}

TEST(UnloadedState, RecoversTheKnownRestShapeWithStiffening) {
  const UnloadedStateOptions o;
  const UnloadedStateResult r = recoverUnloadedShape(loadedCube(), settings(true), kGravity, o);
  expectRecovered(r, o);
  EXPECT_LE(r.iterations, 12);
}

// The phantom at about 2000 elements as the known rest shape, loaded by prone gravity with the
// stiffening driver (the pipeline's default material and element), recovered from its loaded shape.
TEST(UnloadedState, RecoversThePhantomsRestShape) {
  ModelCase c = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  c.meshing.target_elements = 2000;
  const SimulationModel model = buildSimulationModel(c);
  SimulationSettings s = settings(true);
  const Eigen::Vector3d g_prone = s.gravity_mps2 * c.prone_gravity_direction.normalized();
  SimulationSettings tight = s;
  tight.settle.increment_tolerance_m = 1e-7;
  const GravityLoading forward = loadWithGravity(model.mesh, tight, g_prone);
  ASSERT_TRUE(forward.settled) << forward.failure;
  const TetMesh loaded = withNodes(model.mesh, model.mesh.nodes() + forward.displacement_m);
  const UnloadedStateOptions o;
  const UnloadedStateResult r = recoverUnloadedShape(loaded, s, g_prone, o);
  ASSERT_TRUE(r.converged) << r.failure;
  EXPECT_LE(r.max_residual_m, o.tolerance_m);
  EXPECT_LE(r.iterations, 10);
  const Eigen::VectorXd d = (r.unloaded_nodes_m - model.mesh.nodes()).rowwise().norm();
  const double sag = forward.displacement_m.rowwise().norm().maxCoeff();
  EXPECT_GT(sag, 3e-3);
  EXPECT_LT(d.mean(), 0.3e-3) << "max " << d.maxCoeff() << " m";
  EXPECT_LT(d.maxCoeff(), 1e-3);
  EXPECT_TRUE(invertedTets(model.mesh.tets(), r.unloaded_nodes_m).empty());
  std::printf("    %d elements, sag %.2f mm; %d iterations, %.2f s; |X0 - known| mean %.4f mm, max %.4f mm\n",
              model.mesh.numTets(), sag * 1e3, r.iterations, r.seconds, d.mean() * 1e3, d.maxCoeff() * 1e3);
}

TEST(UnloadedState, TheIterationLimitEndsWithoutConvergingAndSaysWhy) {
  UnloadedStateOptions o;
  o.max_iterations = 2;
  const UnloadedStateResult r = recoverUnloadedShape(loadedCube(), settings(false), kGravity, o);
  EXPECT_FALSE(r.converged);
  EXPECT_EQ(r.iterations, 2);
  EXPECT_NE(r.failure.find("iteration 2: not converged in 2 iterations"), std::string::npos) << r.failure;
  ASSERT_EQ(r.history.size(), 2u);
  EXPECT_LT(r.history[1].max_residual_m, r.history[0].max_residual_m);
  EXPECT_EQ(r.max_residual_m, r.history[1].max_residual_m);  // the better of the two is returned
}

TEST(UnloadedState, StartsFromTheGivenShape) {
  // Started at the answer of a first run, the iteration converges at once.
  UnloadedStateOptions o;
  const UnloadedStateResult first = recoverUnloadedShape(loadedCube(), settings(false), kGravity, o);
  ASSERT_TRUE(first.converged) << first.failure;
  o.initial_unloaded_nodes_m = first.unloaded_nodes_m;
  const UnloadedStateResult again = recoverUnloadedShape(loadedCube(), settings(false), kGravity, o);
  ASSERT_TRUE(again.converged) << again.failure;
  EXPECT_EQ(again.iterations, 1);
}

TEST(UnloadedState, ALoadTooLargeEndsWithoutConvergingAndSaysWhy) {
  // 50 Pa: the cube would hang tens of centimetres; no rest shape of valid elements reproduces it.
  for (bool stiffening : {false, true}) {
    SCOPED_TRACE(stiffening ? "stiffening" : "co-rotated");
    UnloadedStateOptions o;
    o.max_iterations = 8;
    UnloadedStateResult r;
    ASSERT_NO_THROW(r = recoverUnloadedShape(loadedCube(), settings(stiffening, 50.0), kGravity * 4.0, o));
    EXPECT_FALSE(r.converged);
    EXPECT_NE(r.failure.find("iteration "), std::string::npos) << r.failure;
    EXPECT_GE(r.iterations, 1);
    EXPECT_LE(r.iterations, o.max_iterations);
    EXPECT_TRUE(r.unloaded_nodes_m.allFinite());
    EXPECT_TRUE(invertedTets(cube().tets(), r.unloaded_nodes_m).empty());
    std::printf("    %s: %s\n", stiffening ? "stiffening" : "co-rotated", r.failure.c_str());
  }
}

// Soft tissue on an anthropomorphic mesh (the VICTRE image's case at 3k elements, every modulus
// × 0.5, ν 0.477, as a sample of the lesion ensemble takes it): at a few nodes the fixed-point map
// does not contract, a full step overshoots them and the largest residual grows. The recovery goes
// back to the best X0 with its plain step halved, and converges; going on from the worse shape
// instead stops after 7 loadings with the residual grown to 1.05 mm.
TEST(UnloadedState, AfterALoadingThatFoundNoBetterShapeItStepsFromTheBestOneShortened) {
  const std::string path = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/victre_case.yaml";
  ModelCase c = loadModelCase(path);
  c.meshing.target_elements = 3000;
  const SimulationModel model = buildSimulationModel(c);
  UncertaintySampleParams soft;
  soft.youngs_modulus_factor = 0.5;
  soft.poisson_ratio = 0.477;
  const PipelineSettings s = sampleSettings(loadPipelineSettings(path), soft);
  UnloadedStateOptions o;
  o.stiffening = s.stiffening;
  o.coarse_meshes = buildCoarseMeshes(c, model, s.simulation.solver.coarsening);
  const UnloadedStateResult r = recoverUnloadedShape(model.mesh, s.simulation, proneGravity(c, s.simulation), o);
  ASSERT_TRUE(r.converged) << r.failure;
  EXPECT_LE(r.max_residual_m, o.tolerance_m);
  // Some loading found no better shape, and the next X0 was the best one's plain step halved.
  int backs = 0;
  double best = std::numeric_limits<double>::infinity();
  for (size_t k = 0; k + 1 < r.history.size(); ++k) {
    const UnloadedIteration& h = r.history[k];
    if (h.max_residual_m >= best) {
      ++backs;
      EXPECT_FALSE(r.history[k + 1].accelerated) << k;
      EXPECT_LE(r.history[k + 1].step_fraction, 0.5) << k;
      // After a plain step from the best X0, a shorter one: no X0 is loaded twice.
      if (!h.accelerated) EXPECT_LT(r.history[k + 1].step_fraction, h.step_fraction) << k;
    }
    best = std::min(best, h.max_residual_m);
  }
  std::printf("[ measure  ] %d tets, E x 0.5: X0 in %d loadings (%d back to the best), residual %.4f mm, %.1f s\n",
              model.mesh.numTets(), r.iterations, backs, 1e3 * r.max_residual_m, r.seconds);
  EXPECT_GE(backs, 1);
}

TEST(UnloadedState, BadInputThrowsNamingTheValue) {
  const SimulationSettings s = settings(false);
  auto with = [&](auto change) {
    UnloadedStateOptions o;
    change(o);
    return invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), s, kGravity, o); });
  };
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.max_iterations = 0; }).find("max_iterations = 0"), std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.tolerance_m = -1e-5; }).find("tolerance_m = -1e-05"), std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.tolerance_m = std::numeric_limits<double>::infinity(); }).find("tolerance_m"),
            std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.max_growing_iterations = 0; }).find("max_growing_iterations = 0"),
            std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.stiffening.history_size = 0; }).find("history_size"), std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) { o.initial_unloaded_nodes_m = Points::Zero(3, 3); })
                .find("initial_unloaded_nodes_m rows = 3"),
            std::string::npos);
  EXPECT_NE(with([](UnloadedStateOptions& o) {
              o.initial_unloaded_nodes_m = cube().nodes();
              o.initial_unloaded_nodes_m.col(0) *= -1.0;  // a mirror image: every element inverted
            }).find("inverted elements"),
            std::string::npos);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), s, Eigen::Vector3d(0, nan, -9.81)); })
                .find("gravity_mps2"),
            std::string::npos);
  SimulationSettings mg = s;
  mg.solver.kind = SolverSettings::Kind::kMultigrid;
  const std::string e = invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), mg, kGravity); });
  EXPECT_NE(e.find("'multigrid'"), std::string::npos) << e;
  EXPECT_NE(e.find("'aggregation' or 'cholmod'"), std::string::npos) << e;
  UnloadedStateOptions with_levels;
  with_levels.coarse_meshes.push_back(cube());
  const std::string levels = invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), s, kGravity, with_levels); });
  EXPECT_NE(levels.find("1 coarse meshes given for a solver other than 'multigrid'"), std::string::npos) << levels;
  SimulationSettings bad_set = s;
  bad_set.fixed_node_set = "chest_wal";
  const std::string f = invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), bad_set, kGravity); });
  EXPECT_NE(f.find("'chest_wal'"), std::string::npos) << f;
  EXPECT_NE(f.find("did you mean 'chest_wall'"), std::string::npos) << f;
  SimulationSettings bad_material = s;
  bad_material.material.poisson_ratio = 0.5;
  EXPECT_NE(invalidArgumentOf([&] { recoverUnloadedShape(loadedCube(), bad_material, kGravity); }).find("poisson_ratio"),
            std::string::npos);
}

TEST(UnloadedState, WithoutGravityTheLoadedShapeIsItsOwnRestShape) {
  for (bool stiffening : {false, true}) {
    const UnloadedStateResult r = recoverUnloadedShape(loadedCube(), settings(stiffening), Eigen::Vector3d::Zero());
    ASSERT_TRUE(r.converged) << r.failure;
    EXPECT_LE(r.iterations, 1);
    EXPECT_LT(r.max_residual_m, 1e-12);  // the rest state's elastic forces vanish up to rounding
    EXPECT_EQ(r.unloaded_nodes_m, loadedCube().nodes());
  }
}

TEST(UnloadedState, WithNodesKeepsTheElementsAndNodeSetsAndRefusesInvertedElements) {
  const Points moved = cube().nodes() * 2.0;
  const TetMesh m = withNodes(cube(), moved);
  EXPECT_EQ(m.nodes(), moved);
  EXPECT_EQ(m.tets(), cube().tets());
  EXPECT_EQ(m.regionLabels(), cube().regionLabels());
  EXPECT_EQ(m.nodeSets(), cube().nodeSets());
  EXPECT_THROW(withNodes(cube(), Points::Zero(4, 3)), std::invalid_argument);
  Points mirrored = cube().nodes();
  mirrored.col(2) *= -1.0;
  EXPECT_NE(invalidArgumentOf([&] { withNodes(cube(), mirrored); }).find("inverted"), std::string::npos);
}

// A multigrid on a rest shape its coarse levels do not mesh (an unloaded X0 of a prone image) takes
// the prolongations of the shape they mesh: here the cube turned 90° about the z axis through the
// origin, so that it lies beside its coarse level. Built on the turned cube alone the hierarchy is
// refused (its nodes lie outside the level); with the cube's own nodes as the meshed shape its
// loading settles where CHOLMOD's does (the slow reference).
TEST(UnloadedState, AMultigridOnAnotherRestShapeTakesTheProlongationsOfTheMeshedShape) {
  const TetMesh coarse = makeBoxMesh({2, 2, 2}, {0.04, 0.04, 0.04});
  Eigen::Matrix3d turn;
  turn << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  const TetMesh turned = withNodes(cube(), cube().nodes() * turn.transpose());
  SimulationSettings mg = settings(false);
  mg.solver.kind = SolverSettings::Kind::kMultigrid;
  mg.solver.relative_tolerance = 1e-8;
  EXPECT_THROW(buildSimulator(turned, mg, {coarse}), std::invalid_argument);
  const std::string wrong = invalidArgumentOf([&] { buildSimulator(turned, mg, {coarse}, Points::Zero(4, 3)); });
  EXPECT_NE(wrong.find("meshed_nodes_m"), std::string::npos) << wrong;

  SettleOptions tight = mg.settle;
  tight.increment_tolerance_m = 1e-8;
  mg.settle = tight;
  SimulationSettings direct = settings(false);
  direct.settle = tight;
  const Eigen::Vector3d g = turn * kGravity;
  const GravityLoading by_multigrid = loadWithGravity(turned, mg, g, {}, Points(), {coarse}, cube().nodes());
  const GravityLoading by_cholmod = loadWithGravity(turned, direct, g);
  ASSERT_TRUE(by_multigrid.settled) << by_multigrid.failure;
  ASSERT_TRUE(by_cholmod.settled) << by_cholmod.failure;
  const double sag = by_cholmod.displacement_m.rowwise().norm().maxCoeff();
  const double gap = (by_multigrid.displacement_m - by_cholmod.displacement_m).rowwise().norm().maxCoeff();
  std::printf("[ measure  ] turned cube: sag %.2f mm, multigrid - CHOLMOD %.2e mm (%d and %d steps)\n", 1e3 * sag,
              1e3 * gap, by_multigrid.steps, by_cholmod.steps);
  EXPECT_GT(sag, 5e-3);
  EXPECT_LT(gap, 1e-3 * sag);
}
