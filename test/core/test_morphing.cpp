// Surface morphing: closest points, the target vector field against exact distances, the force
// generator, and the phantom pulled onto its supine target.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "../../src/core/util/closest_point.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/morphing/surface_field.h"
#include "breast_sim/core/morphing/surface_morphing.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "sliding_block.h"

using namespace breast_sim::core;

namespace {

// A UV sphere of radius r about c [m].
TargetSurface sphere(const Eigen::Vector3d& c, double r, int n_lat = 40, int n_lon = 80) {
  TargetSurface s;
  std::vector<Eigen::Vector3d> v;
  v.push_back(c + Eigen::Vector3d(0, 0, r));
  for (int i = 1; i < n_lat; ++i)
    for (int j = 0; j < n_lon; ++j) {
      const double th = M_PI * i / n_lat, ph = 2 * M_PI * j / n_lon;
      v.push_back(c + r * Eigen::Vector3d(std::sin(th) * std::cos(ph), std::sin(th) * std::sin(ph), std::cos(th)));
    }
  v.push_back(c - Eigen::Vector3d(0, 0, r));
  s.vertices_m.resize(static_cast<Eigen::Index>(v.size()), 3);
  for (size_t i = 0; i < v.size(); ++i) s.vertices_m.row(static_cast<Eigen::Index>(i)) = v[i].transpose();
  std::vector<Eigen::Vector3i> f;
  auto ring = [&](int i, int j) { return 1 + (i - 1) * n_lon + (j % n_lon); };
  for (int j = 0; j < n_lon; ++j) f.emplace_back(0, ring(1, j), ring(1, j + 1));
  for (int i = 1; i < n_lat - 1; ++i)
    for (int j = 0; j < n_lon; ++j) {
      f.emplace_back(ring(i, j), ring(i + 1, j), ring(i + 1, j + 1));
      f.emplace_back(ring(i, j), ring(i + 1, j + 1), ring(i, j + 1));
    }
  const int south = static_cast<int>(v.size()) - 1;
  for (int j = 0; j < n_lon; ++j) f.emplace_back(south, ring(n_lat - 1, j + 1), ring(n_lat - 1, j));
  s.triangles.resize(static_cast<Eigen::Index>(f.size()), 3);
  for (size_t i = 0; i < f.size(); ++i) s.triangles.row(static_cast<Eigen::Index>(i)) = f[i].transpose();
  return s;
}

double bruteForceDistance(const TargetSurface& s, const Eigen::Vector3d& p) {
  double best = 1e300;
  for (Eigen::Index f = 0; f < s.triangles.rows(); ++f)
    best = std::min(best, (p - closestPointOnTriangle(p, s.vertices_m.row(s.triangles(f, 0)), s.vertices_m.row(s.triangles(f, 1)),
                                                      s.vertices_m.row(s.triangles(f, 2))))
                              .norm());
  return best;
}

const std::string kPhantomCase = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml";

}  // namespace

TEST(ClosestPoint, OnATriangleIsNoFartherThanAnySampledPointOfIt) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1), w(0, 1);
  for (int t = 0; t < 200; ++t) {
    const Eigen::Vector3d a(u(rng), u(rng), u(rng)), b(u(rng), u(rng), u(rng)), c(u(rng), u(rng), u(rng));
    const Eigen::Vector3d p = 2 * Eigen::Vector3d(u(rng), u(rng), u(rng));
    const Eigen::Vector3d q = closestPointOnTriangle(p, a, b, c);
    // q lies in the triangle: barycentric coordinates in [0, 1].
    Eigen::Matrix<double, 3, 2> E;
    E << b - a, c - a;
    const Eigen::Vector2d st = E.colPivHouseholderQr().solve(q - a);
    EXPECT_GE(st.minCoeff(), -1e-9);
    EXPECT_LE(st.sum(), 1 + 1e-9);
    for (int k = 0; k < 300; ++k) {
      double s = w(rng), r = w(rng);
      if (s + r > 1) s = 1 - s, r = 1 - r;
      EXPECT_LE((p - q).norm(), (p - (a + s * (b - a) + r * (c - a))).norm() + 1e-12);
    }
  }
}

