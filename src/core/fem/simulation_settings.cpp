#include "breast_sim/core/fem/simulation_settings.h"

#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/fem/anp_tet_fem.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/unloaded_state.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/tissue_labels.h"
#include "breast_sim/core/solver/aggregation_multigrid.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "../util/yaml_fields.h"

namespace breast_sim::core {

namespace {
double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}
template <class T>
[[noreturn]] void invalid(const char* name, const T& v, const char* range) {
  std::ostringstream s;
  s << "simulation setting '" << name << "' = " << v << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}
}  // namespace

std::string SolverSettings::kindName(Kind k) {
  switch (k) {
    case Kind::kMultigrid: return "multigrid";
    case Kind::kCholmod: return "cholmod";
    case Kind::kJacobiPcg: return "jacobi-pcg";
    case Kind::kAggregation: return "aggregation";
  }
  return "?";
}

SolverSettings::Kind SolverSettings::kindFromName(const std::string& name) {
  if (name == "multigrid") return Kind::kMultigrid;
  if (name == "cholmod") return Kind::kCholmod;
  if (name == "jacobi-pcg") return Kind::kJacobiPcg;
  if (name == "aggregation") return Kind::kAggregation;
  throw std::invalid_argument("unknown solver '" + name + "': expected multigrid, aggregation, cholmod or jacobi-pcg");
}

void SettleOptions::validate() const {
  if (!(time_step_s >= 0) || !std::isfinite(time_step_s)) invalid("settle.time_step_s", time_step_s, "≥ 0 s (0 = the dynamics time step)");
  if (!(increment_tolerance_m > 0)) invalid("settle.increment_tolerance_m", increment_tolerance_m, "> 0 m, e.g. 1e-5");
  if (consecutive_steps < 1) invalid("settle.consecutive_steps", consecutive_steps, "≥ 1");
  if (max_steps < 1) invalid("settle.max_steps", max_steps, "≥ 1");
}

void SimulationSettings::validate() const {
  material.validate();
  dynamics.validate();
  settle.validate();
  if (!(solver.relative_tolerance > 0 && solver.relative_tolerance < 1))
    invalid("solver.relative_tolerance", solver.relative_tolerance, "a value in (0, 1), e.g. 1e-3");
  if (solver.max_iterations < 1) invalid("solver.max_iterations", solver.max_iterations, "≥ 1");
  if (solver.projection_vectors < 1 || solver.projection_vectors > kMaxProjectionVectors)
    invalid("solver.projection_vectors", solver.projection_vectors,
            ("1 .. " + std::to_string(kMaxProjectionVectors) + " (1 = the warm start alone)").c_str());
  if (solver.multigrid.pre_smoothing_steps < 1 || solver.multigrid.post_smoothing_steps < 1)
    invalid("solver.multigrid smoothing steps", solver.multigrid.pre_smoothing_steps, "≥ 1");
  if (solver.multigrid.coarse_update_interval < 1)
    invalid("solver.multigrid.coarse_update_interval", solver.multigrid.coarse_update_interval, "≥ 1");
  if (!(solver.multigrid.coarse_update_cost_iterations > 0) || !std::isfinite(solver.multigrid.coarse_update_cost_iterations))
    invalid("solver.multigrid.coarse_update_cost_iterations", solver.multigrid.coarse_update_cost_iterations, "> 0, e.g. 5");
  if (solver.cholmod.blas_threads < 0)
    invalid("solver.cholmod.blas_threads", solver.cholmod.blas_threads, "≥ 0 (0 = as configured)");
  if (!(gravity_mps2 >= 0) || !std::isfinite(gravity_mps2)) invalid("gravity_mps2", gravity_mps2, "≥ 0 m/s², e.g. 9.81");
  if (solver.coarsening.max_coarsest_elements < 10)
    invalid("solver.coarsening.max_coarsest_elements", solver.coarsening.max_coarsest_elements, "≥ 10");
  if (!(anp_element_volume_fraction >= 0 && anp_element_volume_fraction <= 1))
    invalid("anp_element_volume_fraction", anp_element_volume_fraction, "a share in [0, 1], e.g. 0 (pure ANP)");
  if (!(anp_inversion_barrier >= 0 && anp_inversion_barrier < 1))
    invalid("anp_inversion_barrier", anp_inversion_barrier, "a volume ratio in [0, 1), e.g. 0.3 (0 = off)");
  if (!(anp_inversion_barrier_stiffness > 0) || !std::isfinite(anp_inversion_barrier_stiffness))
    invalid("anp_inversion_barrier_stiffness", anp_inversion_barrier_stiffness, "a positive multiple of the bulk modulus, e.g. 100");
  for (const auto& [region, e] : region_youngs_modulus_pa)
    if (!(e > 0) || !std::isfinite(e))
      invalid(("region_youngs_modulus_pa[" + std::to_string(region) + "]").c_str(), e, "a positive modulus in Pa");
}

