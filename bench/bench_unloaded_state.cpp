// The unloaded reference shape of the phantom (fem/unloaded_state.h, docs/unloaded_state.md): the
// fixed-point iteration's residual per iteration, its time, how far the unloaded shape X0 lies from
// the prone shape, and the supine shape loaded from X0 with supine gravity against the prone shape
// loaded with g_supine − g_prone (the chest wall fixed, no sliding), nodes and lesions. Prints tables;
// --json FILE writes the same figures.
//   bench_unloaded_state [--case config/phantom_default.yaml] [--elements 12000]
//                        [--solver multigrid|aggregation|cholmod] [--stiffening 0|1] [--tolerance-mm 0.01]
//                        [--max-iterations 30] [--no-supine] [--json FILE]
// The case's `simulation:` map gives the material, elements and settle options (defaults: E 2 kPa,
// ν 0.48, the default element, stiffening on); --solver replaces its solver ('multigrid': the coarse
// levels are meshed of the prone domain, and each simulator on an X0 takes the prone shape's
// prolongations, as the pipeline's do).
#include <cstdio>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/fem/unloaded_state.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/solver/multigrid.h"

using namespace breast_sim::core;
namespace bench = breast_sim::bench;

namespace {

struct Distances {
  double mean_mm = 0.0, max_mm = 0.0;
};

Distances distances(const Points& a, const Points& b) {
  const Eigen::VectorXd d = (a - b).rowwise().norm();
  return {d.mean() * 1e3, d.maxCoeff() * 1e3};
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml", json_path;
  std::string solver = "cholmod";
  int elements = 12000, stiffening = 1, max_iterations = 30;
  double tolerance_mm = 0.01;
  bool supine = true;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--case") case_path = bench::argValue(argc, argv, i);
    else if (a == "--elements") elements = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--solver") solver = bench::argValue(argc, argv, i);
    else if (a == "--stiffening") stiffening = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--tolerance-mm") tolerance_mm = std::stod(bench::argValue(argc, argv, i));
    else if (a == "--max-iterations") max_iterations = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--no-supine") supine = false;
    else if (a == "--json") json_path = bench::argValue(argc, argv, i);
    else {
      std::fprintf(stderr,
                   "usage: bench_unloaded_state [--case FILE] [--elements N] [--solver multigrid|aggregation|cholmod] "
                   "[--stiffening 0|1] [--tolerance-mm MM] [--max-iterations N] [--no-supine] [--json FILE]\n");
      return 2;
    }
  }
  ModelCase c = loadModelCase(case_path);
  c.meshing.target_elements = elements;
  auto t0 = bench::Clock::now();
  const SimulationModel model = buildSimulationModel(c);
  const double mesh_s = bench::since(t0);
  SimulationSettings s = loadSimulationSettings(case_path);
  s.solver.kind = SolverSettings::kindFromName(solver);
  s.stiffening = stiffening != 0;
  s.sliding = false;
  const Eigen::Vector3d g_prone = s.gravity_mps2 * c.prone_gravity_direction.normalized();
  const Eigen::Vector3d g_supine = c.phantom && c.phantom->gravity_supine_mps2.norm() > 0
                                       ? Eigen::Vector3d(s.gravity_mps2 * c.phantom->gravity_supine_mps2.normalized())
                                       : Eigen::Vector3d(-g_prone);
  std::printf("case %s: %d elements, %d nodes (meshed in %.1f s); solver %s, stiffening %s, E %.0f Pa, nu %.2f\n",
              c.name.c_str(), model.mesh.numTets(), model.mesh.numNodes(), mesh_s, solver.c_str(),
              s.stiffening ? "on" : "off", s.material.youngs_modulus_pa, s.material.poisson_ratio);

  UnloadedStateOptions o;
  o.tolerance_m = tolerance_mm * 1e-3;
  o.max_iterations = max_iterations;
  double coarse_s = 0.0;
  if (s.solver.kind == SolverSettings::Kind::kMultigrid) {
    t0 = bench::Clock::now();
    o.coarse_meshes = buildCoarseMeshes(c, model, s.solver.coarsening);
    coarse_s = bench::since(t0);
    std::printf("%zu coarse levels meshed in %.1f s (not in the recovery's time)\n", o.coarse_meshes.size(), coarse_s);
  }
  const UnloadedStateResult r = recoverUnloadedShape(model.mesh, s, g_prone, o);
  std::printf("\n%-5s %-12s %-13s %-12s %-8s %s\n", "iter", "max res mm", "mean res mm", "settle steps", "s", "step");
  nlohmann::json hist = nlohmann::json::array();
  for (size_t k = 0; k < r.history.size(); ++k) {
    const UnloadedIteration& it = r.history[k];
    char step[32];
    std::snprintf(step, sizeof step, it.step_fraction < 1.0 ? "plain x %.4g" : "plain", it.step_fraction);
    std::printf("%-5zu %-12.5f %-13.6f %-12d %-8.2f %s\n", k + 1, it.max_residual_m * 1e3, it.mean_residual_m * 1e3,
                it.settle_steps, it.seconds, it.accelerated ? "anderson" : step);
    hist.push_back({{"iteration", k + 1},
                    {"max_residual_mm", it.max_residual_m * 1e3},
                    {"mean_residual_mm", it.mean_residual_m * 1e3},
                    {"settle_steps", it.settle_steps},
                    {"seconds", it.seconds},
                    {"accelerated", it.accelerated},
                    {"step_fraction", it.step_fraction}});
  }
  const Distances x0 = distances(r.unloaded_nodes_m, model.mesh.nodes());
  std::printf("\nconverged %s in %d iterations, %.1f s; residual max %.5f mm, mean %.6f mm%s%s\n",
              r.converged ? "yes" : "no", r.iterations, r.seconds, r.max_residual_m * 1e3, r.mean_residual_m * 1e3,
              r.failure.empty() ? "" : "; ", r.failure.c_str());
  std::printf("unloaded shape X0 vs prone shape: mean %.3f mm, max %.3f mm\n", x0.mean_mm, x0.max_mm);

