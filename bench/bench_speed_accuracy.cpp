// Speed against accuracy: our settled gravity states against an independent CalculiX
// reference (neo-Hookean, NLGEOM; reference/calculix.h), two studies:
//
//  locking  at one mesh, error against Poisson's ratio ν: our formulations (--locking-methods,
//           settled tightly: no solver error), CalculiX C3D4 (the same elements, neo-Hookean) and
//           CalculiX C3D10 (quadratic tetrahedra on the same corners: the locking-free reference).
//           Errors are against C3D10.
//  sweep    element counts × methods: compute time to a settled state [s] against the error of the
//           settled displacement [mm] with respect to the reference on the finest mesh
//           (--reference-target, --reference-element), interpolated at our nodes. Methods:
//             linear/multigrid                linear FEM (no rotations), multigrid-PCG, settle()
//             corotated/multigrid             co-rotated FEM, multigrid-PCG, settle()
//             corotated/cholmod               co-rotated FEM, CHOLMOD, settle()
//             corotated+stiffening/multigrid  von Mises stiffening with time-step reversal (the main job)
//             corotated+stiffening/cholmod    the same with CHOLMOD
//             corotated-det[+stiffening]/...  with the fixed co-rotated J − 1 volume term (docs/corotated)
//             anp[+stiffening]/...            average-nodal-pressure tetrahedra (fem/anp_tet_fem.h)
//             anp-b<β>-j<J_b>-c<c>[+stiffening]/... ANP keeping the share β of the bulk modulus per
//                                             element, and an inversion barrier below J_b of stiffness
//                                             c × bulk modulus (each optional; c 100 by default)
//           Time = the settling steps (the simulator's set-up — multigrid hierarchy, CHOLMOD
//           analysis — is listed beside it, not included; meshing is listed too). A run that throws
//           (e.g. a solver returning non-finite velocities) is a row "FAILED" with the message; the
//           sweep goes on. With per-tissue moduli in the case (simulation.tissue_youngs_modulus_pa,
//           a stiff inclusion), --uniform-modulus-methods NAME,... also runs those methods with E0
//           everywhere ("NAME uniform-E"): the error of a model that ignores the inclusion.
//           --wall sliding: the chest wall slides instead of being fixed, in a form CalculiX can
//           solve exactly: every method settles with the wall fixed, then the wall nodes are
//           released onto implicit sliding (sliding/wall_slip.h) with friction off (μ = 0, no
//           stick spring to speak of), skin–wall contact off and a tangential tether κ_0 / w_i
//           (--tether-pa-per-mm, the case's limiting weights w_i) — an elastic, path-independent
//           problem; methods are named "<formulation>+sliding/<solver>". The reference holds each
//           wall node's normal DOF (the wall must be a plane y = const: checked) and puts grounded
//           springs A_i κ_0 / w_i on x and z (CalculixNodeSupport). Errors then include the wall nodes.
//
//   bench_speed_accuracy [--study locking|sweep|all] [--case FILE] [--load supine|hanging]
//        [--targets 5000,10000,20000,47895,99390] [--methods NAME,...] [--reference-target 99390]
//        [--reference-element c3d10|c3d4] [--locking-target 10000] [--nus 0.3,0.4,0.45,0.48,0.49,0.495]
//        [--locking-methods corotated/cholmod,corotated-det/cholmod,anp/cholmod]
//        [--ccx-threads 2] [--cache DIR] [--json FILE] [--csv FILE] [--curve-method NAME]
//        [--lesion-target-mm 2] [--uniform-modulus-methods NAME,...] [--wall fixed|sliding]
//        [--tether-pa-per-mm 50]
// The CalculiX results are cached (reference/calculix.h): a rerun only pays for our runs.
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/reference/calculix.h"
#include "breast_sim/core/reference/error_metrics.h"
#include "breast_sim/core/reference/model_choice.h"
#include "breast_sim/core/reference/reference_case.h"
#include "breast_sim/core/sliding/wall_slip.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

std::vector<std::string> splitNames(const std::string& text) {
  std::vector<std::string> out;
  std::stringstream ss(text);
  for (std::string t; std::getline(ss, t, ',');)
    if (!t.empty()) out.push_back(t);
  return out;
}

Points lesionPoints(const ModelCase& c) {
  Points p(static_cast<Eigen::Index>(c.lesions.size()), 3);
  for (std::size_t i = 0; i < c.lesions.size(); ++i) p.row(i) = c.lesions[i].position_m.transpose();
  return p;
}

