// Implicit sliding on the chest wall (wall_slip.h): a block on a plane slides above the friction
// angle and sticks below it without leaving the plane; the two-breast phantom under supine gravity
// with stiffening and reversal settles with its wall sliding laterally while the medial rim, held by
// the Gaussian tether, moves far less.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/sliding/wall_slip.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "sliding_block.h"

using namespace breast_sim::core;

namespace {

using Block = test_fixtures::SlidingBlock;

}  // namespace

TEST(WallSlip, BlockSlidesAboveTheFrictionAngleAndSticksBelowItOnThePlane) {
  WallSlipSettings ws;
  ws.static_friction = 0.2;
  ws.kinetic_friction = 0.15;
  ws.tether_stiffness_pa_per_m = 0;  // no limiting factor
  ws.contact = false;
  // Below: tan θ = 1/9.81 ≈ 0.10 < μ_s.
  {
    Block b(Eigen::Vector3d(1.0, 0.0, -9.81), 0.033);
    WallSlip slip(b.geometry, b.mesh, ws);
    slip.attach(*b.sim);
    int slipping = -1;
    for (int k = 0; k < 40; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      slipping = slip.afterStep(*b.sim).slipping;
    }
    const double speed = b.sim->state().velocity_mps.cwiseAbs().maxCoeff();
    std::printf("[ measure  ] below the friction angle: bottom moved %.4f mm along x, %.5f mm off the plane, "
                "%d nodes slipping, speed %.2g m/s\n",
                1e3 * b.meanBottom(0), 1e3 * b.meanBottom(2), slipping, speed);
    // Pre-slip (μ_s ρ g H / κ_f = 20 µm) and some local slip while the sudden load rings down, then
    // it stands still.
    EXPECT_LT(std::abs(b.meanBottom(0)), 0.25e-3);
    EXPECT_LT(std::abs(b.meanBottom(2)), 0.01e-3);
    EXPECT_EQ(slipping, 0);
    EXPECT_LT(speed, 1e-3);
  }
  // Above: tan θ = 4/9.81 ≈ 0.41 > μ_s: it slides, decelerated by kinetic friction.
  {
    const double dt = 0.01;
    Block b(Eigen::Vector3d(4.0, 0.0, -9.81), dt);
    WallSlip slip(b.geometry, b.mesh, ws);
    slip.attach(*b.sim);
    int slipping = 0;
    for (int k = 0; k < 10; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      slipping = slip.afterStep(*b.sim).slipping;
    }
    const double t = b.sim->state().time_s;
    const double x = b.meanBottom(0);
    // Rigid sliding would move (g_x − μ_k g) t²/2; mass damping (1/s) and the elastic start take a
    // little of it.
    const double rigid = 0.5 * (4.0 - 0.15 * 9.81) * t * t;
    std::printf("[ measure  ] above the friction angle: bottom moved %.3f mm along x in %.2f s (rigid, kinetic "
                "friction: %.3f mm), %.5f mm off the plane, %d of %zu nodes slipping\n",
                1e3 * x, t, 1e3 * rigid, 1e3 * b.meanBottom(2), slipping, slip.nodes().size());
    EXPECT_GT(x, 0.5 * rigid);
    EXPECT_LT(x, 1.2 * rigid);
    EXPECT_LT(std::abs(b.meanBottom(2)), 0.01e-3);
    EXPECT_EQ(slipping, static_cast<int>(slip.nodes().size()));
  }
}

