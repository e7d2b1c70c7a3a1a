// Whole-step benchmark, the seed paper's Table 1 on this machine: the phantom under supine gravity,
// chest wall fixed, E = 2 kPa, ν = 0.48, dt = 0.033 s, 25 implicit co-rotated steps per size with the
// multigrid-PCG solver (and CHOLMOD as the same-run baseline), then a settling study: time to a
// settled gravity state at about 50k elements for several settling time steps, each against a tightly
// settled CHOLMOD reference of the same run (accuracy in mm). Prints tables; --json FILE writes the
// same figures.
//   bench_simulation [--targets 47895,99390,158340,313335] [--steps 25] [--baseline-steps 3]
//                    [--tol 1e-2] [--cap K] [--settle-target 47895] [--settle-dts 0.033,0.1,0.33,1]
//                    [--tols 1e-1,1e-2,1e-3,1e-6] [--caps 2,3,4,6] [--projections 1,2,4] [--study-steps N]
//                    [--coarse-interval 50] [--coarse-adaptive 0|1] [--no-baseline] [--no-settle]
//                    [--element linear|anp] [--volume-term trace|determinant] [--json FILE]
// --element / --volume-term choose the element formulation (simulation.element, .volume_term) of
// every run; the defaults are the seed's element, co-rotated linear tetrahedra (with the library's
// J − 1 volume term), whatever the library's default element.
// --cap K stops PCG after at most K iterations per step in the Table-1 runs (the step is used).
// --coarse-interval N recomputes the multigrid's Galerkin operators at least every N-th step, and
// --coarse-adaptive 1 (the default) earlier once the PCG iterations their age lost are worth a
// renewal (MultigridOptions::coarse_update_adaptive); 0 renews every N-th step only.
// The accuracy study (at the first size): per-step PCG tolerance (--tols) and per-step iteration caps
// (--caps k: at most k PCG iterations, or fewer at --tol, the step used either way, as real-time
// multigrid simulations run a fixed number of cycles per step) against step time and the error of the
// dynamic path after 3 and after --study-steps steps (default --steps), against CHOLMOD's exact solves;
// --projections k: rows at --tol whose PCG starts from k vectors (PcgOptions::projection_vectors;
// 1 = the last velocity alone), the other rows from the default.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#if defined(__x86_64__)
#include <immintrin.h>
#endif
#include <omp.h>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {


// Peak resident memory of this process since the last resetPeakMemory() [MB] (Linux VmHWM).
double peakMemoryMb() {
  std::ifstream f("/proc/self/status");
  for (std::string line; std::getline(f, line);)
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  return 0.0;
}
void resetPeakMemory() { std::ofstream("/proc/self/clear_refs") << "5"; }

#if defined(__x86_64__)
// Sum of n floats from `a`, four 8-wide accumulators (AVX2), over [i0, i1).
__attribute__((target("avx2"))) float sumAvx2(const float* a, size_t i0, size_t i1) {
  __m256 s0 = _mm256_setzero_ps(), s1 = s0, s2 = s0, s3 = s0;
  size_t i = i0;
  for (; i + 32 <= i1; i += 32) {
    s0 = _mm256_add_ps(s0, _mm256_loadu_ps(a + i));
    s1 = _mm256_add_ps(s1, _mm256_loadu_ps(a + i + 8));
    s2 = _mm256_add_ps(s2, _mm256_loadu_ps(a + i + 16));
    s3 = _mm256_add_ps(s3, _mm256_loadu_ps(a + i + 24));
  }
  alignas(32) float t[8];
  _mm256_store_ps(t, _mm256_add_ps(_mm256_add_ps(s0, s1), _mm256_add_ps(s2, s3)));
  float sum = t[0] + t[1] + t[2] + t[3] + t[4] + t[5] + t[6] + t[7];
  for (; i < i1; ++i) sum += a[i];
  return sum;
}
#endif

