// Sliding on the chest wall: normal field and level set of a segmented wall, a block on an inclined
// plane with friction, a shell on a curved wall, and the two-breast phantom with the Gaussian limit.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <random>
#include <set>

#include <Eigen/Geometry>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "sliding_block.h"

using namespace breast_sim::core;

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr std::uint16_t kWall = 40, kFat = 1;

// Label image: wall (40) where inside(p), fat (1) elsewhere.
template <class Inside>
LabelImage maskImage(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, double voxel, Inside inside,
                     const Eigen::Matrix3d& direction = Eigen::Matrix3d::Identity()) {
  const Eigen::Vector3i size = ((hi - lo) / voxel).array().ceil().cast<int>() + 1;
  LabelImage im(size, Eigen::Vector3d::Constant(voxel), lo, kFat);
  im.direction = direction;
  for (int k = 0; k < size.z(); ++k)
    for (int j = 0; j < size.y(); ++j)
      for (int i = 0; i < size.x(); ++i)
        if (inside(im.indexToPhysical(Eigen::Vector3d(i, j, k)))) im.at(i, j, k) = kWall;
  return im;
}

double angleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) * 180.0 / kPi;
}

TetMesh transformed(const TetMesh& m, const std::function<Eigen::Vector3d(const Eigen::Vector3d&)>& f) {
  Points p(m.numNodes(), 3);
  for (int i = 0; i < m.numNodes(); ++i) p.row(i) = f(m.nodes().row(i).transpose()).transpose();
  TetMesh out(p, m.tets(), m.regionLabels());
  for (const auto& [name, set] : m.nodeSets()) out.setNodeSet(name, set);
  return out;
}

SlidingSettings unlimited() {
  SlidingSettings s;
  s.gaussian_limit = false;
  s.thickness_limit = false;
  s.max_slide_m = 0.0;
  return s;
}

}  // namespace

TEST(NormalQuantile, InvertsTheNormalDistributionFunction) {
  for (double p : {1e-9, 1e-4, 0.01, 0.02425, 0.2, 0.5, 0.7, 0.97575, 0.999, 1 - 1e-9}) {
    const double x = normalQuantile(p);
    EXPECT_NEAR(0.5 * std::erfc(-x / std::sqrt(2.0)), p, 1e-14 + 1e-12 * p) << p;
  }
  EXPECT_THROW(normalQuantile(0.0), std::invalid_argument);
  EXPECT_THROW(normalQuantile(1.0), std::invalid_argument);
}

// An inclined plane segmented on a rotated voxel grid: the normal field equals the plane normal
// (< 1° more than 4σ from the image border), the signed distance matches the exact one within
// 0.1 mm up to 4 mm from the plane, and projection lands on the plane within 0.1 mm.
TEST(ChestWallSurface, PlanarMaskGivesThePlaneNormalDistanceAndProjection) {
  const Eigen::Vector3d n = Eigen::Vector3d(-0.35, 0.2, 1.0).normalized();  // out of the wall
  const Eigen::Vector3d c(0.001, -0.002, 0.0005);
  const Eigen::Matrix3d dir = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
  // Grid axes rotated; lo is the origin in grid coordinates mapped through dir.
  const double half = 0.03;
  const Eigen::Vector3d origin = c - dir * Eigen::Vector3d::Constant(half);
  const LabelImage im = maskImage(origin, origin + Eigen::Vector3d::Constant(2 * half), 1e-3,
                                  [&](const Eigen::Vector3d& p) { return (p - c).dot(n) < 0; }, dir);
  // maskImage sizes the grid by (hi − lo) / voxel: with a rotated grid that is the cube of side 2·half.
  const ChestWallSurface wall(im, {kWall});
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const Eigen::Vector3d t1 = n.unitOrthogonal(), t2 = n.cross(t1);
  double worst_angle = 0, worst_dist = 0, worst_proj = 0;
  for (int k = 0; k < 300; ++k) {
    const Eigen::Vector3d p = c + 0.016 * u(rng) * t1 + 0.016 * u(rng) * t2 + 0.004 * u(rng) * n;
    // Keep points whose grid index is more than 4σ + 1 voxel from the border.
    const Eigen::Vector3d ijk = im.physicalToIndex(p);
    if ((ijk.array() < 9).any() || (ijk.array() > im.size.cast<double>().array() - 10).any()) continue;
    worst_angle = std::max(worst_angle, angleDeg(wall.normal(p), n));
    worst_dist = std::max(worst_dist, std::abs(wall.signedDistance(p) - (p - c).dot(n)));
    const WallProjection pr = wall.project(p);
    ASSERT_TRUE(pr.converged);
    worst_proj = std::max(worst_proj, std::abs((pr.point_m - c).dot(n)));
  }
  EXPECT_LT(worst_angle, 1.0);
  EXPECT_LT(worst_dist, 1.5e-4);
  EXPECT_LT(worst_proj, 1e-4);
  // The signed distance is positive outside the wall and its gradient is the normal.
  Eigen::Vector3d g;
  const double h = wall.signedDistance(c + 0.002 * n, g);
  EXPECT_GT(h, 0.0019);
  EXPECT_LT(angleDeg(g, n), 1.0);
  EXPECT_NEAR(g.norm(), 1.0, 0.03);
  // Finite-difference check of ∇h along a random direction. ∇h comes from the filtered gradient (the
  // derivative of the smooth field), h from the trilinear interpolant of S, whose slope within a
  // voxel is a one-voxel difference: they agree on the voxel scale, so the step is half a voxel.
  const Eigen::Vector3d p0 = c + 0.001 * n + 0.003 * t1, d = Eigen::Vector3d(0.3, -0.5, 0.8).normalized();
  const double e = 5e-4;
  wall.signedDistance(p0, g);
  const double fd = (wall.signedDistance(p0 + e * d) - wall.signedDistance(p0 - e * d)) / (2 * e);
  EXPECT_NEAR(fd, g.dot(d), 0.02);
}