Eigen::VectorXd elementYoungsModuli(const TetMesh& mesh, const SimulationSettings& s) {
  if (s.region_youngs_modulus_pa.empty()) return {};
  const std::vector<int>& labels = mesh.regionLabels();
  Eigen::VectorXd e = Eigen::VectorXd::Constant(mesh.numTets(), s.material.youngs_modulus_pa);
  for (int t = 0; t < mesh.numTets() && t < static_cast<int>(labels.size()); ++t) {
    const auto it = s.region_youngs_modulus_pa.find(labels[t]);
    if (it != s.region_youngs_modulus_pa.end()) e[t] = it->second;
  }
  return e;
}

SimulationSettings loadSimulationSettings(const std::string& yaml_path) {
  using namespace yaml_fields;
  const YAML::Node root = loadFile(yaml_path);
  SimulationSettings s;
  if (!root.IsMap() || !root["simulation"]) return s;
  const YAML::Node m = root["simulation"];
  if (m.IsNull()) return s;
  const std::string f = yaml_path;
  checkKeys(m,
            {"youngs_modulus_pa", "poisson_ratio", "density_kg_per_m3", "time_step_s", "mass_damping_per_s",
             "stiffness_damping_s", "solver", "solver_relative_tolerance", "solver_max_iterations",
             "multigrid_smoother", "multigrid_chebyshev_ratio", "multigrid_smoothing_steps", "multigrid_coarse_update_interval",
             "multigrid_coarse_update_adaptive", "multigrid_coarse_update_cost_iterations",
             "multigrid_max_coarsest_elements", "fixed_node_set", "gravity_mps2", "stiffening", "volume_term", "element", "anp_element_volume_fraction", "anp_inversion_barrier", "anp_inversion_barrier_stiffness", "sliding", "reference_state", "settle_time_step_s",
             "settle_increment_tolerance_mm", "settle_max_steps", "tissue_youngs_modulus_pa"},
            f, "simulation");
  const double inf = std::numeric_limits<double>::infinity();
  auto key = [](const char* k) { return std::string("simulation.") + k; };
  if (m["youngs_modulus_pa"]) s.material.youngs_modulus_pa = numberIn(m["youngs_modulus_pa"], f, key("youngs_modulus_pa"), 0, inf, true, false, "Pa");
  if (m["poisson_ratio"]) s.material.poisson_ratio = numberIn(m["poisson_ratio"], f, key("poisson_ratio"), -1, 0.5, true, true);
  if (m["density_kg_per_m3"]) s.material.density_kg_per_m3 = numberIn(m["density_kg_per_m3"], f, key("density_kg_per_m3"), 0, inf, true, false, "kg/m^3");
  if (m["time_step_s"]) s.dynamics.time_step_s = numberIn(m["time_step_s"], f, key("time_step_s"), 0, 100, true, false, "s");
  if (m["mass_damping_per_s"]) s.dynamics.mass_damping_per_s = numberIn(m["mass_damping_per_s"], f, key("mass_damping_per_s"), 0, inf, false, false, "1/s");
  if (m["stiffness_damping_s"]) s.dynamics.stiffness_damping_s = numberIn(m["stiffness_damping_s"], f, key("stiffness_damping_s"), 0, inf, false, false, "s");
  if (m["solver"]) s.solver.kind = SolverSettings::kindFromName(choice(m["solver"], f, key("solver"), {"multigrid", "aggregation", "cholmod", "jacobi-pcg"}));
  if (m["solver_relative_tolerance"]) s.solver.relative_tolerance = numberIn(m["solver_relative_tolerance"], f, key("solver_relative_tolerance"), 0, 1, true, true);
  if (m["solver_max_iterations"]) s.solver.max_iterations = static_cast<int>(integer(m["solver_max_iterations"], f, key("solver_max_iterations"), 1, 100000));
  if (m["multigrid_smoother"]) {
    const std::string sm = choice(m["multigrid_smoother"], f, key("multigrid_smoother"), {"jacobi", "gauss-seidel", "chebyshev"});
    s.solver.multigrid.smoother = sm == "jacobi"         ? MultigridOptions::Smoother::kJacobi
                                  : sm == "gauss-seidel" ? MultigridOptions::Smoother::kGaussSeidel
                                                         : MultigridOptions::Smoother::kChebyshev;
  }
  if (m["multigrid_chebyshev_ratio"])
    s.solver.multigrid.chebyshev_ratio = numberIn(m["multigrid_chebyshev_ratio"], f, key("multigrid_chebyshev_ratio"), 1.5, 100);
  if (m["multigrid_smoothing_steps"])
    s.solver.multigrid.pre_smoothing_steps = s.solver.multigrid.post_smoothing_steps =
        static_cast<int>(integer(m["multigrid_smoothing_steps"], f, key("multigrid_smoothing_steps"), 1, 10));
  if (m["multigrid_coarse_update_interval"])
    s.solver.multigrid.coarse_update_interval = static_cast<int>(integer(m["multigrid_coarse_update_interval"], f, key("multigrid_coarse_update_interval"), 1, 1000));
  if (m["multigrid_coarse_update_adaptive"])
    s.solver.multigrid.coarse_update_adaptive = boolean(m["multigrid_coarse_update_adaptive"], f, key("multigrid_coarse_update_adaptive"));
  if (m["multigrid_coarse_update_cost_iterations"])
    s.solver.multigrid.coarse_update_cost_iterations =
        numberIn(m["multigrid_coarse_update_cost_iterations"], f, key("multigrid_coarse_update_cost_iterations"), 0, 1000, true, false);
  if (m["multigrid_max_coarsest_elements"])
    s.solver.coarsening.max_coarsest_elements = static_cast<int>(integer(m["multigrid_max_coarsest_elements"], f, key("multigrid_max_coarsest_elements"), 10, 100000));
  if (m["fixed_node_set"]) s.fixed_node_set = m["fixed_node_set"].IsNull() ? "" : text(m["fixed_node_set"], f, key("fixed_node_set"));
  if (m["gravity_mps2"]) s.gravity_mps2 = numberIn(m["gravity_mps2"], f, key("gravity_mps2"), 0, 1000, false, false, "m/s^2");
  if (m["stiffening"]) s.stiffening = boolean(m["stiffening"], f, key("stiffening"));
  if (m["sliding"]) s.sliding = boolean(m["sliding"], f, key("sliding"));
  if (m["reference_state"])
    s.reference_state = choice(m["reference_state"], f, key("reference_state"), {"unloaded", "prone"}) == "prone"
                            ? SimulationSettings::ReferenceState::kProne
                            : SimulationSettings::ReferenceState::kUnloaded;
  if (m["element"])
    s.element = choice(m["element"], f, key("element"), {"linear", "anp"}) == "linear"
                    ? SimulationSettings::Element::kLinearTet
                    : SimulationSettings::Element::kAnpTet;
  if (m["anp_element_volume_fraction"])
    s.anp_element_volume_fraction =
        numberIn(m["anp_element_volume_fraction"], f, key("anp_element_volume_fraction"), 0, 1);
  if (m["anp_inversion_barrier"])
    s.anp_inversion_barrier = numberIn(m["anp_inversion_barrier"], f, key("anp_inversion_barrier"), 0, 1, false, true);
  if (m["anp_inversion_barrier_stiffness"])
    s.anp_inversion_barrier_stiffness =
        numberIn(m["anp_inversion_barrier_stiffness"], f, key("anp_inversion_barrier_stiffness"), 0, 1e6, true, false);
  if (m["volume_term"])
    s.volume_term = choice(m["volume_term"], f, key("volume_term"), {"trace", "determinant"}) == "trace"
                        ? CorotatedTetFem::VolumeTerm::kTrace
                        : CorotatedTetFem::VolumeTerm::kDeterminant;
  if (m["settle_time_step_s"]) s.settle.time_step_s = numberIn(m["settle_time_step_s"], f, key("settle_time_step_s"), 0, 100, false, false, "s");
  if (m["settle_increment_tolerance_mm"]) s.settle.increment_tolerance_m = 1e-3 * numberIn(m["settle_increment_tolerance_mm"], f, key("settle_increment_tolerance_mm"), 0, 10, true, false, "mm");
  if (m["settle_max_steps"]) s.settle.max_steps = static_cast<int>(integer(m["settle_max_steps"], f, key("settle_max_steps"), 1, 1000000));
  if (m["tissue_youngs_modulus_pa"]) {
    // Tissue names (the classes of model/tissue_labels.h, which are the elements' region labels).
    const YAML::Node t = m["tissue_youngs_modulus_pa"];
    if (!t.IsMap())
      throw std::runtime_error(f + ": simulation.tissue_youngs_modulus_pa: expected a map tissue -> Pa, e.g. {lesion: 20000}");
    checkKeys(t, {"fat", "fibroglandular", "skin", "lesion"}, f, "simulation.tissue_youngs_modulus_pa");
    for (const TissueClass c : {TissueClass::kFat, TissueClass::kFibroglandular, TissueClass::kSkin, TissueClass::kLesion}) {
      const std::string name = tissueClassName(c);
      if (t[name])
        s.region_youngs_modulus_pa[static_cast<int>(c)] =
            numberIn(t[name], f, key("tissue_youngs_modulus_pa.") + name, 0, inf, true, false, "Pa");
    }
  }
  try {
    s.validate();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(yaml_path + ": 'simulation': " + e.what());
  }
  return s;
}