/// One settled run of our model.
struct OurRun {
  Points u;
  double settle_seconds = 0, setup_seconds = 0;
  int steps = 0;
  bool settled = false;
  int inverted = 0;
  std::vector<int> inverted_elements;
  long reversed = 0;
  double alpha = 0;
  bool stiffened = false;            ///< ran the stiffening driver
  double modulus_excess = 0;         ///< its largest E_r − 1 at the end (elements with a local α excepted)
  int locally_stiffened = 0;         ///< elements it keeps stiffer locally, and their volume share [%]
  double locally_stiffened_percent = 0;
  std::string failure;  ///< what a run that threw said ("" = it ran)
};

/// The sliding wall of --wall sliding: what WallSlip gets (friction and contact off, a tether).
struct SlidingWall {
  bool on = false;
  SlidingSettings sliding;  ///< the case's node set and limiting factors
  WallSlipSettings slip;
};

SlidingWall slidingWall(const std::string& case_file, double tether_pa_per_mm) {
  const PipelineSettings ps = loadPipelineSettings(case_file);
  SlidingWall w;
  w.on = true;
  w.sliding = ps.sliding;
  w.slip = ps.wall_slip;
  w.slip.static_friction = 0.0;
  w.slip.kinetic_friction = 0.0;
  w.slip.static_threshold_pa = 0.0;
  // The stick spring must be positive: 1 Pa/m, 5e-5 of the tether at 50 Pa/mm (it follows a
  // slipping node, so it pulls only between a stick and the next slip).
  w.slip.friction_stiffness_pa_per_m = 1.0;
  w.slip.contact = false;
  w.slip.tether_stiffness_pa_per_m = 1e3 * tether_pa_per_mm;
  return w;
}

/// The reference's supports for the sliding wall on a mesh: each WallSlip node has its normal (y)
/// held and grounded springs A_i κ_g,i on x and z; chest-wall nodes WallSlip does not take stay
/// fixed. Throws when the wall is not the plane y = const at the nodes (normal off y by > 2°).
CalculixLoadCase slidingReference(CalculixLoadCase load, const ModelCase& c, const TetMesh& mesh, const SlidingWall& w,
                                  double* max_normal_angle_deg) {
  const WallSlip slip = WallSlip::fromCase(c, mesh, w.sliding, w.slip);
  const Eigen::VectorXd& area = slip.geometry().nodeAreas();
  double worst = 0;
  std::vector<char> sliding(mesh.numNodes(), 0);
  for (size_t i = 0; i < slip.nodes().size(); ++i) {
    const int v = slip.nodes()[i];
    Eigen::Vector3d grad;
    slip.geometry().surface().signedDistance(mesh.nodes().row(v).transpose(), grad);
    const double cosang = std::abs(grad.y()) / std::max(grad.norm(), 1e-300);
    worst = std::max(worst, std::acos(std::min(1.0, cosang)) * 180.0 / M_PI);
    CalculixNodeSupport sup;
    sup.node = v;
    sup.fixed = {{false, true, false}};
    const double k = area[static_cast<Eigen::Index>(i)] * slip.tetherStiffness()[static_cast<Eigen::Index>(i)];
    sup.spring_n_per_m = Eigen::Vector3d(k, 0.0, k);
    load.node_supports.push_back(sup);
    sliding[v] = 1;
  }
  if (max_normal_angle_deg) *max_normal_angle_deg = worst;
  if (worst > 2.0)
    throw std::invalid_argument("--wall sliding: the chest wall's normal is " + std::to_string(worst) +
                                " degrees off y at a wall node; the reference needs a planar wall y = const");
  for (int v : mesh.nodeSet(load.fixed_node_set))
    if (!sliding[v]) {
      CalculixNodeSupport sup;
      sup.node = v;
      sup.fixed = {{true, true, true}};
      load.node_supports.push_back(sup);
    }
  load.fixed_node_set = "";
  return load;
}