TEST(ChestWallSurface, RejectsAnImageWithoutWallAndBadOptions) {
  const LabelImage im({10, 10, 10}, {1e-3, 1e-3, 1e-3}, {0, 0, 0}, kFat);
  try {
    ChestWallSurface w(im, {kWall});
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("labels: 40"), std::string::npos) << e.what();
  }
  ChestWallFieldOptions o;
  o.sigma_m = -1;
  EXPECT_THROW(o.validate(), std::invalid_argument);
}

namespace {

// A block (20 × 20 × 10 mm, 4 × 4 × 2 cubes) resting with its z_min face on the plane through the
// origin inclined by θ about y; gravity −z. Returns the mean downhill slide of the bottom nodes
// after each step.
struct InclineRun {
  std::vector<double> mean_downhill_m;
  double min_plane_distance_m = 1e9;  ///< of the bottom nodes, exact plane distance
  double mean_cross_slide_m = 0;      ///< mean signed slide across the slope (along y), last step
  int stiffness_limited = 0;
  double predicted_velocity_mps = 0;
};

InclineRun runIncline(double theta_deg, const SlidingSettings& s, int steps,
                      const std::function<Eigen::Vector3d(int)>& gravity_at_step) {
  const double th = theta_deg * kPi / 180.0;
  const Eigen::Vector3d n(-std::sin(th), 0, std::cos(th)), t1(std::cos(th), 0, std::sin(th));
  Eigen::Matrix3d R;
  R << t1, Eigen::Vector3d::UnitY(), n;
  const TetMesh box = makeBoxMesh({4, 4, 2}, {0.02, 0.02, 0.01});
  const TetMesh m = transformed(box, [&](const Eigen::Vector3d& p) {
    return Eigen::Vector3d(R * (p - Eigen::Vector3d(0.01, 0.01, 0.0)));
  });
  const LabelImage im = maskImage({-0.045, -0.02, -0.035}, {0.03, 0.02, 0.035}, 1e-3,
                                  [&](const Eigen::Vector3d& p) { return p.dot(n) < 0; });
  auto wall = std::make_shared<const ChestWallSurface>(im, std::set<std::uint16_t>{kWall});
  ElasticMaterial mat;
  mat.poisson_ratio = 0.45;
  DynamicsParams p;
  p.gravity_mps2 = gravity_at_step(0);
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<CholmodSolver>());
  const std::vector<int>& bottom = m.nodeSet("z_min");
  ChestWallSliding sliding(m, bottom, wall, s, nullptr, TissueLabels{}, {}, n);
  sliding.attach(sim);
  InclineRun r;
  const Eigen::Vector3d downhill = -t1;
  for (int k = 0; k < steps; ++k) {
    sim.setGravity(gravity_at_step(k));
    sim.step();
    const SlidingStepStats st = sliding.update(sim);
    r.stiffness_limited += st.stiffness_limited;
    const Points u = sim.displacement();
    double mean = 0;
    r.mean_cross_slide_m = 0;
    for (int v : bottom) {
      const Eigen::Vector3d x = m.nodes().row(v).transpose() + u.row(v).transpose();
      r.min_plane_distance_m = std::min(r.min_plane_distance_m, x.dot(n));
      mean += u.row(v).dot(downhill);
      r.mean_cross_slide_m += u(v, 1) / bottom.size();
    }
    r.mean_downhill_m.push_back(mean / bottom.size());
    if (k % 10 == 9 && std::getenv("BREAST_SIM_TEST_VERBOSE"))
      std::printf("  θ %.0f° step %d: mean downhill slide %.4f mm, moving %d, stuck %d, stiffness-limited %d\n",
                  theta_deg, k + 1, 1e3 * r.mean_downhill_m.back(), st.moving, st.stuck, st.stiffness_limited);
  }
  // Uniform traction of the block's weight: τ_t = ρ g H sin θ, τ_n = ρ g H cos θ.
  const double rgh = mat.density_kg_per_m3 * 9.81 * 0.01;
  r.predicted_velocity_mps =
      s.mobility_m_per_pa_s * std::max(0.0, rgh * std::sin(th) - s.kinetic_friction * rgh * std::cos(th));
  return r;
}

}  // namespace

