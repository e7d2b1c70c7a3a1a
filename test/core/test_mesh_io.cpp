#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mesh/tet_mesh.h"

#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::TempDir;
namespace fs = std::filesystem;

namespace {

void writeText(const std::string& path, const std::string& text) {
  std::ofstream(path, std::ios::binary) << text;
}

std::string readBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// Two unit cubes side by side (scaled by 1 cm and shifted off the origin so coordinates have many
// digits), 6 tets each, with labels 29, 7 and 0 interleaved so writers that group by label change the
// order, and two node sets.
TetMesh twoCubeMesh() {
  const double h = 0.0123456789;
  const Eigen::RowVector3d origin(0.1234567891234, -0.0512, 0.3);
  Points x(12, 3);
  for (int i = 0; i < 12; ++i) x.row(i) = origin + h * Eigen::RowVector3d(i % 3, (i / 3) % 2, i / 6);
  // Node (i, j, k) of the 3×2×2 grid has index i + 3j + 6k.
  auto cube = [](int i0) {
    const int c[8] = {i0, i0 + 1, i0 + 3, i0 + 4, i0 + 6, i0 + 7, i0 + 9, i0 + 10};  // (x, y, z) bits
    // Corners by bit pattern xyz: 0=000 1=100 2=010 3=110 4=001 5=101 6=011 7=111, around diagonal 0–7.
    const int t[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
    std::vector<std::array<int, 4>> tets;
    for (const auto& tet : t) tets.push_back({c[tet[0]], c[tet[1]], c[tet[2]], c[tet[3]]});
    return tets;
  };
  const auto a = cube(0), b = cube(1);
  Tets tets(12, 4);
  std::vector<int> labels;
  for (int i = 0; i < 6; ++i) {
    tets.row(2 * i) << a[i][0], a[i][1], a[i][2], a[i][3];
    tets.row(2 * i + 1) << b[i][0], b[i][1], b[i][2], b[i][3];
    labels.push_back(29);
    labels.push_back(i < 2 ? 0 : 7);
  }
  TetMesh mesh(x, tets, labels);
  mesh.setNodeSet(node_sets::kChestWall, {0, 3, 6, 9});  // the face x = x0
  mesh.setNodeSet(node_sets::kNipple, {11});
  return mesh;
}

void expectSameMesh(const TetMesh& expected, const TetMesh& actual, double rel_tol, bool node_sets) {
  ASSERT_EQ(actual.numNodes(), expected.numNodes());
  ASSERT_EQ(actual.numTets(), expected.numTets());
  const double scale = expected.nodes().cwiseAbs().maxCoeff();
  EXPECT_LE((actual.nodes() - expected.nodes()).cwiseAbs().maxCoeff(), rel_tol * scale);
  EXPECT_EQ(actual.tets(), expected.tets());
  EXPECT_EQ(actual.regionLabels(), expected.regionLabels());
  if (node_sets) {
    EXPECT_EQ(actual.nodeSets(), expected.nodeSets());
  }
}

void expectAllPositive(const TetMesh& m) {
  for (int t = 0; t < m.numTets(); ++t) {
    EXPECT_GT(signedTetVolume(m.nodes().row(m.tets()(t, 0)), m.nodes().row(m.tets()(t, 1)),
                              m.nodes().row(m.tets()(t, 2)), m.nodes().row(m.tets()(t, 3))), 0.0)
        << "tet " << t;
  }
}

std::vector<int> row(const TetMesh& m, int t) { return {m.tets()(t, 0), m.tets()(t, 1), m.tets()(t, 2), m.tets()(t, 3)}; }

/// A file and how its reader must refuse it.
struct BadFile {
  std::string file;
  std::string text;
  std::string place;  // ":<line>:" or ": byte "
  std::string what;
};

/// Writes each file and checks that reading it throws a message that starts with its path and
/// holds the place and what is wrong.
void expectRefused(const TempDir& dir, const std::vector<BadFile>& cases) {
  for (const BadFile& c : cases) {
    SCOPED_TRACE(c.file);
    const std::string path = dir.path(c.file);
    writeText(path, c.text);
    try {
      readTetMesh(path);
      ADD_FAILURE() << "no exception";
    } catch (const std::runtime_error& e) {
      const std::string msg = e.what();
      EXPECT_EQ(msg.rfind(path, 0), 0u) << "message starts with the path: " << msg;
      EXPECT_NE(msg.find(c.place), std::string::npos) << "place '" << c.place << "' in: " << msg;
      EXPECT_NE(msg.find(c.what), std::string::npos) << "'" << c.what << "' in: " << msg;
    }
  }
}

// The node sets the hand-written files below give, in the same geometry for every format:
// A (0,0,0), B (1,0,0), C (0,1,0), D (0,0,1), E (1,1,−0.5); tets ABCD (+), ABCE (−), BCED (−).
// The three fill the space around edge BC without overlapping: E lies below ABC and beyond BCD.
Points handWrittenNodes() {
  Points x(5, 3);
  x << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, -0.5;
  return x;
}

// ABCD as written; ABCE and BCED were negative, so their last two nodes come back swapped.
void expectHandWrittenTets(const TetMesh& m) {
  ASSERT_EQ(m.numTets(), 3);
  EXPECT_EQ(row(m, 0), (std::vector<int>{0, 1, 2, 3}));
  EXPECT_EQ(row(m, 1), (std::vector<int>{0, 1, 4, 2}));
  EXPECT_EQ(row(m, 2), (std::vector<int>{1, 2, 3, 4}));
  expectAllPositive(m);
}

const char* kMsh41Ascii = R"($MeshFormat
4.1 0 8
$EndMeshFormat
$Comments
written by hand
$EndComments
$PhysicalNames
3
2 5 "skin"
3 29 "glandular"
3 7 "fat"
$EndPhysicalNames
$Entities
1 0 1 2
10 0 0 0 0
3 0 0 -1 1 1 1 1 5 0
1 0 0 -1 1 1 1 1 29 0
2 0 0 -1 1 1 1 0 0
$EndEntities
$Nodes
2 5 10 55
0 10 0 1
10
0 0 0
3 1 0 4
20
30
40
55
1 0 0
0 1 0
0 0 1
1 1 -0.5
$EndNodes
$Elements
4 5 1 9
0 10 15 1
1 10
2 3 2 1
2 20 30 40
3 1 4 2
4 10 20 30 55
3 10 20 30 40
3 2 4 1
9 20 30 55 40
$EndElements
)";

const char* kMsh22Ascii = R"($MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
2
2 5 "skin"
3 29 "glandular"
$EndPhysicalNames
$Nodes
5
10 0 0 0
20 1 0 0
30 0 1 0
40 0 0 1
55 1 1 -0.5
$EndNodes
$Elements
5
1 15 2 0 10 10
2 2 2 5 3 20 30 40
4 4 2 29 1 10 20 30 55
3 4 2 29 1 10 20 30 40
9 4 2 0 2 20 30 55 40
$EndElements
)";

}  // namespace

