#include "breast_sim/core/model/model_case.h"

#include <chrono>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <set>
#include <sstream>
#include <stdexcept>

#include <yaml-cpp/yaml.h>

#include "breast_sim/core/model/phantom.h"
#include "../util/yaml_fields.h"

namespace breast_sim::core {
namespace {

namespace fs = std::filesystem;

using namespace yaml_fields;

std::set<std::uint16_t> labelSet(const YAML::Node& n, const std::string& file, const std::string& key) {
  if (!n.IsSequence()) fail(file, key, "expected a list of label values, e.g. [1, 29]");
  std::set<std::uint16_t> out;
  for (const auto& v : n) out.insert(static_cast<std::uint16_t>(integer(v, file, key, 0, 65535)));
  return out;
}

MeshingOptions parseMeshing(const YAML::Node& m, const std::string& file, double* snap_tolerance_m) {
  MeshingOptions o;
  checkKeys(m, {"target_elements", "interior_size_mm", "skin_size_factor", "grading_distance_mm",
                "lesion_size_factor", "lesion_grading_distance_mm", "facet_angle_deg", "facet_distance_mm",
                "cell_radius_edge_ratio", "perturb", "exude", "max_size_iterations", "max_elements",
                "min_island_volume_fraction", "lesion_snap_tolerance_mm"},
            file, "meshing");
  // Checked here with the names and units the user typed; MeshingOptions::validate() checks again.
  auto get = [&](const char* key, double scale, double& out, double lo, bool lo_open, const char* range) {
    if (!m[key]) return;
    const std::string k = std::string("meshing.") + key;
    const double v = number(m[key], file, k);
    if (v < lo || (lo_open && v == lo)) fail(file, k, std::string("expected ") + range + ", got " + YAML::Dump(m[key]));
    out = v * scale;
  };
  if (m["target_elements"]) o.target_elements = static_cast<int>(integer(m["target_elements"], file, "meshing.target_elements", 0, 100'000'000));
  if (m["max_size_iterations"]) o.max_size_iterations = static_cast<int>(integer(m["max_size_iterations"], file, "meshing.max_size_iterations", 1, 20));
  if (m["max_elements"]) o.max_elements = static_cast<int>(integer(m["max_elements"], file, "meshing.max_elements", 1, 2'000'000'000));
  get("interior_size_mm", 1e-3, o.interior_size_m, 0.0, true, "a positive size in mm, e.g. 6");
  get("skin_size_factor", 1.0, o.skin_size_factor, 0.0, true, "a factor in (0, 1]");
  get("grading_distance_mm", 1e-3, o.grading_distance_m, 0.0, true, "a positive distance in mm");
  get("lesion_size_factor", 1.0, o.lesion_size_factor, 0.0, true, "a factor in (0, 1]");
  get("lesion_grading_distance_mm", 1e-3, o.lesion_grading_distance_m, 0.0, true, "a positive distance in mm");
  get("facet_angle_deg", 1.0, o.facet_angle_deg, 0.0, true, "an angle in (0, 30] degrees");
  get("facet_distance_mm", 1e-3, o.facet_distance_m, 0.0, false, "0 (automatic) or a positive distance in mm");
  get("cell_radius_edge_ratio", 1.0, o.cell_radius_edge_ratio, 2.0, false, "a ratio >= 2");
  get("min_island_volume_fraction", 1.0, o.min_island_volume_fraction, 0.0, false, "a fraction in [0, 1)");
  get("lesion_snap_tolerance_mm", 1e-3, *snap_tolerance_m, 0.0, false, "a distance >= 0 in mm");
  for (const char* key : {"perturb", "exude"}) {
    if (!m[key]) continue;
    try {
      (std::string(key) == "perturb" ? o.perturb : o.exude) = m[key].as<bool>();
    } catch (const YAML::Exception&) {
      fail(file, std::string("meshing.") + key, "expected true or false");
    }
  }
  try {
    o.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(file + ": " + e.what());
  }
  return o;
}

/// prone_gravity_direction and nipples_mm of an image: or mesh: map.
void readPlacement(const YAML::Node& m, const std::string& file, const std::string& section, ModelCase& c) {
  if (m["prone_gravity_direction"]) {
    const Eigen::Vector3d g = vec3(m["prone_gravity_direction"], file, section + ".prone_gravity_direction", "");
    // Only the direction counts: scaled by its largest entry first, so that a long vector (1e200)
    // does not overflow the norm and a tiny one does not underflow it.
    const double largest = g.cwiseAbs().maxCoeff();
    if (!(largest > 0))
      fail(file, section + ".prone_gravity_direction", "must be a non-zero vector: give the chest wall → nipple direction");
    c.prone_gravity_direction = (g / largest).normalized();
  }
  if (m["nipples_mm"]) {
    if (!m["nipples_mm"].IsSequence()) fail(file, section + ".nipples_mm", "expected a list of [x, y, z] in mm");
    for (const auto& n : m["nipples_mm"]) c.nipples_m.push_back(vec3(n, file, section + ".nipples_mm") * 1e-3);
  }
}

/// The `mesh:` map: reads and prepares the mesh, then makes its label image.
void loadMeshSource(const YAML::Node& m, const std::string& file, ModelCase& c) {
  if (!m.IsMap()) fail(file, "mesh", "expected a map {path, units, chest_wall, ...}");
  checkKeys(m, {"path", "units", "chest_wall", "skin", "nipple", "regions", "voxel_size_mm", "nipples_mm",
                "prone_gravity_direction"},
            file, "mesh");
  UserMeshSource& s = c.mesh_source;
  if (!m["path"]) fail(file, "mesh.path", "missing: give the mesh file (.msh .vtu .vtk .node/.ele .inp)");
  s.path = pathBeside(file, text(m["path"], file, "mesh.path"));
  if (!m["units"]) fail(file, "mesh.units", "missing: say whether the file's coordinates are in m or mm");
  s.length_unit_m = choice(m["units"], file, "mesh.units", {"m", "mm"}) == "m" ? 1.0 : 1e-3;
  if (m["chest_wall"]) s.chest_wall_set = text(m["chest_wall"], file, "mesh.chest_wall");
  if (m["skin"]) s.skin_set = text(m["skin"], file, "mesh.skin");
  if (m["nipple"]) s.nipple_set = text(m["nipple"], file, "mesh.nipple");
  if (m["voxel_size_mm"]) s.voxel_size_m = 1e-3 * numberIn(m["voxel_size_mm"], file, "mesh.voxel_size_mm", 0.1, 10.0, false, false, "mm");
  if (m["regions"]) {
    const YAML::Node r = m["regions"];
    checkKeys(r, {"fat", "fibroglandular", "skin", "lesion"}, file, "mesh.regions");
    const std::pair<const char*, TissueClass> classes[] = {{"fat", TissueClass::kFat},
                                                           {"fibroglandular", TissueClass::kFibroglandular},
                                                           {"skin", TissueClass::kSkin},
                                                           {"lesion", TissueClass::kLesion}};
    for (const auto& [name, cls] : classes) {
      if (!r[name]) continue;
      const std::string key = std::string("mesh.regions.") + name;
      if (!r[name].IsSequence()) fail(file, key, "expected a list of element region labels, e.g. [1, 2]");
      for (const auto& v : r[name]) {
        const int label = static_cast<int>(integer(v, file, key, -2'000'000'000L, 2'000'000'000L));
        if (!s.regions.emplace(label, cls).second)
          fail(file, key, "region label " + std::to_string(label) + " is in two lists");
      }
    }
    if (s.regions.empty()) fail(file, "mesh.regions", "lists no region label");
  }
  readPlacement(m, file, "mesh", c);
  if (m["nipples_mm"] && !s.nipple_set.empty())
    fail(file, "mesh.nipples_mm", "give either nipples_mm or the node set mesh.nipple, not both");
  std::shared_ptr<TetMesh> mesh;
  try {
    mesh = std::make_shared<TetMesh>(readUserMesh(s, &c.mesh_report));
  } catch (const std::runtime_error& e) {
    throw std::runtime_error(file + ": mesh: " + e.what());
  }
  if (mesh->hasNodeSet(node_sets::kNipple)) {
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    for (int v : mesh->nodeSet(node_sets::kNipple)) centroid += mesh->nodes().row(v).transpose();
    c.nipples_m.push_back(centroid / static_cast<double>(mesh->nodeSet(node_sets::kNipple).size()));
  }
  const auto t = std::chrono::steady_clock::now();
  try {
    c.image = voxelizeModel(*mesh, c.labels, s.voxel_size_m, kUserMeshImageMarginM);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(file + ": " + e.what());
  }
  c.mesh_report.voxelize_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
  c.mesh = std::move(mesh);
}

}  // namespace

ModelCase loadModelCase(const std::string& yaml_path) { return loadModelCase(yaml_path, {}); }

ModelCase loadModelCase(const std::string& yaml_path, const std::function<void(const std::string&)>& stage,
                        const MriSourceReader& read_mri) {
  if (!fs::exists(yaml_path)) throw std::runtime_error(yaml_path + ": no such case file");
  if (stage) stage("reading");
  const YAML::Node root = yaml_fields::loadFile(yaml_path);  // with its base: file, if any
  ModelCase c;
  c.source_path = yaml_path;
  c.name = fs::path(yaml_path).stem().string();
  const std::string source = caseSource(root, yaml_path);
  if (source == "phantom") {
    auto phantom = std::make_shared<Phantom>(generatePhantom(loadPhantomParams(yaml_path)));
    c.image = phantom->labels;
    c.nipples_m = phantom->nipples_m;
    c.prone_gravity_direction = phantom->gravity_prone_mps2.normalized();
    c.lesions = phantom->lesions;
    c.phantom = phantom;
  } else if (source == "mesh") {
    loadMeshSource(root["mesh"], yaml_path, c);
  } else if (source == "mri") {
    // Read and segmented by the MRI module (mri/mri_case.h); its labels carry the default label values.
    if (!read_mri)
      fail(yaml_path, "mri", "a prone MRI case is segmented before it is meshed: run it with breast_sim_run or the node");
    read_mri(yaml_path, c);
  } else {
    const YAML::Node img = root["image"];
    checkKeys(img, {"path", "labels", "nipples_mm", "prone_gravity_direction"}, yaml_path, "image");
    if (!img["path"]) fail(yaml_path, "image.path", "missing: give the label image file (NIfTI, NRRD or MetaImage)");
    c.image = readLabelImage(pathBeside(yaml_path, text(img["path"], yaml_path, "image.path")));
    if (img["labels"]) {
      const YAML::Node l = img["labels"];
      checkKeys(l, {"fat", "fibroglandular", "skin", "lesion", "chest_wall"}, yaml_path, "image.labels");
      if (l["fat"]) c.labels.fat = labelSet(l["fat"], yaml_path, "image.labels.fat");
      if (l["fibroglandular"]) c.labels.fibroglandular = labelSet(l["fibroglandular"], yaml_path, "image.labels.fibroglandular");
      if (l["skin"]) c.labels.skin = labelSet(l["skin"], yaml_path, "image.labels.skin");
      if (l["lesion"]) c.labels.lesion = labelSet(l["lesion"], yaml_path, "image.labels.lesion");
      if (l["chest_wall"]) c.labels.chest_wall = labelSet(l["chest_wall"], yaml_path, "image.labels.chest_wall");
      try {
        c.labels.validate();
      } catch (const std::invalid_argument& e) {
        throw std::runtime_error(yaml_path + ": " + e.what());
      }
    }
    readPlacement(img, yaml_path, "image", c);
  }
  if (root["lesions"]) {
    if (!root["lesions"].IsSequence()) fail(yaml_path, "lesions", "expected a list of {name, position_mm, radius_mm}");
    for (const auto& l : root["lesions"]) {
      checkKeys(l, {"name", "position_mm", "radius_mm"}, yaml_path, "lesions[]");
      Lesion les;
      les.name = l["name"] ? text(l["name"], yaml_path, "lesions[].name") : "L" + std::to_string(c.lesions.size() + 1);
      if (!l["position_mm"]) fail(yaml_path, "lesions[" + les.name + "].position_mm", "missing");
      les.position_m = vec3(l["position_mm"], yaml_path, "lesions[" + les.name + "].position_mm") * 1e-3;
      if (l["radius_mm"]) les.radius_m = number(l["radius_mm"], yaml_path, "lesions[" + les.name + "].radius_mm") * 1e-3;
      if (les.radius_m < 0) fail(yaml_path, "lesions[" + les.name + "].radius_mm", "must be ≥ 0");
      c.lesions.push_back(les);
    }
  }
  // A mesh that segments its lesions brings them, unless the case lists its own.
  if (c.mesh && !root["lesions"]) c.lesions = lesionsOfRegions(*c.mesh);
  if (root["meshing"]) c.meshing = parseMeshing(root["meshing"], yaml_path, &c.lesion_snap_tolerance_m);
  return c;
}

MeshingOptions loadMeshingOptions(const std::string& yaml_path, double* lesion_snap_tolerance_m) {
  const YAML::Node root = yaml_fields::loadFile(yaml_path);
  double snap_m = ModelCase{}.lesion_snap_tolerance_m;
  MeshingOptions o;
  if (root.IsMap() && root["meshing"]) o = parseMeshing(root["meshing"], yaml_path, &snap_m);
  if (lesion_snap_tolerance_m) *lesion_snap_tolerance_m = snap_m;
  return o;
}

SimulationModel buildSimulationModel(const ModelCase& model_case) {
  std::vector<RefinementPoint> refine;
  for (const auto& l : model_case.lesions) refine.push_back({l.position_m, l.radius_m});
  SimulationModel model;
  if (model_case.mesh) {
    model.mesh = *model_case.mesh;
    const UserMeshReport& r = model_case.mesh_report;
    model.meshing.seconds = r.voxelize_seconds;
    model.meshing.interior_size_m = r.interior_size_m;
    model.meshing.skin_size_m = r.skin_size_m;
    model.meshing.num_chest_wall_faces = r.chest_wall_faces;
    model.meshing.num_skin_faces = r.skin_faces;
    model.meshing.num_components = r.components;
    model.meshing.tissue_voxels = std::count_if(model_case.image.labels.begin(), model_case.image.labels.end(),
                                                [&](std::uint16_t l) { return model_case.labels.isTissue(l); });
    model.meshing.voxel_volume_m3 = static_cast<double>(model.meshing.tissue_voxels) * model_case.image.spacing_m.prod();
  } else {
    model.mesh = meshLabelImage(model_case.image, model_case.labels, refine, model_case.meshing, &model.meshing);
  }

  if (!model_case.nipples_m.empty()) {
    // The skin node nearest each nipple point; a point far from the skin is a coordinate mistake.
    const double tolerance_m = std::max(10e-3, 2.0 * model.meshing.skin_size_m);
    const auto& skin = model.mesh.nodeSet(node_sets::kSkin);
    std::vector<int> nipple;
    for (size_t i = 0; i < model_case.nipples_m.size(); ++i) {
      const Eigen::Vector3d& p = model_case.nipples_m[i];
      int best = -1;
      double best_d = std::numeric_limits<double>::infinity();
      for (int v : skin) {
        const double d = (model.mesh.nodes().row(v).transpose() - p).norm();
        if (d < best_d) best_d = d, best = v;
      }
      if (best < 0 || !(best_d <= tolerance_m)) {
        std::ostringstream s;
        s.precision(4);
        s << "case '" << model_case.name << "': nipple " << i + 1 << " at (" << p.x() * 1e3 << ", " << p.y() * 1e3
          << ", " << p.z() * 1e3 << ") mm is " << best_d * 1e3 << " mm from the nearest skin node (tolerance "
          << tolerance_m * 1e3 << " mm); give it in the image's patient space (LPS, mm)";
        throw std::invalid_argument(s.str());
      }
      nipple.push_back(best);
    }
    model.mesh.setNodeSet(node_sets::kNipple, nipple);
  }

  Points lesion_points(static_cast<Eigen::Index>(model_case.lesions.size()), 3);
  std::vector<std::string> names;
  for (size_t i = 0; i < model_case.lesions.size(); ++i) {
    lesion_points.row(static_cast<Eigen::Index>(i)) = model_case.lesions[i].position_m.transpose();
    names.push_back(model_case.lesions[i].name);
  }
  try {
    model.lesion_embedding = PointEmbedding(model.mesh, lesion_points, names, model_case.lesion_snap_tolerance_m);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("case '" + model_case.name + "': " + e.what());
  }
  model.lesions = model_case.lesions;
  model.quality = qualityStats(model.mesh.tets(), model.mesh.nodes());
  return model;
}

}  // namespace breast_sim::core
