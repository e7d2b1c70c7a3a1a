#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <set>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/mesh/tet_quality.h"

using namespace breast_sim::core;

namespace {

// Unit cube [0,1]³ (scaled by `h` metres) split into 6 tetrahedra around the diagonal 0–6.
TetMesh cubeMesh(double h = 1.0) {
  Points x(8, 3);
  for (int i = 0; i < 8; ++i) x.row(i) << h * (i & 1), h * ((i >> 1) & 1), h * ((i >> 2) & 1);
  Tets t(6, 4);
  t << 0, 1, 3, 7,  0, 1, 7, 5,  0, 5, 7, 4,  0, 3, 2, 7,  0, 2, 6, 7,  0, 6, 4, 7;
  return TetMesh(x, t, {1, 1, 1, 2, 2, 2});
}

Eigen::Vector3d regular(int i) {
  const Eigen::Vector3d v[4] = {{1, 1, 1}, {1, -1, -1}, {-1, 1, -1}, {-1, -1, 1}};
  return v[i];
}

}  // namespace

TEST(TetMesh, ConstructorMakesEveryTetrahedronPositive) {
  const TetMesh m = cubeMesh();
  for (int t = 0; t < m.numTets(); ++t) {
    SCOPED_TRACE("tet " + std::to_string(t));
    EXPECT_GT(signedTetVolume(m.nodes().row(m.tets()(t, 0)), m.nodes().row(m.tets()(t, 1)),
                              m.nodes().row(m.tets()(t, 2)), m.nodes().row(m.tets()(t, 3))), 0.0);
  }
  EXPECT_NEAR(m.volume(), 1.0, 1e-14);
}

TEST(TetMesh, CubeBoundaryIsClosedWithOutwardNormals) {
  const TetMesh m = cubeMesh(0.01);
  const BoundarySurface& b = m.boundary();
  EXPECT_EQ(b.triangles.rows(), 12);  // two triangles per cube face
  EXPECT_TRUE(isClosedManifold(b.triangles));
  EXPECT_EQ(b.nodes.size(), 8u);
  const Eigen::Vector3d centre(0.005, 0.005, 0.005);
  for (Eigen::Index f = 0; f < b.triangles.rows(); ++f) {
    const Eigen::Vector3d c = (m.nodes().row(b.triangles(f, 0)) + m.nodes().row(b.triangles(f, 1)) +
                               m.nodes().row(b.triangles(f, 2))).transpose() / 3.0;
    EXPECT_GT((c - centre).dot(b.normals.row(f).transpose()), 0.0) << "face " << f;
    EXPECT_NEAR(b.normals.row(f).norm(), 1.0, 1e-12);
  }
  // Divergence theorem: the boundary encloses the mesh volume.
  double vol = 0;
  for (Eigen::Index f = 0; f < b.triangles.rows(); ++f)
    vol += signedTetVolume(Eigen::Vector3d::Zero(), m.nodes().row(b.triangles(f, 0)),
                           m.nodes().row(b.triangles(f, 1)), m.nodes().row(b.triangles(f, 2)));
  EXPECT_NEAR(vol, m.volume(), 1e-15);
  // The total kept at construction is the sum of the elements' rest volumes, to the bit, in a copy too.
  EXPECT_EQ(m.volume(), m.tetVolumes().sum());
  const TetMesh copy = m;
  EXPECT_EQ(copy.volume(), m.tetVolumes().sum());
}

TEST(TetMesh, OpenSurfaceIsNotClosed) {
  Triangles tris(2, 3);
  tris << 0, 1, 2, 0, 2, 3;
  EXPECT_FALSE(isClosedManifold(tris));
  Triangles twice(2, 3);
  twice << 0, 1, 2, 0, 1, 2;  // same orientation twice: not a consistent closed surface
  EXPECT_FALSE(isClosedManifold(twice));
}