TEST(MeshIo, EveryFormatRoundTripsNodesTetsLabelsAndNodeSets) {
  const TetMesh mesh = twoCubeMesh();
  struct Case {
    std::string file;
    MeshWriteOptions options;
    bool binary;     // coordinates must come back bit for bit
    bool node_sets;  // the format holds node sets
  };
  MeshWriteOptions msh22a, msh22b, msh41a, msh41b, vtk_ascii;
  msh22b.gmsh = {GmshVersion::kMsh22, true};
  msh41a.gmsh = {GmshVersion::kMsh41, false};
  msh41b.gmsh = {GmshVersion::kMsh41, true};
  vtk_ascii.vtk.binary = false;
  const std::vector<Case> cases = {
      {"msh22_ascii.msh", msh22a, false, false}, {"msh22_binary.msh", msh22b, true, false},
      {"msh41_ascii.msh", msh41a, false, false}, {"msh41_binary.msh", msh41b, true, false},
      {"binary.vtu", {}, true, true},            {"ascii.vtu", vtk_ascii, false, true},
      {"binary.vtk", {}, true, true},            {"ascii.vtk", vtk_ascii, false, true},
      {"mesh.node", {}, false, false},           {"mesh.inp", {}, false, true},
  };
  TempDir dir("breast_sim_mesh_io");
  for (const Case& c : cases) {
    for (double unit : {1.0, 1e-3}) {
      SCOPED_TRACE(c.file + " with length unit " + std::to_string(unit) + " m");
      const std::string path = dir.path(c.file);
      writeTetMesh(path, mesh, {}, unit, c.options);
      const TetMesh back = readTetMesh(path, unit);
      // Text writers print the shortest exact decimal; VTK's ASCII writer prints fewer digits.
      const bool vtk_ascii_text = !c.binary && c.file.find("vt") != std::string::npos;
      const double tol = (c.binary && unit == 1.0) ? 0.0 : vtk_ascii_text ? 1e-9 : 1e-12;
      expectSameMesh(mesh, back, tol, c.node_sets);
    }
  }
}

TEST(MeshIo, LengthUnitScalesCoordinatesOnReadAndWrite) {
  const TetMesh mesh = twoCubeMesh();
  TempDir dir("breast_sim_mesh_io");
  for (const std::string file : {"mm.msh", "mm.inp", "mm.vtu", "mm.ele"}) {
    SCOPED_TRACE(file);
    writeTetMesh(dir.path(file), mesh, {}, 1e-3);  // file in mm
    const TetMesh as_metres = readTetMesh(dir.path(file), 1.0);
    EXPECT_NEAR(as_metres.nodes()(1, 0), 1000.0 * mesh.nodes()(1, 0), 1e-9);
    EXPECT_NEAR(readTetMesh(dir.path(file), 1e-3).nodes()(1, 0), mesh.nodes()(1, 0), 1e-15);
  }
  EXPECT_THROW(readTetMesh(dir.path("mm.msh"), 0.0), std::invalid_argument);
  EXPECT_THROW(writeTetMesh(dir.path("x.msh"), mesh, {}, -1.0), std::invalid_argument);
}

TEST(MeshIo, VtuKeepsPointAndCellFieldsForParaView) {
  const TetMesh mesh = twoCubeMesh();
  MeshFields fields;
  Eigen::MatrixXd displacement = Eigen::MatrixXd::Random(mesh.numNodes(), 3) * 1e-3;  // [m]
  fields.point_data.push_back({"displacement", displacement, /*is_length=*/true});
  fields.cell_data.push_back({"von_mises", Eigen::VectorXd::LinSpaced(mesh.numTets(), 0.0, 1e3)});
  fields.cell_data.push_back({"modulus_factor", Eigen::VectorXd::Constant(mesh.numTets(), 1.5)});
  TempDir dir("breast_sim_mesh_io");
  for (const std::string file : {"fields.vtu", "fields.vtk"}) {
    SCOPED_TRACE(file);
    writeTetMesh(dir.path(file), mesh, fields, 1e-3);  // coordinates and displacement in mm
    MeshFields back;
    const TetMesh m = readVtkUnstructured(dir.path(file), 1e-3, &back);
    expectSameMesh(mesh, m, 1e-12, true);
    ASSERT_EQ(back.point_data.size(), 1u);
    EXPECT_EQ(back.point_data[0].name, "displacement");
    EXPECT_TRUE(back.point_data[0].values.isApprox(displacement * 1e3, 1e-12));  // stored in mm
    ASSERT_EQ(back.cell_data.size(), 2u);
    EXPECT_EQ(back.cell_data[0].name, "von_mises");
    EXPECT_EQ(back.cell_data[0].values, fields.cell_data[0].values);
    EXPECT_EQ(back.cell_data[1].values, fields.cell_data[1].values);
  }
}