/// Settles the model under gravity g with a method named "<formulation>/<solver>": formulation
/// linear | corotated | corotated-det | anp, each but linear optionally +stiffening, solver
/// multigrid | cholmod. tight = CHOLMOD-style
/// reference settling (dt 1 s, increments below 1e-8 m).
OurRun runOurs(const ModelCase& c, const SimulationModel& m, SimulationSettings s, const Eigen::Vector3d& g,
               const std::string& method, bool tight = false, const SlidingWall& wall = SlidingWall()) {
  const std::size_t slash = method.find('/');
  if (slash == std::string::npos) throw std::invalid_argument("method '" + method + "': expected <formulation>/<solver>");
  std::string form = method.substr(0, slash);
  const std::string solver = method.substr(slash + 1);
  const std::size_t plus_sliding = form.find("+sliding");
  if (plus_sliding != std::string::npos) {
    if (!wall.on) throw std::invalid_argument("method '" + method + "': +sliding needs --wall sliding");
    form.erase(plus_sliding, 8);
  }
  // "anp-b<β>-j<J_b>-c<c>": ANP with the element volume fraction β, the inversion barrier J_b and
  // its stiffness factor c (AnpTetFem::setElementVolumeFraction, setInversionBarrier), each optional.
  double anp_beta = 0.0, anp_barrier = 0.0, anp_barrier_c = SimulationSettings{}.anp_inversion_barrier_stiffness;
  if (form.rfind("anp-", 0) == 0) {
    const std::size_t end = std::min(form.find('+'), form.size());
    std::size_t pos = 3;
    while (pos < end && form[pos] == '-') {
      const char which = pos + 1 < end ? form[pos + 1] : '?';
      const std::size_t next = std::min(form.find('-', pos + 1), end);
      double v = 0.0;
      try {
        v = std::stod(form.substr(pos + 2, next - pos - 2));
      } catch (const std::exception&) {
        throw std::invalid_argument("method '" + method + "': expected anp-b<share>-j<ratio>, e.g. anp-j0.5");
      }
      if (which == 'b') anp_beta = v;
      else if (which == 'j') anp_barrier = v;
      else if (which == 'c') anp_barrier_c = v;
      else throw std::invalid_argument("method '" + method + "': anp options are -b<share>, -j<ratio> and -c<factor>");
      pos = next;
    }
    form = "anp" + form.substr(end);
  }
  if (form != "linear" && form != "corotated" && form != "corotated+stiffening" && form != "corotated-det" &&
      form != "corotated-det+stiffening" && form != "anp" && form != "anp+stiffening")
    throw std::invalid_argument("method '" + method +
                                "': formulation must be linear, corotated, corotated+stiffening, corotated-det, "
                                "corotated-det+stiffening, anp or anp+stiffening");
  // "-det": the fixed co-rotated J − 1 volume term (docs/corotated) instead of the seed's trace term.
  // The method, not the case file, decides the volume term.
  s.volume_term = form.rfind("corotated-det", 0) == 0 ? CorotatedTetFem::VolumeTerm::kDeterminant
                                                      : CorotatedTetFem::VolumeTerm::kTrace;
  s.element = form.rfind("anp", 0) == 0 ? SimulationSettings::Element::kAnpTet : SimulationSettings::Element::kLinearTet;
  s.anp_element_volume_fraction = anp_beta;
  s.anp_inversion_barrier = anp_barrier;
  s.anp_inversion_barrier_stiffness = anp_barrier_c;
  const bool stiffening = form.size() > 11 && form.substr(form.size() - 11) == "+stiffening";
  s.solver.kind = SolverSettings::kindFromName(solver);
  s.dynamics.gravity_mps2 = g;
  SimulatorBuild b = buildSimulator(c, m, s);
  DynamicSimulator& sim = *b.simulator;
  if (form == "linear") dynamic_cast<CorotatedTetFem&>(sim.elements()).setCorotated(false);
  OurRun r;
  r.setup_seconds = b.hierarchy_seconds + b.setup_seconds;
  if (!stiffening) {
    SettleOptions o = s.settle;
    if (tight) {
      o.time_step_s = 1.0;
      o.increment_tolerance_m = 1e-8;
      o.max_steps = 300;
    }
    const SettleResult sr = settle(sim, o);
    r.settle_seconds = sr.seconds;
    r.steps = sr.steps;
    r.settled = sr.settled;
  } else {
    // As breast_sim_run: settling time step, stiffening driver until its settle criterion holds.
    DynamicsParams p = sim.params();
    if (s.settle.time_step_s > 0) p.time_step_s = s.settle.time_step_s;
    sim.setParams(p);
    StiffeningSimulation stiff(sim, m.mesh);
    stiff.setGravity(g);
    const auto t0 = Clock::now();
    long calls = 0;
    while (stiff.stats().steps < s.settle.max_steps && calls < 2L * s.settle.max_steps) {
      ++calls;
      const StiffeningStepResult sr = stiff.step();
      if (sr.advanced && stiff.settled()) break;
    }
    r.settle_seconds = since(t0);
    const RunStats st = stiff.stats();
    r.steps = static_cast<int>(st.steps);
    r.settled = st.settled;
    r.reversed = st.reversed_steps;
    r.alpha = st.final_alpha_per_pa;
    r.stiffened = true;
    r.modulus_excess = st.max_modulus_excess;
    r.locally_stiffened = st.locally_stiffened_elements;
    r.locally_stiffened_percent = st.locally_stiffened_volume_percent;
  }
  if (wall.on) {
    // Release the wall onto implicit sliding and settle again (the pipeline's loop: springs before,
    // friction after each accepted step), at the settling time step, until no node moves more than
    // the settle tolerance in consecutive steps.
    const auto t0 = Clock::now();
    WallSlip slip = WallSlip::fromCase(c, m.mesh, wall.sliding, wall.slip);
    slip.attach(sim);
    std::unique_ptr<StiffeningSimulation> stiff;
    if (stiffening) {
      stiff = std::make_unique<StiffeningSimulation>(sim, m.mesh);
      stiff->setGravity(g);
    }
    DynamicsParams p = sim.params();
    if (s.settle.time_step_s > 0) p.time_step_s = s.settle.time_step_s;
    sim.setParams(p);
    int quiet = 0, steps = 0;
    bool settled = false;
    for (long calls = 0; steps < s.settle.max_steps && calls < 2L * s.settle.max_steps; ++calls) {
      const Eigen::VectorXd before = sim.state().displacement_m;
      slip.beforeStep(sim);
      bool advanced = true;
      if (stiff) advanced = stiff->step().advanced;
      else sim.step();
      if (!advanced) continue;
      slip.afterStep(sim);
      ++steps;
      const Eigen::VectorXd du = sim.state().displacement_m - before;
      double largest = 0;
      for (Eigen::Index n = 0; n < du.size() / 3; ++n) largest = std::max(largest, du.segment<3>(3 * n).norm());
      quiet = largest <= s.settle.increment_tolerance_m ? quiet + 1 : 0;
      if (quiet >= s.settle.consecutive_steps) {
        settled = true;
        break;
      }
    }
    r.settle_seconds += since(t0);
    r.steps += steps;
    r.settled = r.settled && settled;
    if (stiff) r.reversed += stiff->stats().reversed_steps;
  }
  r.u = sim.displacement();
  r.inverted_elements = invertedTets(m.mesh.tets(), m.mesh.nodes() + r.u);
  r.inverted = static_cast<int>(r.inverted_elements.size());
  return r;
}