TEST(WallSlip, AHeldWallDoesNotSlipAboveTheFrictionAngleAndStopsASlippingNode) {
  // Above the friction angle (tan θ ≈ 0.41 > μ_s) the block slides (test above); held, no node starts
  // to slip and the bottom stays within the stick springs' elastic pre-slip (ρ g_x H / κ_f ≈ 40 µm);
  // held while it slides, every node sticks where it is.
  WallSlipSettings ws;
  ws.tether_stiffness_pa_per_m = 0;
  ws.contact = false;
  {
    Block b(Eigen::Vector3d(4.0, 0.0, -9.81), 0.01);
    WallSlip slip(b.geometry, b.mesh, ws);
    slip.attach(*b.sim);
    slip.setHeld(true, *b.sim);
    EXPECT_TRUE(slip.held());
    int slipping = -1;
    for (int k = 0; k < 40; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      slipping = slip.afterStep(*b.sim).slipping;
    }
    std::printf("[ measure  ] held wall above the friction angle: bottom moved %.4f mm along x, %d nodes slipping\n",
                1e3 * b.meanBottom(0), slipping);
    EXPECT_EQ(slipping, 0);
    EXPECT_LT(std::abs(b.meanBottom(0)), 0.1e-3);
  }
  {
    Block b(Eigen::Vector3d(4.0, 0.0, -9.81), 0.01);
    WallSlip slip(b.geometry, b.mesh, ws);
    slip.attach(*b.sim);
    for (int k = 0; k < 10; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      slip.afterStep(*b.sim);
    }
    ASSERT_GT(slip.afterStep(*b.sim).slipping, 0);
    const double x0 = b.meanBottom(0);
    slip.setHeld(true, *b.sim);
    for (int i = 0; i < static_cast<int>(slip.nodes().size()); ++i) EXPECT_EQ(slip.slipping()[static_cast<size_t>(i)], 0);
    EXPECT_EQ(slip.slipDirections().cwiseAbs().maxCoeff(), 0.0);
    for (int k = 0; k < 40; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      EXPECT_EQ(slip.afterStep(*b.sim).slipping, 0);
    }
    // It comes to rest on its stick springs: within the elastic pre-slip plus the stop from speed.
    std::printf("[ measure  ] held while sliding: bottom moved %.3f mm after the hold\n", 1e3 * (b.meanBottom(0) - x0));
    EXPECT_LT(b.meanBottom(0) - x0, 2e-3);
    slip.setHeld(false, *b.sim);
    for (int k = 0; k < 10; ++k) {
      slip.beforeStep(*b.sim);
      b.sim->step();
      slip.afterStep(*b.sim);
    }
    EXPECT_GT(slip.afterStep(*b.sim).slipping, 0);  // released, it slides again
  }
}

TEST(WallSlip, NodesOfTheSetFarFromTheWallStayWhereTheyAre) {
  // A wall node set that also holds nodes far from the wall (here the block's top, 10 mm up; on a
  // label image, faces that cut through the body at the image border): the wall field gives them no
  // level to slide on and no normal load, so free they would fall with the block. They are held at
  // their rest points; the bottom still slides, sheared against them.
  Block b(Eigen::Vector3d(4.0, 0.0, -9.81), 0.01);
  std::vector<int> set = b.mesh.nodeSet("z_min"), top = b.mesh.nodeSet("z_max");
  set.insert(set.end(), top.begin(), top.end());
  SlidingSettings s;
  s.gaussian_limit = false;
  s.thickness_limit = false;
  s.rim_band = false;
  auto wall = std::make_shared<const ChestWallSurface>(b.image, std::set<std::uint16_t>{Block::kWall});
  auto geometry = std::make_shared<ChestWallSliding>(b.mesh, set, wall, s, nullptr, TissueLabels{},
                                                     std::vector<Eigen::Vector3d>{}, Eigen::Vector3d::UnitZ());
  ASSERT_EQ(geometry->heldNodes(), static_cast<int>(top.size()));
  WallSlipSettings ws;
  ws.tether_stiffness_pa_per_m = 0;
  ws.contact = false;
  WallSlip slip(geometry, b.mesh, ws);
  slip.attach(*b.sim);
  for (int k = 0; k < 20; ++k) {
    slip.beforeStep(*b.sim);
    b.sim->step();
    slip.afterStep(*b.sim);
  }
  double top_move = 0;
  for (int v : top) top_move = std::max(top_move, b.sim->state().displacement_m.segment<3>(3 * v).norm());
  std::printf("[ measure  ] top held: top nodes moved at most %.4f mm, bottom %.3f mm along x\n", 1e3 * top_move,
              1e3 * b.meanBottom(0));
  EXPECT_LT(top_move, 0.01e-3);
  EXPECT_GT(b.meanBottom(0), 0.01e-3);
  EXPECT_LT(std::abs(b.meanBottom(2)), 0.01e-3);
}