TEST(MeshIo, VtuWritesADeformedConfigurationWhenGivenPositions) {
  const TetMesh mesh = twoCubeMesh();
  // A rotation plus stretch keeps every element positively oriented.
  const Eigen::Matrix3d F = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() *
                            Eigen::Vector3d(1.2, 0.9, 1.1).asDiagonal();
  const Points x = (mesh.nodes() * F.transpose()).rowwise() + Eigen::RowVector3d(0.01, -0.02, 0.03);
  TempDir dir("breast_sim_mesh_io");
  MeshWriteOptions options;
  options.vtk.positions_m = &x;
  for (const std::string file : {"deformed.vtu", "deformed.vtk"}) {
    SCOPED_TRACE(file);
    writeTetMesh(dir.path(file), mesh, {}, 1.0, options);
    const TetMesh back = readTetMesh(dir.path(file));
    EXPECT_TRUE(back.nodes().isApprox(x, 1e-14));
    EXPECT_EQ(back.tets(), mesh.tets());
  }
  const Points wrong = x.topRows(3);
  options.vtk.positions_m = &wrong;
  try {
    writeTetMesh(dir.path("bad.vtu"), mesh, {}, 1.0, options);
    FAIL() << "positions of the wrong size were written";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("3 node positions given for a mesh of 12 nodes"), std::string::npos) << e.what();
  }
}

TEST(MeshIo, FieldWithWrongRowCountIsRejectedByName) {
  const TetMesh mesh = twoCubeMesh();
  TempDir dir("breast_sim_mesh_io");
  struct Case {
    std::string what;
    MeshFields fields;
    std::string message;
  };
  std::vector<Case> cases(4);
  cases[0] = {"point field with #N + 1 rows", {}, "point field 'displacement' has 13 rows; expected 12"};
  cases[0].fields.point_data.push_back({"displacement", Eigen::MatrixXd::Zero(mesh.numNodes() + 1, 3)});
  cases[1] = {"cell field with #T - 1 rows", {}, "cell field 'von_mises' has 11 rows; expected 12"};
  cases[1].fields.cell_data.push_back({"von_mises", Eigen::MatrixXd::Zero(mesh.numTets() - 1, 1)});
  cases[2] = {"reserved name", {}, "'region' is reserved"};
  cases[2].fields.cell_data.push_back({"region", Eigen::MatrixXd::Zero(12, 1)});
  cases[3] = {"repeated name", {}, "'s' is given twice"};
  cases[3].fields.cell_data.push_back({"s", Eigen::MatrixXd::Zero(12, 1)});
  cases[3].fields.cell_data.push_back({"s", Eigen::MatrixXd::Zero(12, 1)});
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    try {
      writeTetMesh(dir.path("bad.vtu"), mesh, c.fields);
      ADD_FAILURE() << "no exception";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(c.message), std::string::npos) << e.what();
    }
    EXPECT_FALSE(fs::exists(dir.path("bad.vtu"))) << "nothing is written when a field is bad";
  }
}

TEST(MeshIo, FieldsAreRejectedForFormatsThatCannotHoldThem) {
  const TetMesh mesh = twoCubeMesh();
  MeshFields fields;
  fields.cell_data.push_back({"von_mises", Eigen::VectorXd::Zero(mesh.numTets())});
  TempDir dir("breast_sim_mesh_io");
  for (const std::string file : {"f.msh", "f.inp", "f.node"}) {
    SCOPED_TRACE(file);
    EXPECT_THROW(writeTetMesh(dir.path(file), mesh, fields), std::invalid_argument);
  }
}

TEST(MeshIo, HandWrittenMsh41AsciiWithTagGapsAndMixedElementsIsRead) {
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("hand41.msh"), kMsh41Ascii);
  const TetMesh m = readTetMesh(dir.path("hand41.msh"));
  EXPECT_EQ(m.nodes(), handWrittenNodes());  // file order of the tags 10, 20, 30, 40, 55
  expectHandWrittenTets(m);                   // sorted by element tag 3, 4, 9
  // Volume 1 has physical tag 29; volume 2 has none, so its entity tag 2 is the label.
  EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 29, 2}));
  // The named surface group "skin" (the triangle 20 30 40) is a node set; the point is skipped.
  ASSERT_TRUE(m.hasNodeSet("skin"));
  EXPECT_EQ(m.nodeSet("skin"), (std::vector<int>{1, 2, 3}));
  EXPECT_EQ(m.nodeSets().size(), 1u);
}

TEST(MeshIo, HandWrittenMsh22AsciiWithTagGapsAndMixedElementsIsRead) {
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("hand22.msh"), kMsh22Ascii);
  const TetMesh m = readTetMesh(dir.path("hand22.msh"));
  EXPECT_EQ(m.nodes(), handWrittenNodes());
  expectHandWrittenTets(m);
  // Element 9 has physical tag 0 (no physical group), so its elementary tag 2 is the label.
  EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 29, 2}));
  EXPECT_EQ(m.nodeSet("skin"), (std::vector<int>{1, 2, 3}));
}

TEST(MeshIo, HandWrittenAbaqusInpIsRead) {
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("hand.inp"), R"(** hand-written deck, lengths in mm
*Heading
 three tets; this line is free text, 1, 2, 3
*Node, nset=ALLNODES
1, 0.0, 0.0, 0.0
2, 1.0, 0.0, 0.0
5, 0.0, 1.0, 0.0
7, 0.0, 0.0, 1.0
9, 1.0, 1.0, -0.5
*element, type=S3, elset=SKIN_TRIS
100, 2, 5, 7
*ELEMENT, TYPE=C3D4, ELSET=REGION_29
3, 1, 2, 5, 7
** an element over two lines, in a set without digits (numbered after REGION_29)
*Element, Type=c3d4, Elset=Fat
4, 1, 2,
   5, 9
*ELEMENT, TYPE=C3D4
8, 2, 5, 9, 7
*ELSET, ELSET=Deep
8, 100
*NSET, NSET=chest_wall
1, 2
*Nset, nset=skin, generate
5, 9, 2
*NSET, NSET=both
chest_wall, 9
*MATERIAL, NAME=fat
*ELASTIC
3000., 0.49
)");
  const TetMesh m = readTetMesh(dir.path("hand.inp"), 1e-3);
  EXPECT_TRUE(m.nodes().isApprox(handWrittenNodes() * 1e-3, 1e-15));
  expectHandWrittenTets(m);
  // REGION_29 keeps 29; Fat and Deep, without a number, follow it in order of appearance.
  EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 30, 31}));
  EXPECT_EQ(m.nodeSet("ALLNODES"), (std::vector<int>{0, 1, 2, 3, 4}));
  EXPECT_EQ(m.nodeSet("chest_wall"), (std::vector<int>{0, 1}));
  EXPECT_EQ(m.nodeSet("skin"), (std::vector<int>{2, 3, 4}));
  EXPECT_EQ(m.nodeSet("both"), (std::vector<int>{0, 1, 4}));
}

