#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include <Eigen/Dense>

#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/mesh/box_mesh.h"

using namespace breast_sim::core;

namespace {
TetMesh cubeMesh(double h) {
  Points x(8, 3);
  for (int i = 0; i < 8; ++i) x.row(i) << h * (i & 1), h * ((i >> 1) & 1), h * ((i >> 2) & 1);
  Tets t(6, 4);
  t << 0, 1, 3, 7, 0, 1, 7, 5, 0, 5, 7, 4, 0, 3, 2, 7, 0, 2, 6, 7, 0, 6, 4, 7;
  return TetMesh(x, t);
}
}  // namespace

TEST(PointEmbedding, BarycentricWeightsReproduceThePoint) {
  const TetMesh m = cubeMesh(0.02);
  Points p(3, 3);
  p << 0.005, 0.012, 0.017, 0.019, 0.001, 0.002, 0.01, 0.01, 0.01;
  const PointEmbedding e(m, p, {"a", "b", "c"});
  for (int i = 0; i < 3; ++i) {
    SCOPED_TRACE("point " + std::to_string(i));
    EXPECT_GE(e.points()[i].weights.minCoeff(), -1e-10);
    EXPECT_NEAR(e.points()[i].weights.sum(), 1.0, 1e-12);
  }
  const Points back = e.positions(m.nodes());
  EXPECT_LT((back - p).cwiseAbs().maxCoeff(), 1e-15);
}

TEST(PointEmbedding, AffineDisplacementIsInterpolatedExactly) {
  const TetMesh m = cubeMesh(0.03);
  Eigen::Matrix3d A;
  A << 0.1, -0.2, 0.05, 0.3, 0.0, -0.1, 0.02, 0.04, -0.3;
  const Eigen::RowVector3d b(0.001, -0.002, 0.003);
  Points u(m.numNodes(), 3);
  for (int i = 0; i < m.numNodes(); ++i) u.row(i) = m.nodes().row(i) * A.transpose() + b;
  Points p(2, 3);
  p << 0.011, 0.022, 0.004, 0.029, 0.015, 0.027;
  const PointEmbedding e(m, p);
  const Points up = e.interpolate(u);
  for (int i = 0; i < 2; ++i) {
    const Eigen::RowVector3d expected = p.row(i) * A.transpose() + b;
    EXPECT_LT((up.row(i) - expected).norm(), 1e-15);
  }
}

TEST(PointEmbedding, PointOutsideTheMeshIsAClearError) {
  const TetMesh m = cubeMesh(0.02);
  Points p(1, 3);
  p << 0.025, 0.01, 0.01;  // 5 mm beyond the x = 20 mm face
  try {
    PointEmbedding e(m, p, {"lesion_1"});
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& ex) {
    const std::string what = ex.what();
    EXPECT_NE(what.find("lesion_1"), std::string::npos) << what;
    EXPECT_NE(what.find("5 mm outside"), std::string::npos) << what;
  }
}

TEST(PointEmbedding, PointJustOutsideIsSnappedWithinTolerance) {
  const TetMesh m = cubeMesh(0.02);
  Points p(1, 3);
  p << 0.0203, 0.01, 0.01;  // 0.3 mm outside
  const PointEmbedding e(m, p, {"near_skin"}, 1e-3);
  EXPECT_NEAR(e.points()[0].outside_distance_m, 3e-4, 1e-9);
  const Points q = e.positions(m.nodes());
  EXPECT_LT((q.row(0) - Eigen::RowVector3d(0.02, 0.01, 0.01)).norm(), 1e-12);  // the closest surface point
  // Off a corner: the closest point is the corner itself.
  Points corner(1, 3);
  corner << 0.0205, -0.0004, 0.0203;
  const PointEmbedding c(m, corner, {"corner"}, 1e-3);
  EXPECT_LT((c.positions(m.nodes()).row(0) - Eigen::RowVector3d(0.02, 0.0, 0.02)).norm(), 1e-12);
  EXPECT_NEAR(c.points()[0].outside_distance_m, std::sqrt(0.5e-3 * 0.5e-3 + 0.4e-3 * 0.4e-3 + 0.3e-3 * 0.3e-3), 1e-12);
}

