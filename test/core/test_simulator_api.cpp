// Driving the core with a mesh of one's own: a mesh read from an Abaqus deck, simulation settings,
// buildSimulator(mesh, settings, coarse meshes) with every solver, and settle() under gravity.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mesh/tet_mesh.h"

#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::TempDir;
namespace fs = std::filesystem;

namespace {

// A 9 × 4.5 × 4.5 cm block held on its side x = 0 (node set "chest_wall"), at three resolutions of
// the same domain (the coarse ones nest in the fine one), each written to an .inp file and read back
// as a researcher's meshes would be.
const Eigen::Vector3d kSize(0.09, 0.045, 0.045);

TetMesh blockMesh(const Eigen::Vector3i& cells) {
  TetMesh m = makeBoxMesh(cells, kSize);
  m.setNodeSet("chest_wall", m.nodeSet("x_min"));
  return m;
}

struct Meshes {
  TetMesh fine;
  std::vector<TetMesh> coarse;  // coarsest last
};

const Meshes& meshes() {
  static const Meshes* m = [] {
    auto* out = new Meshes;
    const TempDir dir("breast_sim_simulator_api");
    const std::vector<Eigen::Vector3i> cells = {{12, 6, 6}, {6, 3, 3}, {2, 1, 1}};
    for (size_t l = 0; l < cells.size(); ++l) {
      const std::string path = dir.path("block_" + std::to_string(l) + ".inp");
      writeAbaqusInp(path, blockMesh(cells[l]));
      TetMesh read = readTetMesh(path);
      if (l == 0)
        out->fine = std::move(read);
      else
        out->coarse.push_back(std::move(read));
    }
    return out;
  }();
  return *m;
}

// E = 20 kPa, ν = 0.45, 1000 kg/m³ under gravity along −z (a sag of about 2 cm at the free end);
// the default solver tolerance and settling criterion.
SimulationSettings settings(SolverSettings::Kind kind) {
  SimulationSettings s;
  s.material.youngs_modulus_pa = 20000.0;
  s.material.poisson_ratio = 0.45;
  s.dynamics.gravity_mps2 = {0.0, 0.0, -9.81};
  s.solver.kind = kind;
  return s;
}

struct Settled {
  Eigen::VectorXd u;  // #3N [m]
  SettleResult r;
  SimulatorBuild b;
};

Settled settleWith(const SimulationSettings& s, std::vector<TetMesh> coarse = {}) {
  Settled out;
  out.b = buildSimulator(meshes().fine, s, std::move(coarse));
  out.r = settle(*out.b.simulator, s.settle);
  out.u = out.b.simulator->displacement().reshaped<Eigen::RowMajor>();
  return out;
}

const Settled& exact() {
  static const Settled e = settleWith(settings(SolverSettings::Kind::kCholmod));
  return e;
}

std::string errorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "(no error)";
}

}  // namespace

TEST(SimulatorApi, NodeSetsRoundTripThroughAnAbaqusDeck) {
  const TetMesh original = blockMesh({12, 6, 6});
  const TetMesh& read = meshes().fine;
  ASSERT_EQ(read.numNodes(), original.numNodes());
  ASSERT_EQ(read.numTets(), original.numTets());
  EXPECT_EQ(read.nodeSets(), original.nodeSets());
  EXPECT_LE((read.nodes() - original.nodes()).cwiseAbs().maxCoeff(), 1e-12);
}

// CHOLMOD's settled block is the reference: a plausible sag (millimetres to centimetres, finite,
// downwards at the free end), with the held side still.
TEST(SimulatorApi, CholmodSettlesTheBlockUnderGravity) {
  const Settled& e = exact();
  ASSERT_TRUE(e.r.settled) << e.r.steps << " steps, last increment " << e.r.last_increment_m;
  EXPECT_EQ(e.b.multigrid_levels, 0);
  ASSERT_TRUE(e.u.allFinite());
  const double umax = maxNodalNorm(e.u);
  EXPECT_GT(umax, 1e-3);
  EXPECT_LT(umax, 0.03);
  for (int v : meshes().fine.nodeSet("chest_wall")) EXPECT_EQ(e.u.segment<3>(3 * v).norm(), 0.0);
  for (int v : meshes().fine.nodeSet("x_max")) EXPECT_LT(e.u[3 * v + 2], 0.0);
}

// Every solver settles to CHOLMOD's state within 1e-3 of the largest displacement; the geometric
// multigrid with the coarse meshes read from their decks.
TEST(SimulatorApi, EverySolverSettlesToTheDirectSolversState) {
  const Settled& e = exact();
  const double umax = maxNodalNorm(e.u);
  for (const SolverSettings::Kind kind :
       {SolverSettings::Kind::kJacobiPcg, SolverSettings::Kind::kAggregation, SolverSettings::Kind::kMultigrid}) {
    SCOPED_TRACE(SolverSettings::kindName(kind));
    const bool mg = kind == SolverSettings::Kind::kMultigrid;
    const Settled s = settleWith(settings(kind), mg ? meshes().coarse : std::vector<TetMesh>{});
    ASSERT_TRUE(s.r.settled) << s.r.steps << " steps";
    ASSERT_TRUE(s.u.allFinite());
    EXPECT_LT(maxNodalNorm(s.u - e.u), 1e-3 * umax);
    if (mg) {
      EXPECT_EQ(s.b.multigrid_levels, 3);
      EXPECT_EQ(s.b.level_nodes, (std::vector<int>{meshes().fine.numNodes(), meshes().coarse[0].numNodes(),
                                                   meshes().coarse[1].numNodes()}));
    } else {
      EXPECT_EQ(s.b.multigrid_levels, 0);
    }
  }
}