TEST(MeshIo, AbaqusNamedAndNumberedSetsNeverShareALabel) {
  const std::string nodes = "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n5, 0.5, 0.5, -1\n";
  struct Case {
    std::string name;
    std::string elements;
    std::vector<int> labels;
  };
  const std::vector<Case> cases = {
      // FAT used to get rank 1, the label REGION_1 has.
      {"named set before a numbered one",
       "*ELEMENT, TYPE=C3D4, ELSET=FAT\n1, 1, 2, 3, 4\n*ELEMENT, TYPE=C3D4, ELSET=REGION_1\n2, 1, 2, 3, 5\n",
       {2, 1}},
      {"named *ELSET after numbered blocks",
       "*ELEMENT, TYPE=C3D4, ELSET=REGION_2\n1, 1, 2, 3, 4\n*ELEMENT, TYPE=C3D4\n2, 1, 2, 3, 5\n"
       "*ELSET, ELSET=GLAND\n2\n",
       {2, 3}},
      {"named sets alone are ranked from 1",
       "*ELEMENT, TYPE=C3D4, ELSET=FAT\n1, 1, 2, 3, 4\n*ELEMENT, TYPE=C3D4, ELSET=DEEP\n2, 1, 2, 3, 5\n",
       {1, 2}},
      {"a negative number does not lower the ranks",
       "*ELEMENT, TYPE=C3D4, ELSET=R_-2\n1, 1, 2, 3, 4\n*ELEMENT, TYPE=C3D4, ELSET=FAT\n2, 1, 2, 3, 5\n",
       {-2, 1}},
  };
  TempDir dir("breast_sim_mesh_io");
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    writeText(dir.path("sets.inp"), nodes + c.elements);
    EXPECT_EQ(readTetMesh(dir.path("sets.inp")).regionLabels(), c.labels);
  }
}

TEST(MeshIo, HandWrittenTetGenPairIsReadFromEitherPath) {
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("hand.node"), R"(# 0-based points, one attribute, boundary markers
5 3 1 1
0 0 0 0   7 1
1 1 0 0   7 1  # inline comment

2 0 1 0   7 0
3 0 0 1   7 0
4 1 1 -0.5   7 1
)");
  writeText(dir.path("hand.ele"), R"(3 4 1
# region attribute as TetGen writes it
0 0 1 2 3 29
1 0 1 2 4 2.9e1
2 1 2 4 3 -7
)");
  for (const std::string file : {"hand.node", "hand.ele"}) {
    SCOPED_TRACE(file);
    const TetMesh m = readTetMesh(dir.path(file));
    EXPECT_EQ(m.nodes(), handWrittenNodes());
    expectHandWrittenTets(m);
    EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 29, -7}));
  }
}

TEST(MeshIo, VtkFilesFromOtherToolsGiveTetsAndLabelsAndSkipOtherCells) {
  TempDir dir("breast_sim_mesh_io");
  // As meshio writes a Gmsh mesh: labels in "gmsh:physical", a triangle cell among the tetrahedra.
  writeText(dir.path("other.vtu"), R"(<?xml version="1.0"?>
<VTKFile type="UnstructuredGrid" version="0.1" byte_order="LittleEndian">
  <UnstructuredGrid>
    <Piece NumberOfPoints="5" NumberOfCells="4">
      <Points>
        <DataArray type="Float64" NumberOfComponents="3" format="ascii">
          0 0 0  1 0 0  0 1 0  0 0 1  1 1 -0.5
        </DataArray>
      </Points>
      <Cells>
        <DataArray type="Int64" Name="connectivity" format="ascii">1 2 3  0 1 2 3  0 1 2 4  1 2 4 3</DataArray>
        <DataArray type="Int64" Name="offsets" format="ascii">3 7 11 15</DataArray>
        <DataArray type="UInt8" Name="types" format="ascii">5 10 10 10</DataArray>
      </Cells>
      <CellData>
        <DataArray type="Int32" Name="gmsh:physical" format="ascii">5 29 29 2</DataArray>
      </CellData>
    </Piece>
  </UnstructuredGrid>
</VTKFile>
)");
  writeText(dir.path("other.vtk"), R"(# vtk DataFile Version 4.2
hand-written
ASCII
DATASET UNSTRUCTURED_GRID
POINTS 5 double
0 0 0 1 0 0 0 1 0 0 0 1 1 1 -0.5
CELLS 4 19
3 1 2 3
4 0 1 2 3
4 0 1 2 4
4 1 2 4 3
CELL_TYPES 4
5
10
10
10
CELL_DATA 4
SCALARS label int 1
LOOKUP_TABLE default
5 29 29 2
POINT_DATA 5
SCALARS nodeset_skin int 1
LOOKUP_TABLE default
0 1 1 1 0
)");
  for (const std::string file : {"other.vtu", "other.vtk"}) {
    SCOPED_TRACE(file);
    const TetMesh m = readTetMesh(dir.path(file));
    EXPECT_EQ(m.nodes(), handWrittenNodes());
    expectHandWrittenTets(m);
    EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 29, 2}));
  }
  EXPECT_EQ(readTetMesh(dir.path("other.vtk")).nodeSet("skin"), (std::vector<int>{1, 2, 3}));
}