  nlohmann::json out = {{"case", c.name},
                        {"elements", model.mesh.numTets()},
                        {"nodes", model.mesh.numNodes()},
                        {"solver", solver},
                        {"stiffening", s.stiffening},
                        {"youngs_modulus_pa", s.material.youngs_modulus_pa},
                        {"poisson_ratio", s.material.poisson_ratio},
                        {"tolerance_mm", tolerance_mm},
                        {"coarse_levels", o.coarse_meshes.size()},
                        {"coarse_meshing_seconds", coarse_s},
                        {"converged", r.converged},
                        {"failure", r.failure},
                        {"iterations", r.iterations},
                        {"seconds", r.seconds},
                        {"max_residual_mm", r.max_residual_m * 1e3},
                        {"mean_residual_mm", r.mean_residual_m * 1e3},
                        {"history", hist},
                        {"unloaded_vs_prone_mean_mm", x0.mean_mm},
                        {"unloaded_vs_prone_max_mm", x0.max_mm}};

  if (supine && r.converged) {
    // The superposition: the prone shape is stress-free and takes g_supine − g_prone.
    const GravityLoading superposed = loadWithGravity(model.mesh, s, g_supine - g_prone, o.stiffening, Points(), o.coarse_meshes);
    // The unloaded reference: X0 takes g_supine.
    const TetMesh rest = withNodes(model.mesh, r.unloaded_nodes_m);
    const GravityLoading unloaded = loadWithGravity(rest, s, g_supine, o.stiffening, Points(), o.coarse_meshes,
                                                    o.coarse_meshes.empty() ? Points() : model.mesh.nodes());
    std::printf("\nsupine, prone + (g_supine - g_prone): %s, %d steps, %.1f s\n",
                superposed.settled ? "settled" : superposed.failure.c_str(), superposed.steps, superposed.seconds);
    std::printf("supine, X0 + g_supine:               %s, %d steps, %.1f s\n",
                unloaded.settled ? "settled" : unloaded.failure.c_str(), unloaded.steps, unloaded.seconds);
    out["supine_superposed_settled"] = superposed.settled;
    out["supine_unloaded_settled"] = unloaded.settled;
    out["supine_superposed_seconds"] = superposed.seconds;
    out["supine_unloaded_seconds"] = unloaded.seconds;
    if (superposed.settled && unloaded.settled) {
      const Points x_superposed = model.mesh.nodes() + superposed.displacement_m;
      const Points x_unloaded = r.unloaded_nodes_m + unloaded.displacement_m;
      const Distances d = distances(x_unloaded, x_superposed);
      const Distances sag_superposed = distances(x_superposed, model.mesh.nodes());
      const Distances sag_unloaded = distances(x_unloaded, model.mesh.nodes());
      std::printf("supine node positions, unloaded vs superposed: mean %.3f mm, max %.3f mm\n", d.mean_mm, d.max_mm);
      std::printf("supine displacement from prone: superposed mean %.2f max %.2f mm; unloaded mean %.2f max %.2f mm\n",
                  sag_superposed.mean_mm, sag_superposed.max_mm, sag_unloaded.mean_mm, sag_unloaded.max_mm);
      out["supine_nodes_unloaded_vs_superposed_mean_mm"] = d.mean_mm;
      out["supine_nodes_unloaded_vs_superposed_max_mm"] = d.max_mm;
      out["supine_displacement_superposed_mean_mm"] = sag_superposed.mean_mm;
      out["supine_displacement_superposed_max_mm"] = sag_superposed.max_mm;
      out["supine_displacement_unloaded_mean_mm"] = sag_unloaded.mean_mm;
      out["supine_displacement_unloaded_max_mm"] = sag_unloaded.max_mm;
      const Points l_prone = model.lesion_embedding.positions(model.mesh.nodes());
      const Points l_superposed = model.lesion_embedding.positions(x_superposed);
      const Points l_unloaded = model.lesion_embedding.positions(x_unloaded);
      const Points l_x0 = model.lesion_embedding.positions(r.unloaded_nodes_m);
      std::printf("\n%-14s %-14s %-20s %-18s %s\n", "lesion", "X0-prone mm", "superposed move mm", "unloaded move mm",
                  "unloaded-superposed mm");
      nlohmann::json les = nlohmann::json::array();
      for (int i = 0; i < model.lesion_embedding.size(); ++i) {
        const double in_x0 = (l_x0.row(i) - l_prone.row(i)).norm() * 1e3;
        const double mt = (l_superposed.row(i) - l_prone.row(i)).norm() * 1e3;
        const double mu = (l_unloaded.row(i) - l_prone.row(i)).norm() * 1e3;
        const double du = (l_unloaded.row(i) - l_superposed.row(i)).norm() * 1e3;
        const std::string name = i < static_cast<int>(model.lesions.size()) ? model.lesions[i].name : std::to_string(i);
        std::printf("%-14s %-14.2f %-20.2f %-18.2f %.2f\n", name.c_str(), in_x0, mt, mu, du);
        les.push_back({{"name", name},
                       {"unloaded_vs_prone_mm", in_x0},
                       {"supine_move_superposed_mm", mt},
                       {"supine_move_unloaded_mm", mu},
                       {"supine_unloaded_vs_superposed_mm", du}});
      }
      out["lesions"] = les;
    }
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return r.converged ? 0 : 1;
}
