// A case's effective settings written back as a case file (pipeline/case_file.h). Each map below
// names the keys its reader (model_case.cpp, phantom_io.cpp, simulation_settings.cpp,
// pipeline_settings.cpp, mri_case.cpp, segmentation_settings.cpp) accepts, in the same units;
// test_case_file changes every key in turn and checks that the reader reads back exactly that change.
#include "breast_sim/core/pipeline/case_file.h"

#include <cmath>
#include <cstdio>
#include <stdexcept>

#include <yaml-cpp/yaml.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/mri/mri_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "../util/yaml_fields.h"

namespace breast_sim::core {
namespace {

/// A number with 12 significant digits, as the readers take it (no quotes).
std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.12g", v);
  return buf;
}
double mm(double metres) { return metres * 1e3; }

/// One map of the output; keys in the order they are added.
class Map {
 public:
  Map& n(const char* key, double v) { return add(key, num(v)); }
  Map& i(const char* key, long v) { return add(key, std::to_string(v)); }
  Map& b(const char* key, bool v) { return add(key, v ? "true" : "false"); }
  Map& s(const char* key, const std::string& v) {
    node_[key] = v;
    return *this;
  }
  Map& node(const char* key, const YAML::Node& v) {
    node_[key] = v;
    return *this;
  }
  const YAML::Node& yaml() const { return node_; }

