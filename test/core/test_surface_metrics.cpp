// Surface metrics between a model's skin and a target (surfaceMatch, surfaceSamples): the target's
// part on the chest wall is left out of target → skin and counted, and a real miss still counts.
#include <gtest/gtest.h>

#include <string>

#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/morphing/target_surface.h"

using namespace breast_sim::core;

namespace {

// A 20 × 20 × 10 mm block (2 mm cubes) on the chest wall z = 0: chest-wall nodes on z = 0, skin the
// other boundary nodes (so the skin, like a breast model's, stops one element above the wall).
TetMesh block() {
  TetMesh m = makeBoxMesh({10, 10, 5}, {0.02, 0.02, 0.01});
  m.setNodeSet(node_sets::kChestWall, m.nodeSet("z_min"));
  std::vector<char> wall(static_cast<size_t>(m.numNodes()), 0);
  for (int n : m.nodeSet("z_min")) wall[static_cast<size_t>(n)] = 1;
  std::vector<int> skin;
  for (int n : m.boundary().nodes)
    if (!wall[static_cast<size_t>(n)]) skin.push_back(n);
  m.setNodeSet(node_sets::kSkin, skin);
  return m;
}

// The block's whole boundary, base on the wall included, at positions x (a closed target surface).
TargetSurface closedTarget(const TetMesh& m, const Points& x) {
  TargetSurface t;
  t.vertices_m = x;
  t.triangles = m.boundary().triangles;
  return t;
}

int baseSamples(const TargetSurface& t) {
  const Points s = surfaceSamples(t);
  int n = 0;
  for (Eigen::Index i = 0; i < s.rows(); ++i) n += s(i, 2) < 1e-9;
  return n;
}

}  // namespace

TEST(SurfaceMetrics, TheTargetsBaseOnTheChestWallIsLeftOutAndCounted) {
  const TetMesh m = block();
  const TargetSurface target = closedTarget(m, m.nodes());
  const SurfaceDistance d(target);
  const SurfaceMatch all = surfaceMatch(m, m.nodes(), m.nodeSet(node_sets::kSkin), d, target, 0.0);
  const SurfaceMatch match = surfaceMatch(m, m.nodes(), m.nodeSet(node_sets::kSkin), d, target);
  // Counting the base, a model that sits exactly on its target misses it by up to half the block's
  // width (the base's centre is 10 mm from the nearest skin).
  EXPECT_NEAR(all.target_to_model.max_m, 0.010, 1e-3);
  EXPECT_EQ(all.target_on_chest_wall, 0);
  EXPECT_EQ(all.target_to_model.count, all.target_samples);
  // Without it, target → skin is the gap the skin leaves above the wall: at most one element.
  EXPECT_LE(match.target_to_model.max_m, 2e-3 + 1e-9);
  EXPECT_LT(match.target_to_model.mean_m, 1e-4);
  EXPECT_GE(match.target_on_chest_wall, baseSamples(target));
  EXPECT_EQ(match.target_to_model.count + match.target_on_chest_wall, match.target_samples);
  EXPECT_EQ(match.target_samples, static_cast<int>(surfaceSamples(target).rows()));
  // Skin → target is measured against the whole target either way.
  EXPECT_LT(match.model_to_target.max_m, 1e-9);
  EXPECT_EQ(match.model_to_target.count, all.model_to_target.count);
}

