// Cross-sections: the cut of a tetrahedron by a plane, checked against exact areas, and the figure
// written for a deformed box.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include <Eigen/Geometry>

#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/render/cross_section.h"

using namespace breast_sim::core;

namespace {

/// Area of a planar convex polygon given in order [m²].
double polygonArea(const std::vector<Eigen::Vector3d>& p) {
  Eigen::Vector3d a = Eigen::Vector3d::Zero();
  for (size_t i = 1; i + 1 < p.size(); ++i) a += (p[i] - p[0]).cross(p[i + 1] - p[0]);
  return 0.5 * a.norm();
}

}  // namespace

TEST(TetPlaneSection, CutsTheCornerTetrahedronInTrianglesOfTheExactArea) {
  // Corner tet (0,0,0), e_x, e_y, e_z: the plane z = t cuts a right triangle with legs 1 − t.
  const Eigen::Vector3d o(0, 0, 0), a(1, 0, 0), b(0, 1, 0), c(0, 0, 1);
  for (double t : {0.1, 0.5, 0.9}) {
    const auto p = tetPlaneSection(o, a, b, c, 2, t);
    ASSERT_EQ(p.size(), 3u) << t;
    for (const auto& q : p) EXPECT_NEAR(q.z(), t, 1e-15);
    EXPECT_NEAR(polygonArea(p), 0.5 * (1 - t) * (1 - t), 1e-14) << t;
  }
  // Planes that miss it give nothing.
  EXPECT_TRUE(tetPlaneSection(o, a, b, c, 2, 1.5).empty());
  EXPECT_TRUE(tetPlaneSection(o, a, b, c, 0, -0.1).empty());
}

TEST(TetPlaneSection, QuadrilateralCutsAreOrderedAndConvex) {
  // The plane x + ... : for the tet (0,0,0),(1,0,0),(0,1,0),(1,1,1) the plane x = 0.5 separates two
  // vertices from two: a quadrilateral. Ordered points give the same area by the fan from any start.
  const Eigen::Vector3d p0(0, 0, 0), p1(1, 0, 0), p2(0, 1, 0), p3(1, 1, 1);
  const auto q = tetPlaneSection(p0, p1, p2, p3, 0, 0.5);
  ASSERT_EQ(q.size(), 4u);
  std::vector<Eigen::Vector3d> rotated(q.begin() + 1, q.end());
  rotated.push_back(q.front());
  EXPECT_NEAR(polygonArea(q), polygonArea(rotated), 1e-14);
  // Convex and ordered: consecutive edge cross products all point the same way.
  const Eigen::Vector3d n = (q[1] - q[0]).cross(q[2] - q[1]);
  for (size_t i = 0; i < 4; ++i) {
    const Eigen::Vector3d e0 = q[(i + 1) % 4] - q[i], e1 = q[(i + 2) % 4] - q[(i + 1) % 4];
    EXPECT_GT(e0.cross(e1).dot(n), 0.0) << i;
  }
}

TEST(TetPlaneSection, TheCutsOfABoxMeshAddUpToItsCrossSection) {
  // A 3 × 2 × 4 cm box cut at a height that is not a node plane: the polygons tile the 3 × 2 cm
  // rectangle exactly, whatever the tetrahedra.
  const TetMesh mesh = makeBoxMesh(Eigen::Vector3i(3, 2, 4), Eigen::Vector3d(0.03, 0.02, 0.04));
  const Points& x = mesh.nodes();
  const Tets& T = mesh.tets();
  for (int axis = 0; axis < 3; ++axis) {
    const double value = 0.37 * (x.col(axis).maxCoeff() - x.col(axis).minCoeff()) + x.col(axis).minCoeff();
    double area = 0;
    for (Eigen::Index t = 0; t < T.rows(); ++t)
      area += polygonArea(tetPlaneSection(x.row(T(t, 0)).transpose(), x.row(T(t, 1)).transpose(), x.row(T(t, 2)).transpose(),
                                          x.row(T(t, 3)).transpose(), axis, value));
    const double sides[3] = {0.03, 0.02, 0.04};
    EXPECT_NEAR(area, sides[(axis + 1) % 3] * sides[(axis + 2) % 3], 1e-12) << "axis " << axis;
  }
}

TEST(CrossSections, WritesAPngAndNamesBadInput) {
  const TetMesh mesh = makeBoxMesh(Eigen::Vector3i(3, 3, 3), Eigen::Vector3d(0.03, 0.03, 0.03));
  Points sheared = mesh.nodes();
  sheared.col(0) += 0.3 * sheared.col(2);
  std::vector<CrossSectionConfiguration> rows(2);
  rows[0].title = "rest";
  rows[1].title = "sheared";
  rows[1].positions_m = &sheared;
  rows[1].lesions_m = Points(1, 3);
  rows[1].lesions_m << 0.015, 0.015, 0.015;
  const std::string path = (std::filesystem::temp_directory_path() / "breast_sim_test_cross_sections.png").string();
  std::filesystem::remove(path);
  writeCrossSections(path, mesh, rows);
  std::ifstream in(path, std::ios::binary);
  char magic[8] = {};
  in.read(magic, 8);
  EXPECT_EQ(std::string(magic + 1, 3), "PNG");
  EXPECT_GT(std::filesystem::file_size(path), 1000u);

  Points wrong(3, 3);
  rows[1].positions_m = &wrong;
  try {
    writeCrossSections(path, mesh, rows);
    FAIL() << "a configuration of the wrong size was drawn";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("'sheared' has 3 positions"), std::string::npos) << e.what();
  }
  rows[1].positions_m = &sheared;
  EXPECT_THROW(writeCrossSections("/nonexistent_dir/x.png", mesh, rows), std::runtime_error);
}