TEST(SimulatorApi, CholmodBlasThreadsArePassedOnAndLeaveTheStateAsItIs) {
  SimulationSettings s = settings(SolverSettings::Kind::kCholmod);
  EXPECT_EQ(s.solver.cholmod.blas_threads, 0);  // as configured
  s.solver.cholmod.blas_threads = 1;
  const Settled one = settleWith(s);
  ASSERT_TRUE(one.r.settled);
  EXPECT_EQ(one.r.steps, exact().r.steps);
  EXPECT_LE(maxNodalNorm(one.u - exact().u), 1e-12 * maxNodalNorm(exact().u));
  s.solver.cholmod.blas_threads = -1;
  EXPECT_NE(errorOf([&] { buildSimulator(meshes().fine, s); }).find("solver.cholmod.blas_threads"), std::string::npos);
}

TEST(SimulatorApi, MultigridWithoutCoarseMeshesSaysWhatToGiveOrChoose) {
  const std::string e = errorOf([] { buildSimulator(meshes().fine, settings(SolverSettings::Kind::kMultigrid)); });
  EXPECT_NE(e.find("coarse meshes"), std::string::npos) << e;
  EXPECT_NE(e.find("'aggregation'"), std::string::npos) << e;
  EXPECT_NE(e.find("'cholmod'"), std::string::npos) << e;
  EXPECT_THROW(buildSimulator(meshes().fine, settings(SolverSettings::Kind::kMultigrid)), std::invalid_argument);
}

TEST(SimulatorApi, CoarseMeshesWithAnotherSolverAreRejected) {
  for (const SolverSettings::Kind kind : {SolverSettings::Kind::kCholmod, SolverSettings::Kind::kAggregation}) {
    EXPECT_THROW(buildSimulator(meshes().fine, settings(kind), meshes().coarse), std::invalid_argument);
    const std::string e = errorOf([&] { buildSimulator(meshes().fine, settings(kind), meshes().coarse); });
    EXPECT_NE(e.find("used only by the solver 'multigrid'"), std::string::npos) << e;
  }
}

// A coarse mesh that does not cover the fine one is named as MeshHierarchy names it.
TEST(SimulatorApi, ACoarseMeshOfAnotherDomainIsRejected) {
  const TetMesh smaller = makeBoxMesh({2, 1, 1}, kSize / 2);
  EXPECT_THROW(buildSimulator(meshes().fine, settings(SolverSettings::Kind::kMultigrid), {smaller}),
               std::invalid_argument);
}

TEST(SimulatorApi, AMisspeltFixedNodeSetNamesTheSetsAndTheNearOne) {
  const TetMesh& box = meshes().fine;
  TetMesh m(box.nodes(), box.tets());
  m.setNodeSet("CHESTWALL", box.nodeSet("x_min"));
  m.setNodeSet("skin", box.boundary().nodes);
  SimulationSettings s = settings(SolverSettings::Kind::kCholmod);
  s.fixed_node_set = "Chest_Wall";
  EXPECT_THROW(buildSimulator(m, s), std::invalid_argument);
  const std::string e = errorOf([&] { buildSimulator(m, s); });
  EXPECT_NE(e.find("fixed_node_set 'Chest_Wall' is not a node set of the mesh (it has: CHESTWALL, skin); did you mean "
                   "'CHESTWALL'?"),
            std::string::npos)
      << e;
  s.fixed_node_set = "ribs";  // nothing near: no suggestion
  EXPECT_EQ(errorOf([&] { buildSimulator(m, s); }).find("did you mean"), std::string::npos);
  const TetMesh bare(box.nodes(), box.tets());
  EXPECT_NE(errorOf([&] { buildSimulator(bare, s); }).find("(it has none)"), std::string::npos);
  s.fixed_node_set = "";  // holds nothing: builds
  EXPECT_NO_THROW(buildSimulator(bare, s));
}

TEST(TetMeshNodeSetNames, NearestNameIsCaseInsensitiveOrWithinTwoEdits) {
  const TetMesh& box = meshes().fine;
  TetMesh m(box.nodes(), box.tets());
  m.setNodeSet("CHESTWALL", {0});
  m.setNodeSet("skin", {1});
  m.setNodeSet("nipple", {2});
  EXPECT_EQ(m.nodeSetNames(), "CHESTWALL, nipple, skin");
  EXPECT_EQ(m.nearestNodeSetName("skin"), "skin");          // itself
  EXPECT_EQ(m.nearestNodeSetName("SKIN"), "skin");          // case
  EXPECT_EQ(m.nearestNodeSetName("Chest_Wall"), "CHESTWALL");  // case and one insertion
  EXPECT_EQ(m.nearestNodeSetName("skni"), "skin");          // transposition
  EXPECT_EQ(m.nearestNodeSetName("nippels"), "nipple");     // two edits
  EXPECT_EQ(m.nearestNodeSetName("ribs"), "");
  EXPECT_EQ(m.nearestNodeSetName("skn"), "skin");           // short names: one edit …
  EXPECT_EQ(m.nearestNodeSetName("sk"), "");                // … not two
  EXPECT_EQ(m.nearestNodeSetName(""), "");
  m.setNodeSet("Skin", {3});  // two sets equal but for case: the alphabetically first, never a lookup
  EXPECT_EQ(m.nearestNodeSetName("SKIN"), "Skin");
  EXPECT_EQ(m.nearestNodeSetName("skin"), "skin");
  try {
    m.nodeSet("Nipple");
    FAIL() << "no error for a missing node set";
  } catch (const std::out_of_range& e) {
    EXPECT_NE(std::string(e.what()).find("did you mean 'nipple'?"), std::string::npos) << e.what();
  }
}