TEST(SurfaceDistance, MatchesBruteForceOverAllTriangles) {
  const TargetSurface s = sphere(Eigen::Vector3d(0.01, -0.02, 0.03), 0.05, 12, 24);
  const SurfaceDistance d(s);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-0.1, 0.1);
  for (int i = 0; i < 300; ++i) {
    const Eigen::Vector3d p(u(rng), u(rng), u(rng));
    EXPECT_NEAR(d.distance(p), bruteForceDistance(s, p), 1e-12);
  }
}

// The batch query, on all threads, gives each point's single query to the bit, for triangles and
// for a point cloud.
TEST(SurfaceDistance, BatchQueryGivesTheSingleQueriesBits) {
  const TargetSurface s = sphere(Eigen::Vector3d(0.01, -0.02, 0.03), 0.05, 12, 24);
  TargetSurface cloud;
  cloud.vertices_m = s.vertices_m;
  std::mt19937 rng(6);
  std::uniform_real_distribution<double> u(-0.1, 0.1);
  Points p(501, 3);
  for (Eigen::Index i = 0; i < p.rows(); ++i) p.row(i) << u(rng), u(rng), u(rng);
  for (const TargetSurface& t : {s, cloud}) {
    const SurfaceDistance d(t);
    const Eigen::VectorXd batch = d.distances(p);
    ASSERT_EQ(batch.size(), p.rows());
    for (Eigen::Index i = 0; i < p.rows(); ++i) EXPECT_EQ(batch[i], d.distance(p.row(i).transpose())) << "point " << i;
  }
}

// The field's vector is the exact vector to the nearest surface point within 10 mm of the surface
// (where morphing works), and close to it farther out, away from the sphere's centre (the medial
// axis, where the nearest point jumps).
TEST(SurfaceVectorField, PointsToTheNearestTargetPointWithinAFractionOfAVoxel) {
  const Eigen::Vector3d c(0.01, -0.02, 0.03);
  const double r = 0.05;
  const TargetSurface s = sphere(c, r);
  SurfaceFieldOptions o;
  o.voxel_size_m = 1e-3;
  const SurfaceVectorField field(s, Eigen::AlignedBox3d(c.array() - 0.07, c.array() + 0.07), o);
  const SurfaceDistance exact(s);
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-0.08, 0.08);
  double worst_near = 0, worst_far = 0, worst_distance = 0;
  int tested = 0;
  for (int i = 0; i < 2000; ++i) {
    const Eigen::Vector3d p = c + Eigen::Vector3d(u(rng), u(rng), u(rng));
    if ((p - c).norm() < 0.02) continue;
    Eigen::Vector3d q;
    const double d = exact.distance(p, &q);
    const Eigen::Vector3d v = field.vectorToSurface(p);
    (d < 0.01 ? worst_near : worst_far) = std::max(d < 0.01 ? worst_near : worst_far, (v - (q - p)).norm());
    worst_distance = std::max(worst_distance, std::abs(v.norm() - d));
    ++tested;
  }
  EXPECT_GT(tested, 1500);
  // Near the surface the candidates hold the nearest triangle or a neighbour of it: the vector's
  // tangential error stays below a quarter voxel, its length error far below.
  EXPECT_LT(worst_near, 0.25e-3) << "worst error near the surface " << worst_near * 1e3 << " mm";
  EXPECT_LT(worst_far, 3e-3) << "worst direction error far out " << worst_far * 1e3 << " mm";
  EXPECT_LT(worst_distance, 0.05e-3) << "worst distance error " << worst_distance * 1e3 << " mm";
  // Outside the grid the vector still points back to the surface.
  const Eigen::Vector3d far = c + Eigen::Vector3d(0.5, 0, 0);
  EXPECT_NEAR(field.vectorToSurface(far).x(), -(0.5 - r), 2e-3);
}