// Above the friction angle the block slides downhill, at most at the speed that mobility and kinetic
// friction give for the block's mean traction (the bottom also spreads sideways under its weight
// and the traction is not uniform, so the measured speed is lower), straight down the slope on
// average, and never into the plane (its bottom stays within 0.1 mm of it).
TEST(Sliding, WallNodesWhereTheFieldDescribesNoWallAreHeld) {
  // The block's bottom (20 × 20 mm, 5 × 5 nodes 5 mm apart) as the wall set, on wall images that
  // differ in where the image starts along x and how deep the wall reaches into the block.
  const TetMesh mesh = makeBoxMesh({4, 4, 2}, {0.02, 0.02, 0.01});
  SlidingSettings s = unlimited();
  s.rim_band = false;
  auto held = [&](double x_lo_m, double wall_top_m) {
    const LabelImage im = maskImage(Eigen::Vector3d(x_lo_m, -0.03, -0.02), Eigen::Vector3d(0.05, 0.05, 0.02), 1e-3,
                                    [&](const Eigen::Vector3d& p) { return p.z() < wall_top_m; });
    auto wall = std::make_shared<const ChestWallSurface>(im, std::set<std::uint16_t>{kWall});
    const ChestWallSliding cw(mesh, mesh.nodeSet("z_min"), wall, s, nullptr, TissueLabels{}, {}, Eigen::Vector3d::UnitZ());
    std::vector<double> xs;  // the held nodes' x [m]
    for (size_t i = 0; i < cw.nodes().size(); ++i)
      if (cw.heldFlags()[i]) xs.push_back(mesh.nodes()(cw.nodes()[i], 0));
    EXPECT_EQ(cw.heldNodes(), static_cast<int>(xs.size()));
    return xs;
  };
  // On the wall, the image 30 mm beyond the block: every node slides.
  EXPECT_TRUE(held(-0.03, 0.0).empty());
  // The image starts 1 mm before the block (within σ = 2 mm): the column at x = 0 is held, the one at
  // 5 mm is not.
  const std::vector<double> border = held(-0.001, 0.0);
  EXPECT_EQ(border.size(), 5u);
  for (double x : border) EXPECT_NEAR(x, 0.0, 1e-12);
  // 3 mm deep in the wall mask (more than σ): all held; 1 mm deep: none.
  EXPECT_EQ(held(-0.03, 0.0035).size(), 25u);
  EXPECT_TRUE(held(-0.03, 0.0015).empty());
}

TEST(Sliding, BlockSlidesDownASteepInclineWithoutPenetrating) {
  SlidingSettings s = unlimited();
  s.static_friction = 0.3;
  s.kinetic_friction = 0.2;
  const InclineRun r = runIncline(30.0, s, 60, [](int) { return Eigen::Vector3d(0, 0, -9.81); });
  const double v = (r.mean_downhill_m[59] - r.mean_downhill_m[39]) / (20 * 0.033);
  EXPECT_GT(r.mean_downhill_m.back(), 5e-4);
  EXPECT_GT(v, 0.1 * r.predicted_velocity_mps);
  EXPECT_LT(v, 1.25 * r.predicted_velocity_mps);
  EXPECT_GT(r.min_plane_distance_m, -1e-4);
  EXPECT_LT(std::abs(r.mean_cross_slide_m), 0.02 * r.mean_downhill_m.back());
}

// Below the friction angle (tan 10° = 0.18 < μ_s = 0.3) only some rim nodes slip a little and come
// to rest (partial slip of an elastic block); a block sliding on a 30° slope stops once gravity
// turns so that the effective slope is 5° (below the kinetic friction angle).
TEST(Sliding, BlockStaysOnAShallowInclineAndStopsWhenTheSlopeDrops) {
  // The friction law node by node: without the traction and move smoothing of the robustness steps
  // (with them a node held by static friction is handed its neighbours' moves and stays on kinetic
  // friction: the smoothing does not keep a stuck node still).
  SlidingSettings s = unlimited();
  s.static_friction = 0.3;
  s.kinetic_friction = 0.2;
  s.traction_smoothing_rings = 0;
  s.move_smoothing_iterations = 0;
  const InclineRun steep = runIncline(30.0, s, 30, [](int) { return Eigen::Vector3d(0, 0, -9.81); });
  const InclineRun still = runIncline(10.0, s, 40, [](int) { return Eigen::Vector3d(0, 0, -9.81); });
  EXPECT_LT(std::abs(still.mean_downhill_m[29]), 0.2 * steep.mean_downhill_m[29]);
  // decelerating to rest: the last ten steps move less than a quarter of the first ten
  EXPECT_LT(std::abs(still.mean_downhill_m[39] - still.mean_downhill_m[29]), 0.25 * std::abs(still.mean_downhill_m[9]));
  // 30° plane; after 30 steps gravity turns by 25° about y towards the plane normal: slope 5°.
  const double turn = 25.0 * kPi / 180.0;
  const InclineRun stop = runIncline(30.0, s, 60, [&](int k) {
    return k < 30 ? Eigen::Vector3d(0, 0, -9.81) : Eigen::Vector3d(9.81 * std::sin(turn), 0, -9.81 * std::cos(turn));
  });
  EXPECT_GT(stop.mean_downhill_m[29], 2e-4);
  EXPECT_LT(std::abs(stop.mean_downhill_m[59] - stop.mean_downhill_m[49]), 1e-6);
  EXPECT_GT(stop.min_plane_distance_m, -1e-4);
}