// What this machine reads [GB/s] with the benchmark's threads from an array of `bytes` (the best
// of 40 passes after one that pages it in): the bound the sparse kernels are measured against.
double readBandwidthGBs(size_t bytes) {
#if !defined(__x86_64__)
  (void)bytes;
  return 0.0;  // the probe is x86 only
#else
  if (!__builtin_cpu_supports("avx2")) return 0.0;
  const size_t n = bytes / sizeof(float);
  std::vector<float> a(n, 1.0f);
  double best = 1e30, keep = 0.0;
  for (int rep = 0; rep < 41; ++rep) {
    const auto t0 = Clock::now();
    double total = 0.0;
#pragma omp parallel reduction(+ : total)
    {
      const size_t p = static_cast<size_t>(omp_get_thread_num()), np = static_cast<size_t>(omp_get_num_threads());
      total += sumAvx2(a.data(), n * p / np, n * (p + 1) / np);
    }
    const double t = since(t0);
    keep += total;
    if (rep > 0) best = std::min(best, t);
  }
  return keep > 0 ? bytes / best / 1e9 : 0.0;
#endif
}


struct StepRun {
  std::vector<double> total, assembly, setup, solve, iterations;
  int unconverged = 0;
};

/// Coarse-operator renewals of the simulator's multigrid so far (−1 without a multigrid).
long coarseRenewals(DynamicSimulator& sim) {
  if (auto* pcg = dynamic_cast<PcgSolver*>(&sim.solver()))
    if (auto* mg = dynamic_cast<MultigridPreconditioner*>(&pcg->preconditioner())) return mg->coarseRenewals();
  return -1;
}

