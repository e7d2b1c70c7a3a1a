// breast_sim_stability_map: where do the methods fail? Runs the phantom's hard load case (prone rest
// shape, chest wall fixed, supine gravity) with five methods over Poisson ratio, Young's modulus,
// time step and initial α (material/stability_map.h), prints a table and writes CSV / JSON for
// scripts/plot_stability_map.py.
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "breast_sim/core/material/stability_map.h"

using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_stability_map [--quick] [--csv FILE] [--json FILE] [--case FILE]
                                 [--target-elements N] [--methods m1,m2,...] [--max-time S]

Runs the stability map (see include/breast_sim/core/material/stability_map.h):
  --quick               trimmed grid (nu 0.28/0.48/0.495 x dt 0.033/0.33 s, 2 s simulated)
  --csv FILE            one row per run
  --json FILE           the same rows and the settings
  --case FILE           phantom case (default: config/phantom_default.yaml of the source tree)
  --target-elements N   mesh size (default 3000)
  --methods LIST        subset of linear,corotated,vonmises_no_reversal,full,explicit_euler,anp,anp_full
  --max-time S          simulated-time limit per run [s] (default 4, quick 2; at least 80 steps)
  --threads N           OpenMP threads per run at most (default 1: the runs are small); a step
                        uses fewer while other work holds cores
  --gravity X,Y,Z       gravity [m/s^2] instead of the phantom's supine gravity
  --nu A,B,.. --E A,B,.. [Pa] --dt A,B,.. [s] --alpha-scale A,B,..
                        a custom grid: the product of the given lists (others at their defaults
                        0.48, 2000 Pa, 0.033 s, 1) replaces the built-in one
)";

std::vector<std::string> split(const std::string& v) {
  std::vector<std::string> out;
  std::stringstream ss(v);
  for (std::string t; std::getline(ss, t, ',');) out.push_back(t);
  return out;
}

}  // namespace