TEST(PointEmbedding, GridSearchAgreesWithBruteForceOverAllElements) {
  // Slow reference: test every element for every point.
  const TetMesh m = makeBoxMesh({5, 4, 3}, {0.05, 0.04, 0.03});
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> ux(0.0, 0.05), uy(0.0, 0.04), uz(0.0, 0.03);
  Points p(200, 3);
  for (int i = 0; i < p.rows(); ++i) p.row(i) << ux(rng), uy(rng), uz(rng);
  const PointEmbedding e(m, p);
  for (int i = 0; i < p.rows(); ++i) {
    bool inside_found = false;
    for (int t = 0; t < m.numTets() && !inside_found; ++t) {
      const Eigen::Vector4d w = barycentricCoordinates(p.row(i).transpose(), m.nodes().row(m.tets()(t, 0)),
                                                       m.nodes().row(m.tets()(t, 1)), m.nodes().row(m.tets()(t, 2)),
                                                       m.nodes().row(m.tets()(t, 3)));
      inside_found = w.minCoeff() >= -1e-10;
    }
    ASSERT_TRUE(inside_found);
    EXPECT_GE(e.points()[i].weights.minCoeff(), -1e-10) << "point " << i;
    EXPECT_LT((e.positions(m.nodes()).row(i) - p.row(i)).norm(), 1e-15);
  }
  EXPECT_THROW(e.interpolate(Points::Zero(3, 3)), std::invalid_argument);
}

TEST(PointEmbedding, SnappedPointsMatchTheExactDistanceToTheBox) {
  // Reference for the face grid: the exact distance to the box, for points scattered around a box
  // mesh up to 6 mm outside it (tolerance 5 mm: the ones within are embedded in one call, each
  // farther one must be refused).
  const TetMesh m = makeBoxMesh({6, 5, 4}, {0.05, 0.04, 0.03});
  const Eigen::Vector3d lo(0, 0, 0), hi(0.05, 0.04, 0.03);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> ux(-0.006, 0.056), uy(-0.006, 0.046), uz(-0.006, 0.036);
  const double tolerance = 0.005;
  std::vector<Eigen::Vector3d> accepted;
  int refused = 0;
  for (int i = 0; i < 1000; ++i) {
    const Eigen::Vector3d q(ux(rng), uy(rng), uz(rng));
    if ((q.cwiseMax(lo).cwiseMin(hi) - q).norm() <= tolerance) {
      accepted.push_back(q);
      continue;
    }
    EXPECT_THROW(PointEmbedding(m, Points(q.transpose()), {"x"}, tolerance), std::invalid_argument) << "point " << i;
    ++refused;
  }
  Points p(static_cast<Eigen::Index>(accepted.size()), 3);
  for (size_t i = 0; i < accepted.size(); ++i) p.row(static_cast<Eigen::Index>(i)) = accepted[i].transpose();
  const PointEmbedding e(m, p, {}, tolerance);
  const Points at = e.positions(m.nodes());
  int snapped = 0;
  for (Eigen::Index i = 0; i < p.rows(); ++i) {
    const Eigen::Vector3d q = p.row(i).transpose(), closest = q.cwiseMax(lo).cwiseMin(hi);
    EXPECT_NEAR(e.points()[static_cast<size_t>(i)].outside_distance_m, (closest - q).norm(), 1e-12) << "point " << i;
    EXPECT_LT((at.row(i).transpose() - closest).norm(), 1e-12) << "point " << i;  // the box's closest point
    snapped += (closest - q).norm() > 0;
  }
  EXPECT_GT(snapped, 200);
  EXPECT_GT(refused, 20);
}

TEST(PointEmbedding, BarycentricCoordinatesMatchADenseSolve) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-0.01, 0.01);
  for (int k = 0; k < 100; ++k) {
    Eigen::Vector3d v[5];
    for (auto& x : v) x << u(rng), u(rng), u(rng);
    Eigen::Matrix3d m;
    m << v[1] - v[0], v[2] - v[0], v[3] - v[0];
    if (std::abs(m.determinant()) < 1e-9) continue;
    const Eigen::Vector3d l = m.fullPivLu().solve(v[4] - v[0]);
    const Eigen::Vector4d w = barycentricCoordinates(v[4], v[0], v[1], v[2], v[3]);
    EXPECT_LT((w - Eigen::Vector4d(1 - l.sum(), l.x(), l.y(), l.z())).cwiseAbs().maxCoeff(), 1e-8) << k;
  }
}
