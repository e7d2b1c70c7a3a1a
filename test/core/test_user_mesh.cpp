// A user's own mesh as a case (`mesh:`, model/user_mesh.h): read from .inp, .vtu, .vtk (node sets
// and all) and Gmsh (the shipped case) files,
// checked with clear errors, voxelized so that the chest-wall field and the multigrid work on it,
// and run through the pipeline with the same result as the image case it was written from.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <string>

#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/model/user_mesh.h"
#include "breast_sim/core/pipeline/case_file.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/sliding/chest_wall_surface.h"
#include "pipeline_fixtures.h"
#include "temp_dir.h"

namespace breast_sim::core {
namespace {

using test_fixtures::kConfigDir;
using test_fixtures::phantom;

const std::string kMeshCase = kConfigDir + "mesh_case.yaml";

std::string errorOf(const std::string& case_path) {
  try {
    loadModelCase(case_path);
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "no error";
}

/// A case file for `mesh_file` (in the same folder) with the phantom's gravity direction and nipple.
std::string caseText(const std::string& mesh_file, const std::string& units, const std::string& extra = "") {
  return "mesh:\n  path: " + mesh_file + "\n  units: " + units +
         "\n  regions: {fat: [1], fibroglandular: [2], skin: [3], lesion: [4]}\n"
         "  skin: skin\n  nipple: nipple\n  prone_gravity_direction: [0, -1, 0]\n" + extra +
         "lesions:\n  - {name: L1, position_mm: [10, -25, 5], radius_mm: 3}\n";
}

/// The small phantom's model written to an .inp (mm) and read back as a mesh case, beside its image
/// twin: the same case and model as if from an image (no phantom, so the same supine gravity), with
/// the mesh case's lesion embedded alike.
struct PhantomAsMeshCase {
  test::TempDir dir{"breast_sim_user_mesh_case"};
  ModelCase c, image_case;
  SimulationModel m, image_model;
  PhantomAsMeshCase() {
    const test_fixtures::SmallPhantom& p = phantom();
    writeTetMesh(dir.path("model.inp"), p.m.mesh, {}, 1e-3);
    c = loadModelCase(dir.write("case.yaml", caseText("model.inp", "mm")));
    m = buildSimulationModel(c);
    image_case = p.c;
    image_case.phantom.reset();
    image_case.lesions = c.lesions;
    image_model = p.m;
    image_model.lesions = c.lesions;
    image_model.lesion_embedding = m.lesion_embedding;
  }
};

// The box [0, 40]×[0, 20]×[0, 30] mm with its face y = 20 mm on the chest wall (outward normal +y):
// tissue inside, wall behind the face and past the box's sides, air in front.
TEST(UserMesh, TheLabelImagePutsTheWallBehindTheWallFacesAndPastTheRim) {
  TetMesh box = makeBoxMesh({8, 4, 6}, {0.04, 0.02, 0.03});
  std::vector<int> wall, skin;
  for (int v = 0; v < box.numNodes(); ++v) {
    const Eigen::Vector3d p = box.nodes().row(v).transpose();
    const bool on_boundary = p.minCoeff() < 1e-9 || p.x() > 0.04 - 1e-9 || p.y() > 0.02 - 1e-9 || p.z() > 0.03 - 1e-9;
    if (p.y() > 0.02 - 1e-9) wall.push_back(v);
    if (on_boundary && !(p.y() > 0.02 - 1e-9 && p.x() > 1e-9 && p.x() < 0.04 - 1e-9 && p.z() > 1e-9 && p.z() < 0.03 - 1e-9))
      skin.push_back(v);
  }
  box = TetMesh(box.nodes(), box.tets(), std::vector<int>(box.numTets(), 1));
  box.setNodeSet(node_sets::kChestWall, wall);
  box.setNodeSet(node_sets::kSkin, skin);
  const TissueLabels labels;
  const LabelImage image = voxelizeModel(box, labels, 1e-3, 10e-3);
  auto at = [&](double x_mm, double y_mm, double z_mm) {
    const Eigen::Vector3d p(x_mm * 1e-3, y_mm * 1e-3, z_mm * 1e-3);
    const Eigen::Vector3d idx = (p - image.origin_m) / 1e-3;
    return image.at(static_cast<int>(std::lround(idx.x())), static_cast<int>(std::lround(idx.y())),
                    static_cast<int>(std::lround(idx.z())));
  };
  EXPECT_EQ(at(20, 10, 15), 1);    // tissue
  EXPECT_EQ(at(20, 25, 15), 40);   // behind the wall face
  EXPECT_EQ(at(-5, 25, 15), 40);   // behind the wall's plane, past the rim
  EXPECT_EQ(at(20, 29, 35), 40);
  EXPECT_EQ(at(20, -5, 15), 0);    // in front of the skin
  EXPECT_EQ(at(-5, 10, 15), 0);    // beside the tissue, in front of the wall
  EXPECT_EQ(at(45, 15, 15), 0);

  // The chest-wall field's surface passes through the wall face: |h| ≤ half a voxel at its nodes.
  const ChestWallSurface surface(image, labels.chest_wall);
  double worst = 0.0;
  for (int v : wall) worst = std::max(worst, std::abs(surface.signedDistance(box.nodes().row(v).transpose())));
  EXPECT_LE(worst, 0.55e-3);  // half a voxel: voxel centres on the face are tissue
}

// Lesions from the mesh's lesion elements: the box with the slabs x < 10 mm and x > 30 mm labelled
// lesion has two, at the slabs' centres, each with the radius of the sphere of its volume.
TEST(UserMesh, EachPieceOfLesionElementsIsALesion) {
  const TetMesh box = makeBoxMesh({8, 4, 6}, {0.04, 0.02, 0.03});
  std::vector<int> labels(box.numTets(), static_cast<int>(TissueClass::kFat));
  for (int t = 0; t < box.numTets(); ++t) {
    double x = 0;
    for (int k = 0; k < 4; ++k) x += 0.25 * box.nodes()(box.tets()(t, k), 0);
    if (x < 0.01 || x > 0.03) labels[t] = static_cast<int>(TissueClass::kLesion);
  }
  std::vector<Lesion> lesions = lesionsOfRegions(TetMesh(box.nodes(), box.tets(), labels));
  ASSERT_EQ(lesions.size(), 2u);
  EXPECT_EQ(lesions[0].name, "L1");
  EXPECT_EQ(lesions[1].name, "L2");
  std::sort(lesions.begin(), lesions.end(), [](const Lesion& a, const Lesion& b) { return a.position_m.x() < b.position_m.x(); });
  const double radius = std::cbrt(3.0 * (0.01 * 0.02 * 0.03) / (4.0 * M_PI));
  EXPECT_LE((lesions[0].position_m - Eigen::Vector3d(0.005, 0.01, 0.015)).norm(), 1e-12);
  EXPECT_LE((lesions[1].position_m - Eigen::Vector3d(0.035, 0.01, 0.015)).norm(), 1e-12);
  for (const Lesion& l : lesions) EXPECT_NEAR(l.radius_m, radius, 1e-12);
  EXPECT_TRUE(lesionsOfRegions(box).empty());
}

TEST(UserMesh, TheShippedGmshCaseLoadsWithItsNodeSetsAndTissues) {
  const ModelCase c = loadModelCase(kMeshCase);
  ASSERT_TRUE(c.mesh);
  const SimulationModel m = buildSimulationModel(c);
  EXPECT_EQ(m.mesh.numTets(), 14132);
  EXPECT_EQ(c.mesh_report.components, 1);
  EXPECT_EQ(c.mesh_report.chest_wall_faces, 978);
  EXPECT_EQ(c.mesh_report.skin_faces, 1848);
  const auto& r = m.mesh.regionLabels();
  EXPECT_EQ(std::count(r.begin(), r.end(), static_cast<int>(TissueClass::kFat)), 12268);
  EXPECT_EQ(std::count(r.begin(), r.end(), static_cast<int>(TissueClass::kFibroglandular)), 1864);
  ASSERT_EQ(m.mesh.nodeSet(node_sets::kNipple).size(), 1u);
  EXPECT_GT(m.meshing.interior_size_m, 2e-3);
  EXPECT_LT(m.meshing.interior_size_m, 8e-3);
  // The mesh's volume and its voxels agree (1 mm voxels, 448 cm³; the flat wall of 122 cm² gains or
  // loses up to half a voxel layer, 1.4 %, with the grid's alignment).
  EXPECT_NEAR(m.meshing.voxel_volume_m3 / m.mesh.volume(), 1.0, 0.02);
  // The wall field passes within about half a voxel of every wall node; no skin node lies behind it.
  const ChestWallSurface surface(c.image, c.labels.chest_wall);
  double worst_wall = 0.0, deepest_skin = 0.0;
  for (int v : m.mesh.nodeSet(node_sets::kChestWall))
    worst_wall = std::max(worst_wall, std::abs(surface.signedDistance(m.mesh.nodes().row(v).transpose())));
  for (int v : m.mesh.nodeSet(node_sets::kSkin))
    deepest_skin = std::min(deepest_skin, surface.signedDistance(m.mesh.nodes().row(v).transpose()));
  std::printf("[ measure  ] wall nodes within %.3f mm of the field's surface, skin at most %.3f mm behind it\n",
              worst_wall * 1e3, -deepest_skin * 1e3);
  EXPECT_LE(worst_wall, 0.6e-3);
  EXPECT_GE(deepest_skin, -0.6e-3);
}

// The phantom's model written in a format is the same model read back as a mesh case, and the
// pipeline on it (CHOLMOD, wall fixed) settles where the image case settles.
TEST(UserMesh, APhantomModelWrittenOutIsTheSameCaseInEveryFormat) {
  const test_fixtures::SmallPhantom& p = phantom();
  const test::TempDir dir("breast_sim_user_mesh");
  PipelineSettings s;
  s.simulation.solver.kind = SolverSettings::Kind::kCholmod;
  s.simulation.sliding = false;
  s.morphing.enabled = false;
  ModelCase image_case = p.c;
  image_case.phantom.reset();  // the same supine gravity as a case without the phantom
  image_case.lesions = {Lesion{"L1", Eigen::Vector3d(10e-3, -25e-3, 5e-3), 3e-3}};
  SimulationModel image_model = p.m;
  image_model.lesions = image_case.lesions;
  Points lesion(1, 3);
  lesion.row(0) = image_case.lesions[0].position_m.transpose();
  image_model.lesion_embedding = PointEmbedding(p.m.mesh, lesion, {"L1"}, 2e-3);
  ProneToSupinePipeline reference(image_case, image_model, s);
  reference.runGravity();
  ASSERT_TRUE(reference.gravityReport().converged);

  for (const std::string file : {"model.inp", "model.vtu", "model.vtk", "model.msh", "model.node"}) {
    SCOPED_TRACE(file);
    const bool in_mm = file == "model.inp" || file == "model.msh";
    TetMesh written = p.m.mesh;
    writeTetMesh(dir.path(file), written, {}, in_mm ? 1e-3 : 1.0);
    std::string extra;
    if (file == "model.msh" || file == "model.node") {
      // The Gmsh and TetGen writers write no node sets (a Gmsh file's come from its physical groups,
      // as in the shipped case): the case must say that the wall's set is missing.
      const std::string why = errorOf(dir.write("case_msh.yaml", caseText(file, in_mm ? "mm" : "m")));
      EXPECT_NE(why.find("no node set 'chest_wall'"), std::string::npos) << why;
      continue;
    }
    const std::string case_path = dir.write("case.yaml", caseText(file, in_mm ? "mm" : "m"));
    SCOPED_TRACE(file);
    const ModelCase c = loadModelCase(case_path);
    const SimulationModel m = buildSimulationModel(c);
    ASSERT_EQ(m.mesh.numNodes(), p.m.mesh.numNodes());
    EXPECT_LE((m.mesh.nodes() - p.m.mesh.nodes()).cwiseAbs().maxCoeff(), 1e-12);
    EXPECT_EQ(m.mesh.tets(), p.m.mesh.tets());
    EXPECT_EQ(m.mesh.regionLabels(), p.m.mesh.regionLabels());
    EXPECT_EQ(m.mesh.nodeSet(node_sets::kChestWall), p.m.mesh.nodeSet(node_sets::kChestWall));
    EXPECT_EQ(m.mesh.nodeSet(node_sets::kSkin), p.m.mesh.nodeSet(node_sets::kSkin));
    EXPECT_EQ(m.mesh.nodeSet(node_sets::kNipple), p.m.mesh.nodeSet(node_sets::kNipple));
    ProneToSupinePipeline pipe(c, m, s);
    pipe.runGravity();
    ASSERT_TRUE(pipe.gravityReport().converged);
    EXPECT_LE((pipe.positions() - reference.positions()).cwiseAbs().maxCoeff(), 1e-9);
    EXPECT_LE((pipe.lesionPositions() - reference.lesionPositions()).norm(), 1e-9);
  }
}

// With sliding and the default (geometric multigrid) solver, both need the label image: the mesh
// case's own (voxelized) gives the image case's result within a millimetre (measured 0.31 mm, both
// from their unloaded shapes, the default of a case that is not the software phantom; 0.55 mm from
// the prone shape: within the stick/slip path's own spread).
TEST(UserMesh, SlidingAndTheMultigridRunOnTheMeshCasesOwnImage) {
  const PhantomAsMeshCase t;
  PipelineSettings s;
  s.morphing.enabled = false;
  ProneToSupinePipeline reference(t.image_case, t.image_model, s), pipe(t.c, t.m, s);
  reference.runGravity();
  pipe.runGravity();
  ASSERT_TRUE(pipe.gravityReport().converged);
  ASSERT_TRUE(pipe.slidingReport().converged);
  EXPECT_EQ(pipe.metrics().inverted_elements, 0);
  const double lesion_mm = 1e3 * (pipe.lesionPositions() - reference.lesionPositions()).norm();
  const double moved_mm = 1e3 * (reference.lesionPositions() - t.image_model.lesion_embedding.positions(t.image_model.mesh.nodes())).norm();
  const double nodes_mm = 1e3 * (pipe.positions() - reference.positions()).rowwise().norm().maxCoeff();
  std::printf("[ measure  ] mesh case vs image case with sliding: lesion %.3f mm apart (it moved %.1f mm), "
              "nodes at most %.3f mm; sliding %d vs %d steps\n",
              lesion_mm, moved_mm, nodes_mm, pipe.slidingReport().steps, reference.slidingReport().steps);
  EXPECT_GT(moved_mm, 2.0);
  EXPECT_LE(lesion_mm, 1.5);
}

TEST(UserMesh, BadMeshesAndCasesGetAClearError) {
  const test_fixtures::SmallPhantom& p = phantom();
  const test::TempDir dir("breast_sim_user_mesh_bad");
  writeTetMesh(dir.path("model.inp"), p.m.mesh, {}, 1e-3);
  auto expectError = [&](const std::string& text, const std::string& part) {
    const std::string why = errorOf(dir.write("bad.yaml", text));
    EXPECT_NE(why.find(part), std::string::npos) << "expected '" << part << "' in: " << why;
  };
  // The unit: missing, or wrong for the size.
  expectError("mesh: {path: model.inp}\n", "'mesh.units': missing");
  expectError(caseText("model.inp", "m"), "a breast spans 0.02 to 1 m: is mesh.units right?");
  expectError(caseText("model.inp", "cm"), "mesh.units");
  // Node sets: missing (the message lists the file's), holding interior nodes.
  expectError(caseText("model.inp", "mm", "  chest_wall: WALL\n"), "no node set 'WALL' (mesh.chest_wall); the file has");
  expectError(caseText("model.inp", "mm", "  chest_wall: WALL\n"), "chest_wall");
  // Regions: a label in no list; several labels without a map.
  expectError("mesh:\n  path: model.inp\n  units: mm\n  regions: {fat: [1, 2]}\n",
              "region label 4 (22 elements) is in none of mesh.regions' lists");
  expectError("mesh:\n  path: model.inp\n  units: mm\n", "say which tissue each is in mesh.regions");
  expectError("mesh:\n  path: model.inp\n  units: mm\n  regions: {fat: [1, 2], lesion: [2]}\n", "is in two lists");
  // Exactly one source.
  expectError("mesh: {path: model.inp, units: mm}\nimage: {path: x.nrrd}\n", "give exactly one of");
  expectError(caseText("missing.inp", "mm"), "missing.inp: cannot open for reading");
  expectError("mesh:\n  path: model.inp\n  units: mm\n  regions: {fat: []}\n", "'mesh.regions': lists no region label");
  expectError(caseText("model.inp", "mm", "  nipples_mm: [[0, -60, 0]]\n"), "give either nipples_mm or the node set mesh.nipple");
  expectError(caseText("model.inp", "mm", "  voxel_size_mm: 0\n"), "mesh.voxel_size_mm");
  // Without `lesions:` the mesh's lesion elements are the lesions: the phantom's two
  // (config/phantom_default.yaml), found within 1 mm and 0.5 mm of radius (measured at most 0.67 mm
  // and 0.24 mm).
  {
    const ModelCase own = loadModelCase(dir.write("own_lesions.yaml", "mesh:\n  path: model.inp\n  units: mm\n"
                                                  "  regions: {fat: [1], fibroglandular: [2], skin: [3], lesion: [4]}\n"));
    ASSERT_EQ(own.lesions.size(), 2u);
    const Lesion truth[2] = {{"lower_inner", Eigen::Vector3d(-15e-3, -20e-3, -20e-3), 3e-3},
                             {"upper_outer", Eigen::Vector3d(20e-3, -35e-3, 15e-3), 5e-3}};
    for (const Lesion& t : truth) {
      const auto found = std::find_if(own.lesions.begin(), own.lesions.end(),
                                      [&](const Lesion& l) { return (l.position_m - t.position_m).norm() <= 1e-3; });
      ASSERT_NE(found, own.lesions.end()) << t.name;
      EXPECT_NEAR(found->radius_m, t.radius_m, 0.5e-3) << t.name;
    }
    EXPECT_NO_THROW(buildSimulationModel(own));
  }
  // A label image above 2^26 voxels: the message gives the voxel size to choose.
  expectError(caseText("model.inp", "mm", "  voxel_size_mm: 0.1\n"), "choose mesh.voxel_size_mm ≥");

  // A node set with an interior node, a piece that floats free, unused nodes (dropped).
  TetMesh mesh = p.m.mesh;
  std::vector<bool> boundary(mesh.numNodes(), false);
  for (int v : mesh.boundary().nodes) boundary[v] = true;
  const int interior = static_cast<int>(std::find(boundary.begin(), boundary.end(), false) - boundary.begin());
  std::vector<int> wall = mesh.nodeSet(node_sets::kChestWall);
  wall.push_back(interior);
  mesh.setNodeSet("WALL_AND_INSIDE", wall);
  mesh.setNodeSet("ONE", {mesh.boundary().nodes.front()});
  mesh.setNodeSet("ALL", mesh.boundary().nodes);
  writeTetMesh(dir.path("inside.inp"), mesh, {}, 1e-3);
  expectError(caseText("inside.inp", "mm", "  chest_wall: ONE\n"), "node set 'ONE' covers no boundary face");
  expectError(caseText("inside.inp", "mm", "  chest_wall: ALL\n"), "every boundary face is on the chest wall");
  expectError(caseText("inside.inp", "mm", "  chest_wall: WALL_AND_INSIDE\n"), "1 of its");
  expectError(caseText("inside.inp", "mm", "  chest_wall: WALL_AND_INSIDE\n"), "are not on the mesh's boundary");

  const int n = mesh.numNodes();
  Points nodes(n + 5, 3);
  nodes.topRows(n) = mesh.nodes();
  const Eigen::RowVector3d far(0.3, 0.0, 0.0);
  nodes.row(n) = far;
  nodes.row(n + 1) = far + Eigen::RowVector3d(0.01, 0, 0);
  nodes.row(n + 2) = far + Eigen::RowVector3d(0, 0.01, 0);
  nodes.row(n + 3) = far + Eigen::RowVector3d(0, 0, 0.01);
  nodes.row(n + 4) = far + Eigen::RowVector3d(0.02, 0.02, 0.02);  // used by no tetrahedron
  Tets tets(mesh.numTets() + 1, 4);
  tets.topRows(mesh.numTets()) = mesh.tets();
  tets.row(mesh.numTets()) << n, n + 1, n + 2, n + 3;
  std::vector<int> labels = mesh.regionLabels();
  labels.push_back(1);
  TetMesh island(nodes, tets, labels);
  for (const auto& [name, set] : p.m.mesh.nodeSets()) island.setNodeSet(name, set);
  writeTetMesh(dir.path("island.inp"), island, {}, 1e-3);
  expectError(caseText("island.inp", "mm"), "a piece of 1 tetrahedra around (300, 0, 0) mm");
  expectError(caseText("island.inp", "mm"), "would float free");

  TetMesh spare(nodes, mesh.tets(), mesh.regionLabels());
  for (const auto& [name, set] : p.m.mesh.nodeSets()) spare.setNodeSet(name, set);
  writeTetMesh(dir.path("spare.inp"), spare, {}, 1e-3);
  const ModelCase c = loadModelCase(dir.write("spare.yaml", caseText("spare.inp", "mm")));
  EXPECT_EQ(c.mesh_report.unused_nodes, 5);
  EXPECT_EQ(c.mesh->numNodes(), n);

  // Elements that overlap: a tetrahedron repeated.
  std::ofstream(dir.path("twice.inp")) << "*NODE\n1, 0, 0, 0\n2, 10, 0, 0\n3, 0, 10, 0\n4, 0, 0, 10\n"
                                           "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n2, 1, 2, 3, 4\n";
  const std::string why = errorOf(dir.write("twice.yaml", "mesh: {path: twice.inp, units: mm}\n"));
  EXPECT_NE(why.find("twice.inp"), std::string::npos) << why;
  EXPECT_NE(why.find("overlapping or duplicate elements"), std::string::npos) << why;
}

TEST(UserMesh, TheEffectiveCaseNamesTheMeshByItsAbsolutePath) {
  const std::string yaml = effectiveCaseYaml(kMeshCase);
  EXPECT_NE(yaml.find("mesh:"), std::string::npos);
  EXPECT_NE(yaml.find(std::filesystem::absolute(kConfigDir + "../test/data/dome_breast.msh").lexically_normal().string()),
            std::string::npos)
      << yaml;
}


// docs/case_files.md's `mesh:` block is a case that loads (its path made absolute).
TEST(UserMesh, TheDocumentedMeshBlockIsACase) {
  std::ifstream in(kConfigDir + "../docs/case_files.md");
  const std::string doc((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const size_t section = doc.find("## A mesh of your own");
  ASSERT_NE(section, std::string::npos);
  const size_t open = doc.find("```\n", section), close = doc.find("```", open + 4);
  ASSERT_NE(close, std::string::npos);
  std::string block = doc.substr(open + 4, close - open - 4);
  const std::string rel = "../test/data/";
  ASSERT_NE(block.find(rel), std::string::npos) << block;
  block.replace(block.find(rel), rel.size(), kConfigDir + "../test/data/");
  const test::TempDir dir("breast_sim_user_mesh_doc");
  const ModelCase c = loadModelCase(dir.write("doc.yaml", block));
  ASSERT_TRUE(c.mesh);
  EXPECT_EQ(c.mesh->numTets(), 14132);
  ASSERT_EQ(c.lesions.size(), 1u);
}


// The whole pipeline (gravity, sliding, morphing to a target file) on a mesh case: the phantom's
// model read back from an .inp, morphing to the phantom's supine skin written as OBJ, with the main
// job's settings. It matches the target as the image case does (at 2k elements neither reaches the
// p95 tolerance in the stage's 300 steps: measured 0.291 / 1.626 mm against 0.260 / 1.553 mm), and
// its lesion lands where the image case's does within the spread of the stick/slip path: runs that
// differ only in their last bits take other stick/slip branches along the wall, which alone move a
// lesion by up to 1.3 mm (docs/uncertainty.md, "path"); measured 0.78 and 1.07 mm with two
// summation orders.
TEST(UserMesh, TheWholePipelineMorphsAMeshCaseToATargetFile) {
  const PhantomAsMeshCase t;
  writePhantomSurface(t.dir.path("target.obj"), phantom().c.phantom->supine_surface);
  PipelineSettings s = loadPipelineSettings(test_fixtures::kPhantomCase);
  s.morphing.target = t.dir.path("target.obj");
  s.morphing.target_length_unit_m = 1.0;  // the file is in metres
  // The phantom's target was made for its prone reference (SimulationSettings::ReferenceState);
  // its image and its mesh are not the phantom, whose default that is.
  s.simulation.reference_state = SimulationSettings::ReferenceState::kProne;
  ProneToSupinePipeline reference(t.image_case, t.image_model, s), pipe(t.c, t.m, s);
  ASSERT_TRUE(pipe.hasTarget());
  reference.run();
  pipe.run();
  ASSERT_EQ(pipe.stage(), PipelineStage::kDone);
  const StageReport& mr = pipe.morphingReport();
  const StageReport& rr = reference.morphingReport();
  const double lesion_mm = 1e3 * (pipe.lesionPositions() - reference.lesionPositions()).norm();
  std::printf("[ measure  ] morphing: mesh case %.3f / %.3f mm (mean / p95) in %d steps, image case %.3f / %.3f mm in %d; "
              "lesions %.3f mm apart\n",
              1e3 * mr.surface_mean_m, 1e3 * mr.surface_p95_m, mr.steps, 1e3 * rr.surface_mean_m, 1e3 * rr.surface_p95_m,
              rr.steps, lesion_mm);
  EXPECT_EQ(mr.converged, rr.converged);
  EXPECT_LE(mr.surface_mean_m, s.morphing.tolerance_mean_m);
  EXPECT_NEAR(mr.surface_mean_m, rr.surface_mean_m, 0.1e-3);
  EXPECT_NEAR(mr.surface_p95_m, rr.surface_p95_m, 0.2e-3);
  EXPECT_EQ(pipe.metrics().inverted_elements, 0);
  EXPECT_LE(lesion_mm, 1.5);
}

}  // namespace
}  // namespace breast_sim::core
