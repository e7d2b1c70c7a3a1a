// The simulated supine MRI (mri/supine_resampling.h): the fast rasterisation against its slow
// reference, a known affine displacement warping a linear image exactly, the identity, the chest wall
// and air outside, the supine grid, and the written geometry.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <gtest/gtest.h>
#include <omp.h>

#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/supine_resampling.h"
#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::TempDir;

namespace {

// A 40 x 30 x 24 mm box of tetrahedra placed at `corner` [m].
TetMesh boxAt(const Eigen::Vector3i& cells, const Eigen::Vector3d& corner) {
  const TetMesh box = makeBoxMesh(cells, Eigen::Vector3d(40e-3, 30e-3, 24e-3));
  Points nodes = box.nodes();
  nodes.rowwise() += corner.transpose();
  return TetMesh(nodes, box.tets(), box.regionLabels());
}

// A prone image on an oblique grid around the box: values random (seeded), labels in stripes, the
// voxels behind y = 20 mm chest wall (label 40).
struct Prone {
  ScalarImage image;
  LabelImage labels;
};
Prone proneImage(double spacing_m) {
  Prone p;
  ImageGeometry& g = p.image.geometry;
  g.spacing_m = Eigen::Vector3d(spacing_m, 1.25 * spacing_m, spacing_m);
  const double a = 0.2;
  g.direction << std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1;
  g.origin_m = Eigen::Vector3d(-20e-3, -25e-3, -15e-3);
  g.size = Eigen::Vector3i(static_cast<int>(80e-3 / g.spacing_m.x()), static_cast<int>(70e-3 / g.spacing_m.y()),
                           static_cast<int>(55e-3 / g.spacing_m.z()));
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(0.0f, 1000.0f);
  p.image.values.resize(static_cast<std::size_t>(g.numVoxels()));
  for (float& v : p.image.values) v = u(rng);
  p.labels.size = g.size;
  p.labels.spacing_m = g.spacing_m;
  p.labels.origin_m = g.origin_m;
  p.labels.direction = g.direction;
  p.labels.labels.resize(p.image.values.size());
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) {
        const Eigen::Vector3d x = g.indexToPhysical(Eigen::Vector3d(i, j, k));
        p.labels.at(i, j, k) = x.y() > 20e-3 ? 40 : static_cast<std::uint16_t>(1 + (i + 2 * j + 3 * k) % 3);
      }
  return p;
}

// A smooth non-affine displacement (a sag and a twist) [m].
Points smoothDisplacement(const TetMesh& mesh) {
  Points u(mesh.numNodes(), 3);
  for (int n = 0; n < mesh.numNodes(); ++n) {
    const Eigen::Vector3d x = mesh.nodes().row(n).transpose();
    u.row(n) << 3e-3 * std::sin(60 * x.y()) + 0.1 * x.z(), -6e-3 * std::cos(40 * x.x()), 2e-3 * std::sin(50 * x.x() + 30 * x.y());
  }
  return u;
}

}  // namespace

TEST(SupineResampling, TheFastPathMatchesTheSlowReferenceBitForBit) {
  const Prone prone = proneImage(1.5e-3);
  const TetMesh mesh = boxAt(Eigen::Vector3i(6, 5, 4), Eigen::Vector3d(-10e-3, -15e-3, -5e-3));
  const Points u = smoothDisplacement(mesh);
  Points deformed = mesh.nodes() + u;
  const ImageGeometry grid = supineGrid(prone.image.geometry, deformed);
  const SupineImages fast = resampleToSupine(mesh, u, &prone.image, &prone.labels, grid);
  const SupineImages slow = resampleToSupineReference(mesh, u, &prone.image, &prone.labels, grid);
  ASSERT_GT(fast.body_voxels, 1000);
  EXPECT_EQ(fast.body_voxels, slow.body_voxels);
  EXPECT_EQ(fast.image.values, slow.image.values);
  EXPECT_EQ(fast.labels.labels, slow.labels.labels);
  // The same with 1 thread and with 2.
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  const SupineImages one = resampleToSupine(mesh, u, &prone.image, &prone.labels, grid);
  omp_set_num_threads(std::max(2, threads));
  const SupineImages two = resampleToSupine(mesh, u, &prone.image, &prone.labels, grid);
  omp_set_num_threads(threads);
  EXPECT_EQ(one.image.values, two.image.values);
  EXPECT_EQ(one.labels.labels, fast.labels.labels);
}