TEST(MeshIo, NegativelyOrientedTetsInAFileComeBackPositive) {
  // Every writer writes the mesh's positive order, so put a negative tet into each format by hand.
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("neg.msh"), "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n1 0 0 0\n2 1 0 0\n"
                                 "3 0 1 0\n4 0 0 1\n$EndNodes\n$Elements\n1\n1 4 2 3 3 1 3 2 4\n$EndElements\n");
  writeText(dir.path("neg.inp"), "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n"
                                 "*ELEMENT, TYPE=C3D4, ELSET=R3\n1, 1, 3, 2, 4\n");
  writeText(dir.path("neg.node"), "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n");
  writeText(dir.path("neg.ele"), "1 4 1\n1 1 3 2 4 3\n");
  for (const std::string file : {"neg.msh", "neg.inp", "neg.ele"}) {
    SCOPED_TRACE(file);
    const TetMesh m = readTetMesh(dir.path(file));
    EXPECT_EQ(row(m, 0), (std::vector<int>{0, 2, 3, 1}));  // (1 3 2 4) with its last two swapped
    expectAllPositive(m);
    EXPECT_NEAR(m.volume(), 1.0 / 6.0, 1e-15);
    EXPECT_EQ(m.regionLabels(), std::vector<int>{3});
  }
}

TEST(MeshIo, MalformedFilesNameTheFileAndThePlace) {
  TempDir dir("breast_sim_mesh_io");
  const std::string nodes3 = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n3\n1 0 0 0\n2 1 0 0\n3 0 1 0\n$EndNodes\n";
  const std::string nodes4 = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n$EndNodes\n";
  // Binary files cut in the middle of their node data.
  const TetMesh mesh = twoCubeMesh();
  MeshWriteOptions b22, b41;
  b22.gmsh = {GmshVersion::kMsh22, true};
  b41.gmsh = {GmshVersion::kMsh41, true};
  writeTetMesh(dir.path("full22.msh"), mesh, {}, 1.0, b22);
  writeTetMesh(dir.path("full41.msh"), mesh, {}, 1.0, b41);
  const std::string full22 = readBytes(dir.path("full22.msh"));
  const std::string full41 = readBytes(dir.path("full41.msh"));

  const std::vector<BadFile> cases = {
      {"no_elements.msh", nodes3, ":9:", "without an $Elements section"},
      {"mesh.msh", nodes3 + "$Elements\n1\n7 4 2 1 1 1 2 3\n$EndElements\n", ":12:",
       "expected 4 node indices for element 7, got 3"},
      {"bad_number.msh", "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n1\n1 0 0.5abc 0\n$EndNodes\n", ":6:",
       "got '0.5abc'"},
      {"out_of_range.msh", nodes4 + "$Elements\n1\n1 4 2 1 1 1 2 3 99\n$EndElements\n", ":13:",
       "element 1 refers to node 99, which is not in $Nodes"},
      {"count.msh", nodes4 + "$Elements\n2\n1 4 2 1 1 1 2 3 4\n$EndElements\n", ":14:",
       "expected an element number, type and tag count, got 1 values"},
      {"v40.msh", "$MeshFormat\n4 0 8\n$EndMeshFormat\n", ":2:", "MSH 4.0 is not supported"},
      {"truncated22.msh", full22.substr(0, 200), ":6:", "header says 12 nodes but the file can hold at most 5"},
      {"truncated41.msh", full41.substr(0, full41.find("$EndNodes") - 40), ": byte ", "truncated"},
      {"node.inp", "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n*ELEMENT, TYPE=C3D4\n\n1, 1, 2, 3, 5\n",
       ":8:", "element 1 refers to node 5"},
      {"number.inp", "** comment\n*NODE\n1, 0, zero, 0\n", ":3:", "got 'zero'"},
      {"short.inp", "*NODE\n1, 0, 0, 0\n*ELEMENT, TYPE=C3D4, ELSET=A\n1, 1, 1\n", ":4:",
       "expected 4 node indices for C3D4 element 1, got 2"},
      {"include.inp", "*INCLUDE, INPUT=nodes.inp\n", ":1:", "*INCLUDE is not supported"},
      {"range.ele", "1 4 0\n1 1 2 3 9\n", ":2:", "tetrahedron 1 refers to node 9"},
      {"few.ele", "2 4 0\n1 1 2 3 4\n# the second tetrahedron is missing\n", ":3:", "after 1 of 2 tetrahedra"},
      {"word.ele", "1 4 0\n1 1 2 x 4\n", ":2:", "expected a node index, got 'x'"},
      {"mesh.stl", "solid\n", "mesh.stl", "unknown mesh file extension '.stl'"},
      {"garbage.vtu", "not xml at all\n", "garbage.vtu", "not a VTK XML unstructured grid"},
  };
  writeText(dir.path("range.node"), "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n");
  writeText(dir.path("few.node"), "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n");
  writeText(dir.path("word.node"), "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n");
  expectRefused(dir, cases);
  // The example from the issue, word for word.
  try {
    readTetMesh(dir.path("mesh.msh"));
    ADD_FAILURE() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), dir.path("mesh.msh") + ":12: expected 4 node indices for element 7, got 3");
  }
  // A missing file names itself too (both halves of a TetGen pair are needed).
  for (const std::string file : {"missing.msh", "missing.inp", "missing.vtu", "few_missing.ele"}) {
    SCOPED_TRACE(file);
    try {
      readTetMesh(dir.path(file));
      ADD_FAILURE() << "no exception";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find("missing."), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("cannot open"), std::string::npos) << e.what();
    }
  }
}