/// Where the inverted elements of a run are: how many have k = 0..4 nodes in the fixed node set and
/// on the skin, and their rest volumes against the mesh's mean (the locking study prints it).
std::string invertedSummary(const SimulationModel& m, const std::string& fixed_set, const std::vector<int>& inverted) {
  if (inverted.empty()) return "";
  std::vector<char> fixed(m.mesh.numNodes(), 0), skin(m.mesh.numNodes(), 0);
  if (m.mesh.hasNodeSet(fixed_set))
    for (int n : m.mesh.nodeSet(fixed_set)) fixed[n] = 1;
  if (m.mesh.hasNodeSet("skin"))
    for (int n : m.mesh.nodeSet("skin")) skin[n] = 1;
  const Eigen::VectorXd vol = m.mesh.tetVolumes();
  int on_wall[5] = {0, 0, 0, 0, 0}, touching_skin = 0;
  double largest = 0.0;
  for (int e : inverted) {
    int f = 0, k = 0;
    for (int i = 0; i < 4; ++i) f += fixed[m.mesh.tets()(e, i)], k += skin[m.mesh.tets()(e, i)];
    ++on_wall[f];
    touching_skin += k > 0;
    largest = std::max(largest, vol[e] / vol.mean());
  }
  std::ostringstream o;
  o << "inverted: wall nodes 0/1/2/3: " << on_wall[0] << "/" << on_wall[1] << "/" << on_wall[2] << "/" << on_wall[3]
    << ", " << touching_skin << " touching the skin, largest rest volume " << std::fixed << std::setprecision(1)
    << 100.0 * largest << " % of the mean";
  return o.str();
}

nlohmann::json errorsJson(const DisplacementErrors& e) {
  return {{"error_mean_mm", e.mean_mm},
          {"error_rms_mm", e.rms_mm},
          {"error_p95_mm", e.p95_mm},
          {"error_max_mm", e.max_mm},
          {"lesion_error_mm", e.lesion_error_mm},
          {"lesion_error_max_mm", e.lesion_max_mm},
          {"surface_distance_mean_mm", e.surface_distance_mean_mm},
          {"surface_distance_max_mm", e.surface_distance_max_mm},
          {"rest_surface_distance_mean_mm", e.rest_surface_distance_mean_mm},
          {"volume_change_percent", e.volume_change_percent},
          {"reference_volume_change_percent", e.reference_volume_change_percent},
          {"max_displacement_mm", e.max_displacement_mm},
          {"reference_max_displacement_mm", e.reference_max_displacement_mm}};
}

}  // namespace