TEST(TetMesh, RejectsBadInputWithAClearMessage) {
  Points x(4, 3);
  x << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1;
  Tets out_of_range(1, 4);
  out_of_range << 0, 1, 2, 4;
  try {
    TetMesh m(x, out_of_range);
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("node 4"), std::string::npos) << e.what();
  }
  Tets repeated(1, 4);
  repeated << 0, 1, 2, 2;
  EXPECT_THROW(TetMesh(x, repeated), std::invalid_argument);
  Points flat = x;
  flat(3, 2) = 0.0;  // coplanar
  Tets ok(1, 4);
  ok << 0, 1, 2, 3;
  EXPECT_THROW(TetMesh(flat, ok), std::invalid_argument);
  Points nan = x;
  nan(2, 1) = std::nan("");
  EXPECT_THROW(TetMesh(nan, ok), std::invalid_argument);
  EXPECT_THROW(TetMesh(x, ok, {1, 2}), std::invalid_argument);
}

TEST(TetMesh, NodeSetsAreSortedUniqueAndValidated) {
  TetMesh m = cubeMesh();
  m.setNodeSet("chest_wall", {3, 1, 1, 0});
  EXPECT_EQ(m.nodeSet("chest_wall"), (std::vector<int>{0, 1, 3}));
  EXPECT_THROW(m.setNodeSet("skin", {8}), std::invalid_argument);
  EXPECT_THROW(m.setNodeSet("", {1}), std::invalid_argument);
  try {
    m.nodeSet("nipple");
    FAIL();
  } catch (const std::out_of_range& e) {
    EXPECT_NE(std::string(e.what()).find("chest_wall"), std::string::npos) << e.what();
  }
}

TEST(TetQuality, RegularTetrahedronIsIdeal) {
  const TetQuality q = tetQuality(regular(0), regular(1), regular(3), regular(2));  // positive order
  EXPECT_GT(q.volume_m3, 0.0);
  EXPECT_NEAR(q.aspect_ratio, 1.0, 1e-12);
  EXPECT_NEAR(q.min_dihedral_deg, std::acos(1.0 / 3.0) * 180.0 / M_PI, 1e-9);
  EXPECT_NEAR(q.volume_m3, 8.0 / 3.0, 1e-12);
  const TetQuality inverted = tetQuality(regular(0), regular(1), regular(2), regular(3));
  EXPECT_LT(inverted.volume_m3, 0.0);
  EXPECT_EQ(inverted.min_dihedral_deg, 0.0);  // meaningless for an inverted element: reported as 0
}

TEST(TetQuality, SliverHasSmallDihedralAndLargeAspectRatio) {
  // Four nearly coplanar points on a square: the classic sliver.
  const TetQuality q = tetQuality({0, 0, 0}, {1, 0, 0}, {1, 1, 1e-3}, {0, 1, 0});
  EXPECT_LT(q.min_dihedral_deg, 1.0);
  EXPECT_GT(q.aspect_ratio, 100.0);
}

TEST(TetQuality, QualityIsScaleInvariant) {
  const TetQuality a = tetQuality({0, 0, 0}, {1, 0, 0}, {0.3, 1, 0}, {0.2, 0.4, 0.8});
  const TetQuality b = tetQuality({0, 0, 0}, {1e-3, 0, 0}, {0.3e-3, 1e-3, 0}, {0.2e-3, 0.4e-3, 0.8e-3});
  EXPECT_NEAR(a.aspect_ratio, b.aspect_ratio, 1e-9);
  EXPECT_NEAR(a.min_dihedral_deg, b.min_dihedral_deg, 1e-9);
  EXPECT_NEAR(a.volume_m3 * 1e-9, b.volume_m3, 1e-20);
}

TEST(TetQuality, InvertedElementsAreDetected) {
  const TetMesh m = cubeMesh();
  EXPECT_TRUE(invertedTets(m.tets(), m.nodes()).empty());
  Points moved = m.nodes();
  moved(7, 0) = -2.0;  // push the far corner through the opposite faces
  moved(7, 1) = -2.0;
  moved(7, 2) = -2.0;
  const auto bad = invertedTets(m.tets(), moved);
  EXPECT_FALSE(bad.empty());
  const QualityStats s = qualityStats(m.tets(), moved);
  EXPECT_EQ(s.num_inverted, static_cast<int>(bad.size()));
  const QualityStats rest = qualityStats(m.tets(), m.nodes());
  EXPECT_EQ(rest.num_inverted, 0);
  EXPECT_NEAR(rest.total_volume_m3, 1.0, 1e-14);
}