// Counts from a header used to size reservations: "$Nodes 2000000000" in a tiny file gave a bare
// std::bad_alloc without the path.
TEST(MeshIo, HeaderCountsTheFileCannotHoldAreErrorsNamingThePlace) {
  TempDir dir("breast_sim_mesh_io");
  const std::string head22 = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n";
  const std::string head41 = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n";
  const std::string nodes4 = head22 + "$Nodes\n4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n$EndNodes\n";
  // Binary MSH 4.1 with the node or element total (the second uint64 after the section name)
  // raised to 2·10⁹.
  MeshWriteOptions b41;
  b41.gmsh = {GmshVersion::kMsh41, true};
  writeTetMesh(dir.path("full41.msh"), twoCubeMesh(), {}, 1.0, b41);
  const std::string full41 = readBytes(dir.path("full41.msh"));
  const auto withTotal = [&](const std::string& section, std::size_t& at) {
    at = full41.find(section + "\n") + section.size() + 1 + 8;
    std::string bytes = full41;
    const std::uint64_t total = 2000000000;
    std::memcpy(&bytes[at], &total, sizeof total);
    return bytes;
  };
  std::size_t nodes_at = 0, elements_at = 0;
  const std::string huge_nodes41 = withTotal("$Nodes", nodes_at);
  const std::string huge_elements41 = withTotal("$Elements", elements_at);

  const std::vector<BadFile> cases = {
      {"nodes22.msh", head22 + "$Nodes\n2000000000\n1 0 0 0\n$EndNodes\n", ":5:",
       "header says 2000000000 nodes but the file can hold at most 2 (19 bytes follow, each needs at least 8)"},
      {"elements22.msh", nodes4 + "$Elements\n2000000000\n1 4 0 1 2 3 4\n$EndElements\n", ":12:",
       "header says 2000000000 elements but the file can hold at most"},
      {"binary22.msh", "$MeshFormat\n2.2 1 8\n" + std::string("\1\0\0\0\n", 5) +
                           "$EndMeshFormat\n$Nodes\n2000000000\n" + std::string(28, '\0') + "\n$EndNodes\n",
       ":6:", "header says 2000000000 nodes but the file can hold at most 1"},
      {"nodes41.msh", head41 + "$Nodes\n1 2000000000 1 2000000000\n0 1 0 1\n1\n0 0 0\n$EndNodes\n", ":5:",
       "header says 2000000000 nodes but the file can hold at most"},
      {"elements41.msh", head41 +
           "$Nodes\n1 1 1 1\n0 1 0 1\n1\n0 0 0\n$EndNodes\n$Elements\n1 2000000000 1 2000000000\n"
           "0 1 15 1\n1 1\n$EndElements\n",
       ":11:", "header says 2000000000 elements but the file can hold at most"},
      {"entities41.msh", head41 + "$Entities\n0 0 0 1\n1 0 0 0 1 1 1 2000000000\n$EndEntities\n", ":6:",
       "header says 2000000000 physical tags but the file can hold at most"},
      {"binary_nodes41.msh", huge_nodes41, ": byte " + std::to_string(nodes_at) + ":",
       "header says 2000000000 nodes but the file can hold at most"},
      {"binary_elements41.msh", huge_elements41, ": byte " + std::to_string(elements_at) + ":",
       "header says 2000000000 elements but the file can hold at most"},
      {"huge.node", "# comment\n2000000000 3 0 0\n1 0 0 0\n", ":2:",
       "header says 2000000000 points but the file can hold at most 1 (8 bytes follow, each needs at least 8)"},
      {"bad_count.ele", "2000000000 4 0\n1 1 2 3 4\n", ":1:",
       "header says 2000000000 tetrahedra but the file can hold at most 1"},
  };
  writeText(dir.path("bad_count.node"), "4 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n");
  expectRefused(dir, cases);
}

// Counts, tags and ids a file merely claims: each is checked before it sizes anything or becomes a
// label, and refused with the file and the place (found by the fuzz targets, fuzz/).
TEST(MeshIo, ClaimedCountsTagsAndIdsAreRefusedNamingThePlace) {
  TempDir dir("breast_sim_mesh_io");
  const std::string nodes4 = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n$EndNodes\n";
  const std::string inp_nodes = "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n";
  const auto vtu = [](const std::string& piece, const std::string& points, const std::string& connectivity,
                      const std::string& offsets) {
    return "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
           "<UnstructuredGrid>\n<Piece " + piece + ">\n<Points>\n"
           "<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">" + points + "</DataArray>\n</Points>\n"
           "<Cells>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">" + connectivity + "</DataArray>\n"
           "<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">" + offsets + "</DataArray>\n"
           "<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">10</DataArray>\n</Cells>\n</Piece>\n"
           "</UnstructuredGrid>\n</VTKFile>\n";
  };
  const std::string points4 = "0 0 0 1 0 0 0 1 0 0 0 1";
  const std::string legacy = "# vtk DataFile Version 4.2\nhand-written\nASCII\nDATASET UNSTRUCTURED_GRID\n";
  const std::string legacy_points = legacy + "POINTS 4 double\n0 0 0 1 0 0 0 1 0 0 0 1\n";
  const std::vector<BadFile> cases = {
      // 3 + ntags overflowed (undefined behaviour).
      {"ntags.msh", nodes4 + "$Elements\n1\n1 4 9223372036854775807 1 2 3 4\n$EndElements\n", ":13:",
       "element 1 announces 9223372036854775807 tags but the line has 4 values after them"},
      // Cut to an int: 2^32 became label 0.
      {"tag.msh", nodes4 + "$Elements\n1\n1 4 2 4294967296 1 1 2 3 4\n$EndElements\n", ":13:",
       "region tag of element 1 is 4294967296, which does not fit a 32-bit integer"},
      {"physical.msh", "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$PhysicalNames\n1\n2 4294967297 \"skin\"\n$EndPhysicalNames\n",
       ":6:", "physical tag is 4294967297, which does not fit a 32-bit integer"},
      // 10^8 numbers (1.6 GB of set entries) were generated from one line.
      {"generate.inp", inp_nodes + "*NSET, NSET=ALL, GENERATE\n1, 100000000, 1\n", ":9:",
       "GENERATE range 1, 100000000, 1 names 100000000 nodes, more than the file's 9 lines can define"},
      // last − first overflowed a long long.
      {"generate_span.inp", inp_nodes + "*ELSET, ELSET=ALL, GENERATE\n-9223372036854775808, 9223372036854775807\n",
       ":9:", "names 2^64 elements, more than the file's 9 lines can define"},
      {"generate_step.inp", inp_nodes + "*NSET, NSET=ALL, GENERATE\n1, 4, 0\n", ":9:",
       "bad GENERATE range 1, 4, 0: expected first <= last and an increment >= 1"},
      // A VTU point id beyond int was cut to a valid one (2^32 → 0).
      {"id.vtu", vtu("NumberOfPoints=\"4\" NumberOfCells=\"1\"", points4, "4294967296 1 2 3", "4"), ":9:",
       "connectivity entry 0 is point 4294967296, but the piece has 4 points"},
      // Counts VTK allocated before reading any data.
      {"points.vtu", vtu("NumberOfPoints=\"3000000000\" NumberOfCells=\"1\"", points4, "0 1 2 3", "4"), ":4:",
       "<Piece> NumberOfPoints is '3000000000'; expected 0 to 2147483647"},
      {"claim.vtu", vtu("NumberOfPoints=\"2000000000\" NumberOfCells=\"1\"", points4, "0 1 2 3", "4"), ":6:",
       "the DataArray should hold 6000000000 values, but its 23 characters hold at most 12"},
      {"offsets.vtu", vtu("NumberOfPoints=\"4\" NumberOfCells=\"1\"", points4, "0 1 2 3", "9"), ":10:",
       "the last cell offset is 9 but the connectivity holds 4 ids"},
      {"legacy_points.vtk", legacy + "POINTS 2000000000 float\n0 0 0\n", ":5:",
       "header says 6000000000 point coordinates but the file can hold at most"},
      // Cells that overrun their data, or a cell section without types, crashed VTK 9.1's reader.
      {"legacy_cells.vtk", legacy_points + "CELLS 2 6\n4 0 1 2 3\n9\nCELL_TYPES 2\n10\n10\n", ":7:",
       "cell 1 has 9 points, more than the 0 values left in CELLS"},
      {"legacy_types.vtk", legacy_points + "CELLS 1 5\n4 0 1 2 3\n", ":7:", "CELLS without CELL_TYPES"},
      {"legacy_type_count.vtk", legacy_points + "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 3\n10 10 10\n", ":9:",
       "CELL_TYPES 3 for 1 cells"},
      {"legacy_point_data.vtk",
       legacy_points + "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n10\nPOINT_DATA 7\nSCALARS s float\nLOOKUP_TABLE default\n1 2 3 4\n",
       ":11:", "POINT_DATA 7 for 4 points"},
      {"legacy_id.vtk", legacy_points + "CELLS 1 5\n4 0 1 2 4294967296\nCELL_TYPES 1\n10\n", "legacy_id.vtk: ",
       "cell 0 refers to point 4294967296, but the file has 4 points"},
      {"legacy_binary.vtk", "# vtk DataFile Version 4.2\nx\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS 4 double\n" +
                                std::string(40, '\0'), ": byte ", "header says 12 point coordinates but the file can hold at most 5"},
  };
  expectRefused(dir, cases);
  // A folder named like a mesh file: its "size" was allocated.
  std::filesystem::create_directory(dir.path("folder.msh"));
  try {
    readTetMesh(dir.path("folder.msh"));
    ADD_FAILURE() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), dir.path("folder.msh") + ": is a folder, not a mesh file");
  }
}

