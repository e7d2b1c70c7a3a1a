// PhantomParams from the 'phantom:' map of a case file, and a phantom surface written as OBJ or STL
// (phantom.h). The shapes, the label image and the parameter checks are in phantom.cpp.
#include "breast_sim/core/model/phantom.h"

#include <algorithm>
#include <cctype>
#include <fstream>
#include <cmath>
#include <functional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <yaml-cpp/yaml.h>

#include "../util/yaml_fields.h"

namespace breast_sim::core {

// ---------------------------------------------------------------------------------------------------
// YAML

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kMm = 1e-3;
constexpr double kDeg = kPi / 180.0;

std::string describe(const YAML::Node& node) {
  if (node.IsScalar()) return "'" + node.Scalar() + "'";
  if (node.IsNull()) return "(empty)";
  YAML::Emitter out;
  out << YAML::Flow << node;
  return out.c_str();
}

[[noreturn]] void badValue(const std::string& key, const YAML::Node& node, const std::string& expected) {
  throw std::invalid_argument("key 'phantom." + key + "' = " + describe(node) + ": expected " + expected);
}

double readNumber(const YAML::Node& node, const std::string& key, const std::string& expected) {
  if (!node.IsScalar()) badValue(key, node, expected);
  try {
    return node.as<double>();
  } catch (const YAML::Exception&) {
    badValue(key, node, expected);
  }
}

int readInt(const YAML::Node& node, const std::string& key, const std::string& expected) {
  if (!node.IsScalar()) badValue(key, node, expected);
  try {
    return node.as<int>();
  } catch (const YAML::Exception&) {
    badValue(key, node, expected);
  }
}

std::string readWord(const YAML::Node& node, const std::string& key, const std::string& expected) {
  if (!node.IsScalar()) badValue(key, node, expected);
  return node.Scalar();
}

Lesion readLesion(const YAML::Node& node, const std::string& key) {
  if (!node.IsMap()) badValue(key, node, "a map {name, position_mm: [x, y, z], radius_mm}");
  Lesion l;
  bool has_position = false;
  for (const auto& kv : node) {
    if (!kv.first.IsScalar()) badValue(key, node, "a map whose keys are name, position_mm, radius_mm");
    const std::string k = kv.first.Scalar();
    const YAML::Node& v = kv.second;
    if (k == "name") {
      l.name = readWord(v, key + ".name", "a name (string)");
    } else if (k == "position_mm") {
      const std::string what = "three numbers [x, y, z] in mm (LPS)";
      if (!v.IsSequence() || v.size() != 3) badValue(key + ".position_mm", v, what);
      for (int c = 0; c < 3; ++c) l.position_m[c] = kMm * readNumber(v[c], key + ".position_mm", what);
      has_position = true;
    } else if (k == "radius_mm") {
      l.radius_m = kMm * readNumber(v, key + ".radius_mm", "a radius in mm (0 = a point)");
    } else {
      throw std::invalid_argument("unknown key 'phantom." + key + "." + k +
                                  "'; a lesion has the keys name, position_mm, radius_mm");
    }
  }
  if (!has_position) badValue(key, node, "a position_mm: [x, y, z] entry");
  return l;
}

/// The sizes a case file may give, checked before PhantomParams::validate computes the image grid
/// in voxels (as int): a length beyond 10 m or a voxel or triangle edge below 0.01 mm would overflow
/// those counts long before the image-size check could refuse them.
constexpr double kMaxLengthM = 10.0;
constexpr double kMinStepM = 1e-5;

void checkScale(const PhantomParams& p) {
  const std::pair<const char*, double> lengths[] = {
      {"breast_separation_mm", p.breast_separation_m},   {"chest_wall_radius_mm", p.chest_wall_radius_m},
      {"chest_wall_thickness_mm", p.chest_wall_thickness_m}, {"lateral_semi_axis_mm", p.lateral_semi_axis_m},
      {"si_semi_axis_mm", p.si_semi_axis_m},             {"depth_mm", p.depth_m},
      {"skin_thickness_mm", p.skin_thickness_m},         {"supine_lateral_shift_mm", p.supine_lateral_shift_m},
      {"voxel_size_mm", p.voxel_size_m},                 {"margin_mm", p.margin_m},
      {"surface_edge_mm", p.surface_edge_m}};
  const auto mm = [](double v_m) {
    std::ostringstream s;
    s << v_m / kMm;
    return s.str();
  };
  for (const auto& [key, v] : lengths) {
    if (!(std::abs(v) <= kMaxLengthM)) {
      throw std::invalid_argument("key 'phantom." + std::string(key) + "' = " + mm(v) + " mm: expected a length of at most " +
                                  mm(kMaxLengthM) + " mm");
    }
  }
  for (const auto& [key, v] : {std::pair<const char*, double>{"voxel_size_mm", p.voxel_size_m},
                               std::pair<const char*, double>{"surface_edge_mm", p.surface_edge_m}}) {
    if (!(v >= kMinStepM)) {
      throw std::invalid_argument("key 'phantom." + std::string(key) + "' = " + mm(v) + " mm: expected a positive step of at least " +
                                  mm(kMinStepM) + " mm");
    }
  }
  for (std::size_t i = 0; i < p.lesions.size(); ++i) {
    const Lesion& l = p.lesions[i];
    if (!(l.position_m.cwiseAbs().maxCoeff() <= kMaxLengthM) || !(std::abs(l.radius_m) <= kMaxLengthM)) {
      throw std::invalid_argument("key 'phantom.lesions[" + std::to_string(i) + "]': a position or radius beyond " +
                                  mm(kMaxLengthM) + " mm");
    }
  }
}

}  // namespace

