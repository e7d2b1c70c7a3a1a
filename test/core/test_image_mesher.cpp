#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/image_mesher.h"

using namespace breast_sim::core;

namespace {

constexpr double kRadius = 0.03;     // hemisphere radius [m]
constexpr double kSlab = 0.006;      // chest-wall slab thickness [m]

// A hemisphere of fat (label 1) with a fibroglandular core (29) resting on a chest-wall slab (40) at
// y ∈ [0, 6] mm; tissue protrudes towards −y. 1 mm voxels, origin chosen so the base centre is (0,0,0).
LabelImage hemisphereImage() {
  const double h = 1e-3;
  const int nx = 70, ny = 44, nz = 70;
  LabelImage img(Eigen::Vector3i(nx, ny, nz), Eigen::Vector3d(h, h, h),
                 Eigen::Vector3d(-34.5e-3, -36.5e-3, -34.5e-3));
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const Eigen::Vector3d p = img.indexToPhysical(Eigen::Vector3d(i, j, k));
        if (p.y() >= 0 && p.y() < kSlab && std::hypot(p.x(), p.z()) < kRadius + 6e-3) img.at(i, j, k) = 40;
        else if (p.y() < 0 && p.norm() < kRadius) img.at(i, j, k) = p.norm() < 0.012 ? 29 : 1;
      }
  return img;
}

}  // namespace

TEST(ImageMesher, HemisphereMeshIsClosedValidAndKeepsTheVolume) {
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.interior_size_m = 8e-3;
  MeshingReport rep;
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {}, opt, &rep);
  EXPECT_GT(m.numTets(), 500);
  EXPECT_TRUE(isClosedManifold(m.boundary().triangles));
  const QualityStats q = qualityStats(m.tets(), m.nodes());
  EXPECT_EQ(q.num_inverted, 0);
  EXPECT_GT(q.min_dihedral_deg, 2.0);
  const double analytic = 2.0 / 3.0 * M_PI * std::pow(kRadius, 3);
  EXPECT_NEAR(m.volume() / analytic, 1.0, 0.03) << "mesh " << m.volume() << " analytic " << analytic;
  EXPECT_NEAR(m.volume() / rep.voxel_volume_m3, 1.0, 0.03);
  EXPECT_GT(rep.num_chest_wall_faces, 0);
  EXPECT_GT(rep.num_skin_faces, 0);
}

TEST(ImageMesher, ChestWallAndSkinNodeSetsLieOnTheirSurfaces) {
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.interior_size_m = 8e-3;
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {}, opt);
  const auto& chest = m.nodeSet(node_sets::kChestWall);
  const auto& skin = m.nodeSet(node_sets::kSkin);
  ASSERT_FALSE(chest.empty());
  ASSERT_FALSE(skin.empty());
  // The tissue/slab interface is at y = 0; nodes on the rim where skin meets the wall may sit a
  // little off it, all within one skin element.
  int on_wall = 0;
  for (int v : chest) {
    EXPECT_NEAR(m.nodes()(v, 1), 0.0, 3e-3) << "chest-wall node " << v;
    on_wall += std::abs(m.nodes()(v, 1)) < 1.5e-3;
  }
  EXPECT_GT(on_wall, 0.9 * chest.size());
  int on_sphere = 0;
  for (int v : skin) on_sphere += std::abs(m.nodes().row(v).norm() - kRadius) < 1.5e-3;
  EXPECT_GT(on_sphere, 0.9 * skin.size());
}

TEST(ImageMesher, RegionLabelsFollowTheTissueClasses) {
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.interior_size_m = 5e-3;
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {}, opt);
  int fat = 0, gland = 0, gland_inside = 0;
  for (int t = 0; t < m.numTets(); ++t) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) c += m.nodes().row(m.tets()(t, k)).transpose() / 4;
    if (m.regionLabels()[t] == static_cast<int>(TissueClass::kFat)) ++fat;
    if (m.regionLabels()[t] == static_cast<int>(TissueClass::kFibroglandular)) {
      ++gland;
      gland_inside += c.norm() < 0.016;
    }
  }
  EXPECT_GT(fat, 0);
  EXPECT_GT(gland, 0);
  EXPECT_EQ(gland_inside, gland);
}