TEST(WallSlip, ExtraSpringsAreSetWithTheWallsAndSummedOnASharedNode) {
  // The morphing's implicit pull goes to the simulator with the wall's springs (one set per
  // simulator): on a wall node the two blocks are summed, elsewhere the extra spring is its own.
  WallSlipSettings ws;
  ws.contact = false;
  Block b(Eigen::Vector3d(1.0, 0.0, -9.81), 0.033);
  WallSlip slip(b.geometry, b.mesh, ws);
  slip.attach(*b.sim);
  for (int k = 0; k < 3; ++k) {  // a deformed state, so the wall springs carry force
    slip.beforeStep(*b.sim);
    b.sim->step();
    slip.afterStep(*b.sim);
  }
  slip.beforeStep(*b.sim);
  const Eigen::VectorXd wall_only = b.sim->currentSpringForces();
  const int shared = slip.nodes().front();
  int other = -1;  // a node off the wall
  for (int v = 0; v < b.mesh.numNodes() && other < 0; ++v)
    if (std::find(slip.nodes().begin(), slip.nodes().end(), v) == slip.nodes().end()) other = v;
  ASSERT_GE(other, 0);
  NodeSprings extra;
  extra.nodes = {shared, other};
  Eigen::Matrix3d k1 = Eigen::Matrix3d::Zero(), k2 = Eigen::Matrix3d::Identity() * 3.0;
  k1(0, 0) = 50.0;
  k1(0, 1) = k1(1, 0) = 10.0;
  k1(1, 1) = 20.0;
  extra.stiffness_n_per_m = {k1, k2};
  extra.anchors_m.resize(2, 3);
  extra.anchors_m.row(0) = b.mesh.nodes().row(shared) + Eigen::RowVector3d(1e-3, -2e-3, 0.5e-3);
  extra.anchors_m.row(1) = b.mesh.nodes().row(other) + Eigen::RowVector3d(0, 0, 4e-3);
  slip.beforeStep(*b.sim, &extra);
  const Eigen::VectorXd both = b.sim->currentSpringForces();
  const Eigen::VectorXd& u = b.sim->state().displacement_m;
  for (int j = 0; j < 2; ++j) {
    const int v = extra.nodes[static_cast<size_t>(j)];
    const Eigen::Vector3d x = b.mesh.nodes().row(v).transpose() + u.segment<3>(3 * v);
    const Eigen::Vector3d f_extra = -extra.stiffness_n_per_m[static_cast<size_t>(j)] * (x - extra.anchors_m.row(j).transpose());
    EXPECT_LT((both.segment<3>(3 * v) - wall_only.segment<3>(3 * v) - f_extra).norm(), 1e-9 * (1 + f_extra.norm()))
        << "node " << v;
  }
  // Every other node keeps its wall force, and the summed stiffness is on the shared node only once.
  Eigen::VectorXd rest = both - wall_only;
  for (int v : extra.nodes) rest.segment<3>(3 * v).setZero();
  EXPECT_EQ(rest.cwiseAbs().maxCoeff(), 0.0);
  EXPECT_EQ(b.sim->springNodes().size(), slip.nodes().size() + 1);
  // A list whose sizes do not match is refused.
  extra.anchors_m.conservativeResize(1, 3);
  EXPECT_THROW(slip.beforeStep(*b.sim, &extra), std::invalid_argument);
}

TEST(WallSlip, BadSettingsAreNamed) {
  WallSlipSettings s;
  s.kinetic_friction = 0.5;
  try {
    s.validate();
    FAIL() << "accepted kinetic_friction > static_friction";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("kinetic_friction"), std::string::npos) << e.what();
  }
  s = WallSlipSettings{};
  s.normal_stiffness_pa_per_m = 0;
  EXPECT_THROW(s.validate(), std::invalid_argument);
}