 private:
  Map& add(const char* key, const std::string& text) {
    node_[key] = YAML::Load(text);  // a plain scalar, emitted without quotes
    return *this;
  }
  YAML::Node node_{YAML::NodeType::Map};
};

YAML::Node vec3mm(const Eigen::Vector3d& p_m) {
  YAML::Node v(YAML::NodeType::Sequence);
  for (int k = 0; k < 3; ++k) v.push_back(YAML::Load(num(mm(p_m[k]))));
  v.SetStyle(YAML::EmitterStyle::Flow);
  return v;
}

YAML::Node phantomMap(const PhantomParams& p) {
  Map m;
  m.i("num_breasts", p.num_breasts)
      .s("side", p.side == BreastSide::kLeft ? "left" : "right")
      .n("breast_separation_mm", mm(p.breast_separation_m))
      .s("chest_wall_shape", p.chest_wall_shape == ChestWallShape::kPlanar ? "planar" : "cylindrical")
      .n("chest_wall_radius_mm", mm(p.chest_wall_radius_m))
      .n("chest_wall_thickness_mm", mm(p.chest_wall_thickness_m))
      .n("lateral_semi_axis_mm", mm(p.lateral_semi_axis_m))
      .n("si_semi_axis_mm", mm(p.si_semi_axis_m))
      .n("depth_mm", mm(p.depth_m))
      .n("gland_scale", p.gland_scale)
      .n("skin_thickness_mm", mm(p.skin_thickness_m))
      .n("supine_depth_scale", p.supine_depth_scale)
      .n("supine_lateral_share", p.supine_lateral_share)
      .n("supine_lateral_shift_mm", mm(p.supine_lateral_shift_m))
      .n("supine_gravity_tilt_deg", p.supine_gravity_tilt_rad * 180.0 / M_PI)
      .n("gravity_mps2", p.gravity_mps2)
      .n("voxel_size_mm", mm(p.voxel_size_m))
      .n("margin_mm", mm(p.margin_m))
      .i("supersampling", p.supersampling)
      .n("surface_edge_mm", mm(p.surface_edge_m));
  YAML::Node lesions(YAML::NodeType::Sequence);
  for (const Lesion& l : p.lesions) {
    Map e;
    e.s("name", l.name).node("position_mm", vec3mm(l.position_m)).n("radius_mm", mm(l.radius_m));
    YAML::Node y = e.yaml();
    y.SetStyle(YAML::EmitterStyle::Flow);
    lesions.push_back(y);
  }
  m.node("lesions", lesions);
  return m.yaml();
}

/// The `mri:` map with every key (paths absolute; midline_x_mm `auto` when not given).
YAML::Node mriMap(const MriCaseSource& m) {
  Map out;
  out.s("path", m.path).s("series_uid", m.series_uid).s("breasts", breastsName(m.breasts));
  if (std::isnan(m.midline_x_m)) out.s("midline_x_mm", "auto");
  else out.n("midline_x_mm", mm(m.midline_x_m));
  out.s("lesion_labels", m.lesion_labels).s("truth", m.truth);
  return out.yaml();
}

YAML::Node segmentationMap(const SegmentationSettings& s) {
  Map m;
  YAML::Node g(YAML::NodeType::Sequence);
  for (int k = 0; k < 3; ++k) g.push_back(YAML::Load(num(s.prone_gravity_direction[k])));
  g.SetStyle(YAML::EmitterStyle::Flow);
  m.node("prone_gravity_direction", g)
      .b("bias_correction", s.bias_correction)
      .i("n4_shrink_factor", s.n4_shrink_factor)
      .i("n4_fitting_levels", s.n4_fitting_levels)
      .i("n4_iterations", s.n4_iterations)
      .n("n4_spline_distance_mm", s.n4_spline_distance_mm)
      .n("smoothing_sigma_mm", s.smoothing_sigma_mm)
      .n("body_threshold", s.body_threshold)
      .n("body_noise_margin", s.body_noise_margin)
      .n("min_fat_component_share", s.min_fat_component_share)
      .n("chest_wall_min_thickness_mm", s.chest_wall_min_thickness_mm)
      .n("boundary_median_window_mm", s.boundary_median_window_mm)
      .n("boundary_smoothing_mm", s.boundary_smoothing_mm)
      .n("boundary_outlier_mm", s.boundary_outlier_mm)
      .n("min_boundary_coverage", s.min_boundary_coverage)
      .n("min_component_share", s.min_component_share)
      .n("skin_thickness_mm", s.skin_thickness_mm);
  return m.yaml();
}

YAML::Node meshingMap(const MeshingOptions& o, double lesion_snap_tolerance_m) {
  Map m;
  m.i("target_elements", o.target_elements)
      .n("interior_size_mm", mm(o.interior_size_m))
      .n("skin_size_factor", o.skin_size_factor)
      .n("grading_distance_mm", mm(o.grading_distance_m))
      .n("lesion_size_factor", o.lesion_size_factor)
      .n("lesion_grading_distance_mm", mm(o.lesion_grading_distance_m))
      .n("lesion_snap_tolerance_mm", mm(lesion_snap_tolerance_m))
      .n("facet_angle_deg", o.facet_angle_deg)
      .n("facet_distance_mm", mm(o.facet_distance_m))
      .n("cell_radius_edge_ratio", o.cell_radius_edge_ratio)
      .b("perturb", o.perturb)
      .b("exude", o.exude)
      .i("max_size_iterations", o.max_size_iterations)
      .i("max_elements", o.max_elements)
      .n("min_island_volume_fraction", o.min_island_volume_fraction);
  return m.yaml();
}

YAML::Node simulationMap(const SimulationSettings& s, bool software_phantom) {
  const MultigridOptions& mg = s.solver.multigrid;
  const char* smoother = mg.smoother == MultigridOptions::Smoother::kJacobi        ? "jacobi"
                         : mg.smoother == MultigridOptions::Smoother::kGaussSeidel ? "gauss-seidel"
                                                                                   : "chebyshev";
  if (mg.pre_smoothing_steps != mg.post_smoothing_steps)
    throw std::invalid_argument("effectiveCaseYaml: pre- and post-smoothing steps differ (" +
                                std::to_string(mg.pre_smoothing_steps) + ", " + std::to_string(mg.post_smoothing_steps) +
                                "); a case file has one multigrid_smoothing_steps");
  YAML::Node tissues(YAML::NodeType::Map);
  for (const TissueClass c : {TissueClass::kFat, TissueClass::kFibroglandular, TissueClass::kSkin, TissueClass::kLesion}) {
    const auto it = s.region_youngs_modulus_pa.find(static_cast<int>(c));
    if (it != s.region_youngs_modulus_pa.end()) tissues[tissueClassName(c)] = YAML::Load(num(it->second));
  }
  tissues.SetStyle(YAML::EmitterStyle::Flow);
  Map m;
  m.n("youngs_modulus_pa", s.material.youngs_modulus_pa)
      .n("poisson_ratio", s.material.poisson_ratio)
      .node("tissue_youngs_modulus_pa", tissues)
      .n("density_kg_per_m3", s.material.density_kg_per_m3)
      .n("gravity_mps2", s.gravity_mps2)
      .n("time_step_s", s.dynamics.time_step_s)
      .n("mass_damping_per_s", s.dynamics.mass_damping_per_s)
      .n("stiffness_damping_s", s.dynamics.stiffness_damping_s)
      .s("element", s.element == SimulationSettings::Element::kLinearTet ? "linear" : "anp")
      .s("volume_term", s.volume_term == CorotatedTetFem::VolumeTerm::kTrace ? "trace" : "determinant")
      .n("anp_inversion_barrier", s.anp_inversion_barrier)
      .n("anp_inversion_barrier_stiffness", s.anp_inversion_barrier_stiffness)
      .n("anp_element_volume_fraction", s.anp_element_volume_fraction)
      .s("solver", SolverSettings::kindName(s.solver.kind))
      .n("solver_relative_tolerance", s.solver.relative_tolerance)
      .i("solver_max_iterations", s.solver.max_iterations)
      .s("multigrid_smoother", smoother)
      .n("multigrid_chebyshev_ratio", mg.chebyshev_ratio)
      .i("multigrid_smoothing_steps", mg.pre_smoothing_steps)
      .i("multigrid_coarse_update_interval", mg.coarse_update_interval)
      .b("multigrid_coarse_update_adaptive", mg.coarse_update_adaptive)
      .n("multigrid_coarse_update_cost_iterations", mg.coarse_update_cost_iterations)
      .i("multigrid_max_coarsest_elements", s.solver.coarsening.max_coarsest_elements)
      .s("fixed_node_set", s.fixed_node_set)
      .b("stiffening", s.stiffening)
      .b("sliding", s.sliding)
      .s("reference_state", s.resolvedReferenceState(software_phantom) == SimulationSettings::ReferenceState::kProne
                                ? "prone"
                                : "unloaded")
      .n("settle_time_step_s", s.settle.time_step_s)
      .n("settle_increment_tolerance_mm", mm(s.settle.increment_tolerance_m))
      .i("settle_max_steps", s.settle.max_steps);
  return m.yaml();
}

YAML::Node stiffeningMap(const StiffeningParams& p) {
  const AlphaControllerParams& a = p.alpha;
  Map m;
  m.n("initial_alpha_per_pa", a.initial_alpha_per_pa)
      .n("min_alpha_per_pa", a.min_alpha_per_pa)
      .n("max_alpha_per_pa", a.max_alpha_per_pa)
      .n("decrease_factor", a.decrease_factor)
      .n("increase_factor", a.increase_factor)
      .n("reversal_growth", a.reversal_growth)
      .n("rate_halving", a.rate_halving)
      .n("min_rate", a.min_rate)
      .i("max_reversals_per_step", p.max_reversals_per_step)
      .n("settle_max_speed_mm_per_s", mm(p.settle.max_speed_mps))
      .n("settle_max_relative_residual", p.settle.max_relative_residual)
      .i("settle_consecutive_steps", p.settle.consecutive_steps)
      .n("settle_max_modulus_excess", p.settle.max_modulus_excess);
  return m.yaml();
}

YAML::Node slidingMap(const PipelineSettings& s) {
  const SlidingSettings& d = s.sliding;
  const WallSlipSettings& w = s.wall_slip;
  const SlidingStageSettings& st = s.sliding_stage;
  Map m;
  m.s("method", s.sliding_method == PipelineSettings::SlidingMethod::kImplicit ? "implicit" : "explicit")
      .n("normal_stiffness_pa_per_mm", w.normal_stiffness_pa_per_m * 1e-3)
      .n("friction_stiffness_pa_per_mm", w.friction_stiffness_pa_per_m * 1e-3)
      .n("tether_stiffness_pa_per_mm", w.tether_stiffness_pa_per_m * 1e-3)
      .n("stick_speed_mm_per_s", mm(w.stick_speed_mps))
      .b("contact", w.contact)
      .n("contact_gap_mm", mm(w.contact_gap_m))
      .n("normal_sigma_mm", mm(d.field.sigma_m))
      .n("mobility_mm_per_pa_s", mm(d.mobility_m_per_pa_s))
      .n("static_friction", d.static_friction)
      .n("kinetic_friction", d.kinetic_friction)
      .n("static_threshold_pa", d.static_threshold_pa)
      .n("inertia", d.inertia)
      .n("max_step_mm", mm(d.max_step_m))
      .n("max_slide_mm", mm(d.max_slide_m))
      .b("thickness_limit", d.thickness_limit)
      .b("gaussian_limit", d.gaussian_limit)
      .n("gaussian_amplitude", d.gaussian_amplitude)
      .n("gaussian_sigma_mm", mm(d.gaussian_sigma_m))
      .n("gaussian_sigma_fraction", d.gaussian_sigma_fraction)
      .n("time_step_s", st.time_step_s)
      .n("settle_increment_tolerance_mm", mm(st.increment_tolerance_m))
      .s("settle_increment_measure",
         st.increment_measure == SlidingStageSettings::IncrementMeasure::kAllMax ? "all_max" : "off_wall");
  return m.yaml();
}

YAML::Node morphingMap(const MorphingStageSettings& d) {
  using M = MorphingStageSettings::IncrementMeasure;
  Map m;
  m.b("enabled", d.enabled)
      .s("target", d.target)
      .n("target_unit_mm", mm(d.target_length_unit_m))
      .n("gain_pa_per_mm", d.forces.gain_pa_per_m * 1e-3)
      .n("spring_pa_per_mm", d.forces.spring_pa_per_m * 1e-3)
      .n("max_traction_pa", d.forces.max_traction_pa)
      .n("max_distance_mm", mm(d.forces.max_distance_m))
      .b("skip_constrained", d.forces.skip_constrained)
      .n("voxel_size_mm", mm(d.field.voxel_size_m))
      .i("max_voxels_per_axis", d.field.max_voxels_per_axis)
      .n("time_step_s", d.time_step_s)
      .n("tolerance_mean_mm", mm(d.tolerance_mean_m))
      .n("tolerance_p95_mm", mm(d.tolerance_p95_m))
      .n("increment_tolerance_mm", mm(d.increment_tolerance_m))
      .s("increment_measure", d.increment_measure == M::kAllMax      ? "all_max"
                              : d.increment_measure == M::kPulledP95 ? "pulled_p95"
                                                                     : "off_wall")
      .n("volume_tolerance_percent", d.volume_tolerance_percent)
      .n("alpha_reversal_growth", d.alpha_reversal_growth)
      .i("max_steps", d.max_steps)
      .n("max_step_move_mm", mm(d.max_step_move_m))
      .n("max_step_volume_change_percent", d.max_step_volume_change_percent);
  return m.yaml();
}

YAML::Node coarseStartMap(const CoarseStartSettings& c) {
  Map m;
  m.i("elements", c.elements).n("snap_tolerance_mm", mm(c.snap_tolerance_m));
  return m.yaml();
}

YAML::Node uncertaintyMap(const UncertaintySettings& u) {
  Map m;
  m.b("enabled", u.enabled)
      .i("samples", u.samples)
      .n("youngs_modulus_factor_min", u.youngs_modulus_factor_min)
      .n("youngs_modulus_factor_max", u.youngs_modulus_factor_max)
      .n("poisson_ratio_min", u.poisson_ratio_min)
      .n("poisson_ratio_max", u.poisson_ratio_max)
      .n("time_step_factor_min", u.time_step_factor_min)
      .n("time_step_factor_max", u.time_step_factor_max)
      .n("confidence", u.confidence);
  return m.yaml();
}

}  // namespace