// Sets that copy sets doubled with each copy ("S1 = S0, S0", "S2 = S1, S1", …): 2^60 entries. Merged,
// each holds its distinct numbers.
TEST(MeshIo, AbaqusSetsCopyingSetsStayTheirDistinctNumbers) {
  std::string deck = "*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 0, 1, 0\n4, 0, 0, 1\n*ELEMENT, TYPE=C3D4, ELSET=E0\n1, 1, 2, 3, 4\n"
                     "*NSET, NSET=S0\n1, 2, 3, 4\n";
  for (int k = 1; k <= 60; ++k) {
    deck += "*NSET, NSET=S" + std::to_string(k) + "\nS" + std::to_string(k - 1) + ", S" + std::to_string(k - 1) + "\n";
    deck += "*ELSET, ELSET=E" + std::to_string(k) + "\nE" + std::to_string(k - 1) + ", E" + std::to_string(k - 1) + "\n";
  }
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("copies.inp"), deck);
  const TetMesh m = readTetMesh(dir.path("copies.inp"));
  EXPECT_EQ(m.nodeSet("S60"), (std::vector<int>{0, 1, 2, 3}));
  EXPECT_EQ(m.regionLabels(), std::vector<int>{0});  // E0 ends in 0: label 0
}

// VTK's own writers in every variant (test/data/vtk_variants, make_vtk_variants.py): legacy 4.2 and
// 5.1, ASCII and binary; XML ascii, inline and appended, raw and base64, uncompressed, zlib, LZ4 and
// LZMA, 32- and 64-bit headers. Each reads to the same mesh and fields.
TEST(MeshIo, VtkFilesOfEveryWriterVariantReadTheSame) {
  const std::string folder = std::string(BREAST_SIM_TEST_DATA_DIR) + "/vtk_variants";
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(folder)) {
    const std::string ext = entry.path().extension().string();
    if (ext != ".vtk" && ext != ".vtu") continue;
    SCOPED_TRACE(entry.path().filename().string());
    ++files;
    MeshFields fields;
    const TetMesh m = readVtkUnstructured(entry.path().string(), 1.0, &fields);
    EXPECT_EQ(m.nodes(), handWrittenNodes());
    expectHandWrittenTets(m);
    EXPECT_EQ(m.regionLabels(), (std::vector<int>{29, 29, 2}));
    EXPECT_EQ(m.nodeSet("skin"), (std::vector<int>{1, 2, 3}));
    std::map<std::string, Eigen::MatrixXd> point;
    for (const MeshField& f : fields.point_data) point[f.name] = f.values;
    ASSERT_EQ(point.size(), 5u);  // the string array is not a field
    EXPECT_EQ(point["temperature"].col(0).transpose(), Eigen::RowVectorXd((Eigen::RowVectorXd(5) << 1, -2, 3, -4, 5).finished()));
    EXPECT_EQ(point["displacement_mm"].row(3), Eigen::RowVector3d(3, -3, 1.5));
    EXPECT_EQ(point["ids"](4, 0), 14.0);
    EXPECT_EQ(point["flags"].col(0).transpose(), Eigen::RowVectorXd((Eigen::RowVectorXd(5) << 1, 0, 1, 1, 0).finished()));
    EXPECT_EQ(point["big"](4, 0), 1099511627776.0);
    ASSERT_EQ(fields.cell_data.size(), 1u);
    EXPECT_EQ(fields.cell_data[0].name, "von_mises_pa");
    // Cells 1…3 (the tetrahedra; cell 0 is the skipped triangle): (1, 10), (2, 20), (3, 30).
    EXPECT_EQ(fields.cell_data[0].values.row(2), Eigen::RowVector2d(3, 30));
  }
  EXPECT_EQ(files, 11);
}