PhantomParams loadPhantomParams(const std::string& yaml_path) {
  const std::string where = "phantom case '" + yaml_path + "': ";
  YAML::Node root;
  try {
    root = yaml_fields::loadFile(yaml_path);  // with its base: file, if any
  } catch (const std::runtime_error& e) {
    throw std::runtime_error(where + "cannot be read: " + e.what());
  }
  if (!root.IsMap()) throw std::runtime_error(where + "expected a map with a 'phantom:' entry at the top level");
  const YAML::Node& croot = root;
  const YAML::Node ph = croot["phantom"];
  if (!ph) throw std::runtime_error(where + "has no 'phantom:' map (is it an image case?)");
  PhantomParams p;
  if (ph.IsNull()) return p;
  if (!ph.IsMap()) throw std::runtime_error(where + "'phantom:' is " + describe(ph) + ": expected a map of parameters");

  const std::string mm = "a number in mm";
  const auto length = [&](double& field) {
    return [&field, mm](const YAML::Node& v, const std::string& k) { field = kMm * readNumber(v, k, mm); };
  };
  const auto number = [](double& field, std::string expected) {
    return [&field, expected](const YAML::Node& v, const std::string& k) { field = readNumber(v, k, expected); };
  };
  using Handler = std::function<void(const YAML::Node&, const std::string&)>;
  const std::vector<std::pair<std::string, Handler>> handlers = {
      {"num_breasts", [&](const YAML::Node& v, const std::string& k) { p.num_breasts = readInt(v, k, "1 or 2"); }},
      {"side",
       [&](const YAML::Node& v, const std::string& k) {
         const std::string s = readWord(v, k, "'left' or 'right'");
         if (s == "left") p.side = BreastSide::kLeft;
         else if (s == "right") p.side = BreastSide::kRight;
         else badValue(k, v, "'left' or 'right'");
       }},
      {"breast_separation_mm", length(p.breast_separation_m)},
      {"chest_wall_shape",
       [&](const YAML::Node& v, const std::string& k) {
         const std::string s = readWord(v, k, "'planar' or 'cylindrical'");
         if (s == "planar") p.chest_wall_shape = ChestWallShape::kPlanar;
         else if (s == "cylindrical") p.chest_wall_shape = ChestWallShape::kCylindrical;
         else badValue(k, v, "'planar' or 'cylindrical'");
       }},
      {"chest_wall_radius_mm", length(p.chest_wall_radius_m)},
      {"chest_wall_thickness_mm", length(p.chest_wall_thickness_m)},
      {"lateral_semi_axis_mm", length(p.lateral_semi_axis_m)},
      {"si_semi_axis_mm", length(p.si_semi_axis_m)},
      {"depth_mm", length(p.depth_m)},
      {"gland_scale", number(p.gland_scale, "a fraction in [0, 1)")},
      {"skin_thickness_mm", length(p.skin_thickness_m)},
      {"supine_depth_scale", number(p.supine_depth_scale, "a factor in (0, 1]")},
      {"supine_lateral_share", number(p.supine_lateral_share, "a fraction in [0, 1]")},
      {"supine_lateral_shift_mm", length(p.supine_lateral_shift_m)},
      {"supine_gravity_tilt_deg",
       [&](const YAML::Node& v, const std::string& k) {
         p.supine_gravity_tilt_rad = kDeg * readNumber(v, k, "an angle in degrees");
       }},
      {"gravity_mps2", number(p.gravity_mps2, "an acceleration in m/s^2")},
      {"voxel_size_mm", length(p.voxel_size_m)},
      {"margin_mm", length(p.margin_m)},
      {"supersampling",
       [&](const YAML::Node& v, const std::string& k) { p.supersampling = readInt(v, k, "an integer in [1, 4]"); }},
      {"surface_edge_mm", length(p.surface_edge_m)},
      {"lesions",
       [&](const YAML::Node& v, const std::string& k) {
         p.lesions.clear();
         if (v.IsNull()) return;
         if (!v.IsSequence()) badValue(k, v, "a list of {name, position_mm: [x, y, z], radius_mm}");
         for (std::size_t i = 0; i < v.size(); ++i) p.lesions.push_back(readLesion(v[i], k + "[" + std::to_string(i) + "]"));
       }},
  };

  try {
    for (const auto& kv : ph) {
      if (!kv.first.IsScalar()) {
        throw std::invalid_argument("a key of 'phantom:' is " + describe(kv.first) + "; keys must be plain words");
      }
      const std::string key = kv.first.Scalar();
      const auto it = std::find_if(handlers.begin(), handlers.end(), [&](const auto& h) { return h.first == key; });
      if (it == handlers.end()) {
        std::string known;
        for (const auto& h : handlers) known += (known.empty() ? "" : ", ") + h.first;
        throw std::invalid_argument("unknown key 'phantom." + key + "' (value " + describe(kv.second) +
                                    "); expected one of: " + known);
      }
      it->second(kv.second, key);
    }
    checkScale(p);
    p.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(where + e.what());
  }
  return p;
}