std::string effectiveCaseYaml(const std::string& case_path) {
  double snap_m = 0.0;
  const MeshingOptions meshing = loadMeshingOptions(case_path, &snap_m);
  return effectiveCaseYaml(case_path, meshing, snap_m, loadPipelineSettings(case_path));
}

std::string effectiveCaseYaml(const std::string& case_path, const MeshingOptions& meshing,
                              double lesion_snap_tolerance_m, const PipelineSettings& settings) {
  const YAML::Node root = yaml_fields::loadFile(case_path);
  const std::string source = yaml_fields::caseSource(root, case_path);
  YAML::Node out(YAML::NodeType::Map);
  if (source == "phantom") {
    out["phantom"] = phantomMap(loadPhantomParams(case_path));
  } else if (source == "mri") {
    out["mri"] = mriMap(loadMriCaseSource(case_path));
    out["segmentation"] = segmentationMap(loadSegmentationSettings(case_path));
  } else {
    YAML::Node map = YAML::Clone(root[source]);  // image: or mesh:, with its path made absolute
    if (map.IsMap() && map["path"] && map["path"].IsScalar())
      map["path"] = yaml_fields::pathBeside(case_path, map["path"].as<std::string>());
    out[source] = map;
  }
  if (root["lesions"]) out["lesions"] = YAML::Clone(root["lesions"]);
  out["meshing"] = meshingMap(meshing, lesion_snap_tolerance_m);
  out["simulation"] = simulationMap(settings.simulation, source == "phantom");
  out["stiffening"] = stiffeningMap(settings.stiffening);
  out["sliding"] = slidingMap(settings);
  out["morphing"] = morphingMap(settings.morphing);
  out["coarse_start"] = coarseStartMap(settings.coarse_start);
  out["uncertainty"] = uncertaintyMap(settings.uncertainty);
  YAML::Emitter e;
  e << out;
  if (!e.good()) throw std::runtime_error("effectiveCaseYaml: " + e.GetLastError());
  return std::string(e.c_str()) + "\n";
}

}  // namespace breast_sim::core
