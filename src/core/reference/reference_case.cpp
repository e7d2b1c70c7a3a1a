// Load cases of the speed–accuracy study (reference/reference_case.h).

#include "breast_sim/core/reference/reference_case.h"

#include "../util/yaml_fields.h"

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include <unistd.h>

#include "breast_sim/core/mesh/mesh_io.h"

#include "breast_sim/core/model/phantom.h"

namespace breast_sim::core {

std::string gravityLoadCaseName(GravityLoadCase c) { return c == GravityLoadCase::kProneHanging ? "hanging" : "supine"; }

GravityLoadCase gravityLoadCaseFromName(const std::string& name) {
  if (name == "supine") return GravityLoadCase::kProneToSupine;
  if (name == "hanging") return GravityLoadCase::kProneHanging;
  throw std::invalid_argument("gravity load '" + name + "': expected supine (g_supine - g_prone) or hanging (g_prone)");
}

Eigen::Vector3d gravityLoad(const ModelCase& c, GravityLoadCase which, double g) {
  if (!(g > 0)) throw std::invalid_argument("gravityLoad: magnitude " + std::to_string(g) + " m/s^2: expected > 0");
  if (!(c.prone_gravity_direction.norm() > 0))
    throw std::invalid_argument("gravityLoad: case '" + c.name + "' has a zero prone_gravity_direction");
  const Eigen::Vector3d prone = g * c.prone_gravity_direction.normalized();
  if (which == GravityLoadCase::kProneHanging) return prone;
  const Eigen::Vector3d supine = c.phantom ? Eigen::Vector3d(c.phantom->gravity_supine_mps2) : Eigen::Vector3d(-prone);
  return supine - prone;
}

SimulationModel cachedSimulationModel(const ModelCase& c, const std::string& cache_dir, bool* from_cache) {
  namespace fs = std::filesystem;
  if (from_cache) *from_cache = false;
  if (cache_dir.empty()) return buildSimulationModel(c);
  std::ostringstream k;
  k.precision(17);
  if (!c.source_path.empty()) {
    // The case as read, with its base files merged in: an edit of a base changes the key too.
    try {
      k << YAML::Dump(yaml_fields::loadFile(c.source_path));
    } catch (const std::exception&) {
      k << c.name;  // the file is gone: the case as loaded (the rest of the key) still tells
    }
  } else {
    k << c.name;
  }
  const MeshingOptions& o = c.meshing;
  k << "|" << o.target_elements << "," << o.interior_size_m << "," << o.skin_size_factor << "," << o.grading_distance_m
    << "," << o.lesion_size_factor << "," << o.lesion_grading_distance_m << "," << o.facet_angle_deg << ","
    << o.facet_distance_m << "," << o.cell_radius_edge_ratio << "," << o.perturb << o.exude << ","
    << o.min_island_volume_fraction << "|" << c.lesion_snap_tolerance_m;
  for (const Lesion& l : c.lesions) k << "|" << l.name << "," << l.position_m.transpose() << "," << l.radius_m;
  const fs::path file = fs::path(cache_dir) / (referenceCacheKey(k.str()) + ".model.vtu");
  Points lesion_points(static_cast<Eigen::Index>(c.lesions.size()), 3);
  std::vector<std::string> names;
  for (std::size_t i = 0; i < c.lesions.size(); ++i) {
    lesion_points.row(i) = c.lesions[i].position_m.transpose();
    names.push_back(c.lesions[i].name);
  }
  if (fs::exists(file)) {
    SimulationModel m;
    m.mesh = readTetMesh(file.string());
    m.lesions = c.lesions;
    m.lesion_embedding = PointEmbedding(m.mesh, lesion_points, names, c.lesion_snap_tolerance_m);
    if (from_cache) *from_cache = true;
    return m;
  }
  SimulationModel m = buildSimulationModel(c);
  fs::create_directories(cache_dir);
  const fs::path tmp = file.string() + ".tmp" + std::to_string(::getpid()) + ".vtu";
  writeTetMesh(tmp.string(), m.mesh);
  fs::rename(tmp, file);
  return m;
}

CalculixLoadCase referenceLoadCase(const SimulationSettings& s, const Eigen::Vector3d& g, ReferenceElement element) {
  if (!s.region_youngs_modulus_pa.empty())
    throw std::invalid_argument("referenceLoadCase: the settings give per-tissue Young's moduli "
                                "(simulation.tissue_youngs_modulus_pa); pass the mesh so that they reach its elements");
  CalculixLoadCase l;
  l.material = s.material;
  l.gravity_mps2 = g;
  l.fixed_node_set = s.fixed_node_set;
  l.element = element;
  return l;
}

CalculixLoadCase referenceLoadCase(const SimulationSettings& s, const TetMesh& mesh, const Eigen::Vector3d& g,
                                   ReferenceElement element) {
  SimulationSettings uniform = s;
  uniform.region_youngs_modulus_pa.clear();
  CalculixLoadCase l = referenceLoadCase(uniform, g, element);
  const Eigen::VectorXd e = elementYoungsModuli(mesh, s);
  if (e.size() != 0) l.modulus_factors = e / s.material.youngs_modulus_pa;
  return l;
}

}  // namespace breast_sim::core
