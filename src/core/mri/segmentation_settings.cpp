// SegmentationSettings: checks and the case file's `segmentation:` map.
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

#include "breast_sim/core/mri/mri_segmentation.h"
#include "../util/yaml_fields.h"

namespace breast_sim::core {

namespace {

void check(bool ok, const std::string& field, double value, const std::string& range) {
  if (ok) return;
  std::ostringstream s;
  s << "segmentation." << field << " = " << value << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

}  // namespace

void SegmentationSettings::validate() const {
  const double g = prone_gravity_direction.norm();
  check(std::isfinite(g) && g > 1e-9, "prone_gravity_direction (length)", g, "a non-zero vector [x, y, z]");
  check(n4_shrink_factor >= 1 && n4_shrink_factor <= 16, "n4_shrink_factor", n4_shrink_factor, "a whole number in [1, 16]");
  check(n4_fitting_levels >= 1 && n4_fitting_levels <= 8, "n4_fitting_levels", n4_fitting_levels, "a whole number in [1, 8]");
  check(n4_iterations >= 1 && n4_iterations <= 1000, "n4_iterations", n4_iterations, "a whole number in [1, 1000]");
  check(n4_spline_distance_mm >= 10 && n4_spline_distance_mm <= 1000, "n4_spline_distance_mm", n4_spline_distance_mm,
        "[10, 1000] mm");
  check(smoothing_sigma_mm >= 0 && smoothing_sigma_mm <= 10, "smoothing_sigma_mm", smoothing_sigma_mm, "[0, 10] mm");
  check(body_threshold > 0 && body_threshold < 1, "body_threshold", body_threshold, "(0, 1), a share of the fat level");
  check(body_noise_margin >= 0 && body_noise_margin <= 100, "body_noise_margin", body_noise_margin,
        "[0, 100] spreads of the background noise");
  check(min_fat_component_share >= 0 && min_fat_component_share <= 1, "min_fat_component_share", min_fat_component_share,
        "[0, 1]");
  check(chest_wall_min_thickness_mm >= 0.5 && chest_wall_min_thickness_mm <= 100, "chest_wall_min_thickness_mm",
        chest_wall_min_thickness_mm, "[0.5, 100] mm");
  check(boundary_median_window_mm >= 0 && boundary_median_window_mm <= 500, "boundary_median_window_mm",
        boundary_median_window_mm, "[0, 500] mm (0 = no median)");
  check(boundary_smoothing_mm > 0 && boundary_smoothing_mm <= 100, "boundary_smoothing_mm", boundary_smoothing_mm,
        "(0, 100] mm");
  check(boundary_outlier_mm > 0 && boundary_outlier_mm <= 100, "boundary_outlier_mm", boundary_outlier_mm, "(0, 100] mm");
  check(min_boundary_coverage >= 0 && min_boundary_coverage <= 1, "min_boundary_coverage", min_boundary_coverage, "[0, 1]");
  check(min_component_share >= 0 && min_component_share <= 1, "min_component_share", min_component_share, "[0, 1]");
  check(skin_thickness_mm >= 0 && skin_thickness_mm <= 10, "skin_thickness_mm", skin_thickness_mm, "[0, 10] mm");
}

SegmentationSettings loadSegmentationSettings(const std::string& yaml_path) {
  using namespace yaml_fields;
  const YAML::Node root = loadFile(yaml_path);
  SegmentationSettings s;
  if (!root.IsMap() || !root["segmentation"]) return s;
  const YAML::Node m = root["segmentation"];
  const std::string f = yaml_path;
  if (!m.IsMap()) fail(f, "segmentation", "expected a map of settings");
  checkKeys(m,
            {"prone_gravity_direction", "bias_correction", "n4_shrink_factor", "n4_fitting_levels", "n4_iterations",
             "n4_spline_distance_mm", "smoothing_sigma_mm", "body_threshold", "body_noise_margin",
             "min_fat_component_share", "chest_wall_min_thickness_mm", "boundary_median_window_mm",
             "boundary_smoothing_mm", "boundary_outlier_mm", "min_boundary_coverage", "min_component_share",
             "skin_thickness_mm"},
            f, "segmentation");
  const auto key = [](const char* k) { return std::string("segmentation.") + k; };
  if (m["prone_gravity_direction"]) {
    s.prone_gravity_direction = vec3(m["prone_gravity_direction"], f, key("prone_gravity_direction"), "");
    if (s.prone_gravity_direction.norm() < 1e-9)
      fail(f, key("prone_gravity_direction"), "expected a non-zero direction [x, y, z] (chest wall -> nipple)");
  }
  if (m["bias_correction"]) s.bias_correction = boolean(m["bias_correction"], f, key("bias_correction"));
  if (m["n4_shrink_factor"]) s.n4_shrink_factor = static_cast<int>(integer(m["n4_shrink_factor"], f, key("n4_shrink_factor"), 1, 16));
  if (m["n4_fitting_levels"]) s.n4_fitting_levels = static_cast<int>(integer(m["n4_fitting_levels"], f, key("n4_fitting_levels"), 1, 8));
  if (m["n4_iterations"]) s.n4_iterations = static_cast<int>(integer(m["n4_iterations"], f, key("n4_iterations"), 1, 1000));
  if (m["n4_spline_distance_mm"])
    s.n4_spline_distance_mm = numberIn(m["n4_spline_distance_mm"], f, key("n4_spline_distance_mm"), 10, 1000, false, false, "mm");
  if (m["smoothing_sigma_mm"])
    s.smoothing_sigma_mm = numberIn(m["smoothing_sigma_mm"], f, key("smoothing_sigma_mm"), 0, 10, false, false, "mm");
  if (m["body_threshold"]) s.body_threshold = numberIn(m["body_threshold"], f, key("body_threshold"), 0, 1, true, true);
  if (m["body_noise_margin"]) s.body_noise_margin = numberIn(m["body_noise_margin"], f, key("body_noise_margin"), 0, 100);
  if (m["min_fat_component_share"])
    s.min_fat_component_share = numberIn(m["min_fat_component_share"], f, key("min_fat_component_share"), 0, 1);
  if (m["chest_wall_min_thickness_mm"])
    s.chest_wall_min_thickness_mm =
        numberIn(m["chest_wall_min_thickness_mm"], f, key("chest_wall_min_thickness_mm"), 0.5, 100, false, false, "mm");
  if (m["boundary_median_window_mm"])
    s.boundary_median_window_mm =
        numberIn(m["boundary_median_window_mm"], f, key("boundary_median_window_mm"), 0, 500, false, false, "mm");
  if (m["boundary_smoothing_mm"])
    s.boundary_smoothing_mm = numberIn(m["boundary_smoothing_mm"], f, key("boundary_smoothing_mm"), 0, 100, true, false, "mm");
  if (m["boundary_outlier_mm"])
    s.boundary_outlier_mm = numberIn(m["boundary_outlier_mm"], f, key("boundary_outlier_mm"), 0, 100, true, false, "mm");
  if (m["min_boundary_coverage"])
    s.min_boundary_coverage = numberIn(m["min_boundary_coverage"], f, key("min_boundary_coverage"), 0, 1);
  if (m["min_component_share"]) s.min_component_share = numberIn(m["min_component_share"], f, key("min_component_share"), 0, 1);
  if (m["skin_thickness_mm"])
    s.skin_thickness_mm = numberIn(m["skin_thickness_mm"], f, key("skin_thickness_mm"), 0, 10, false, false, "mm");
  return s;
}

std::vector<Lesion> loadCaseLesions(const std::string& yaml_path) {
  using namespace yaml_fields;
  const YAML::Node root = loadFile(yaml_path);
  std::vector<Lesion> out;
  if (!root.IsMap() || !root["lesions"]) return out;
  const YAML::Node list = root["lesions"];
  if (!list.IsSequence()) fail(yaml_path, "lesions", "expected a list of {name, position_mm, radius_mm}");
  for (std::size_t i = 0; i < list.size(); ++i) {
    const YAML::Node l = list[i];
    const std::string key = "lesions[" + std::to_string(i) + "]";
    if (!l.IsMap()) fail(yaml_path, key, "expected a map {name, position_mm, radius_mm}");
    checkKeys(l, {"name", "position_mm", "radius_mm"}, yaml_path, key);
    Lesion lesion;
    lesion.name = l["name"] ? text(l["name"], yaml_path, key + ".name") : "L" + std::to_string(i + 1);
    if (!l["position_mm"]) fail(yaml_path, key + ".position_mm", "missing: the lesion's position [x, y, z] in mm");
    lesion.position_m = 1e-3 * vec3(l["position_mm"], yaml_path, key + ".position_mm");
    if (l["radius_mm"]) lesion.radius_m = 1e-3 * numberIn(l["radius_mm"], yaml_path, key + ".radius_mm", 0, 100, false, false, "mm");
    out.push_back(lesion);
  }
  return out;
}

}  // namespace breast_sim::core