// The case the explicit update could not settle (74–96 % of the steps reversed, rim elements
// flattened): supine gravity after the fixed-wall settle, stiffening with reversal, then the wall
// released onto implicit sliding with the J − 1 volume term, tethered (κ_0 = 5e4 Pa/m) with the
// Gaussian limit (σ a quarter breast) on and off. Measured (3.2k elements): see the [ measure ] lines.
TEST(WallSlip, TwoBreastPhantomSettlesWithStiffeningAndTheGaussianHoldsTheMedialEdge) {
  ModelCase c = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_two_breasts.yaml");
  c.meshing.target_elements = 3000;
  const SimulationModel model = buildSimulationModel(c);
  SimulationSettings ss = loadSimulationSettings(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_two_breasts.yaml");
  ss.solver.kind = SolverSettings::Kind::kCholmod;
  ss.volume_term = CorotatedTetFem::VolumeTerm::kDeterminant;
  const Eigen::Vector3d g = c.phantom->gravity_supine_mps2 - c.phantom->gravity_prone_mps2;
  ss.dynamics.gravity_mps2 = g;
  struct Result {
    bool settled = false;
    long accepted = 0, reversed = 0;
    int inverted = -1;
    double volume_percent = 0, medial_mean_mm = 0, centre_mean_mm = 0, max_slide_mm = 0, normal_error_mm = 0;
  };
  auto run = [&](bool gaussian) {
    SimulatorBuild b = buildSimulator(c, model, ss);
    StiffeningSimulation stiff(*b.simulator, model.mesh);
    stiff.setGravity(g);
    DynamicsParams p = b.simulator->params();
    p.time_step_s = ss.settle.time_step_s;
    b.simulator->setParams(p);
    for (int k = 0; k < 2 * ss.settle.max_steps; ++k)
      if (stiff.step().advanced && stiff.settled()) break;
    EXPECT_TRUE(stiff.settled());
    p.time_step_s = ss.dynamics.time_step_s;
    b.simulator->setParams(p);
    const RunStats before = stiff.stats();
    SlidingSettings sliding;
    sliding.gaussian_limit = gaussian;
    sliding.gaussian_sigma_fraction = 0.25;
    WallSlipSettings ws;
    ws.tether_stiffness_pa_per_m = 5e4;  // the limiting factors act through the tether
    WallSlip slip = WallSlip::fromCase(c, model.mesh, sliding, ws);
    slip.attach(*b.simulator);
    stiff.restartAlphaSearch();
    Result res;
    WallSlipStats last;
    for (int calls = 0; calls < 200 && !res.settled; ++calls) {
      slip.beforeStep(*b.simulator);
      if (!stiff.step().advanced) continue;
      last = slip.afterStep(*b.simulator);
      res.settled = stiff.settled();
    }
    const RunStats rs = stiff.stats();
    res.accepted = rs.steps - before.steps;
    res.reversed = rs.reversed_steps - before.reversed_steps;
    res.inverted = rs.inverted_elements;
    res.volume_percent = rs.volume_change_percent;
    res.max_slide_mm = 1e3 * last.max_slide_m;
    res.normal_error_mm = 1e3 * last.max_normal_error_m;
    // The medial edge (|x| < 40 mm: the breasts start at |x| ≈ 33 mm) against the breast centres
    // (|x| in 70..110 mm, around the nipples at ±90 mm).
    const Points d = slip.slidingVectors(*b.simulator);
    int nm = 0, nc = 0;
    for (int v : slip.nodes()) {
      const double x = std::abs(model.mesh.nodes()(v, 0));
      if (x < 0.04) {
        res.medial_mean_mm += 1e3 * d.row(v).norm();
        ++nm;
      } else if (x > 0.07 && x < 0.11) {
        res.centre_mean_mm += 1e3 * d.row(v).norm();
        ++nc;
      }
    }
    EXPECT_GT(nm, 10);
    EXPECT_GT(nc, 10);
    res.medial_mean_mm /= std::max(1, nm);
    res.centre_mean_mm /= std::max(1, nc);
    std::printf("[ measure  ] implicit sliding, Gaussian %s: settled %d after %ld accepted / %ld reversed steps, "
                "inverted %d, volume %.2f %%, slide: medial edge mean %.2f mm, centre mean %.2f mm, max %.2f mm; "
                "off-wall error %.3f mm\n",
                gaussian ? "on " : "off", res.settled, res.accepted, res.reversed, res.inverted, res.volume_percent,
                res.medial_mean_mm, res.centre_mean_mm, res.max_slide_mm, res.normal_error_mm);
    return res;
  };
  const Result on = run(true), off = run(false);
  for (const Result& r : {on, off}) {
    EXPECT_TRUE(r.settled);
    EXPECT_EQ(r.inverted, 0);
    EXPECT_LE(r.reversed, r.accepted / 10);
    EXPECT_LT(std::abs(r.volume_percent), 3.0);
    EXPECT_LT(r.normal_error_mm, 0.2);
    EXPECT_GT(r.centre_mean_mm, 0.5);  // it slides
  }
  // The Gaussian holds the medial edge: less than half the slide it has without the limit, and
  // less than the centre slides.
  EXPECT_LT(on.medial_mean_mm, 0.5 * off.medial_mean_mm);
  EXPECT_LT(on.medial_mean_mm, on.centre_mean_mm);
}