TEST(SurfaceMetrics, ATargetThatMissesTheSkinStillCounts) {
  const TetMesh m = block();
  // The target's top 5 mm above the model's (z = 15 mm instead of 10 mm); its base stays on the wall.
  Points xt = m.nodes();
  for (Eigen::Index i = 0; i < xt.rows(); ++i) xt(i, 2) *= 1.5;
  const TargetSurface target = closedTarget(m, xt);
  const SurfaceDistance d(target);
  const SurfaceMatch match = surfaceMatch(m, m.nodes(), m.nodeSet(node_sets::kSkin), d, target);
  EXPECT_NEAR(match.target_to_model.max_m, 0.005, 1e-6);
  EXPECT_NEAR(match.model_to_target.max_m, 0.005, 1e-6);
  // Only samples on or next to the wall went (the base and the sides' lowest millimetre).
  EXPECT_GE(match.target_on_chest_wall, baseSamples(target));
  EXPECT_LT(match.target_on_chest_wall, match.target_samples / 2);
  const Points s = surfaceSamples(target);
  int low = 0;
  for (Eigen::Index i = 0; i < s.rows(); ++i) low += s(i, 2) <= kTargetChestWallTolerance_m;
  EXPECT_LE(match.target_on_chest_wall, low);
}

TEST(SurfaceMetrics, SamplesLeaveOutVerticesNoTriangleUses) {
  TargetSurface t;
  t.vertices_m.resize(4, 3);
  t.vertices_m << 0, 0, 0, 1, 0, 0, 0, 1, 0, 5, 5, 5;  // the last vertex is on no triangle
  t.triangles.resize(1, 3);
  t.triangles << 0, 1, 2;
  const Points s = surfaceSamples(t);
  ASSERT_EQ(s.rows(), 4);  // three vertices and the centroid
  EXPECT_LT(s.col(0).maxCoeff(), 1.0 + 1e-12);
  t.triangles.resize(0, 3);  // a point cloud keeps every point
  EXPECT_EQ(surfaceSamples(t).rows(), 4);
}

TEST(SurfaceMetrics, ThePhantomsSkinMatchesItsClosedSurfaceWithoutTheBase) {
  // The prone phantom model at rest against the prone phantom surface, base faces included (as a
  // closed target file would be) and as the pipeline's skin-only target.
  ModelCase c = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  c.meshing.target_elements = 3000;
  const SimulationModel model = buildSimulationModel(c);
  ASSERT_TRUE(c.phantom);
  const PhantomSurface& ps = c.phantom->prone_surface;
  TargetSurface closed;
  closed.vertices_m = ps.vertices_m;
  closed.triangles = ps.triangles;
  const TargetSurface skin_only = skinTarget(ps);
  const Points& x = model.mesh.nodes();
  const std::vector<int>& skin = model.mesh.nodeSet(node_sets::kSkin);
  const SurfaceDistance dc(closed), ds(skin_only);
  const SurfaceMatch with_base = surfaceMatch(model.mesh, x, skin, dc, closed, 0.0);
  const SurfaceMatch closed_match = surfaceMatch(model.mesh, x, skin, dc, closed);
  const SurfaceMatch skin_match = surfaceMatch(model.mesh, x, skin, ds, skin_only);
  std::printf("phantom at rest, 3000 elements: target->skin max %.2f mm counting the base, %.2f mm without "
              "(%d of %d samples left out); skin-only target %.2f mm (%d left out); skin->target p95 %.2f mm\n",
              1e3 * with_base.target_to_model.max_m, 1e3 * closed_match.target_to_model.max_m,
              closed_match.target_on_chest_wall, closed_match.target_samples, 1e3 * skin_match.target_to_model.max_m,
              skin_match.target_on_chest_wall, 1e3 * closed_match.model_to_target.p95_m);
  // The base's centre is a breast radius (> 4 cm) from the skin.
  EXPECT_GT(with_base.target_to_model.max_m, 0.04);
  // Without the base, target → skin is the skin's discretisation: about a millimetre at this size (1.2 mm measured).
  EXPECT_GT(closed_match.target_on_chest_wall, 0);
  EXPECT_LT(closed_match.target_to_model.max_m, 0.0025);
  EXPECT_LT(closed_match.target_to_model.mean_m, 0.0015);
  // A skin-only target has no base vertices among its samples, so nothing of it is on the wall's
  // inside, and it reads as the closed target does.
  EXPECT_LT(skin_match.target_to_model.max_m, 0.0025);
  EXPECT_NEAR(skin_match.target_to_model.mean_m, closed_match.target_to_model.mean_m, 5e-4);
}