TEST(ImageMesher, TargetElementCountIsMet) {
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.target_elements = 6000;
  MeshingReport rep;
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {}, opt, &rep);
  EXPECT_NEAR(m.numTets() / 6000.0, 1.0, 0.25) << m.numTets() << " tets after " << rep.passes << " passes";
}

TEST(ImageMesher, MeshIsFinerNearALesion) {
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.interior_size_m = 8e-3;
  const Eigen::Vector3d lesion(0.01, -0.012, 0.0);
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {{lesion, 2e-3}}, opt);
  double near_sum = 0, far_sum = 0;
  int near_n = 0, far_n = 0;
  const Eigen::VectorXd vol = m.tetVolumes();
  const Eigen::Vector3d mirror(-0.01, -0.012, 0.0);  // same depth, other side
  for (int t = 0; t < m.numTets(); ++t) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) c += m.nodes().row(m.tets()(t, k)).transpose() / 4;
    if ((c - lesion).norm() < 5e-3) near_sum += vol[t], ++near_n;
    if ((c - mirror).norm() < 5e-3) far_sum += vol[t], ++far_n;
  }
  ASSERT_GT(near_n, 0);
  ASSERT_GT(far_n, 0);
  EXPECT_LT(near_sum / near_n, 0.5 * far_sum / far_n);
}

TEST(ImageMesher, BadInputsAreRejectedWithTheirName) {
  LabelImage empty(Eigen::Vector3i(8, 8, 8), Eigen::Vector3d(1e-3, 1e-3, 1e-3), Eigen::Vector3d::Zero());
  EXPECT_THROW(meshLabelImage(empty, TissueLabels{}, {}, MeshingOptions{}), std::invalid_argument);
  MeshingOptions bad;
  bad.interior_size_m = -1;
  try {
    meshLabelImage(hemisphereImage(), TissueLabels{}, {}, bad);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("interior_size_m"), std::string::npos) << e.what();
  }
}

TEST(ImageMesher, FloatingIslandsAreDroppedAndBothBreastsKept) {
  LabelImage img = hemisphereImage();
  // A 3-voxel speck of fat floating in air, far from the breast and the wall.
  for (int k = 60; k < 63; ++k) img.at(5, 5, k) = 1;
  // A second, large component not touching the wall is kept (≥ 1% of the volume).
  for (int k = 2; k < 14; ++k)
    for (int j = 2; j < 14; ++j)
      for (int i = 55; i < 67; ++i) img.at(i, j, k) = 1;
  MeshingOptions opt;
  opt.interior_size_m = 6e-3;
  MeshingReport rep;
  const TetMesh m = meshLabelImage(img, TissueLabels{}, {}, opt, &rep);
  EXPECT_EQ(rep.num_components, 3);  // breast, cube, speck
  EXPECT_EQ(rep.dropped_components, 1);
  EXPECT_LE(rep.dropped_volume_m3, 1e-7);  // at most the speck (27 mm³) went
  EXPECT_NEAR(m.volume() / (2.0 / 3.0 * M_PI * std::pow(kRadius, 3) + 1.728e-6), 1.0, 0.04);
  for (int v = 0; v < m.numNodes(); ++v) EXPECT_GT(m.nodes().row(v).norm(), 0.0);  // no orphan nodes at origin
  const std::vector<bool> used = m.usedNodes();
  EXPECT_EQ(static_cast<int>(std::count(used.begin(), used.end(), true)), m.numNodes());
}

TEST(ImageMesher, TheSameImageGivesTheSameMeshEveryTime) {
  // CGAL's default generator is clock-seeded and advances with every run: without the fixed seed two
  // runs in one process (and any two processes) gave different meshes.
  const LabelImage img = hemisphereImage();
  MeshingOptions opt;
  opt.interior_size_m = 8e-3;
  const TetMesh a = meshLabelImage(img, TissueLabels{}, {}, opt);
  const TetMesh b = meshLabelImage(img, TissueLabels{}, {}, opt);
  ASSERT_EQ(a.numNodes(), b.numNodes());
  ASSERT_EQ(a.numTets(), b.numTets());
  EXPECT_EQ(a.nodes(), b.nodes());
  EXPECT_EQ(a.tets(), b.tets());
  // Another seed is another (equally valid) mesh.
  opt.random_seed = 7;
  const TetMesh c = meshLabelImage(img, TissueLabels{}, {}, opt);
  EXPECT_FALSE(c.numNodes() == a.numNodes() && c.nodes() == a.nodes());
}