TEST(SupineResampling, AnAffineDisplacementWarpsALinearImageExactly) {
  // f(X) = c·X + d on the prone grid: trilinear interpolation reproduces it, so the supine image at y
  // must be f(A⁻¹ (y − b)) for the displacement u(X) = (A − I) X + b.
  Prone prone = proneImage(1.0e-3);
  const Eigen::Vector3d c(2e4, -1e4, 3e4);
  const double d = 500.0;
  const ImageGeometry& pg = prone.image.geometry;
  for (int k = 0; k < pg.size.z(); ++k)
    for (int j = 0; j < pg.size.y(); ++j)
      for (int i = 0; i < pg.size.x(); ++i)
        prone.image.values[pg.index(i, j, k)] = static_cast<float>(c.dot(pg.indexToPhysical(Eigen::Vector3d(i, j, k))) + d);
  const TetMesh mesh = boxAt(Eigen::Vector3i(4, 3, 3), Eigen::Vector3d(-5e-3, -10e-3, 0));
  Eigen::Matrix3d A;
  A << 1.1, 0.15, 0.0, -0.05, 0.8, 0.1, 0.02, 0.0, 1.25;
  const Eigen::Vector3d b(3e-3, -4e-3, 1.5e-3);
  Points u(mesh.numNodes(), 3);
  for (int n = 0; n < mesh.numNodes(); ++n) {
    const Eigen::Vector3d x = mesh.nodes().row(n).transpose();
    u.row(n) = (A * x + b - x).transpose();
  }
  const Points deformed = mesh.nodes() + u;
  const ImageGeometry grid = supineGrid(pg, deformed);
  const SupineImages s = resampleToSupine(mesh, u, &prone.image, nullptr, grid);
  const Eigen::Matrix3d A_inv = A.inverse();
  const Eigen::Vector3d lo = mesh.nodes().colwise().minCoeff().transpose(), hi = mesh.nodes().colwise().maxCoeff().transpose();
  long checked = 0, inside = 0;
  for (int k = 0; k < grid.size.z(); ++k)
    for (int j = 0; j < grid.size.y(); ++j)
      for (int i = 0; i < grid.size.x(); ++i) {
        const Eigen::Vector3d y = grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        const Eigen::Vector3d x = A_inv * (y - b);
        const double margin = ((x - lo).cwiseMin(hi - x)).minCoeff();
        const float value = s.image.values[grid.index(i, j, k)];
        if (margin > 1e-9) {
          ++inside;
          ASSERT_NEAR(value, c.dot(x) + d, 1e-3) << "voxel " << i << " " << j << " " << k;
        } else if (margin < -1e-9) {
          ASSERT_EQ(value, 0.0f) << "voxel " << i << " " << j << " " << k << " lies outside the deformed box";
        }
        ++checked;
      }
  EXPECT_GT(inside, 10000);
  EXPECT_NEAR(static_cast<double>(s.body_voxels), static_cast<double>(inside), 0.02 * inside);
}

TEST(SupineResampling, ZeroDisplacementGivesTheProneVoxels) {
  const Prone prone = proneImage(1.0e-3);
  const TetMesh mesh = boxAt(Eigen::Vector3i(5, 4, 3), Eigen::Vector3d(-8e-3, -12e-3, -2e-3));
  const Points zero = Points::Zero(mesh.numNodes(), 3);
  const ImageGeometry grid = supineGrid(prone.image.geometry, mesh.nodes());
  // The supine grid lies on the prone grid's lattice.
  const Eigen::Vector3d offset = prone.image.geometry.physicalToIndex(grid.origin_m);
  EXPECT_LT((offset - offset.array().round().matrix()).cwiseAbs().maxCoeff(), 1e-9);
  const SupineImages s = resampleToSupine(mesh, zero, &prone.image, &prone.labels, grid);
  long inside = 0;
  for (int k = 0; k < grid.size.z(); ++k)
    for (int j = 0; j < grid.size.y(); ++j)
      for (int i = 0; i < grid.size.x(); ++i) {
        const Eigen::Vector3d y = grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        const Eigen::Vector3i q = prone.image.geometry.physicalToIndex(y).array().round().cast<int>();
        const long v = grid.index(i, j, k), w = prone.image.geometry.index(q.x(), q.y(), q.z());
        if (s.labels.labels[v] == 0) continue;
        ++inside;
        EXPECT_NEAR(s.image.values[v], prone.image.values[w], 2e-3);
        EXPECT_EQ(s.labels.labels[v], prone.labels.labels[w]);
      }
  EXPECT_GT(inside, 20000);
}