int main(int argc, char** argv) {
  std::string study = "all", case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  std::string load_name = "supine", ref_element = "c3d10", json_path, csv_path;
  std::string curve_method = "corotated+stiffening/multigrid";
  std::vector<double> targets = {5000, 10000, 20000, 47895, 99390};
  std::vector<std::string> methods = {"linear/multigrid", "corotated/multigrid", "corotated/cholmod",
                                      "corotated+stiffening/multigrid", "corotated+stiffening/cholmod",
                                      "corotated-det/multigrid", "corotated-det/cholmod"};
  int reference_target = 99390, locking_target = 10000;
  std::vector<double> nus = {0.3, 0.4, 0.45, 0.48, 0.49, 0.495};
  std::vector<std::string> locking_methods = {"corotated/cholmod", "corotated-det/cholmod", "anp/cholmod"};
  double lesion_target_mm = 2.0;
  std::vector<std::string> uniform_methods;
  std::string wall_name = "fixed";
  double tether_pa_per_mm = 50.0;
  CalculixOptions copt;
  copt.threads = 2;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument(k + " needs a value");
      return argv[++i];
    };
    if (k == "--study") study = value();
    else if (k == "--case") case_file = value();
    else if (k == "--load") load_name = value();
    else if (k == "--targets") targets = parseList(value());
    else if (k == "--methods") methods = splitNames(value());
    else if (k == "--reference-target") reference_target = std::stoi(value());
    else if (k == "--reference-element") ref_element = value();
    else if (k == "--locking-target") locking_target = std::stoi(value());
    else if (k == "--nus") nus = parseList(value());
    else if (k == "--locking-methods") locking_methods = splitNames(value());
    else if (k == "--ccx-threads") copt.threads = std::stoi(value());
    else if (k == "--cache") copt.cache_dir = value();
    else if (k == "--json") json_path = value();
    else if (k == "--csv") csv_path = value();
    else if (k == "--curve-method") curve_method = value();
    else if (k == "--lesion-target-mm") lesion_target_mm = std::stod(value());
    else if (k == "--uniform-modulus-methods") uniform_methods = splitNames(value());
    else if (k == "--wall") wall_name = value();
    else if (k == "--tether-pa-per-mm") tether_pa_per_mm = std::stod(value());
    else {
      std::fprintf(stderr,
                   "usage: bench_speed_accuracy [--study locking|sweep|all] [--case FILE] [--load supine|hanging]\n"
                   "         [--targets N,...] [--methods NAME,...] [--reference-target N] [--reference-element c3d10|c3d4]\n"
                   "         [--locking-target N] [--nus 0.3,...] [--locking-methods NAME,...] [--ccx-threads 2] [--cache DIR] [--json FILE] [--csv FILE]\n"
                   "         [--curve-method NAME] [--lesion-target-mm 2] [--uniform-modulus-methods NAME,...]\n"
                   "         [--wall fixed|sliding] [--tether-pa-per-mm 50]\n");
      return 2;
    }
  }
  if (!calculixAvailable(copt.executable)) {
    std::fprintf(stderr, "bench_speed_accuracy: CalculiX (ccx) is not installed: apt-get install calculix-ccx\n");
    return 1;
  }
  const ModelCase base = loadModelCase(case_file);
  const SimulationSettings settings = loadSimulationSettings(case_file);
  const GravityLoadCase which = gravityLoadCaseFromName(load_name);
  const Eigen::Vector3d g = gravityLoad(base, which, settings.gravity_mps2);
  const Points lesions = lesionPoints(base);
  nlohmann::json out;
  out["case"] = base.name;
  out["load"] = load_name;
  out["gravity_mps2"] = {g.x(), g.y(), g.z()};
  out["threads"] = omp_get_max_threads();
  out["ccx_threads"] = copt.threads;
  out["youngs_modulus_pa"] = settings.material.youngs_modulus_pa;
  out["poisson_ratio"] = settings.material.poisson_ratio;
  if (wall_name != "fixed" && wall_name != "sliding")
    throw std::invalid_argument("--wall " + wall_name + ": expected fixed or sliding");
  SlidingWall wall;
  if (wall_name == "sliding") wall = slidingWall(case_file, tether_pa_per_mm);
  out["wall"] = wall_name;
  if (wall.on)
    out["sliding_wall"] = {{"tether_pa_per_mm", tether_pa_per_mm},
                           {"friction", 0.0},
                           {"contact", false},
                           {"gaussian_limit", wall.sliding.gaussian_limit},
                           {"thickness_limit", wall.sliding.thickness_limit}};
  std::string tissue_moduli;
  nlohmann::json region_moduli = nlohmann::json::object();
  for (const auto& [region, e] : settings.region_youngs_modulus_pa) {
    const std::string name = tissueClassName(static_cast<TissueClass>(region));
    tissue_moduli += ", " + name + " " + std::to_string(static_cast<long>(e)) + " Pa";
    region_moduli[name] = e;
  }
  out["tissue_youngs_modulus_pa"] = region_moduli;
  std::printf("case %s, load %s: g = (%.3f, %.3f, %.3f) m/s^2, E = %.0f Pa%s, nu = %.3f, %d threads (ccx %d)\n",
              base.name.c_str(), load_name.c_str(), g.x(), g.y(), g.z(), settings.material.youngs_modulus_pa,
              tissue_moduli.c_str(), settings.material.poisson_ratio, omp_get_max_threads(), copt.threads);

  // ---- locking ------------------------------------------------------------------------------------
  if (study == "locking" || study == "all") {
    ModelCase c = base;
    c.meshing.target_elements = locking_target;
    const SimulationModel m = cachedSimulationModel(c, copt.cache_dir);  // the mesh the cached references belong to
    std::printf("\nLocking at %d elements (%d nodes): error against CalculiX C3D10 (neo-Hookean, NLGEOM) on the same corners\n",
                m.mesh.numTets(), m.mesh.numNodes());
    std::printf("%6s | %-24s | %8s | %22s | %22s | %5s %4s | %7s\n", "nu", "method", "max[mm]",
                "vs C3D10 mean/p95/les", "vs C3D4 mean/p95/les", "steps", "inv", "ccx[s]");
    nlohmann::json rows = nlohmann::json::array();
    for (double nu : nus) {
      SimulationSettings s = settings;
      s.material.poisson_ratio = nu;
      const CalculixResult c4 = solveWithCalculix(m.mesh, referenceLoadCase(s, m.mesh, g, ReferenceElement::kC3D4), copt);
      CalculixResult c10;
      bool have_c10 = true;
      std::string c10_failure;
      try {
        c10 = solveWithCalculix(m.mesh, referenceLoadCase(s, m.mesh, g, ReferenceElement::kC3D10), copt);
      } catch (const std::runtime_error& ex) {
        // C3D10 neo-Hookean runs can stall (increment below the minimum) on these meshes: reported.
        have_c10 = false;
        c10_failure = ex.what();
        std::printf("%6.3f | C3D10 failed: %s\n", nu, ex.what());
      }
      nlohmann::json row = {{"poisson_ratio", nu}, {"ccx_c3d4_seconds", c4.solve_seconds}};
      if (have_c10) {
        const DisplacementErrors e_c4 = compareDisplacements(m.mesh, c4.displacement_m, m.mesh, c10.displacement_m, lesions);
        std::printf("%6.3f | %-24s | %8.3f | %6.3f %6.3f %6.3f mm | %22s | %5s %4s | %7.1f\n", nu, "CalculiX C3D4",
                    e_c4.max_displacement_mm, e_c4.mean_mm, e_c4.p95_mm, e_c4.lesion_max_mm, "", "", "", c4.solve_seconds);
        std::printf("%6.3f | %-24s | %8.3f | %22s | %22s | %5s %4s | %7.1f\n", nu, "CalculiX C3D10",
                    e_c4.reference_max_displacement_mm, "(reference)", "", "", "", c10.solve_seconds);
        row["c3d4_vs_c3d10"] = errorsJson(e_c4);
        row["ccx_c3d10_seconds"] = c10.solve_seconds;
        row["ccx_c3d10_deck_nodes"] = c10.deck_nodes;
      } else {
        row["c3d10_failed"] = c10_failure;
      }
      nlohmann::json ours_rows = nlohmann::json::object();
      for (const std::string& method : locking_methods) {
        const OurRun ours = runOurs(c, m, s, g, method, /*tight=*/true);
        const DisplacementErrors e_oc4 = compareDisplacements(m.mesh, ours.u, m.mesh, c4.displacement_m, lesions);
        nlohmann::json o = {{"vs_c3d4", errorsJson(e_oc4)}, {"settled", ours.settled}, {"steps", ours.steps},
                            {"inverted", ours.inverted}, {"settle_seconds", ours.settle_seconds}};
        if (have_c10) {
          const DisplacementErrors e = compareDisplacements(m.mesh, ours.u, m.mesh, c10.displacement_m, lesions);
          o["vs_c3d10"] = errorsJson(e);
          std::printf("%6.3f | %-24s | %8.3f | %6.3f %6.3f %6.3f mm | %6.3f %6.3f %6.3f mm | %5d %4d |%s\n", nu,
                      method.c_str(), e.max_displacement_mm, e.mean_mm, e.p95_mm, e.lesion_max_mm, e_oc4.mean_mm,
                      e_oc4.p95_mm, e_oc4.lesion_max_mm, ours.steps, ours.inverted, ours.settled ? "" : " (not settled)");
        } else {
          std::printf("%6.3f | %-24s | %8.3f | %22s | %6.3f %6.3f %6.3f mm | %5d %4d |%s\n", nu, method.c_str(),
                      e_oc4.max_displacement_mm, "", e_oc4.mean_mm, e_oc4.p95_mm, e_oc4.lesion_max_mm, ours.steps,
                      ours.inverted, ours.settled ? "" : " (not settled)");
        }
        if (ours.stiffened) {
          std::printf("       |   stiffening: %ld reversed, alpha %.2g /Pa, E_r - 1 <= %.2g, %d elements (%.4f %% of the "
                      "volume) stiffened locally, %.2f s\n",
                      ours.reversed, ours.alpha, ours.modulus_excess, ours.locally_stiffened, ours.locally_stiffened_percent,
                      ours.settle_seconds);
          o["stiffening"] = {{"reversed", ours.reversed}, {"final_alpha_per_pa", ours.alpha},
                             {"modulus_excess", ours.modulus_excess}, {"locally_stiffened_elements", ours.locally_stiffened},
                             {"locally_stiffened_volume_percent", ours.locally_stiffened_percent}};
        }
        const std::string where = invertedSummary(m, s.fixed_node_set, ours.inverted_elements);
        if (!where.empty()) {
          std::printf("       |   %s\n", where.c_str());
          o["inverted_where"] = where;
        }
        std::fflush(stdout);
        ours_rows[method] = o;
      }
      row["ours"] = ours_rows;
      rows.push_back(row);
    }
    out["locking"] = {{"target_elements", locking_target},
                      {"elements", m.mesh.numTets()},
                      {"nodes", m.mesh.numNodes()},
                      {"reference", "CalculiX C3D10 neo-Hookean NLGEOM on the same corner nodes"},
                      {"ours", "each method settled to 1e-8 m increments (dt 1 s)"},
                      {"rows", rows}};
  }

  // ---- sweep --------------------------------------------------------------------------------------
  if (study == "sweep" || study == "all") {
    ModelCase rc = base;
    rc.meshing.target_elements = reference_target;
    const SimulationModel rm = cachedSimulationModel(rc, copt.cache_dir);
    const ReferenceElement rtype = referenceElementFromName(ref_element);
    std::printf("\nReference: CalculiX %s neo-Hookean NLGEOM on %d elements (%d nodes) ...\n",
                referenceElementName(rtype).c_str(), rm.mesh.numTets(), rm.mesh.numNodes());
    std::fflush(stdout);
    CalculixLoadCase rload = referenceLoadCase(settings, rm.mesh, g, rtype);
    double wall_angle_deg = 0;
    if (wall.on) {
      rload = slidingReference(rload, base, rm.mesh, wall, &wall_angle_deg);
      std::printf("  sliding wall: %zu supported nodes (normal y held; x, z on tethers of %.0f Pa/mm / w_i), "
                  "wall normal within %.2f deg of y\n",
                  rload.node_supports.size(), tether_pa_per_mm, wall_angle_deg);
    }
    const CalculixResult ref = solveWithCalculix(rm.mesh, rload, copt);
    const double ref_max = 1e3 * ref.displacement_m.rowwise().norm().maxCoeff();
    const double ref_dv = compareDisplacements(rm.mesh, ref.displacement_m, rm.mesh, ref.displacement_m).volume_change_percent;
    std::printf("  %s, ccx %.1f s, %d deck nodes, largest displacement %.3f mm, volume change %.2f %% (key %s)\n",
                ref.from_cache ? "from the cache" : "computed", ref.solve_seconds, ref.deck_nodes, ref_max, ref_dv,
                ref.key.c_str());
    std::printf("%-32s %8s %7s | %8s %8s %6s %4s | %7s %7s %7s %7s %7s %6s | %4s\n", "method", "tets", "nodes", "settle[s]",
                "setup[s]", "steps", "ok", "mean", "p95", "max", "lesion", "surf", "dV[%]", "inv");
    nlohmann::json rows = nlohmann::json::array();
    std::ofstream csv;
    if (!csv_path.empty()) {
      csv.open(csv_path);
      csv << "method,target_elements,elements,nodes,settle_seconds,setup_seconds,meshing_seconds,steps,settled,"
             "error_mean_mm,error_p95_mm,error_max_mm,lesion_error_max_mm,surface_distance_mean_mm,"
             "volume_change_percent,max_displacement_mm,inverted\n";
    }
    for (double tt : targets) {
      ModelCase c = base;
      c.meshing.target_elements = static_cast<int>(tt);
      const auto tm = Clock::now();
      const SimulationModel m = buildSimulationModel(c);
      const double t_mesh = since(tm);
      // The methods, and those of --uniform-modulus-methods again with E0 everywhere.
      std::vector<std::pair<std::string, bool>> runs;
      for (const std::string& method : methods) runs.push_back({method, false});
      if (!settings.region_youngs_modulus_pa.empty())
        for (const std::string& method : uniform_methods) runs.push_back({method, true});
      for (const auto& [method, uniform] : runs) {
        // CHOLMOD refactorizes every step: past ~100k elements a settling takes minutes; skipped.
        if (method.find("cholmod") != std::string::npos && m.mesh.numTets() > 120000) continue;
        std::string label = uniform ? method + " uniform-E" : method;
        if (wall.on && label.find("+sliding") == std::string::npos) label.insert(label.find('/'), "+sliding");
        SimulationSettings rs = settings;
        if (uniform) rs.region_youngs_modulus_pa.clear();
        OurRun r;
        try {
          r = runOurs(c, m, rs, g, method, /*tight=*/false, wall);
        } catch (const std::exception& ex) {
          r.failure = ex.what();
        }
        if (!r.failure.empty()) {
          std::printf("%-32s %8d %7d | FAILED: %s\n", label.c_str(), m.mesh.numTets(), m.mesh.numNodes(), r.failure.c_str());
          std::fflush(stdout);
          rows.push_back({{"method", label},
                          {"target_elements", static_cast<int>(tt)},
                          {"elements", m.mesh.numTets()},
                          {"nodes", m.mesh.numNodes()},
                          {"failed", r.failure}});
          continue;
        }
        // With a sliding wall the wall nodes move: they count.
        const DisplacementErrors e =
            compareDisplacements(m.mesh, r.u, rm.mesh, ref.displacement_m, lesions, wall.on ? "" : "chest_wall");
        std::printf("%-32s %8d %7d | %8.3f %8.3f %6d %4s | %7.3f %7.3f %7.3f %7.3f %7.3f %6.2f | %4d\n", label.c_str(),
                    m.mesh.numTets(), m.mesh.numNodes(), r.settle_seconds, r.setup_seconds, r.steps,
                    r.settled ? "yes" : "NO", e.mean_mm, e.p95_mm, e.max_mm, e.lesion_max_mm, e.surface_distance_mean_mm,
                    e.volume_change_percent, r.inverted);
        std::fflush(stdout);
        nlohmann::json row = errorsJson(e);
        row.update({{"method", label},
                    {"target_elements", static_cast<int>(tt)},
                    {"elements", m.mesh.numTets()},
                    {"nodes", m.mesh.numNodes()},
                    {"settle_seconds", r.settle_seconds},
                    {"setup_seconds", r.setup_seconds},
                    {"meshing_seconds", t_mesh},
                    {"steps", r.steps},
                    {"settled", r.settled},
                    {"inverted", r.inverted},
                    {"reversed_steps", r.reversed},
                    {"final_alpha_per_pa", r.alpha}});
        rows.push_back(row);
        if (csv)
          csv << label << ',' << static_cast<int>(tt) << ',' << m.mesh.numTets() << ',' << m.mesh.numNodes() << ','
              << r.settle_seconds << ',' << r.setup_seconds << ',' << t_mesh << ',' << r.steps << ',' << (r.settled ? 1 : 0)
              << ',' << e.mean_mm << ',' << e.p95_mm << ',' << e.max_mm << ',' << e.lesion_max_mm << ','
              << e.surface_distance_mean_mm << ',' << e.volume_change_percent << ',' << e.max_displacement_mm << ','
              << r.inverted << '\n';
      }
    }
    out["sweep"] = {{"reference",
                     {{"solver", "CalculiX"},
                      {"element_type", referenceElementName(rtype)},
                      {"material", "neo-Hookean, C10 = mu/2, D1 = 2/K"},
                      {"nlgeom", true},
                      {"target_elements", reference_target},
                      {"elements", rm.mesh.numTets()},
                      {"nodes", rm.mesh.numNodes()},
                      {"deck_nodes", ref.deck_nodes},
                      {"ccx_seconds", ref.solve_seconds},
                      {"max_displacement_mm", ref_max},
                      {"volume_change_percent", ref_dv},
                      {"wall", wall_name},
                      {"wall_normal_max_angle_deg", wall_angle_deg},
                      {"supported_nodes", rload.node_supports.size()},
                      {"key", ref.key}}},
                    {"time", "settling steps only [s]; setup_seconds (multigrid hierarchy, solver analysis) and "
                             "meshing_seconds beside it"},
                    {"rows", rows}};

    // Model no more than a scene needs: the coarsest mesh meeting a lesion-error target.
    std::vector<ErrorCurvePoint> curve;
    for (const auto& r : rows)
      if (r["method"] == curve_method && !r.contains("failed"))
        curve.push_back({r["target_elements"].get<int>(), r["elements"].get<int>(), r["lesion_error_max_mm"].get<double>(),
                         r["settle_seconds"].get<double>()});
    if (!curve.empty()) {
      const ModelChoice mc = chooseCoarsestModel(curve, lesion_target_mm);
      std::printf("\nModel choice (%s, lesion error <= %.1f mm): %s\n", curve_method.c_str(), lesion_target_mm,
                  mc.explanation.c_str());
      out["model_choice"] = {{"method", curve_method},
                             {"measure", "lesion"},
                             {"target_mm", lesion_target_mm},
                             {"met", mc.met},
                             {"target_elements", mc.target_elements},
                             {"elements", mc.elements},
                             {"expected_error_mm", mc.expected_error_mm},
                             {"expected_seconds", mc.expected_seconds},
                             {"explanation", mc.explanation}};
    }
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
  return 0;
}
