// Settings of the combined pipeline: validation and the `sliding:` and `morphing:` maps of a case file.
#include <cmath>
#include <filesystem>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "../util/yaml_fields.h"

namespace breast_sim::core {

void MorphingStageSettings::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "morphing '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  forces.validate();
  field.validate();
  if (!(target_length_unit_m > 0) || !std::isfinite(target_length_unit_m)) bad("target_length_unit_m", target_length_unit_m, "> 0 m per file unit");
  if (!(time_step_s > 0) || time_step_s > 10) bad("time_step_s", time_step_s, "in (0, 10] s");
  if (!(tolerance_mean_m > 0) || !std::isfinite(tolerance_mean_m)) bad("tolerance_mean_m", tolerance_mean_m, "> 0 m");
  if (!(tolerance_p95_m > 0) || !std::isfinite(tolerance_p95_m)) bad("tolerance_p95_m", tolerance_p95_m, "> 0 m");
  if (!(increment_tolerance_m > 0) || !std::isfinite(increment_tolerance_m)) bad("increment_tolerance_m", increment_tolerance_m, "> 0 m");
  if (max_steps < 1) bad("max_steps", max_steps, "≥ 1");
  if (!(volume_tolerance_percent >= 0) || volume_tolerance_percent > 100)
    bad("volume_tolerance_percent", volume_tolerance_percent, "in [0, 100] % (0 = no volume condition)");
  if (!(max_step_move_m >= 0) || !std::isfinite(max_step_move_m)) bad("max_step_move_m", max_step_move_m, ">= 0 m (0 = no bound)");
  if (!(max_step_volume_change_percent >= 0) || !std::isfinite(max_step_volume_change_percent))
    bad("max_step_volume_change_percent", max_step_volume_change_percent, ">= 0 % (0 = no bound)");
  if (!(alpha_reversal_growth >= 1) || !std::isfinite(alpha_reversal_growth))
    bad("alpha_reversal_growth", alpha_reversal_growth, "≥ 1 (1: α doubles per repeated reversal)");
}

void SlidingStageSettings::validate() const {
  if (!(time_step_s >= 0) || time_step_s > 10) {
    std::ostringstream s;
    s << "sliding 'time_step_s' = " << time_step_s << " is invalid: expected in [0, 10] s (0 = the dynamics time step)";
    throw std::invalid_argument(s.str());
  }
  if (!(increment_tolerance_m >= 0) || !std::isfinite(increment_tolerance_m)) {
    std::ostringstream s;
    s << "sliding 'increment_tolerance_m' = " << increment_tolerance_m << " is invalid: expected >= 0 m (0 = the settle tolerance)";
    throw std::invalid_argument(s.str());
  }
}

void CoarseStartSettings::validate() const {
  if (elements < 0 || elements > 100000000) {
    std::ostringstream s;
    s << "coarse_start 'elements' = " << elements << " is invalid: expected 0 (off) or a target element count below the model's";
    throw std::invalid_argument(s.str());
  }
  if (!(snap_tolerance_m > 0) || snap_tolerance_m > 0.1) {
    std::ostringstream s;
    s << "coarse_start 'snap_tolerance_m' = " << snap_tolerance_m << " is invalid: expected in (0, 0.1] m";
    throw std::invalid_argument(s.str());
  }
}