TEST(SupineResampling, OutsideTheBodyTheChestWallStaysAndTheRestIsAir) {
  const Prone prone = proneImage(1.5e-3);
  const TetMesh mesh = boxAt(Eigen::Vector3i(4, 3, 3), Eigen::Vector3d(-10e-3, -15e-3, -5e-3));
  Points u = Points::Zero(mesh.numNodes(), 3);
  u.col(1).setConstant(-8e-3);  // the box moves 8 mm anterior
  SupineResampleOptions o;
  o.margin_m = 25e-3;
  o.air_value = -1.0f;
  const ImageGeometry grid = supineGrid(prone.image.geometry, mesh.nodes() + u, o);
  const SupineImages s = resampleToSupine(mesh, u, &prone.image, &prone.labels, grid, o);
  long wall = 0, air = 0;
  for (int k = 0; k < grid.size.z(); ++k)
    for (int j = 0; j < grid.size.y(); ++j)
      for (int i = 0; i < grid.size.x(); ++i) {
        const long v = grid.index(i, j, k);
        const Eigen::Vector3d y = grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        const bool in_box = (y - mesh.nodes().colwise().minCoeff().transpose() - Eigen::Vector3d(0, -8e-3, 0)).minCoeff() > 1e-6 &&
                            (mesh.nodes().colwise().maxCoeff().transpose() + Eigen::Vector3d(0, -8e-3, 0) - y).minCoeff() > 1e-6;
        if (in_box) continue;
        if (y.y() > 20.5e-3 && insideGrid(prone.image.geometry, y)) {
          ++wall;
          EXPECT_EQ(s.labels.labels[v], 40);
          EXPECT_NEAR(s.image.values[v], sampleTrilinear(prone.image, y), 1e-3);
        } else if (y.y() < 19.5e-3) {
          ++air;
          EXPECT_EQ(s.labels.labels[v], 0);
          EXPECT_EQ(s.image.values[v], -1.0f);
        }
      }
  EXPECT_GT(wall, 1000);
  EXPECT_GT(air, 1000);
}

TEST(SupineResampling, TheSupineGridHoldsTheModelAndIsWrittenWithItsGeometry) {
  const Prone prone = proneImage(1.5e-3);
  const TetMesh mesh = boxAt(Eigen::Vector3i(3, 3, 3), Eigen::Vector3d(-10e-3, -15e-3, -5e-3));
  const Points u = smoothDisplacement(mesh);
  const Points deformed = mesh.nodes() + u;
  SupineResampleOptions o;
  o.margin_m = 5e-3;
  o.spacing_m = Eigen::Vector3d(1e-3, 0, 2e-3);
  const ImageGeometry grid = supineGrid(prone.image.geometry, deformed, o);
  EXPECT_EQ(grid.direction, prone.image.geometry.direction);
  EXPECT_EQ(grid.spacing_m, Eigen::Vector3d(1e-3, prone.image.geometry.spacing_m.y(), 2e-3));
  // The nodes' box in the grid's index space: the margin, plus less than a voxel, on every side.
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e9), hi = Eigen::Vector3d::Constant(-1e9);
  for (int n = 0; n < deformed.rows(); ++n) {
    const Eigen::Vector3d q = grid.physicalToIndex(deformed.row(n).transpose());
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  for (int a = 0; a < 3; ++a) {
    EXPECT_GE(lo[a] * grid.spacing_m[a], 5e-3 - 1e-9);
    EXPECT_LE(lo[a] * grid.spacing_m[a], 5e-3 + grid.spacing_m[a] + 1e-9);
    EXPECT_GE((grid.size[a] - 1 - hi[a]) * grid.spacing_m[a], 5e-3 - 1e-9);
    EXPECT_LE((grid.size[a] - 1 - hi[a]) * grid.spacing_m[a], 5e-3 + grid.spacing_m[a] + 1e-9);
  }
  const SupineImages s = resampleToSupine(mesh, u, &prone.image, &prone.labels, grid, o);
  TempDir dir("breast_sim_supine");
  for (const char* name : {"supine.nii.gz", "supine.nrrd"}) {
    SCOPED_TRACE(name);
    writeMriVolume(dir.path(name), s.image);
    const MriVolume back = readMriVolume(dir.path(name));
    EXPECT_EQ(back.image.geometry.size, grid.size);
    EXPECT_LT((back.image.geometry.origin_m - grid.origin_m).cwiseAbs().maxCoeff(), 1e-8);
    EXPECT_LT((back.image.geometry.direction - grid.direction).cwiseAbs().maxCoeff(), 1e-6);
    EXPECT_EQ(back.image.values, s.image.values);
  }
  // Too many voxels, a missing input, a displacement per node.
  SupineResampleOptions tiny = o;
  tiny.max_voxels = 100;
  EXPECT_THROW(supineGrid(prone.image.geometry, deformed, tiny), std::invalid_argument);
  EXPECT_THROW(resampleToSupine(mesh, u, nullptr, nullptr, grid), std::invalid_argument);
  EXPECT_THROW(resampleToSupine(mesh, u.topRows(3), &prone.image, nullptr, grid), std::invalid_argument);
}