int main(int argc, char** argv) try {
  bool quick = false;
  std::string csv, json, case_file = defaultPhantomCasePath();
  int target = 3000;
  int threads = 1;
  double max_time = 0.0;
  std::set<std::string> methods;
  std::vector<double> nus, Es, dts, alphas;
  bool custom = false, gravity_given = false;
  Eigen::Vector3d gravity = Eigen::Vector3d::Zero();
  auto numbers = [](const std::string& v) {
    std::vector<double> out;
    for (const std::string& t : split(v)) out.push_back(std::stod(t));
    return out;
  };
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument("option " + k + " needs a value\n" + kUsage);
      return argv[++i];
    };
    if (k == "--quick") quick = true;
    else if (k == "--csv") csv = value();
    else if (k == "--json") json = value();
    else if (k == "--case") case_file = value();
    else if (k == "--target-elements") target = std::stoi(value());
    else if (k == "--max-time") max_time = std::stod(value());
    else if (k == "--threads") threads = std::stoi(value());
    else if (k == "--nu") nus = numbers(value()), custom = true;
    else if (k == "--E") Es = numbers(value()), custom = true;
    else if (k == "--dt") dts = numbers(value()), custom = true;
    else if (k == "--alpha-scale") alphas = numbers(value()), custom = true;
    else if (k == "--gravity") {
      const std::vector<double> g = numbers(value());
      if (g.size() != 3) throw std::invalid_argument("--gravity needs X,Y,Z [m/s^2]");
      gravity = Eigen::Vector3d(g[0], g[1], g[2]);
      gravity_given = true;
    } else if (k == "--methods") {
      for (const std::string& m : split(value())) methods.insert(methodName(parseStabilityMethod(m)));
    } else if (k == "--help" || k == "-h") {
      std::cout << kUsage;
      return 0;
    } else {
      throw std::invalid_argument("unknown option " + k + "\n" + kUsage);
    }
  }
  if (threads < 1) throw std::invalid_argument("--threads must be ≥ 1");
  omp_set_num_threads(threads);
  StabilityLoadCase load = makePhantomLoadCase(case_file, target);
  if (gravity_given) load.gravity_mps2 = gravity;
  const StiffeningParams params;  // the robust general preset
  std::printf("case %s: %d tetrahedra, %d nodes, %zu fixed (chest wall), gravity (%.2f, %.2f, %.2f) m/s^2, up to %d threads\n",
              load.name.c_str(), load.mesh.numTets(), load.mesh.numNodes(), load.fixed_nodes.size(), load.gravity_mps2.x(),
              load.gravity_mps2.y(), load.gravity_mps2.z(), omp_get_max_threads());
  std::printf("default alpha %.3g 1/Pa (x0.8 per good step, x2 per reversal), settle: |v| < %.3g m/s and residual < %.3g for %d steps\n\n",
              params.alpha.initial_alpha_per_pa, params.settle.max_speed_mps, params.settle.max_relative_residual,
              params.settle.consecutive_steps);
  std::vector<StabilityRun> grid;
  if (custom) {
    if (nus.empty()) nus = {0.48};
    if (Es.empty()) Es = {2000.0};
    if (dts.empty()) dts = {0.033};
    if (alphas.empty()) alphas = {1.0};
    for (StabilityMethod m : allStabilityMethods())
      for (double nu : nus)
        for (double E : Es)
          for (double dt : dts)
            for (double a : alphas) {
              StabilityRun r;
              r.method = m;
              r.poisson_ratio = nu;
              r.youngs_modulus_pa = E;
              r.time_step_s = dt;
              r.alpha_scale = a;
              r.axis = "custom";
              grid.push_back(r);
            }
  } else {
    grid = stabilityGrid(quick);
  }
  std::vector<StabilityRun> runs;
  for (StabilityRun r : grid) {
    if (!methods.empty() && !methods.count(methodName(r.method))) continue;
    if (max_time > 0) r.max_time_s = max_time;
    runs.push_back(r);
  }
  std::printf("%-21s %-5s %6s %6s %6s %5s | %-11s %5s %5s %6s %5s %8s %7s %7s %6s  %s\n", "method", "axis", "E[Pa]", "nu",
              "dt[s]", "a0x", "outcome", "steps", "settl", "rev[%]", "inv", "alpha", "umax", "dV[%]", "wall", "reason");
  std::printf("%-21s %-5s %6s %6s %6s %5s | %-11s %5s %5s %6s %5s %8s %7s %7s %6s\n", "", "", "", "", "", "", "", "", "", "", "",
              "[1/Pa]", "[mm]", "", "[s]");
  nlohmann::json rows = nlohmann::json::array();
  std::ofstream csv_out;
  if (!csv.empty()) {
    csv_out.open(csv);
    if (!csv_out) throw std::runtime_error("cannot write " + csv);
    csv_out << "method,axis,youngs_modulus_pa,poisson_ratio,shear_modulus_pa,time_step_s,alpha_scale,initial_alpha_per_pa,"
               "outcome,reason,settled,nan,exploded,inverted_elements,steps,reversed_steps,reversal_fraction,"
               "reversal_limit_hits,steps_to_settle,simulated_time_s,wall_s,max_displacement_mm,volume_change_percent,"
               "final_alpha_per_pa,max_modulus_factor\n";
  }
  double total_wall = 0.0;
  for (const StabilityRun& r : runs) {
    const StabilityResult res = runStability(load, r, params);
    const RunStats& s = res.stats;
    total_wall += s.wall_seconds;
    const double mu = r.youngs_modulus_pa / (2.0 * (1.0 + r.poisson_ratio));
    std::printf("%-21s %-5s %6.0f %6.3f %6.3f %5.1f | %-11s %5ld %5ld %6.1f %5d %8.2g %7.2f %7.2f %6.2f  %s\n",
                methodName(r.method), r.axis.c_str(), r.youngs_modulus_pa, r.poisson_ratio, r.time_step_s, r.alpha_scale,
                res.outcome.c_str(), s.steps, s.steps_to_settle, 100.0 * s.reversal_fraction, s.inverted_elements,
                s.final_alpha_per_pa, 1e3 * s.max_displacement_m, s.volume_change_percent, s.wall_seconds, res.reason.c_str());
    std::fflush(stdout);
    nlohmann::json j = {{"method", methodName(r.method)},
                        {"axis", r.axis},
                        {"youngs_modulus_pa", r.youngs_modulus_pa},
                        {"poisson_ratio", r.poisson_ratio},
                        {"shear_modulus_pa", mu},
                        {"time_step_s", r.time_step_s},
                        {"alpha_scale", r.alpha_scale},
                        {"initial_alpha_per_pa", res.initial_alpha_per_pa},
                        {"outcome", res.outcome},
                        {"reason", res.reason},
                        {"settled", s.settled},
                        {"nan", s.nan},
                        {"exploded", s.exploded},
                        {"inverted_elements", s.inverted_elements},
                        {"steps", s.steps},
                        {"reversed_steps", s.reversed_steps},
                        {"reversal_fraction", s.reversal_fraction},
                        {"reversal_limit_hits", s.reversal_limit_hits},
                        {"steps_to_settle", s.steps_to_settle},
                        {"simulated_time_s", s.simulated_time_s},
                        {"wall_s", s.wall_seconds},
                        {"max_displacement_mm", std::isfinite(s.max_displacement_m) ? 1e3 * s.max_displacement_m : -1.0},
                        {"volume_change_percent", std::isfinite(s.volume_change_percent) ? s.volume_change_percent : 0.0},
                        {"final_alpha_per_pa", s.final_alpha_per_pa},
                        {"max_modulus_factor", s.max_modulus_factor}};
    rows.push_back(j);
    if (csv_out) {
      std::string reason = res.reason;
      for (char& c : reason)
        if (c == ',') c = ';';
      char buf[1024];
      std::snprintf(buf, sizeof buf,
                    "%s,%s,%.6g,%.6g,%.6g,%.6g,%.6g,%.6g,%s,%s,%d,%d,%d,%d,%ld,%ld,%.6g,%ld,%ld,%.6g,%.6g,%.6g,%.6g,%.6g,%.6g\n",
                    methodName(r.method), r.axis.c_str(), r.youngs_modulus_pa, r.poisson_ratio, mu, r.time_step_s,
                    r.alpha_scale, res.initial_alpha_per_pa, res.outcome.c_str(), reason.c_str(), s.settled, s.nan,
                    s.exploded, s.inverted_elements, s.steps, s.reversed_steps, s.reversal_fraction, s.reversal_limit_hits,
                    s.steps_to_settle, s.simulated_time_s, s.wall_seconds, 1e3 * s.max_displacement_m,
                    s.volume_change_percent, s.final_alpha_per_pa, s.max_modulus_factor);
      csv_out << buf;
    }
  }
  std::printf("\n%zu runs in %.1f s\n", runs.size(), total_wall);
  if (!json.empty()) {
    nlohmann::json out = {{"tool", "breast_sim_stability_map"},
                          {"case", load.name},
                          {"tets", load.mesh.numTets()},
                          {"nodes", load.mesh.numNodes()},
                          {"fixed_nodes", load.fixed_nodes.size()},
                          {"gravity_mps2", {load.gravity_mps2.x(), load.gravity_mps2.y(), load.gravity_mps2.z()}},
                          {"quick", quick},
                          {"threads", omp_get_max_threads()},
                          {"default_alpha_per_pa", params.alpha.initial_alpha_per_pa},
                          {"settle_max_speed_mps", params.settle.max_speed_mps},
                          {"settle_max_relative_residual", params.settle.max_relative_residual},
                          {"total_wall_s", total_wall},
                          {"runs", rows}};
    std::ofstream(json) << out.dump(1) << '\n';
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "breast_sim_stability_map: %s\n", e.what());
  return 1;
}