void UncertaintySettings::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "uncertainty '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (samples < 4 || samples > 1000) bad("samples", samples, "in [4, 1000] (a region in 3D needs 4 samples)");
  if (!(youngs_modulus_factor_min > 0) || !(youngs_modulus_factor_min <= 100))
    bad("youngs_modulus_factor_min", youngs_modulus_factor_min, "in (0, 100]");
  if (!(youngs_modulus_factor_max >= youngs_modulus_factor_min) || !(youngs_modulus_factor_max <= 100))
    bad("youngs_modulus_factor_max", youngs_modulus_factor_max, "in [youngs_modulus_factor_min, 100]");
  if (!(poisson_ratio_min > 0) || !(poisson_ratio_min < 0.5)) bad("poisson_ratio_min", poisson_ratio_min, "in (0, 0.5)");
  if (!(poisson_ratio_max >= poisson_ratio_min) || !(poisson_ratio_max < 0.5))
    bad("poisson_ratio_max", poisson_ratio_max, "in [poisson_ratio_min, 0.5)");
  if (!(time_step_factor_min > 0) || !(time_step_factor_min <= 10)) bad("time_step_factor_min", time_step_factor_min, "in (0, 10]");
  if (!(time_step_factor_max >= time_step_factor_min) || !(time_step_factor_max <= 10))
    bad("time_step_factor_max", time_step_factor_max, "in [time_step_factor_min, 10]");
  if (!(confidence > 0) || !(confidence < 1)) bad("confidence", confidence, "in (0, 1), e.g. 0.95");
}

void PipelineSettings::validate() const {
  simulation.validate();
  stiffening.validate();
  sliding.validate();
  {
    WallSlipSettings w = wall_slip;  // with the shared friction of `sliding`
    w.static_friction = sliding.static_friction;
    w.kinetic_friction = sliding.kinetic_friction;
    w.static_threshold_pa = sliding.static_threshold_pa;
    w.validate();
  }
  sliding_stage.validate();
  morphing.validate();
  coarse_start.validate();
  uncertainty.validate();
  if (simulation.sliding && (!simulation.stiffening || simulation.fixed_node_set.empty()))
    throw std::invalid_argument(
        "simulation 'sliding' needs 'stiffening: true' and a 'fixed_node_set' (the nodes that slide): turn "
        "sliding off or set both");
}