// A curved shell (arc 40 mm × 8 mm thick × 16 mm long) on a cylinder of radius 40 mm segmented at
// 1 mm, on the upper right side; gravity −y makes it slide around the cylinder. Its wall nodes stay
// on the cylinder within 0.15 mm and outside it by more than −0.1 mm, while sliding several mm.
TEST(Sliding, ShellOnACurvedWallStaysOnTheSurface) {
  const double R = 0.04;
  const TetMesh box = makeBoxMesh({8, 2, 3}, {0.04, 0.008, 0.016});
  const double phi0 = 60.0 * kPi / 180.0;
  const TetMesh m = transformed(box, [&](const Eigen::Vector3d& p) {
    const double phi = phi0 + (p.x() - 0.02) / R, r = R + p.y();
    return Eigen::Vector3d(r * std::cos(phi), r * std::sin(phi), p.z() - 0.008);
  });
  const LabelImage im = maskImage({-0.06, -0.06, -0.02}, {0.06, 0.06, 0.02}, 1e-3,
                                  [&](const Eigen::Vector3d& p) { return p.head<2>().norm() < R; });
  auto wall = std::make_shared<const ChestWallSurface>(im, std::set<std::uint16_t>{kWall});
  ElasticMaterial mat;
  mat.poisson_ratio = 0.45;
  DynamicsParams dp;
  dp.gravity_mps2 = {0, -9.81, 0};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, dp, std::make_unique<CholmodSolver>());
  SlidingSettings s = unlimited();
  s.static_friction = 0.1;
  s.kinetic_friction = 0.05;
  const std::vector<int>& inner = m.nodeSet("y_min");
  ChestWallSliding sliding(m, inner, wall, s, nullptr, TissueLabels{}, {}, Eigen::Vector3d(1, 1, 0));
  sliding.attach(sim);
  double worst_off = 0, worst_in = 0;
  for (int k = 0; k < 60; ++k) {
    sim.step();
    const SlidingStepStats st = sliding.update(sim);
    EXPECT_EQ(st.projection_failures, 0);
    const Points u = sim.displacement();
    for (int v : inner) {
      const double r = (m.nodes().row(v) + u.row(v)).head<2>().norm();
      worst_off = std::max(worst_off, std::abs(r - R));
      worst_in = std::max(worst_in, R - r);
    }
  }
  const Points d = sliding.slidingVectors();
  double mean = 0;
  for (int v : inner) mean += d.row(v).norm();
  mean /= inner.size();
  EXPECT_GT(mean, 1e-3);
  EXPECT_LT(worst_off, 1.5e-4);
  EXPECT_LT(worst_in, 1e-4);
  // Slides go clockwise (down the right side): the angle of every moved node decreased.
  for (int v : inner) {
    const Eigen::Vector3d X = m.nodes().row(v).transpose(), x = X + d.row(v).transpose();
    EXPECT_LT(std::atan2(x.y(), x.x()), std::atan2(X.y(), X.x()) + 1e-9);
  }
}