// ---------------------------------------------------------------------------------------------------
// Output

void writePhantomSurface(const std::string& path, const PhantomSurface& surface) {
  const auto ends_with = [&path](const std::string& ext) {
    if (path.size() < ext.size()) return false;
    std::string tail = path.substr(path.size() - ext.size());
    std::transform(tail.begin(), tail.end(), tail.begin(), [](unsigned char ch) { return std::tolower(ch); });
    return tail == ext;
  };
  const bool obj = ends_with(".obj"), stl = ends_with(".stl");
  if (!obj && !stl)
    throw std::runtime_error("writePhantomSurface: '" + path + "' has an unknown extension; expected .obj or .stl");
  std::ofstream out(path);
  if (!out) throw std::runtime_error("writePhantomSurface: cannot open '" + path + "' for writing");
  out.precision(9);
  const Points& V = surface.vertices_m;
  const Triangles& F = surface.triangles;
  if (obj) {
    out << "# breast_sim software phantom surface, coordinates in metres (LPS)\n";
    for (Eigen::Index i = 0; i < V.rows(); ++i) out << "v " << V(i, 0) << ' ' << V(i, 1) << ' ' << V(i, 2) << '\n';
    for (const bool skin : {true, false}) {
      out << "g " << (skin ? "skin" : "chest_wall") << '\n';
      for (Eigen::Index f = 0; f < F.rows(); ++f)
        if (static_cast<std::size_t>(f) < surface.is_skin.size() && surface.is_skin[f] == skin)
          out << "f " << F(f, 0) + 1 << ' ' << F(f, 1) + 1 << ' ' << F(f, 2) + 1 << '\n';
    }
    // Faces without a flag (is_skin shorter than the triangles) still belong to the surface.
    for (Eigen::Index f = static_cast<Eigen::Index>(surface.is_skin.size()); f < F.rows(); ++f)
      out << "f " << F(f, 0) + 1 << ' ' << F(f, 1) + 1 << ' ' << F(f, 2) + 1 << '\n';
  } else {
    out << "solid breast_sim_phantom\n";
    for (Eigen::Index f = 0; f < F.rows(); ++f) {
      const Eigen::Vector3d a = V.row(F(f, 0)).transpose(), b = V.row(F(f, 1)).transpose(), c = V.row(F(f, 2)).transpose();
      Eigen::Vector3d nrm = (b - a).cross(c - a);
      if (nrm.norm() > 0.0) nrm.normalize();
      out << " facet normal " << nrm.x() << ' ' << nrm.y() << ' ' << nrm.z() << "\n  outer loop\n";
      for (const Eigen::Vector3d* q : {&a, &b, &c})
        out << "   vertex " << q->x() << ' ' << q->y() << ' ' << q->z() << '\n';
      out << "  endloop\n endfacet\n";
    }
    out << "endsolid breast_sim_phantom\n";
  }
  out.close();
  if (!out) throw std::runtime_error("writePhantomSurface: writing '" + path + "' failed");
}

}  // namespace breast_sim::core