StepRun runSteps(DynamicSimulator& sim, int steps) {
  StepRun r;
  for (int s = 0; s < steps; ++s) {
    const StepStats st = sim.step();
    r.total.push_back(st.total_seconds);
    r.assembly.push_back(st.assembly_seconds);
    r.setup.push_back(st.setup_seconds);
    r.solve.push_back(st.solve.seconds);
    r.iterations.push_back(st.solve.iterations);
    if (!st.solve.converged) ++r.unconverged;
  }
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<double> targets = {47895, 99390, 158340, 313335};
  // Seed Table 1 (2012 quad-core): element counts and ms per step.
  const std::vector<double> seed_elements = {47895, 99390, 158340, 313335}, seed_ms = {189, 400, 644, 1432};
  int steps = 25, baseline_steps = 3;
  int table_cap = 0;  // at most this many PCG iterations per step in the Table-1 runs; 0 = the default
  double tol = 1e-2;
  int coarse_interval = SolverSettings{}.multigrid.coarse_update_interval;
  bool coarse_adaptive = SolverSettings{}.multigrid.coarse_update_adaptive;
  int settle_target = 47895;
  std::vector<double> settle_dts = {0.033, 0.1, 0.33, 1.0};
  std::vector<double> tol_study = {1e-1, 1e-2, 1e-3, 1e-6};
  // Per-step iteration caps (at most k PCG iterations per step, at the tolerance --tol).
  std::vector<double> cap_study = {2, 3, 4, 6};
  // Initial guesses from k vectors (PcgOptions::projection_vectors), at the tolerance --tol.
  std::vector<double> projection_study = {1, 4};
  int study_steps = 0;  // steps of the accuracy study; 0 = --steps
  bool baseline = true, settle_study = true;
  std::string json_path;
  SimulationSettings defaults;
  defaults.element = SimulationSettings::Element::kLinearTet;  // the seed's Table 1 element
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument(k + " needs a value");
      return argv[++i];
    };
    if (k == "--targets") targets = parseList(value());
    else if (k == "--steps") steps = std::stoi(value());
    else if (k == "--baseline-steps") baseline_steps = std::stoi(value());
    else if (k == "--tol") tol = std::stod(value());
    else if (k == "--coarse-interval") coarse_interval = std::stoi(value());
    else if (k == "--coarse-adaptive") {
      const std::string v = value();
      if (v != "0" && v != "1") throw std::invalid_argument("--coarse-adaptive takes 0 or 1, not '" + v + "'");
      coarse_adaptive = v == "1";
    }
    else if (k == "--settle-target") settle_target = std::stoi(value());
    else if (k == "--settle-dts") settle_dts = parseList(value());
    else if (k == "--tols") tol_study = parseList(value());
    else if (k == "--cap") table_cap = std::stoi(value());
    else if (k == "--caps") cap_study = parseList(value());
    else if (k == "--projections") projection_study = parseList(value());
    else if (k == "--study-steps") study_steps = std::stoi(value());
    else if (k == "--no-baseline") baseline = false;
    else if (k == "--no-settle") settle_study = false;
    else if (k == "--json") json_path = value();
    else if (k == "--element") {
      const std::string e = value();
      if (e != "linear" && e != "anp") throw std::invalid_argument("--element " + e + ": use linear or anp");
      defaults.element = e == "anp" ? SimulationSettings::Element::kAnpTet : SimulationSettings::Element::kLinearTet;
    } else if (k == "--volume-term") {
      const std::string v = value();
      if (v != "trace" && v != "determinant") throw std::invalid_argument("--volume-term " + v + ": use trace or determinant");
      defaults.volume_term = v == "trace" ? CorotatedTetFem::VolumeTerm::kTrace : CorotatedTetFem::VolumeTerm::kDeterminant;
    } else {
      std::fprintf(stderr,
                   "usage: bench_simulation [--targets N,...] [--steps 25] [--baseline-steps 3] [--tol 1e-2] [--cap K]\n"
                   "         [--coarse-interval 50] [--coarse-adaptive 0|1]\n"
                   "         [--tols 1e-1,...] [--caps 2,3,...] [--projections 1,2,...] [--study-steps N]\n"
                   "         [--settle-target 47895] [--settle-dts 0.033,...] [--no-baseline] [--no-settle]\n"
                   "         [--element linear|anp] [--volume-term trace|determinant] [--json FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml");
  const Eigen::Vector3d g_supine = base.phantom->gravity_supine_mps2;
  nlohmann::json out;
  out["threads"] = omp_get_max_threads();
  out["steps"] = steps;
  out["relative_tolerance"] = tol;
  out["iteration_cap"] = table_cap;
  out["coarse_update_interval"] = coarse_interval;
  out["coarse_update_adaptive"] = coarse_adaptive;
  out["element"] = defaults.element == SimulationSettings::Element::kAnpTet ? "anp" : "linear";
  out["volume_term"] = defaults.volume_term == CorotatedTetFem::VolumeTerm::kDeterminant ? "determinant" : "trace";

  {
    // The roofline the step is held against: the V-cycle's float blocks at 48k elements are ~5 MB,
    // the double matrix ~10 MB (cache-resident), the 319k one's ~70 MB (memory).
    const double cache = readBandwidthGBs(size_t(16) << 20), memory = readBandwidthGBs(size_t(256) << 20);
    std::printf("this machine reads %.0f GB/s from a 16 MB array and %.0f GB/s from a 256 MB one (%d threads, AVX2 sums)\n",
                cache, memory, omp_get_max_threads());
    out["read_bandwidth_gbs"] = {{"array_16mb", cache}, {"array_256mb", memory}};
  }
  std::printf("Table 1 on this machine: %d threads, %d steps of dt 0.033 s, supine gravity, multigrid-PCG to %.0e%s\n",
              omp_get_max_threads(), steps, tol,
              table_cap > 0 ? (" or at most " + std::to_string(table_cap) + " iterations per step").c_str() : "");
  std::printf("(medians over the steps but 'mean'; 'factor.' = the solver's set-up per step; 'first' = the first step, with the\n"
              " solver's first set-up; ns/el/st and the speed-up from the mean, which includes the coarse operators' renewals,\n"
              " 'renew' of them in all steps: at least every %d steps%s; seed = 2012 quad-core, its 25 steps' mean)\n",
              coarse_interval, coarse_adaptive ? ", earlier once the PCG iterations their age lost are worth one" : "");
  std::printf("%8s %7s %7s | %8s %6s %8s %8s %8s %6s %5s | %8s %8s | %9s %8s %7s | %6s %7s\n", "tets", "nodes", "levels",
              "step[ms]", "mean", "assem", "factor.", "solve", "iters", "renew", "first", "setup[s]", "ns/el/st", "peak[MB]",
              "cholmod", "seed", "speedup");
  nlohmann::json rows = nlohmann::json::array();
  double ns_ref = 0.0;
  for (size_t ti = 0; ti < targets.size(); ++ti) {
    resetPeakMemory();
    ModelCase c = base;
    c.meshing.target_elements = static_cast<int>(targets[ti]);
    const auto t0 = Clock::now();
    const SimulationModel model = buildSimulationModel(c);
    const double t_mesh = since(t0);
    SimulationSettings settings = defaults;
    settings.solver.relative_tolerance = tol;
    settings.solver.multigrid.coarse_update_interval = coarse_interval;
    settings.solver.multigrid.coarse_update_adaptive = coarse_adaptive;
    if (table_cap > 0) settings.solver.max_iterations = table_cap;
    settings.dynamics.gravity_mps2 = g_supine;
    SimulatorBuild b = buildSimulator(c, model, settings);
    DynamicSimulator& sim = *b.simulator;
    const StepRun first = runSteps(sim, 1);
    const StepRun run = runSteps(sim, steps - 1);
    const double peak = peakMemoryMb();
    const int inverted = static_cast<int>(invertedTets(model.mesh.tets(), model.mesh.nodes() + sim.displacement()).size());
    // The median step is a step without the coarse operators' renewal (every --coarse-interval-th
    // step); the mean includes its share, as the seed's per-step figure (its 25 steps' total / 25) does.
    const double step_ms = 1e3 * median(run.total);
    const double step_mean_ms = 1e3 * mean(run.total);
    const double ns = 1e9 * mean(run.total) / model.mesh.numTets();
    if (ti == 0) ns_ref = ns;

    double cholmod_ms = 0.0, trajectory_error_mm = -1.0, trajectory_scale_mm = 0.0;
    if (baseline && baseline_steps > 0) {
      SimulationSettings cs = settings;
      cs.solver.kind = SolverSettings::Kind::kCholmod;
      SimulatorBuild cb = buildSimulator(c, model, cs);
      // At the first size CHOLMOD runs the same steps: the loose per-step tolerance's error on the
      // dynamic path (exact solves as reference).
      const int n = ti == 0 ? steps : baseline_steps;
      const StepRun cr = runSteps(*cb.simulator, n);
      cholmod_ms = 1e3 * median(cr.total);
      if (ti == 0) {
        trajectory_error_mm = 1e3 * maxNodalNorm(cb.simulator->state().displacement_m - sim.state().displacement_m);
        trajectory_scale_mm = 1e3 * maxNodalNorm(cb.simulator->state().displacement_m);
      }
    }
    // The seed's figure for this target when it is one of the seed's sizes (a custom size has none).
    double seed = 0.0;
    for (size_t k = 0; k < seed_elements.size(); ++k)
      if (targets[ti] == seed_elements[k]) seed = seed_ms[k];
    const long renewals = coarseRenewals(sim);
    std::printf("%8d %7d %7d | %8.1f %6.1f %8.1f %8.1f %8.1f %6.1f %5ld | %8.1f %8.2f | %9.0f %8.0f %7.0f | %6.0f %6.1fx\n",
                model.mesh.numTets(), model.mesh.numNodes(), b.multigrid_levels, step_ms, step_mean_ms,
                1e3 * median(run.assembly),
                1e3 * median(run.setup), 1e3 * median(run.solve), mean(run.iterations), renewals, 1e3 * first.total[0],
                b.hierarchy_seconds + b.setup_seconds, ns, peak, cholmod_ms, seed, seed > 0 ? seed / step_mean_ms : 0.0);
    if (trajectory_error_mm >= 0)
      std::printf("         after %d steps the multigrid path differs from CHOLMOD's (exact solves) by at most %.2e mm "
                  "(largest displacement %.2f mm)\n", steps, trajectory_error_mm, trajectory_scale_mm);
    std::fflush(stdout);
    rows.push_back({{"target_elements", static_cast<int>(targets[ti])},
                    {"elements", model.mesh.numTets()},
                    {"nodes", model.mesh.numNodes()},
                    {"multigrid_levels", b.multigrid_levels},
                    {"level_nodes", b.level_nodes},
                    {"meshing_s", t_mesh},
                    {"hierarchy_s", b.hierarchy_seconds},
                    {"simulator_setup_s", b.setup_seconds},
                    {"first_step_ms", 1e3 * first.total[0]},
                    {"coarse_renewals", renewals},
                    {"step_ms_median", step_ms},
                    {"step_ms_mean", step_mean_ms},
                    {"assembly_ms_median", 1e3 * median(run.assembly)},
                    {"solver_setup_ms_median", 1e3 * median(run.setup)},
                    {"solve_ms_median", 1e3 * median(run.solve)},
                    {"iterations_mean", mean(run.iterations)},
                    {"unconverged_solves", run.unconverged},
                    {"ns_per_element_step", ns},
                    {"ns_per_element_vs_first_size", ns / ns_ref},
                    {"peak_memory_mb", peak},
                    {"inverted_after", inverted},
                    {"cholmod_step_ms_median", cholmod_ms},
                    {"trajectory_error_vs_cholmod_mm", trajectory_error_mm},
                    {"trajectory_max_displacement_mm", trajectory_scale_mm},
                    {"seed_ms", seed},
                    {"speedup_vs_seed", seed > 0 ? seed / step_mean_ms : 0.0}});
  }
  out["table1"] = rows;
  {
    double lo = 1e300, hi = 0;
    for (const auto& r : rows) {
      lo = std::min(lo, r["ns_per_element_vs_first_size"].get<double>());
      hi = std::max(hi, r["ns_per_element_vs_first_size"].get<double>());
    }
    std::printf("time per element and step relative to the first size: %.2f .. %.2f (target within 0.70 .. 1.30)\n", lo, hi);
    out["ns_per_element_ratio_range"] = {lo, hi};
  }

  if ((!tol_study.empty() || !cap_study.empty()) && !targets.empty()) {
    ModelCase c = base;
    c.meshing.target_elements = static_cast<int>(targets[0]);
    const SimulationModel model = buildSimulationModel(c);
    SimulationSettings settings = defaults;
    settings.dynamics.gravity_mps2 = g_supine;
    settings.solver.multigrid.coarse_update_interval = coarse_interval;
    settings.solver.multigrid.coarse_update_adaptive = coarse_adaptive;
    SimulationSettings cs = settings;
    cs.solver.kind = SolverSettings::Kind::kCholmod;
    SimulatorBuild cb = buildSimulator(c, model, cs);
    const int horizon = study_steps > 0 ? study_steps : steps;
    const int early = std::min(3, horizon);
    runSteps(*cb.simulator, early);
    const Eigen::VectorXd u_early = cb.simulator->state().displacement_m;
    runSteps(*cb.simulator, horizon - early);
    const Eigen::VectorXd u_end = cb.simulator->state().displacement_m;
    const double scale_end = maxNodalNorm(u_end);
    std::printf("\nPer-step solver accuracy, %d tets, %d steps: step time against the error of the dynamic path "
                "(CHOLMOD = exact; largest displacement at the end %.2f mm)\n",
                model.mesh.numTets(), horizon, 1e3 * scale_end);
    std::printf("(a cap of k stops PCG after k iterations, or earlier at the tolerance %.0e; the step is used either way)\n",
                tol);
    std::printf("(vecs: the vectors PCG's initial guess is projected from, 1 = the last velocity alone; default %d)\n",
                settings.solver.projection_vectors);
    std::printf("%9s %5s %4s | %8s %6s %8s %8s %6s %6s | %14s %14s %9s\n", "tolerance", "cap", "vecs", "step[ms]", "mean",
                "assem", "solve", "iters", "capped", "err@3 steps", "err@end", "err/max");
    nlohmann::json trows = nlohmann::json::array();
    struct Variant {
      double tolerance;
      int cap;  // 0 = the default max_iterations
      int vectors;
    };
    std::vector<Variant> variants;
    const int default_vectors = settings.solver.projection_vectors;
    for (double t : tol_study) variants.push_back({t, 0, default_vectors});
    for (double k : cap_study) variants.push_back({tol, static_cast<int>(k), default_vectors});
    for (double k : projection_study) variants.push_back({tol, 0, static_cast<int>(k)});
    for (const Variant& v : variants) {
      SimulationSettings ts = settings;
      ts.solver.relative_tolerance = v.tolerance;
      if (v.cap > 0) ts.solver.max_iterations = v.cap;
      ts.solver.projection_vectors = v.vectors;
      SimulatorBuild tb = buildSimulator(c, model, ts);
      const StepRun a = runSteps(*tb.simulator, early);
      const double e_early = maxNodalNorm(tb.simulator->state().displacement_m - u_early);
      const StepRun b2 = runSteps(*tb.simulator, horizon - early);
      const double e_end = maxNodalNorm(tb.simulator->state().displacement_m - u_end);
      std::vector<double> total = a.total, its = a.iterations, assem = a.assembly, solve = a.solve;
      total.insert(total.end(), b2.total.begin(), b2.total.end());
      its.insert(its.end(), b2.iterations.begin(), b2.iterations.end());
      assem.insert(assem.end(), b2.assembly.begin(), b2.assembly.end());
      solve.insert(solve.end(), b2.solve.begin(), b2.solve.end());
      const int capped = v.cap > 0 ? a.unconverged + b2.unconverged : 0;
      const int inverted =
          static_cast<int>(invertedTets(model.mesh.tets(), model.mesh.nodes() + tb.simulator->displacement()).size());
      const std::string cap_text = v.cap > 0 ? std::to_string(v.cap) : "-";
      std::printf("%9.0e %5s %4d | %8.1f %6.1f %8.1f %8.1f %6.1f %6d | %11.2e mm %11.2e mm %9.1e%s\n", v.tolerance,
                  cap_text.c_str(), v.vectors, 1e3 * median(total), 1e3 * mean(total), 1e3 * median(assem), 1e3 * median(solve), mean(its), capped,
                  1e3 * e_early, 1e3 * e_end, scale_end > 0 ? e_end / scale_end : 0.0,
                  inverted ? ("  (" + std::to_string(inverted) + " inverted)").c_str() : "");
      std::fflush(stdout);
      trows.push_back({{"relative_tolerance", v.tolerance},
                       {"iteration_cap", v.cap},
                       {"projection_vectors", v.vectors},
                       {"step_ms_median", 1e3 * median(total)},
                       {"step_ms_mean", 1e3 * mean(total)},
                       {"assembly_ms_median", 1e3 * median(assem)},
                       {"solve_ms_median", 1e3 * median(solve)},
                       {"iterations_mean", mean(its)},
                       {"capped_steps", capped},
                       {"inverted", inverted},
                       {"path_error_after_3_steps_mm", 1e3 * e_early},
                       {"path_error_at_end_mm", 1e3 * e_end},
                       {"path_error_at_end_relative", scale_end > 0 ? e_end / scale_end : 0.0}});
    }
    out["tolerance_study"] = {{"elements", model.mesh.numTets()},
                              {"steps", horizon},
                              {"max_displacement_at_end_mm", 1e3 * scale_end},
                              {"rows", trows}};
  }

  if (settle_study) {
    ModelCase c = base;
    c.meshing.target_elements = settle_target;
    const SimulationModel model = buildSimulationModel(c);
    SimulationSettings settings = defaults;
    settings.dynamics.gravity_mps2 = g_supine;
    // Reference: CHOLMOD, long steps, settled to 1e-8 m.
    SimulationSettings rs = settings;
    rs.solver.kind = SolverSettings::Kind::kCholmod;
    SimulatorBuild rb = buildSimulator(c, model, rs);
    SettleOptions ro;
    ro.time_step_s = 1.0;
    ro.increment_tolerance_m = 1e-8;
    ro.max_steps = 200;
    const SettleResult ref = settle(*rb.simulator, ro);
    const Eigen::VectorXd u_ref = rb.simulator->state().displacement_m;
    std::printf("\nSettling under supine gravity, %d tets; reference: CHOLMOD, dt 1 s, increments < 1e-5 mm: %s in %d "
                "steps, %.1f s, max displacement %.2f mm\n",
                model.mesh.numTets(), ref.settled ? "settled" : "NOT settled", ref.steps, ref.seconds,
                1e3 * ref.max_displacement_m);
    std::printf("%9s %10s | %6s %8s %8s %8s %8s %7s | %10s %10s %9s\n", "dt[s]", "solver", "steps", "time[s]", "assem",
                "setup", "solve", "iters", "err max", "err mean", "inverted");
    nlohmann::json srows = nlohmann::json::array();
    for (double dt : settle_dts) {
      for (auto kind : {SolverSettings::Kind::kMultigrid, SolverSettings::Kind::kCholmod}) {
        // CHOLMOD's 0.4 s factorization per step makes short settling steps take minutes: skipped.
        if (kind == SolverSettings::Kind::kCholmod && dt < 0.3) continue;
        SimulationSettings s = settings;
        s.solver.kind = kind;
        SimulatorBuild sb = buildSimulator(c, model, s);
        SettleOptions so;
        so.time_step_s = dt;
        so.max_steps = 400;
        const SettleResult r = settle(*sb.simulator, so);
        const Eigen::VectorXd d = sb.simulator->state().displacement_m - u_ref;
        double emax = 0, emean = 0;
        for (int n = 0; n < sb.simulator->numNodes(); ++n) {
          const double e = d.segment<3>(3 * n).norm();
          emax = std::max(emax, e);
          emean += e / sb.simulator->numNodes();
        }
        const int inv = static_cast<int>(invertedTets(model.mesh.tets(), model.mesh.nodes() + sb.simulator->displacement()).size());
        const std::string name = SolverSettings::kindName(kind);
        std::printf("%9.3f %10s | %6d %8.2f %8.2f %8.2f %8.2f %7.1f | %8.3fmm %8.3fmm %9d%s\n", dt, name.c_str(), r.steps,
                    r.seconds, r.assembly_seconds, r.setup_seconds, r.solve_seconds,
                    r.steps ? double(r.solver_iterations) / r.steps : 0.0, 1e3 * emax, 1e3 * emean, inv,
                    r.settled ? "" : "  (not settled)");
        std::fflush(stdout);
        srows.push_back({{"time_step_s", dt},
                         {"solver", name},
                         {"settled", r.settled},
                         {"steps", r.steps},
                         {"seconds", r.seconds},
                         {"assembly_s", r.assembly_seconds},
                         {"solver_setup_s", r.setup_seconds},
                         {"solve_s", r.solve_seconds},
                         {"iterations_per_step", r.steps ? double(r.solver_iterations) / r.steps : 0.0},
                         {"error_max_mm", 1e3 * emax},
                         {"error_mean_mm", 1e3 * emean},
                         {"inverted", inv}});
      }
    }
    out["settle"] = {{"elements", model.mesh.numTets()},
                     {"reference_steps", ref.steps},
                     {"reference_seconds", ref.seconds},
                     {"reference_max_displacement_mm", 1e3 * ref.max_displacement_m},
                     {"runs", srows}};
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
  return 0;
}