TEST(Sliding, SettingsAreValidatedWithTheirRange) {
  auto message = [](SlidingSettings s) {
    try {
      s.validate();
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("(no error)");
  };
  SlidingSettings s;
  EXPECT_EQ(message(s), "(no error)");
  s.kinetic_friction = 0.5;
  EXPECT_NE(message(s).find("kinetic_friction' = 0.5"), std::string::npos) << message(s);
  s = SlidingSettings{};
  s.mobility_m_per_pa_s = -1;
  EXPECT_NE(message(s).find("mobility_m_per_pa_s' = -1"), std::string::npos);
  s = SlidingSettings{};
  s.inertia = 1.0;
  EXPECT_NE(message(s).find("inertia' = 1"), std::string::npos);
  s = SlidingSettings{};
  s.max_wall_distance_m = 0.01;
  EXPECT_NE(message(s).find("max_wall_distance_m"), std::string::npos);
  s = SlidingSettings{};
  s.contact_gap_m = 0.6e-3;  // not below the tolerance (0.5 mm)
  EXPECT_NE(message(s).find("contact_tolerance_m"), std::string::npos) << message(s);
  s = SlidingSettings{};
  s.contact_release_pa = -1;
  EXPECT_NE(message(s).find("contact_release_pa' = -1"), std::string::npos) << message(s);
}

// The bimodal Gaussian in the chest-wall plane: 1 at the nipples' projections, the seed's formula
// elsewhere; plane axes u (nipple to nipple) and v = a × u.
TEST(Sliding, BimodalGaussianFollowsTheSeedFormulaInThePlaneFrame) {
  const LabelImage im = maskImage({-0.1, -0.01, -0.05}, {0.1, 0.03, 0.05}, 2e-3,
                                  [](const Eigen::Vector3d& p) { return p.y() > 0.0; });
  auto wall = std::make_shared<const ChestWallSurface>(im, std::set<std::uint16_t>{kWall});
  const TetMesh box = makeBoxMesh({10, 1, 5}, {0.16, 0.005, 0.08});
  const TetMesh m = transformed(box, [](const Eigen::Vector3d& p) {
    return Eigen::Vector3d(p.x() - 0.08, -p.y(), p.z() - 0.04);
  });
  SlidingSettings s;
  s.gaussian_sigma_m = 0.03;
  s.gaussian_amplitude = 0.8;
  const std::vector<Eigen::Vector3d> nipples = {{0.06, -0.05, 0.01}, {-0.06, -0.05, 0.01}};
  // y_min of the box maps to y = 0 (on the wall).
  ChestWallSliding sl(m, m.nodeSet("y_min"), wall, s, nullptr, TissueLabels{}, nipples, {0, -1, 0});
  EXPECT_LT((sl.planeU() - Eigen::Vector3d::UnitX()).norm(), 1e-12);
  EXPECT_LT((sl.planeV() - Eigen::Vector3d::UnitZ()).norm(), 1e-12);
  auto z = [&](double x, double zz) {
    auto g = [&](double x0) {
      return 0.8 * std::exp(-((x - x0) * (x - x0) + (zz - 0.01) * (zz - 0.01)) / (2 * 0.03 * 0.03));
    };
    return std::min(1.0, g(0.06) + g(-0.06));
  };
  for (const Eigen::Vector3d& p : {Eigen::Vector3d(0.06, 0, 0.01), Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(-0.02, 0.0, 0.03),
                                  Eigen::Vector3d(0.1, -0.02, -0.04)})
    EXPECT_NEAR(sl.gaussianWeight(p), z(p.x(), p.z()), 1e-12);
  EXPECT_THROW(ChestWallSliding(m, m.nodeSet("y_min"), wall, s, nullptr, TissueLabels{}, {}, {0, -1, 0}),
               std::invalid_argument);
}

// The explicit method's limiting factor on the two-breast phantom (curved wall, supine load
// g_supine − g_prone, 4k elements, 60 steps of update()): the bimodal Gaussian (σ a quarter of a
// breast) scales each wall node's permissible shift, so no node slides farther than w_i ·
// max_slide_m (plus the offset from its rest distance to its wall level, clamp(h, 0, ·)); with
// max_slide 5 mm the cap holds hundreds of nodes, the breasts slide laterally, and the medial
// (sternum-side) nodes, w ≈ 0.13, slide less than half as far as without the limit. The limit
// does not keep the medial edge still: with the default 30 mm their permissible shift is ~4 mm.
TEST(Sliding, TwoBreastPhantomGaussianLimitCapsEachWallNodeAtItsPermissibleShift) {
  const std::string yaml = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_two_breasts.yaml";
  ModelCase c = loadModelCase(yaml);
  c.meshing.target_elements = 4000;
  const SimulationModel model = buildSimulationModel(c);
  SimulationSettings ss = loadSimulationSettings(yaml);
  ss.solver.kind = SolverSettings::Kind::kCholmod;
  ss.dynamics.gravity_mps2 = c.phantom->gravity_supine_mps2 - c.phantom->gravity_prone_mps2;
  const double cap = 5e-3;
  struct Result {
    double lateral_mm = 0, medial_max_mm = 0, medial_weight = 0, worst_excess_mm = -1e9;
    int lateral_n = 0, medial_n = 0, at_cap = 0;
  };
  auto run = [&](bool gaussian) {
    SimulatorBuild b = buildSimulator(c, model, ss);
    SlidingSettings s;
    s.gaussian_limit = gaussian;
    s.gaussian_sigma_fraction = 0.25;
    s.max_slide_m = cap;
    ChestWallSliding sl = ChestWallSliding::fromCase(c, model.mesh, s);
    sl.attach(*b.simulator);
    for (int k = 0; k < 60; ++k) {
      b.simulator->step();
      sl.update(*b.simulator);
    }
    const Points d = sl.slidingVectors();
    Result r;
    for (size_t i = 0; i < sl.nodes().size(); ++i) {
      const int v = sl.nodes()[i];
      const Eigen::Vector3d X = model.mesh.nodes().row(v).transpose();
      const double h = sl.surface().signedDistance(X);
      const double level_offset = std::abs(std::clamp(h, 0.0, s.max_wall_distance_m) - h);
      const double w = sl.weights()[i], slide = d.row(v).norm(), limit = w * cap;
      r.worst_excess_mm = std::max(r.worst_excess_mm, 1e3 * (slide - limit - level_offset));
      if (w > 0 && slide >= 0.98 * limit) ++r.at_cap;
      const double x = X.x();
      if (std::abs(x) > 0.07 && std::abs(x) < 0.10) {
        r.lateral_mm += 1e3 * d(v, 0) * (x > 0 ? 1 : -1);  // lateral = away from the sternum
        ++r.lateral_n;
      }
      if (std::abs(x) < 0.04) {
        r.medial_max_mm = std::max(r.medial_max_mm, 1e3 * slide);
        r.medial_weight += w;
        ++r.medial_n;
      }
    }
    r.lateral_mm /= std::max(1, r.lateral_n);
    r.medial_weight /= std::max(1, r.medial_n);
    std::printf("[ measure  ] Gaussian %s: %zu wall nodes, %d at their permissible shift, worst slide beyond it %.4f mm; "
                "mean lateral slide %.2f mm (%d nodes), max medial slide %.2f mm (%d nodes, mean weight %.2f)\n",
                gaussian ? "on " : "off", sl.nodes().size(), r.at_cap, r.worst_excess_mm, r.lateral_mm, r.lateral_n,
                r.medial_max_mm, r.medial_n, r.medial_weight);
    return r;
  };
  const Result with = run(true), without = run(false);
  ASSERT_GT(with.lateral_n, 10);
  ASSERT_GT(with.medial_n, 10);
  EXPECT_LT(with.worst_excess_mm, 0.02);
  EXPECT_LT(without.worst_excess_mm, 0.02);
  EXPECT_GT(with.at_cap, 100);  // the cap binds: the bound above is not vacuous
  EXPECT_LT(with.medial_weight, 0.3);
  EXPECT_GT(with.lateral_mm, 0.5);
  EXPECT_LT(with.medial_max_mm, 0.5 * without.medial_max_mm);
}

namespace {

// A 20×20×10 mm block resting on the plane z = 0 (bottom nodes constrained by sliding), E0 2 kPa.
struct BlockOnPlane {
  TetMesh mesh = makeBoxMesh({4, 4, 2}, {0.02, 0.02, 0.01});
  LabelImage image = maskImage({-0.01, -0.01, -0.02}, {0.03, 0.03, 0.02}, 1e-3,
                               [](const Eigen::Vector3d& p) { return p.z() < 0; });
  std::shared_ptr<const ChestWallSurface> wall = std::make_shared<const ChestWallSurface>(image, std::set<std::uint16_t>{kWall});
  std::unique_ptr<DynamicSimulator> sim;
  BlockOnPlane(const Eigen::Vector3d& g, double dt) : sim(test_fixtures::blockSimulator(mesh, g, dt)) {}
};

}  // namespace

// The reaction of the constraint rows (DynamicSimulator::constraintForces(), which afterStep() reads)
// equals the quasi-static reaction −(f_el + m g) that update() recomputes, once the block is at rest
// (there the inertia and damping terms vanish), to 1e-6 of the largest nodal load.
TEST(Sliding, ConstraintRowReactionEqualsTheElasticReactionAtRest) {
  BlockOnPlane b(Eigen::Vector3d(2.0, 0.0, -9.81), 0.33);
  SlidingSettings s = unlimited();
  s.static_friction = 10.0;  // nothing slides: the block comes to rest on its constraints
  s.kinetic_friction = 10.0;
  ChestWallSliding sl(b.mesh, b.mesh.nodeSet("z_min"), b.wall, s, nullptr, TissueLabels{}, {}, Eigen::Vector3d::UnitZ());
  sl.attach(*b.sim);
  for (int k = 0; k < 80; ++k) b.sim->step();
  ASSERT_LT(b.sim->state().velocity_mps.cwiseAbs().maxCoeff(), 1e-9);
  const Eigen::VectorXd reaction = b.sim->constraintForces();
  const Eigen::VectorXd f_el = b.sim->elasticForces();
  double max_load = 0, max_diff = 0;
  for (int v : sl.nodes()) {
    const Eigen::Vector3d quasi = f_el.segment<3>(3 * v) + b.sim->lumpedMass()[v] * b.sim->params().gravity_mps2;
    const Eigen::Vector3d from_rows = -reaction.segment<3>(3 * v);
    max_load = std::max(max_load, quasi.norm());
    max_diff = std::max(max_diff, (quasi - from_rows).norm());
  }
  ASSERT_GT(max_load, 1e-5);
  EXPECT_LT(max_diff, 1e-6 * max_load) << "max load " << max_load << " N";
  // Free DOFs carry no reaction.
  for (int v = 0; v < b.mesh.numNodes(); ++v) {
    if (!b.sim->constrainedDofs()[3 * v]) {
      EXPECT_EQ(reaction.segment<3>(3 * v).norm(), 0.0);
    }
  }
}

// A forced move that inverts wall elements (one wall node pushed 8 mm across its neighbours, which
// no α saves) is taken back by afterStep(): halved while the stiffening call cannot advance, α's
// escalation undone, until a step advances with no inverted element; the next regular moves pass
// the volume guard, and the block then slides on without any call failing.
TEST(Sliding, AfterStepTakesBackAMoveThatInvertsWallElements) {
  BlockOnPlane b(Eigen::Vector3d(4.0, 0.0, -9.81), 0.033);
  ChestWallSliding sl(b.mesh, b.mesh.nodeSet("z_min"), b.wall, unlimited(), nullptr, TissueLabels{}, {},
                      Eigen::Vector3d::UnitZ());
  StiffeningParams sp;
  sp.max_reversals_per_step = 4;
  StiffeningSimulation stiff(*b.sim, b.mesh, sp);
  sl.attach(*b.sim);
  for (int k = 0; k < 5; ++k) sl.afterStep(stiff, stiff.step());
  const double alpha_before = stiff.controller().alpha();
  // Push the node nearest the middle of the bottom 8 mm along +x.
  int centre = 0;
  for (size_t i = 0; i < sl.nodes().size(); ++i)
    if ((b.mesh.nodes().row(sl.nodes()[i]) - Eigen::RowVector3d(0.01, 0.01, 0)).norm() <
        (b.mesh.nodes().row(sl.nodes()[centre]) - Eigen::RowVector3d(0.01, 0.01, 0)).norm())
      centre = static_cast<int>(i);
  Points bad = sl.targets();
  bad(centre, 0) += 0.008;
  sl.setTargets(*b.sim, bad);
  int take_backs = 0, calls = 0;
  bool advanced = false;
  while (!advanced && calls < 20) {
    const StiffeningStepResult r = stiff.step();
    ++calls;
    const SlidingStepStats st = sl.afterStep(stiff, r);
    if (!r.advanced) {
      EXPECT_TRUE(st.taken_back);
      ++take_backs;
      // α is back where the last accepted step left it, not escalated.
      EXPECT_LE(stiff.controller().alpha(), alpha_before * 1.0001);
    }
    advanced = r.advanced;
  }
  EXPECT_GE(take_backs, 1);
  ASSERT_TRUE(advanced);
  EXPECT_EQ(stiff.stats().inverted_elements, 0);
  // The pushed node ended at most half way (each take-back halves the pending move).
  const double pushed = b.sim->state().displacement_m[3 * sl.nodes()[centre]];
  EXPECT_LT(pushed, 0.5 * 0.008 + 2e-4);
  EXPECT_GT(pushed, 0.0);
  // Regular moves from here on never stall a call.
  int stalls = 0;
  for (int k = 0; k < 30; ++k) {
    const StiffeningStepResult r = stiff.step();
    stalls += r.advanced ? 0 : 1;
    sl.afterStep(stiff, r);
  }
  EXPECT_EQ(stalls, 0);
  EXPECT_EQ(stiff.stats().inverted_elements, 0);
}

namespace {

// A soft cantilever (40 × 10 × 10 mm, E0 2 kPa) held at its x_min end 4 mm above the wall z < 0
// (the end face is the sliding set, too far from the wall to slide: held), its other boundary nodes
// the "skin"; gravity pulls it down and sideways (+x) onto the wall.
struct Cantilever {
  TetMesh mesh;
  LabelImage image = maskImage({-0.01, -0.01, -0.02}, {0.06, 0.02, 0.02}, 1e-3,
                               [](const Eigen::Vector3d& p) { return p.z() < 0; });
  std::shared_ptr<const ChestWallSurface> wall = std::make_shared<const ChestWallSurface>(image, std::set<std::uint16_t>{kWall});
  std::unique_ptr<DynamicSimulator> sim;
  std::vector<int> skin;
  explicit Cantilever(const Eigen::Vector3d& g) {
    const TetMesh box = makeBoxMesh({8, 2, 2}, {0.04, 0.01, 0.01});
    mesh = transformed(box, [](const Eigen::Vector3d& p) { return Eigen::Vector3d(p + Eigen::Vector3d(0, 0, 0.004)); });
    std::vector<char> clamp(mesh.numNodes(), 0), boundary(mesh.numNodes(), 0);
    for (int v : mesh.nodeSet("x_min")) clamp[v] = 1;
    for (Eigen::Index f = 0; f < mesh.boundary().triangles.rows(); ++f)
      for (int c = 0; c < 3; ++c) boundary[mesh.boundary().triangles(f, c)] = 1;
    for (int v = 0; v < mesh.numNodes(); ++v)
      if (boundary[v] && !clamp[v]) skin.push_back(v);
    mesh.setNodeSet(node_sets::kSkin, skin);
    ElasticMaterial mat;
    mat.poisson_ratio = 0.45;
    DynamicsParams p;
    p.gravity_mps2 = g;
    sim = std::make_unique<DynamicSimulator>(mesh, std::make_unique<CorotatedTetFem>(mesh, mat), mat, p,
                                             std::make_unique<CholmodSolver>());
  }
  // Lowest wall distance of any node [m]: the wall's own signed distance h (the mask's surface lies
  // half a voxel below z = 0, at z = -0.5 mm).
  double minH() const {
    double h = 1e9;
    for (int v = 0; v < mesh.numNodes(); ++v)
      h = std::min(h, wall->signedDistance(mesh.nodes().row(v).transpose() + sim->state().displacement_m.segment<3>(3 * v)));
    return h;
  }
};

}  // namespace

// Skin–wall contact: the sagging cantilever's skin nodes that reach the wall become constraints, and
// no node ever enters the wall (wall distance h ≥ −0.1 mm after every call, contact nodes at
// least the gap minus the field's error); the touching nodes slide sideways with the load. Without
// contact the same run goes through the wall (the test can fail). When gravity turns upwards, the
// contacts are pulled off the wall and released (unilateral), and the beam lifts off.
TEST(Sliding, ContactCatchesSkinReachingTheWallAndNeverLetsItPenetrate) {
  const Eigen::Vector3d g_down(3.0, 0.0, -9.81);
  // Gravity ramps up over the first 30 calls (a soft beam would otherwise fall ~10 mm in its first
  // step, through the wall before any contact could see it coming).
  auto run = [](int calls, double* min_z, int* contacts, Cantilever& b, ChestWallSliding& sl,
                StiffeningSimulation& stiff, const Eigen::Vector3d& g) {
    for (int k = 0; k < calls; ++k) {
      stiff.setGravity(std::min(1.0, (k + 1) / 30.0) * g);
      const StiffeningStepResult r = stiff.step();
      const SlidingStepStats st = sl.afterStep(stiff, r);
      *min_z = std::min(*min_z, b.minH());
      *contacts = st.contacts;
      if (std::getenv("BREAST_SIM_TEST_VERBOSE")) {
        int lowest = 0;
        for (int v = 0; v < b.mesh.numNodes(); ++v)
          if (b.mesh.nodes()(v, 2) + b.sim->state().displacement_m[3 * v + 2] <
              b.mesh.nodes()(lowest, 2) + b.sim->state().displacement_m[3 * lowest + 2])
            lowest = v;
        const std::vector<int> cn = sl.contactNodes();
        std::printf("  call %d adv %d rev %d: contacts %d (+%d -%d) lowest node %d z %.3f mm constrained %d contact %d "
                    "vz %.3f m/s taken back %d move %.3f mm\n",
                    k, r.advanced, r.reversals, st.contacts, st.contacts_added, st.contacts_released, lowest,
                    1e3 * (b.mesh.nodes()(lowest, 2) + b.sim->state().displacement_m[3 * lowest + 2]),
                    static_cast<int>(b.sim->constrainedDofs()[3 * lowest]),
                    static_cast<int>(std::find(cn.begin(), cn.end(), lowest) != cn.end()),
                    b.sim->state().velocity_mps[3 * lowest + 2], st.taken_back, 1e3 * st.max_move_m);
      }
    }
  };
  SlidingSettings s = unlimited();
  {  // without contact: through the wall
    Cantilever b(g_down);
    SlidingSettings s0 = s;
    s0.contact = false;
    ChestWallSliding sl(b.mesh, b.mesh.nodeSet("x_min"), b.wall, s0, nullptr, TissueLabels{}, {}, Eigen::Vector3d::UnitZ());
    StiffeningSimulation stiff(*b.sim, b.mesh);
    sl.attach(*b.sim);
    ASSERT_EQ(sl.heldNodes(), static_cast<int>(sl.nodes().size()));  // the clamp is held
    double min_z = 1e9;
    int contacts = 0;
    run(45, &min_z, &contacts, b, sl, stiff, g_down);
    std::printf("without contact: lowest wall distance %.2f mm\n", 1e3 * min_z);
    EXPECT_LT(min_z, -1e-3);
    EXPECT_EQ(contacts, 0);
  }
  Cantilever b(g_down);
  ChestWallSliding sl(b.mesh, b.mesh.nodeSet("x_min"), b.wall, s, nullptr, TissueLabels{}, {}, Eigen::Vector3d::UnitZ());
  StiffeningSimulation stiff(*b.sim, b.mesh);
  sl.attach(*b.sim);
  double min_z = 1e9;
  int contacts = 0;
  run(45, &min_z, &contacts, b, sl, stiff, g_down);
  std::vector<int> cn = sl.contactNodes();
  double contact_min_z = 1e9, mean_dx = 0;
  const Points d = sl.slidingVectors();
  for (int v : cn) {
    contact_min_z = std::min(contact_min_z, b.wall->signedDistance(b.mesh.nodes().row(v).transpose() +
                                                                   b.sim->state().displacement_m.segment<3>(3 * v)));
    mean_dx += d(v, 0) / cn.size();
  }
  std::printf("with contact: %d contact nodes (%d made, %d released), lowest wall distance %.3f mm, of a contact node "
              "%.3f mm, mean slide of the contacts along +x %.2f mm, inverted %d\n",
              contacts, sl.contactsMade(), sl.contactsReleased(), 1e3 * min_z, 1e3 * contact_min_z, 1e3 * mean_dx,
              stiff.stats().inverted_elements);
  EXPECT_GE(contacts, 6);
  EXPECT_GT(min_z, -1e-4);
  EXPECT_GT(contact_min_z, s.contact_gap_m - 1e-4);
  EXPECT_EQ(stiff.stats().inverted_elements, 0);
  EXPECT_GT(mean_dx, 0.0);
  // Every contact node is a skin node and is constrained in the simulator.
  for (int v : cn) {
    EXPECT_TRUE(std::find(b.skin.begin(), b.skin.end(), v) != b.skin.end());
    EXPECT_TRUE(b.sim->constrainedDofs()[3 * v]);
  }
  // Gravity upwards: the contacts pull off the wall and are freed; the clamp stays constrained.
  run(50, &min_z, &contacts, b, sl, stiff, Eigen::Vector3d(-g_down));
  std::printf("gravity up: %d contact nodes left, %d released, lowest wall distance %.2f mm\n", contacts,
              sl.contactsReleased(), 1e3 * b.minH());
  EXPECT_GT(sl.contactsReleased(), 0);
  EXPECT_EQ(contacts, 0);
  EXPECT_GT(b.minH(), s.contact_tolerance_m);
  for (int v : b.mesh.nodeSet("x_min")) EXPECT_TRUE(b.sim->constrainedDofs()[3 * v]);
  for (int v : cn) EXPECT_FALSE(b.sim->constrainedDofs()[3 * v]);
}