TEST(SurfaceVectorField, PointCloudTargetsPointToTheirNearestPoint) {
  TargetSurface cloud;
  cloud.vertices_m = sphere(Eigen::Vector3d::Zero(), 0.04, 80, 160).vertices_m;  // ~1.6 mm apart, as a scanner
  const SurfaceVectorField field(cloud, Eigen::AlignedBox3d(Eigen::Vector3d::Constant(-0.05), Eigen::Vector3d::Constant(0.05)));
  const SurfaceDistance exact(cloud);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-0.05, 0.05);
  double worst = 0;
  for (int i = 0; i < 500; ++i) {
    const Eigen::Vector3d p(u(rng), u(rng), u(rng));
    if (p.norm() < 0.015) continue;
    worst = std::max(worst, field.vectorToSurface(p).norm() - exact.distance(p));
    EXPECT_GE(field.vectorToSurface(p).norm(), exact.distance(p) - 1e-12);  // never nearer than the nearest
  }
  // One point kept per voxel: a near-nearest point, at most a little farther.
  EXPECT_LT(worst, 0.5e-3) << worst * 1e3 << " mm";  // measured 0.32 mm, at points up to 4 cm out
}

TEST(SurfaceVectorField, BadInputIsNamed) {
  TargetSurface empty;
  EXPECT_THROW(SurfaceVectorField(empty, Eigen::AlignedBox3d(Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones())),
               std::invalid_argument);
  TargetSurface bad = sphere(Eigen::Vector3d::Zero(), 0.01, 4, 8);
  bad.triangles(0, 1) = 100000;
  try {
    bad.validate();
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("triangle 0 uses vertex 100000"), std::string::npos) << e.what();
  }
  SurfaceFieldOptions o;
  o.voxel_size_m = 0;
  EXPECT_THROW(o.validate(), std::invalid_argument);
}

// Against brute-force closest points over every triangle / every cloud point, on a small grid of
// 2 mm voxels: the vector always ends on the target and is never shorter than the true distance;
// within 1.5 voxels of the surface it is (nearly always) the exact closest-point vector.
TEST(SurfaceVectorField, MatchesBruteForceClosestPointsOnASmallGrid) {
  const Eigen::Vector3d c(0.004, -0.003, 0.002);
  const TargetSurface tri = sphere(c, 0.02, 10, 20);  // ~6 mm triangles
  TargetSurface cloud;
  cloud.vertices_m = sphere(c, 0.02, 8, 16).vertices_m;  // ~8 mm apart: one point per voxel
  SurfaceFieldOptions o;
  o.voxel_size_m = 2e-3;
  o.margin_m = 0.004;
  const Eigen::AlignedBox3d region(c.array() - 0.03, c.array() + 0.03);
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> u(-0.035, 0.035);
  for (const TargetSurface* target : std::vector<const TargetSurface*>{&tri, &cloud}) {
    const bool is_cloud = target->isPointCloud();
    SCOPED_TRACE(is_cloud ? "point cloud" : "triangles");
    const SurfaceVectorField field(*target, region, o);
    ASSERT_LE(field.size().maxCoeff(), 40);
    auto nearest = [&](const Eigen::Vector3d& p) {  // brute force over all elements
      Eigen::Vector3d best = target->vertices_m.row(0).transpose();
      if (is_cloud) {
        for (Eigen::Index v = 0; v < target->vertices_m.rows(); ++v)
          if ((target->vertices_m.row(v).transpose() - p).norm() < (best - p).norm()) best = target->vertices_m.row(v).transpose();
      } else {
        for (Eigen::Index f = 0; f < target->triangles.rows(); ++f) {
          const Eigen::Vector3d q = closestPointOnTriangle(p, target->vertices_m.row(target->triangles(f, 0)),
                                                           target->vertices_m.row(target->triangles(f, 1)),
                                                           target->vertices_m.row(target->triangles(f, 2)));
          if ((q - p).norm() < (best - p).norm()) best = q;
        }
      }
      return best;
    };
    int near_tested = 0, exact_near = 0;
    double worst_near = 0, worst_excess = 0, worst_near_excess = 0;
    for (int s = 0; s < 3000; ++s) {
      const Eigen::Vector3d p = c + Eigen::Vector3d(u(rng), u(rng), u(rng));
      const Eigen::Vector3d v = field.vectorToSurface(p);
      const Eigen::Vector3d q = nearest(p);
      const double d = (q - p).norm();
      ASSERT_GE(v.norm(), d - 1e-12) << "nearer than the nearest point at sample " << s;
      ASSERT_LT((nearest(p + v) - (p + v)).norm(), 1e-12) << "the vector does not end on the target at sample " << s;
      worst_excess = std::max(worst_excess, v.norm() - d);
      if (d < 3e-3) {  // within 1.5 voxels
        ++near_tested;
        worst_near = std::max(worst_near, (v - (q - p)).norm());
        worst_near_excess = std::max(worst_near_excess, v.norm() - d);
        exact_near += (v - (q - p)).norm() < 1e-12;
      }
    }
    EXPECT_GT(near_tested, 100);
    if (is_cloud) {
      // One point per voxel: the nearest point is always a candidate near the cloud (measured: 113
      // of 113 exact; up to 1.3 mm farther than the nearest point far out).
      EXPECT_EQ(exact_near, near_tested);
    } else {
      // A triangle nobody's nearest can be missed where a neighbour is almost as near (measured:
      // 276 of 280 exact, worst vector error 0.30 mm = 0.15 voxel, length error 0.026 mm).
      EXPECT_GE(exact_near, 0.95 * near_tested);
      EXPECT_LT(worst_near, 0.5e-3) << "worst vector error near the surface " << worst_near * 1e3 << " mm";
      EXPECT_LT(worst_near_excess, 0.1e-3) << "worst distance excess near the surface " << worst_near_excess * 1e3 << " mm";
    }
    EXPECT_LT(worst_excess, 2e-3) << "worst excess distance " << worst_excess * 1e3 << " mm";
  }
}