TEST(TetMesh, OverlappingOrDuplicateElementsAreRejected) {
  Points x(5, 3);
  x << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0.2, 0.2, 0.2;
  Tets duplicate(2, 4);
  duplicate << 0, 1, 2, 3, 0, 1, 2, 3;
  EXPECT_THROW(TetMesh(x, duplicate), std::invalid_argument);
  // Node 4 lies inside tet (0,1,2,3): tets (0,1,2,4) and (0,1,2,3) sit on the same side of face 0-1-2.
  Tets same_side(2, 4);
  same_side << 0, 1, 2, 3, 0, 1, 2, 4;
  try {
    TetMesh m(x, same_side);
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("same side"), std::string::npos) << e.what();
  }
  Points y(6, 3);
  y << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, -1, 0.3, 0.3, 0.5;
  Tets three(3, 4);
  three << 0, 1, 2, 3, 0, 2, 1, 4, 0, 1, 2, 5;  // face 0-1-2 in three elements
  EXPECT_THROW(TetMesh(y, three), std::invalid_argument);
}

TEST(TetMesh, BoundaryBySortingEqualsANaiveFaceCount) {
  // Slow reference: count every face in a map.
  const TetMesh m = cubeMesh();
  Points x(27, 3);
  for (int i = 0; i < 27; ++i) x.row(i) << i % 3, (i / 3) % 3, i / 9;
  std::vector<Eigen::Vector4i> tl;
  const int kuhn[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
  for (int k = 0; k < 2; ++k)
    for (int j = 0; j < 2; ++j)
      for (int i = 0; i < 2; ++i) {
        int c[8];
        for (int b = 0; b < 8; ++b) c[b] = (i + (b & 1)) + 3 * (j + ((b >> 1) & 1)) + 9 * (k + ((b >> 2) & 1));
        for (const auto& t : kuhn) tl.emplace_back(c[t[0]], c[t[1]], c[t[2]], c[t[3]]);
      }
  Tets tets(static_cast<Eigen::Index>(tl.size()), 4);
  for (size_t i = 0; i < tl.size(); ++i) tets.row(static_cast<Eigen::Index>(i)) = tl[i];
  const TetMesh big(x, tets);
  std::map<std::array<int, 3>, int> count;
  for (int t = 0; t < big.numTets(); ++t)
    for (int f = 0; f < 4; ++f) {
      std::array<int, 3> key;
      for (int k = 0, q = 0; k < 4; ++k)
        if (k != f) key[q++] = big.tets()(t, k);
      std::sort(key.begin(), key.end());
      ++count[key];
    }
  std::set<std::array<int, 3>> naive;
  for (const auto& kv : count)
    if (kv.second == 1) naive.insert(kv.first);
  std::set<std::array<int, 3>> fast;
  for (Eigen::Index f = 0; f < big.boundary().triangles.rows(); ++f) {
    std::array<int, 3> key{big.boundary().triangles(f, 0), big.boundary().triangles(f, 1), big.boundary().triangles(f, 2)};
    std::sort(key.begin(), key.end());
    fast.insert(key);
  }
  EXPECT_EQ(fast, naive);
  EXPECT_EQ(naive.size(), 6u * 8u);  // 2×2 squares per side, 2 triangles each
  EXPECT_EQ(m.boundary().triangles.rows(), 12);
}

TEST(TetQuality, NanPositionsCountAsInverted) {
  const TetMesh m = cubeMesh();
  Points moved = m.nodes();
  moved(7, 0) = std::nan("");
  const auto bad = invertedTets(m.tets(), moved);
  EXPECT_FALSE(bad.empty());
  EXPECT_EQ(qualityStats(m.tets(), moved).num_inverted, static_cast<int>(bad.size()));
}