// liblzma allocates the dictionary an xz header declares (up to 1.5 GiB, 4 GiB claimed), and VTK's
// LZMA decompressor sets no memory limit: a block whose header claims more than 64 MiB is refused
// before it is decompressed.
TEST(MeshIo, VtuLzmaBlockDeclaringAHugeDictionaryIsRefused) {
  // The five hand-written points as one LZMA block, as VTK's vtkLZMADataCompressor writes it.
  const std::string xz(
      "\xfd\x37\x7a\x58\x5a\x00\x00\x01\x69\x22\xde\x36\x02\xc0\x17\x78\x21\x01\x16\x00\x09\xc9\xbf\x39\xe0\x00"
      "\x77\x00\x0f\x5d\x00\x00\x6e\x15\x37\xc4\x19\x21\xd8\x27\xb5\xa6\x06\xa6\x90\x00\x00\x00\x23\xe5\x1f\x6b"
      "\x00\x01\x27\x78\x40\xfe\x9d\xa4\x90\x42\x99\x0d\x01\x00\x00\x00\x00\x01\x59\x5a",
      72);
  const auto file = [](const std::string& block) {
    std::string header;
    for (const std::uint32_t v : {1u, 120u, 120u, static_cast<std::uint32_t>(block.size())}) {
      header.append(reinterpret_cast<const char*>(&v), 4);
    }
    return "<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\" header_type=\"UInt32\" "
           "compressor=\"vtkLZMADataCompressor\">\n<UnstructuredGrid>\n<Piece NumberOfPoints=\"5\" NumberOfCells=\"3\">\n"
           "<Points><DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points>\n"
           "<Cells>\n<DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">0 1 2 3 0 1 2 4 1 2 4 3</DataArray>\n"
           "<DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">4 8 12</DataArray>\n"
           "<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">10 10 10</DataArray>\n</Cells>\n</Piece>\n"
           "</UnstructuredGrid>\n<AppendedData encoding=\"raw\">\n_" + header + block + "\n</AppendedData>\n</VTKFile>\n";
  };
  TempDir dir("breast_sim_mesh_io");
  writeText(dir.path("lzma.vtu"), file(xz));
  EXPECT_EQ(readTetMesh(dir.path("lzma.vtu")).nodes(), handWrittenNodes());
  std::string huge = xz;
  huge[18] = '\x27';  // dictionary code 39: 3 GiB
  writeText(dir.path("huge.vtu"), file(huge));
  try {
    readTetMesh(dir.path("huge.vtu"));
    ADD_FAILURE() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("LZMA block 0 of the DataArray is refused: it declares an LZMA2 dictionary of "
                                         "3072 MiB, more than the 64 MiB allowed"),
              std::string::npos)
        << e.what();
  }
}

TEST(MeshIo, FormatIsChosenByCaseInsensitiveExtension) {
  EXPECT_EQ(meshFileFormat("a/b.MSH"), MeshFileFormat::kGmsh);
  EXPECT_EQ(meshFileFormat("b.Vtu"), MeshFileFormat::kVtu);
  EXPECT_EQ(meshFileFormat("b.vtk"), MeshFileFormat::kVtkLegacy);
  EXPECT_EQ(meshFileFormat("b.1.node"), MeshFileFormat::kTetGen);
  EXPECT_EQ(meshFileFormat("b.ele"), MeshFileFormat::kTetGen);
  EXPECT_EQ(meshFileFormat("b.INP"), MeshFileFormat::kAbaqusInp);
  EXPECT_THROW(meshFileFormat("dir.msh/mesh"), std::runtime_error);
}

// Read/write speed is measured by bench_mesh_io, not asserted here (timings are noisy).
TEST(MeshIo, LargeMeshRoundTripsInEveryFormat) {
  // 37³ cubes × 6 = 303,918 tets on 54,872 nodes.
  const int n = 37, m = n + 1;
  Points x(m * m * m, 3);
  for (int i = 0; i < m * m * m; ++i) x.row(i) << 1e-3 * (i % m), 1e-3 * ((i / m) % m), 1e-3 * (i / (m * m));
  const int t[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
  Tets tets(6 * n * n * n, 4);
  std::vector<int> labels(tets.rows());
  int e = 0;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        const int c0 = i + m * (j + m * k);
        const int c[8] = {c0, c0 + 1, c0 + m, c0 + m + 1, c0 + m * m, c0 + m * m + 1, c0 + m * m + m, c0 + m * m + m + 1};
        for (const auto& tet : t) {
          tets.row(e) << c[tet[0]], c[tet[1]], c[tet[2]], c[tet[3]];
          labels[e++] = 1 + (i * 3) / n;
        }
      }
  const TetMesh mesh(x, tets, labels);
  TempDir dir("breast_sim_mesh_io");
  MeshWriteOptions msh41b;
  msh41b.gmsh = {GmshVersion::kMsh41, true};
  const std::vector<std::pair<std::string, MeshWriteOptions>> cases = {
      {"big22.msh", {}}, {"big41b.msh", msh41b}, {"big.inp", {}}, {"big.node", {}}, {"big.vtu", {}}};
  for (const auto& [file, options] : cases) {
    SCOPED_TRACE(file);
    writeTetMesh(dir.path(file), mesh, {}, 1e-3, options);
    const TetMesh back = readTetMesh(dir.path(file), 1e-3);
    ASSERT_EQ(back.numTets(), mesh.numTets());
    ASSERT_EQ(back.numNodes(), mesh.numNodes());
    EXPECT_LT((back.nodes() - mesh.nodes()).cwiseAbs().maxCoeff(), 1e-12);
    EXPECT_EQ(back.regionLabels(), mesh.regionLabels());
  }
}