// rebuild() into storage of a larger or a smaller earlier grid gives exactly a fresh field, and so
// does a copy; a rebuild refused for bad input leaves the field as it was.
TEST(SurfaceVectorField, RebuildAndCopiesEqualAFreshBuild) {
  const TargetSurface big = sphere(Eigen::Vector3d(0.0, 0.0, 0.0), 0.04, 16, 32);
  const TargetSurface small = sphere(Eigen::Vector3d(0.01, 0.0, -0.005), 0.015, 10, 20);
  TargetSurface cloud;
  cloud.vertices_m = sphere(Eigen::Vector3d(0.0, 0.01, 0.0), 0.03, 20, 40).vertices_m;
  SurfaceFieldOptions o;
  o.voxel_size_m = 1.5e-3;
  const Eigen::AlignedBox3d region(Eigen::Vector3d::Constant(-0.01), Eigen::Vector3d::Constant(0.01));
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-0.07, 0.07);
  std::vector<Eigen::Vector3d> pts;
  for (int s = 0; s < 500; ++s) pts.emplace_back(u(rng), u(rng), u(rng));
  auto same = [&](const SurfaceVectorField& a, const SurfaceVectorField& b) {
    ASSERT_EQ(a.size(), b.size());
    ASSERT_EQ(a.numSurfaceVoxels(), b.numSurfaceVoxels());
    for (const auto& p : pts) ASSERT_EQ(a.vectorToSurface(p), b.vectorToSurface(p)) << p.transpose();
  };
  SurfaceVectorField field(big, region, o);
  for (const TargetSurface* t : std::vector<const TargetSurface*>{&small, &cloud, &big, &small}) {
    field.rebuild(*t, region, o);
    same(field, SurfaceVectorField(*t, region, o));
  }
  const SurfaceVectorField copy = field;
  same(copy, SurfaceVectorField(small, region, o));
  SurfaceVectorField assigned(big, region, o);
  assigned = field;  // into larger storage
  same(assigned, copy);
  assigned.rebuild(big, region, o);
  same(assigned, SurfaceVectorField(big, region, o));

  TargetSurface outside;  // a cloud point far outside the grid is clamped onto it: still one voxel
  outside.vertices_m = Eigen::RowVector3d(5.0, 0.0, 0.0);
  EXPECT_NO_THROW(field.rebuild(outside, region, o));
  field.rebuild(cloud, region, o);
  TargetSurface empty;  // invalid input leaves the field as it was
  EXPECT_THROW(field.rebuild(empty, region, o), std::invalid_argument);
  same(field, SurfaceVectorField(cloud, region, o));
}