PipelineSettings loadPipelineSettings(const std::string& yaml_path) {
  using namespace yaml_fields;
  PipelineSettings s;
  s.simulation = loadSimulationSettings(yaml_path);
  const YAML::Node root = loadFile(yaml_path);
  const std::string f = yaml_path;
  const double inf = std::numeric_limits<double>::infinity();
  if (root.IsMap() && root["sliding"] && !root["sliding"].IsNull()) {
    const YAML::Node m = root["sliding"];
    checkKeys(m,
              {"normal_sigma_mm", "mobility_mm_per_pa_s", "static_friction", "kinetic_friction", "static_threshold_pa",
               "inertia", "max_step_mm", "max_slide_mm", "thickness_limit", "gaussian_limit", "gaussian_amplitude",
               "gaussian_sigma_mm", "gaussian_sigma_fraction", "method", "normal_stiffness_pa_per_mm",
               "friction_stiffness_pa_per_mm", "tether_stiffness_pa_per_mm", "stick_speed_mm_per_s", "contact",
               "contact_gap_mm", "time_step_s", "settle_increment_tolerance_mm", "settle_increment_measure"},
              f, "sliding");
    auto key = [](const char* k) { return std::string("sliding.") + k; };
    SlidingSettings& d = s.sliding;
    if (m["normal_sigma_mm"]) d.field.sigma_m = 1e-3 * numberIn(m["normal_sigma_mm"], f, key("normal_sigma_mm"), 0, 50, true, false, "mm");
    if (m["mobility_mm_per_pa_s"]) d.mobility_m_per_pa_s = 1e-3 * numberIn(m["mobility_mm_per_pa_s"], f, key("mobility_mm_per_pa_s"), 0, inf, false, false, "mm/(Pa s)");
    if (m["static_friction"]) d.static_friction = numberIn(m["static_friction"], f, key("static_friction"), 0, 10);
    if (m["kinetic_friction"]) d.kinetic_friction = numberIn(m["kinetic_friction"], f, key("kinetic_friction"), 0, 10);
    if (m["static_threshold_pa"]) d.static_threshold_pa = numberIn(m["static_threshold_pa"], f, key("static_threshold_pa"), 0, inf, false, false, "Pa");
    if (m["inertia"]) d.inertia = numberIn(m["inertia"], f, key("inertia"), 0, 1, false, true);
    if (m["max_step_mm"]) d.max_step_m = 1e-3 * numberIn(m["max_step_mm"], f, key("max_step_mm"), 0, 100, true, false, "mm");
    if (m["max_slide_mm"]) d.max_slide_m = 1e-3 * numberIn(m["max_slide_mm"], f, key("max_slide_mm"), 0, 1000, false, false, "mm");
    if (m["thickness_limit"]) d.thickness_limit = boolean(m["thickness_limit"], f, key("thickness_limit"));
    if (m["gaussian_limit"]) d.gaussian_limit = boolean(m["gaussian_limit"], f, key("gaussian_limit"));
    if (m["gaussian_amplitude"]) d.gaussian_amplitude = numberIn(m["gaussian_amplitude"], f, key("gaussian_amplitude"), 0, 100, true, false);
    if (m["gaussian_sigma_mm"]) d.gaussian_sigma_m = 1e-3 * numberIn(m["gaussian_sigma_mm"], f, key("gaussian_sigma_mm"), 0, 1000, false, false, "mm");
    if (m["gaussian_sigma_fraction"]) d.gaussian_sigma_fraction = numberIn(m["gaussian_sigma_fraction"], f, key("gaussian_sigma_fraction"), 0, 2, true, false);
    if (m["method"]) {
      const std::string method = text(m["method"], f, key("method"));
      if (method == "implicit") s.sliding_method = PipelineSettings::SlidingMethod::kImplicit;
      else if (method == "explicit") s.sliding_method = PipelineSettings::SlidingMethod::kExplicit;
      else throw std::runtime_error(f + ": sliding.method is '" + method + "'; expected implicit or explicit");
    }
    WallSlipSettings& w = s.wall_slip;
    if (m["normal_stiffness_pa_per_mm"]) w.normal_stiffness_pa_per_m = 1e3 * numberIn(m["normal_stiffness_pa_per_mm"], f, key("normal_stiffness_pa_per_mm"), 0, inf, true, false, "Pa/mm");
    if (m["friction_stiffness_pa_per_mm"]) w.friction_stiffness_pa_per_m = 1e3 * numberIn(m["friction_stiffness_pa_per_mm"], f, key("friction_stiffness_pa_per_mm"), 0, inf, true, false, "Pa/mm");
    if (m["tether_stiffness_pa_per_mm"]) w.tether_stiffness_pa_per_m = 1e3 * numberIn(m["tether_stiffness_pa_per_mm"], f, key("tether_stiffness_pa_per_mm"), 0, inf, false, false, "Pa/mm");
    if (m["stick_speed_mm_per_s"]) w.stick_speed_mps = 1e-3 * numberIn(m["stick_speed_mm_per_s"], f, key("stick_speed_mm_per_s"), 0, inf, false, false, "mm/s");
    if (m["contact"]) w.contact = boolean(m["contact"], f, key("contact"));
    if (m["time_step_s"]) s.sliding_stage.time_step_s = numberIn(m["time_step_s"], f, key("time_step_s"), 0, 10, false, false, "s");
    if (m["settle_increment_tolerance_mm"]) s.sliding_stage.increment_tolerance_m = 1e-3 * numberIn(m["settle_increment_tolerance_mm"], f, key("settle_increment_tolerance_mm"), 0, 10, false, false, "mm");
    if (m["settle_increment_measure"]) {
      const std::string measure = text(m["settle_increment_measure"], f, key("settle_increment_measure"));
      if (measure == "all_max") s.sliding_stage.increment_measure = SlidingStageSettings::IncrementMeasure::kAllMax;
      else if (measure == "off_wall") s.sliding_stage.increment_measure = SlidingStageSettings::IncrementMeasure::kOffWall;
      else throw std::runtime_error(f + ": sliding.settle_increment_measure is '" + measure + "'; expected all_max or off_wall");
    }
    if (m["contact_gap_mm"]) w.contact_gap_m = 1e-3 * numberIn(m["contact_gap_mm"], f, key("contact_gap_mm"), 0, 10, false, false, "mm");
  }
  if (root.IsMap() && root["stiffening"] && !root["stiffening"].IsNull()) {
    // The α controller's preset and the fixed-wall settle criterion (StiffeningParams). Ranges that
    // depend on another key (initial within [min, max], min_rate ≤ 1 − decrease_factor) are checked
    // against that key's value as read here, so the error names both.
    const YAML::Node m = root["stiffening"];
    checkKeys(m,
              {"initial_alpha_per_pa", "min_alpha_per_pa", "max_alpha_per_pa", "decrease_factor", "increase_factor",
               "reversal_growth", "rate_halving", "min_rate", "max_reversals_per_step", "settle_max_speed_mm_per_s",
               "settle_max_relative_residual", "settle_consecutive_steps", "settle_max_modulus_excess"},
              f, "stiffening");
    auto key = [](const char* k) { return std::string("stiffening.") + k; };
    AlphaControllerParams& a = s.stiffening.alpha;
    if (m["min_alpha_per_pa"]) a.min_alpha_per_pa = numberIn(m["min_alpha_per_pa"], f, key("min_alpha_per_pa"), 0, 1e6, true, false, "1/Pa");
    if (m["max_alpha_per_pa"])
      a.max_alpha_per_pa = numberIn(m["max_alpha_per_pa"], f, key("max_alpha_per_pa") + " (>= stiffening.min_alpha_per_pa)",
                                    a.min_alpha_per_pa, 1e12, false, false, "1/Pa");
    if (m["initial_alpha_per_pa"])
      a.initial_alpha_per_pa = numberIn(m["initial_alpha_per_pa"], f,
                                        key("initial_alpha_per_pa") + " (within [min_alpha_per_pa, max_alpha_per_pa])",
                                        a.min_alpha_per_pa, a.max_alpha_per_pa, false, false, "1/Pa");
    if (m["decrease_factor"]) a.decrease_factor = numberIn(m["decrease_factor"], f, key("decrease_factor"), 0, 1, true, true);
    if (m["increase_factor"]) a.increase_factor = numberIn(m["increase_factor"], f, key("increase_factor"), 1, 1e6, true, false);
    if (m["reversal_growth"]) a.reversal_growth = numberIn(m["reversal_growth"], f, key("reversal_growth"), 1, 100);
    if (m["rate_halving"]) a.rate_halving = numberIn(m["rate_halving"], f, key("rate_halving"), 0, 1, true, true);
    if (m["min_rate"])
      a.min_rate = numberIn(m["min_rate"], f, key("min_rate") + " (at most 1 - stiffening.decrease_factor)", 0,
                            1 - a.decrease_factor);
    if (m["max_reversals_per_step"])
      s.stiffening.max_reversals_per_step = static_cast<int>(integer(m["max_reversals_per_step"], f, key("max_reversals_per_step"), 1, 1000));
    SettleCriterion& c = s.stiffening.settle;
    if (m["settle_max_speed_mm_per_s"])
      c.max_speed_mps = 1e-3 * numberIn(m["settle_max_speed_mm_per_s"], f, key("settle_max_speed_mm_per_s"), 0, 1e6, true, false, "mm/s");
    if (m["settle_max_relative_residual"])
      c.max_relative_residual = numberIn(m["settle_max_relative_residual"], f, key("settle_max_relative_residual"), 0, 1, true, false);
    if (m["settle_consecutive_steps"])
      c.consecutive_steps = static_cast<int>(integer(m["settle_consecutive_steps"], f, key("settle_consecutive_steps"), 1, 1000));
    if (m["settle_max_modulus_excess"])
      c.max_modulus_excess = numberIn(m["settle_max_modulus_excess"], f, key("settle_max_modulus_excess"), 0, 1, true, false);
    // The defaults of the keys not given must fit the ones given (e.g. min_alpha_per_pa above the
    // default initial α): named by the controller's field.
    try {
      s.stiffening.validate();
    } catch (const std::invalid_argument& e) {
      throw std::runtime_error(f + ": stiffening: " + e.what() + " (set the keys of 'stiffening:' consistently)");
    }
  }
  if (root.IsMap() && root["morphing"] && !root["morphing"].IsNull()) {
    const YAML::Node m = root["morphing"];
    checkKeys(m,
              {"enabled", "target", "target_unit_mm", "gain_pa_per_mm", "max_traction_pa", "max_distance_mm", "skip_constrained",
               "voxel_size_mm", "max_voxels_per_axis", "time_step_s", "tolerance_mean_mm", "tolerance_p95_mm",
               "increment_tolerance_mm", "increment_measure", "max_steps", "alpha_reversal_growth", "spring_pa_per_mm",
               "volume_tolerance_percent", "max_step_move_mm", "max_step_volume_change_percent"},
              f, "morphing");
    auto key = [](const char* k) { return std::string("morphing.") + k; };
    MorphingStageSettings& d = s.morphing;
    if (m["enabled"]) d.enabled = boolean(m["enabled"], f, key("enabled"));
    if (m["target"]) {
      d.target = m["target"].IsNull() ? "" : text(m["target"], f, key("target"));
      if (!isTargetKeyword(d.target)) d.target = pathBeside(yaml_path, d.target);
    }
    if (m["target_unit_mm"]) d.target_length_unit_m = 1e-3 * numberIn(m["target_unit_mm"], f, key("target_unit_mm"), 0, 1e6, true, false, "mm per file unit");
    if (m["gain_pa_per_mm"]) d.forces.gain_pa_per_m = 1e3 * numberIn(m["gain_pa_per_mm"], f, key("gain_pa_per_mm"), 0, inf, false, false, "Pa/mm");
    if (m["max_traction_pa"]) d.forces.max_traction_pa = numberIn(m["max_traction_pa"], f, key("max_traction_pa"), 0, inf, false, false, "Pa");
    if (m["max_distance_mm"]) d.forces.max_distance_m = 1e-3 * numberIn(m["max_distance_mm"], f, key("max_distance_mm"), 0, inf, false, false, "mm");
    if (m["spring_pa_per_mm"]) d.forces.spring_pa_per_m = 1e3 * numberIn(m["spring_pa_per_mm"], f, key("spring_pa_per_mm"), 0, inf, false, false, "Pa/mm");
    if (m["skip_constrained"]) d.forces.skip_constrained = boolean(m["skip_constrained"], f, key("skip_constrained"));
    if (m["voxel_size_mm"]) d.field.voxel_size_m = 1e-3 * numberIn(m["voxel_size_mm"], f, key("voxel_size_mm"), 0, 100, true, false, "mm");
    if (m["max_voxels_per_axis"]) d.field.max_voxels_per_axis = static_cast<int>(integer(m["max_voxels_per_axis"], f, key("max_voxels_per_axis"), 8, 2048));
    if (m["time_step_s"]) d.time_step_s = numberIn(m["time_step_s"], f, key("time_step_s"), 0, 10, true, false, "s");
    if (m["tolerance_mean_mm"]) d.tolerance_mean_m = 1e-3 * numberIn(m["tolerance_mean_mm"], f, key("tolerance_mean_mm"), 0, 1000, true, false, "mm");
    if (m["tolerance_p95_mm"]) d.tolerance_p95_m = 1e-3 * numberIn(m["tolerance_p95_mm"], f, key("tolerance_p95_mm"), 0, 1000, true, false, "mm");
    if (m["increment_tolerance_mm"]) d.increment_tolerance_m = 1e-3 * numberIn(m["increment_tolerance_mm"], f, key("increment_tolerance_mm"), 0, 10, true, false, "mm");
    if (m["increment_measure"]) {
      const std::string measure = text(m["increment_measure"], f, key("increment_measure"));
      if (measure == "all_max") d.increment_measure = MorphingStageSettings::IncrementMeasure::kAllMax;
      else if (measure == "pulled_p95") d.increment_measure = MorphingStageSettings::IncrementMeasure::kPulledP95;
      else if (measure == "off_wall") d.increment_measure = MorphingStageSettings::IncrementMeasure::kOffWall;
      else throw std::runtime_error(f + ": morphing.increment_measure is '" + measure + "'; expected all_max, pulled_p95 or off_wall");
    }
    if (m["alpha_reversal_growth"]) d.alpha_reversal_growth = numberIn(m["alpha_reversal_growth"], f, key("alpha_reversal_growth"), 1, 100);
    if (m["volume_tolerance_percent"]) d.volume_tolerance_percent = numberIn(m["volume_tolerance_percent"], f, key("volume_tolerance_percent"), 0, 100, false, false, "%");
    if (m["max_step_move_mm"]) d.max_step_move_m = 1e-3 * numberIn(m["max_step_move_mm"], f, key("max_step_move_mm"), 0, inf, false, false, "mm");
    if (m["max_step_volume_change_percent"])
      d.max_step_volume_change_percent = numberIn(m["max_step_volume_change_percent"], f, key("max_step_volume_change_percent"), 0, inf, false, false, "%");
    if (m["max_steps"]) d.max_steps = static_cast<int>(integer(m["max_steps"], f, key("max_steps"), 1, 1000000));
  }
  if (root.IsMap() && root["coarse_start"] && !root["coarse_start"].IsNull()) {
    const YAML::Node m = root["coarse_start"];
    checkKeys(m, {"elements", "snap_tolerance_mm"}, f, "coarse_start");
    if (m["elements"]) s.coarse_start.elements = static_cast<int>(integer(m["elements"], f, "coarse_start.elements", 0, 100000000));
    if (m["snap_tolerance_mm"])
      s.coarse_start.snap_tolerance_m = 1e-3 * numberIn(m["snap_tolerance_mm"], f, "coarse_start.snap_tolerance_mm", 0, 100, true, false, "mm");
  }
  if (root.IsMap() && root["uncertainty"] && !root["uncertainty"].IsNull()) {
    const YAML::Node m = root["uncertainty"];
    checkKeys(m,
              {"enabled", "samples", "youngs_modulus_factor_min", "youngs_modulus_factor_max", "poisson_ratio_min",
               "poisson_ratio_max", "time_step_factor_min", "time_step_factor_max", "confidence"},
              f, "uncertainty");
    auto key = [](const char* k) { return std::string("uncertainty.") + k; };
    UncertaintySettings& u = s.uncertainty;
    if (m["enabled"]) u.enabled = boolean(m["enabled"], f, key("enabled"));
    if (m["samples"]) u.samples = static_cast<int>(integer(m["samples"], f, key("samples"), 4, 1000));
    if (m["youngs_modulus_factor_min"]) u.youngs_modulus_factor_min = numberIn(m["youngs_modulus_factor_min"], f, key("youngs_modulus_factor_min"), 0, 100, true);
    if (m["youngs_modulus_factor_max"]) u.youngs_modulus_factor_max = numberIn(m["youngs_modulus_factor_max"], f, key("youngs_modulus_factor_max"), 0, 100, true);
    if (m["poisson_ratio_min"]) u.poisson_ratio_min = numberIn(m["poisson_ratio_min"], f, key("poisson_ratio_min"), 0, 0.5, true, true);
    if (m["poisson_ratio_max"]) u.poisson_ratio_max = numberIn(m["poisson_ratio_max"], f, key("poisson_ratio_max"), 0, 0.5, true, true);
    if (m["time_step_factor_min"]) u.time_step_factor_min = numberIn(m["time_step_factor_min"], f, key("time_step_factor_min"), 0, 10, true);
    if (m["time_step_factor_max"]) u.time_step_factor_max = numberIn(m["time_step_factor_max"], f, key("time_step_factor_max"), 0, 10, true);
    if (m["confidence"]) u.confidence = numberIn(m["confidence"], f, key("confidence"), 0, 1, true, true);
  }
  try {
    s.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(yaml_path + ": " + e.what());
  }
  return s;
}

}  // namespace breast_sim::core
