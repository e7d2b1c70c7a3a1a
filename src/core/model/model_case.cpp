#include "breast_sim/core/model/model_case.h"

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

}  // namespace

ModelCase loadModelCase(const std::string& yaml_path) {
  if (!fs::exists(yaml_path)) throw std::runtime_error(yaml_path + ": no such case file");
  const YAML::Node root = yaml_fields::loadFile(yaml_path);  // with its base: file, if any
  if (!root.IsMap()) throw std::runtime_error(yaml_path + ": expected a map with 'phantom:' or 'image:' at the top");
  ModelCase c;
  c.source_path = yaml_path;
  c.name = fs::path(yaml_path).stem().string();
  const bool has_phantom = static_cast<bool>(root["phantom"]);
  const bool has_image = static_cast<bool>(root["image"]);
  if (has_phantom == has_image)
    throw std::runtime_error(yaml_path + ": give exactly one of 'phantom:' (the software phantom) or 'image:' "
                                         "(a label image), found " + (has_phantom ? "both" : "neither"));
  if (has_phantom) {
    auto phantom = std::make_shared<Phantom>(generatePhantom(loadPhantomParams(yaml_path)));
    c.image = phantom->labels;
    c.nipples_m = phantom->nipples_m;
    c.prone_gravity_direction = phantom->gravity_prone_mps2.normalized();
    c.lesions = phantom->lesions;
    c.phantom = phantom;
  } else {
    const YAML::Node img = root["image"];
    checkKeys(img, {"path", "labels", "nipples_mm", "prone_gravity_direction"}, yaml_path, "image");
    if (!img["path"]) fail(yaml_path, "image.path", "missing: give the label image file (NIfTI, NRRD or MetaImage)");
    fs::path p = text(img["path"], yaml_path, "image.path");
    if (p.is_relative()) p = fs::path(yaml_path).parent_path() / p;
    c.image = readLabelImage(p.lexically_normal().string());
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
    if (img["prone_gravity_direction"]) {
      const Eigen::Vector3d g = vec3(img["prone_gravity_direction"], yaml_path, "image.prone_gravity_direction");
      if (!(g.norm() > 0)) fail(yaml_path, "image.prone_gravity_direction", "must not be zero: give the chest wall → nipple direction");
      c.prone_gravity_direction = g.normalized();
    }
    if (img["nipples_mm"]) {
      if (!img["nipples_mm"].IsSequence()) fail(yaml_path, "image.nipples_mm", "expected a list of [x, y, z] in mm");
      for (const auto& n : img["nipples_mm"]) c.nipples_m.push_back(vec3(n, yaml_path, "image.nipples_mm") * 1e-3);
    }
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
  model.mesh = meshLabelImage(model_case.image, model_case.labels, refine, model_case.meshing, &model.meshing);

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