// max_voxels_per_axis caps the longest axis; below the cap voxel_size_m is used as given.
TEST(SurfaceVectorField, MaxVoxelsPerAxisCapsTheLongestAxis) {
  const TargetSurface s = sphere(Eigen::Vector3d::Zero(), 0.03, 8, 16);
  const Eigen::AlignedBox3d region(Eigen::Vector3d(-0.05, -0.02, -0.03), Eigen::Vector3d(0.05, 0.02, 0.03));
  SurfaceFieldOptions o;
  o.margin_m = 0.0;
  o.voxel_size_m = 1e-9;
  for (int cap : {4, 17, 64}) {
    o.max_voxels_per_axis = cap;
    const SurfaceVectorField f(s, region, o);
    EXPECT_EQ(f.size().x(), cap);  // the longest axis (0.1 m)
    EXPECT_LT(f.size().y(), cap);
    EXPECT_NEAR(f.voxelSize(), 0.1 / (cap - 1), 1e-12);
  }
  o.voxel_size_m = 5e-3;
  o.max_voxels_per_axis = 256;
  const SurfaceVectorField f(s, region, o);
  EXPECT_EQ(f.voxelSize(), 5e-3);
  EXPECT_EQ(f.size(), Eigen::Vector3i(21, 13, 13));
}

TEST(SurfaceMorphing, AlongTheNormalEachStepsForceIsTheNormalComponentOfTheVectorToTheTarget) {
  // A 40 × 40 × 20 mm block, its top face (z = 20 mm, the only skin) pulled towards a 1 mm lattice of
  // points 2 mm above it and offset 0.4 mm in x and y: each top vertex's nearest target point lies
  // (0.4, 0.4, 2) mm away. To the nearest point the force is gain × area × that vector; along the
  // normal (+z, the top face's outward normal) only its 2 mm part.
  const TetMesh mesh = makeBoxMesh(Eigen::Vector3i(4, 4, 2), Eigen::Vector3d(0.04, 0.04, 0.02));
  TargetSurface target;
  target.vertices_m.resize(61 * 61, 3);
  for (int i = 0; i < 61; ++i)
    for (int j = 0; j < 61; ++j) target.vertices_m.row(61 * i + j) << -0.0096 + 0.001 * i, -0.0096 + 0.001 * j, 0.022;
  auto field = std::make_shared<SurfaceVectorField>(
      target, Eigen::AlignedBox3d(Eigen::Vector3d::Zero(), Eigen::Vector3d(0.04, 0.04, 0.025)), SurfaceFieldOptions{0.5e-3, 0.01, 256});
  MorphingOptions o;
  o.max_traction_pa = 0;
  for (const bool along : {false, true}) {
    SCOPED_TRACE(along ? "along the normal" : "to the nearest point");
    auto sim = test_fixtures::blockSimulator(mesh, Eigen::Vector3d::Zero(), 0.033);
    SurfaceMorphing m(mesh, field, mesh.nodeSet("z_max"), {}, o);
    m.setAlongNormal(along);
    m.addForces(*sim);
    const Eigen::VectorXd& f = sim->externalForces();
    ASSERT_EQ(m.vertices().size(), 25u);
    for (size_t k = 0; k < m.vertices().size(); ++k) {
      const int v = m.vertices()[k];
      const Eigen::Vector3d to = field->vectorToSurface(mesh.nodes().row(v).transpose());
      ASSERT_NEAR(to.x(), 0.4e-3, 1e-6);
      ASSERT_NEAR(to.z(), 2e-3, 1e-6);
      const Eigen::Vector3d pull = along ? Eigen::Vector3d(0, 0, to.z()) : to;
      const Eigen::Vector3d expected = o.gain_pa_per_m * m.vertexAreas()[static_cast<Eigen::Index>(k)] * pull;
      EXPECT_LT((f.segment<3>(3 * v) - expected).norm(), 1e-9 * expected.norm()) << "vertex " << v;
      EXPECT_NEAR(m.lastDistances()[static_cast<Eigen::Index>(k)], pull.norm(), 1e-12);
    }
  }
}