namespace {

// The nodes of settings.fixed_node_set (none for ""); `owner` names the mesh's origin in the message.
std::vector<int> fixedNodes(const TetMesh& mesh, const SimulationSettings& settings, const char* owner) {
  if (settings.fixed_node_set.empty()) return {};
  if (!mesh.hasNodeSet(settings.fixed_node_set)) {
    std::string msg = "simulation: fixed_node_set '" + settings.fixed_node_set + "' is not a node set of the " +
                      owner + mesh.nodeSetHint(settings.fixed_node_set);
    if (mesh.nodeSets().empty())
      msg += ": add the held nodes as a node set (TetMesh::setNodeSet, *NSET of an .inp file), or set "
             "fixed_node_set to \"\" to hold none";
    throw std::invalid_argument(msg);
  }
  return mesh.nodeSet(settings.fixed_node_set);
}

// The one build of both overloads. `coarse_from_case`: the coarse meshes were meshed from a case
// (possibly none: the fine mesh is small enough), `meshing_seconds` what that took.
SimulatorBuild build(const TetMesh& mesh, const SimulationSettings& settings, std::vector<TetMesh> coarse_meshes,
                     const Points& meshed_nodes_m, bool coarse_from_case, double meshing_seconds, const char* owner) {
  settings.validate();
  const bool multigrid = settings.solver.kind == SolverSettings::Kind::kMultigrid;
  if (!multigrid && !coarse_meshes.empty())
    throw std::invalid_argument("buildSimulator: " + std::to_string(coarse_meshes.size()) +
                                " coarse meshes given, but they are used only by the solver 'multigrid' (the solver is '" +
                                SolverSettings::kindName(settings.solver.kind) + "')");
  if (multigrid && coarse_meshes.empty() && !coarse_from_case)
    throw std::invalid_argument(
        "buildSimulator: the geometric multigrid needs coarse levels: give coarse meshes of the same domain "
        "(buildSimulator's coarse_meshes, coarsest last), or choose the solver 'aggregation' (smoothed "
        "aggregation, no coarse meshes) or 'cholmod' (direct)");
  SimulatorBuild b;
  const std::vector<int> fixed = fixedNodes(mesh, settings, owner);
  PcgOptions pcg;
  pcg.relative_tolerance = settings.solver.relative_tolerance;
  pcg.max_iterations = settings.solver.max_iterations;
  pcg.projection_vectors = settings.solver.projection_vectors;
  std::unique_ptr<LinearSolver> solver;
  const auto t0 = std::chrono::steady_clock::now();
  switch (settings.solver.kind) {
    case SolverSettings::Kind::kCholmod: solver = std::make_unique<CholmodSolver>(settings.solver.cholmod); break;
    case SolverSettings::Kind::kJacobiPcg: solver = std::make_unique<PcgSolver>(pcg); break;
    case SolverSettings::Kind::kAggregation: {
      // The matrix's pattern is fixed and its values change every step: the aggregates and
      // prolongators of the first step are kept, each step redoes only the Galerkin products and
      // the coarsest factorization.
      AggregationMultigridOptions sa;
      sa.reuse_prolongators = true;
      solver = std::make_unique<AggregationMultigridPcgSolver>(mesh.nodes(), pcg, sa);
      break;
    }
    case SolverSettings::Kind::kMultigrid: {
      std::vector<TetMesh> meshes;
      meshes.reserve(coarse_meshes.size() + 1);
      if (meshed_nodes_m.size() == 0) {
        meshes.push_back(mesh);
      } else {
        try {
          meshes.push_back(withNodes(mesh, meshed_nodes_m));
        } catch (const std::invalid_argument& e) {
          throw std::invalid_argument(std::string("buildSimulator: meshed_nodes_m: ") + e.what());
        }
      }
      for (TetMesh& m : coarse_meshes) meshes.push_back(std::move(m));
      const MeshHierarchy h(std::move(meshes));
      b.multigrid_levels = h.numLevels();
      for (int l = 0; l < h.numLevels(); ++l) b.level_nodes.push_back(h.mesh(l).numNodes());
      MultigridOptions mg = settings.solver.multigrid;
      // The fine-level bound λ_max(D⁻¹A) ≤ 4 holds for four-node element matrices only; the ANP
      // volumetric terms span node stars: estimate it like a coarse level's.
      if (settings.element == SimulationSettings::Element::kAnpTet) mg.fine_eigenvalue_bound = 0.0;
      solver = std::make_unique<MultigridPcgSolver>(h, pcg, mg);
      break;
    }
  }
  b.hierarchy_seconds = meshing_seconds + since(t0);
  const auto t1 = std::chrono::steady_clock::now();
  std::unique_ptr<ElementFormulation> elements;
  if (settings.element == SimulationSettings::Element::kAnpTet) {
    auto anp = std::make_unique<AnpTetFem>(mesh, settings.material);
    anp->setElementYoungsModuli(elementYoungsModuli(mesh, settings));  // empty: E0 everywhere
    anp->setElementVolumeFraction(settings.anp_element_volume_fraction);
    anp->setInversionBarrier(settings.anp_inversion_barrier, settings.anp_inversion_barrier_stiffness);
    elements = std::move(anp);
  } else {
    auto tet = std::make_unique<CorotatedTetFem>(mesh, settings.material);
    tet->setVolumeTerm(settings.volume_term);
    tet->setElementYoungsModuli(elementYoungsModuli(mesh, settings));
    elements = std::move(tet);
  }
  b.simulator = std::make_unique<DynamicSimulator>(mesh, std::move(elements), settings.material, settings.dynamics,
                                                   std::move(solver));
  if (!fixed.empty()) b.simulator->fixNodes(fixed);
  b.setup_seconds = since(t1);
  return b;
}

}  // namespace

SimulatorBuild buildSimulator(const TetMesh& mesh, const SimulationSettings& settings,
                              std::vector<TetMesh> coarse_meshes, const Points& meshed_nodes_m) {
  return build(mesh, settings, std::move(coarse_meshes), meshed_nodes_m, false, 0.0, "mesh");
}

SimulatorBuild buildSimulator(const ModelCase& model_case, const SimulationModel& model,
                              const SimulationSettings& settings, std::optional<std::vector<TetMesh>> coarse_meshes,
                              const Points& meshed_nodes_m) {
  // Invalid settings and a missing node set are reported before the (slow) coarse meshing.
  settings.validate();
  fixedNodes(model.mesh, settings, "model");
  std::vector<TetMesh> coarse;
  double meshing_seconds = 0.0;
  if (coarse_meshes) {
    coarse = std::move(*coarse_meshes);
  } else if (settings.solver.kind == SolverSettings::Kind::kMultigrid) {
    const auto t = std::chrono::steady_clock::now();
    coarse = buildCoarseMeshes(model_case, model, settings.solver.coarsening);
    meshing_seconds = since(t);
  }
  return build(model.mesh, settings, std::move(coarse), meshed_nodes_m, true, meshing_seconds, "model");
}

}  // namespace breast_sim::core
