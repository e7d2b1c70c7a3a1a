// bench_user_mesh: a mesh of the user's own (a `mesh:` case), settled by our solvers and by CalculiX
// side by side in one run, on the same mesh and load: the pipeline's gravity stage with the chest
// wall fixed (g_supine − g_prone on the prone shape, E0 throughout: no stiffening, which CalculiX
// does not model) against CalculiX C3D4 (the same linear tetrahedra, neo-Hookean, NLGEOM, static).
// CalculiX runs once (no cache), with the same thread count; ours --repeats times, whose medians are
// shown (the shared machine's noise moves a single settle by up to 2x). Prints a table; --json FILE
// writes the same figures.
//
// Usage: bench_user_mesh [--case FILE] [--solvers multigrid,aggregation] [--repeats 3] [--ccx-threads N]
//                        [--json FILE]
#include <omp.h>

#include <cstdio>
#include <algorithm>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/reference/calculix.h"
#include "breast_sim/core/reference/reference_case.h"

using namespace breast_sim;
using namespace breast_sim::core;

int main(int argc, char** argv) {
  try {
    std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/mesh_case.yaml", json_path;
    std::string solvers = "multigrid,aggregation";
    int ccx_threads = 0, repeats = 3;
    auto whole = [](const std::string& option, const std::string& text) {
      size_t used = 0;
      int v = 0;
      try {
        v = std::stoi(text, &used);
      } catch (const std::exception&) {
        used = 0;
      }
      if (used == 0 || used != text.size()) throw std::runtime_error(option + " expects a whole number, got '" + text + "'");
      return v;
    };
    for (int i = 1; i < argc; ++i) {
      const std::string a = argv[i];
      if (a == "--case") case_path = bench::argValue(argc, argv, i);
      else if (a == "--solvers") solvers = bench::argValue(argc, argv, i);
      else if (a == "--repeats") repeats = std::max(1, whole(a, bench::argValue(argc, argv, i)));
      else if (a == "--ccx-threads") ccx_threads = whole(a, bench::argValue(argc, argv, i));
      else if (a == "--json") json_path = bench::argValue(argc, argv, i);
      else {
        std::fprintf(stderr, "usage: bench_user_mesh [--case FILE] [--solvers multigrid,aggregation] [--repeats 3] [--ccx-threads N] [--json FILE]\n");
        return 2;
      }
    }
    if (!calculixAvailable()) throw std::runtime_error("CalculiX (ccx) does not run: apt-get install calculix-ccx");
    if (ccx_threads <= 0) ccx_threads = omp_get_max_threads();
    auto t0 = bench::Clock::now();
    const ModelCase c = loadModelCase(case_path);
    if (!c.mesh) throw std::runtime_error(case_path + ": not a mesh case (mesh:)");
    const SimulationModel model = buildSimulationModel(c);
    const double load_s = bench::since(t0);
    PipelineSettings base = loadPipelineSettings(case_path);
    // CalculiX loads the prone shape as stress-free with g_supine − g_prone: so does our run here.
    base.simulation.reference_state = SimulationSettings::ReferenceState::kProne;
    base.simulation.sliding = false;
    base.simulation.stiffening = false;
    base.morphing.enabled = false;

    std::printf("bench_user_mesh: case '%s', %s\n  %d tetrahedra, %d nodes, read + label image %.2f s; E %.0f Pa, nu %.2f; "
                "%d threads (ours), %d (CalculiX); ours: medians of %d runs\n",
                c.name.c_str(), c.mesh_source.path.c_str(), model.mesh.numTets(), model.mesh.numNodes(), load_s,
                base.simulation.material.youngs_modulus_pa, base.simulation.material.poisson_ratio, omp_get_max_threads(),
                ccx_threads, repeats);

    struct Row {
      std::string solver;
      double setup_s = 0, settle_s = 0, settle_min_s = 0, settle_max_s = 0;  // medians; settle's range
      int steps = 0;
      long iterations = 0;  // Krylov iterations of all steps
      bool converged = false;
      Points u;
    };
    std::vector<Row> rows;
    Eigen::Vector3d load = Eigen::Vector3d::Zero();
    std::stringstream list(solvers);
    for (std::string name; std::getline(list, name, ',');) {
      PipelineSettings s = base;
      s.simulation.solver.kind = SolverSettings::kindFromName(name);
      Row r;
      r.solver = name;
      std::vector<double> setup, settle;
      for (int k = 0; k < repeats; ++k) {
        t0 = bench::Clock::now();
        ProneToSupinePipeline pipe(c, model, s);
        setup.push_back(bench::since(t0));
        pipe.runGravity();
        settle.push_back(pipe.gravityReport().seconds);
        r.steps = pipe.gravityReport().steps;
        r.iterations = pipe.simulator().totals().iterations;
        r.converged = pipe.gravityReport().converged;
        r.u = pipe.positions() - model.mesh.nodes();
        load = pipe.gravityLoad();
      }
      r.setup_s = bench::median(setup);
      r.settle_s = bench::median(settle);
      r.settle_min_s = *std::min_element(settle.begin(), settle.end());
      r.settle_max_s = *std::max_element(settle.begin(), settle.end());
      rows.push_back(std::move(r));
    }

    CalculixLoadCase lc = referenceLoadCase(base.simulation, model.mesh, load, ReferenceElement::kC3D4);
    CalculixOptions opt;
    opt.cache_dir = "";  // measured now, beside ours
    opt.threads = ccx_threads;
    t0 = bench::Clock::now();
    const CalculixResult ref = solveWithCalculix(model.mesh, lc, opt);
    const double ccx_s = bench::since(t0);
    const double ref_max_mm = 1e3 * ref.displacement_m.rowwise().norm().maxCoeff();

    std::printf("  load g_supine - g_prone = (%.2f, %.2f, %.2f) m/s^2, chest wall fixed; CalculiX C3D4 NLGEOM: %.2f s "
                "(ccx %.2f s), max displacement %.2f mm\n\n",
                load.x(), load.y(), load.z(), ccx_s, ref.solve_seconds, ref_max_mm);
    std::printf("  %-12s %9s %9s %13s %6s %6s %10s %12s %12s %14s\n", "solver", "setup s", "settle s", "settle range",
                "steps", "iters", "converged", "x ccx settle", "x ccx total", "vs C3D4 mean/max mm");
    nlohmann::json out = {{"case", c.name},
                          {"mesh", c.mesh_source.path},
                          {"elements", model.mesh.numTets()},
                          {"nodes", model.mesh.numNodes()},
                          {"threads", omp_get_max_threads()},
                          {"ccx_threads", ccx_threads},
                          {"repeats", repeats},
                          {"load_mps2", {load.x(), load.y(), load.z()}},
                          {"calculix_c3d4_nlgeom", {{"seconds", ccx_s}, {"solve_seconds", ref.solve_seconds}, {"max_displacement_mm", ref_max_mm}}},
                          {"ours", nlohmann::json::array()}};
    for (const Row& r : rows) {
      const Eigen::VectorXd d = (r.u - ref.displacement_m).rowwise().norm();
      const double mean_mm = 1e3 * d.mean(), max_mm = 1e3 * d.maxCoeff();
      std::printf("  %-12s %9.2f %9.2f %6.2f-%-6.2f %6d %6ld %10s %11.1fx %11.1fx %8.3f / %.3f\n", r.solver.c_str(), r.setup_s,
                  r.settle_s, r.settle_min_s, r.settle_max_s, r.steps, r.iterations, r.converged ? "yes" : "NO", ccx_s / r.settle_s, ccx_s / (r.setup_s + r.settle_s), mean_mm, max_mm);
      out["ours"].push_back({{"solver", r.solver},
                             {"setup_seconds", r.setup_s},
                             {"settle_seconds", r.settle_s},
                             {"settle_seconds_min", r.settle_min_s},
                             {"settle_seconds_max", r.settle_max_s},
                             {"steps", r.steps},
                             {"iterations", r.iterations},
                             {"converged", r.converged},
                             {"ccx_over_settle", ccx_s / r.settle_s},
                             {"ccx_over_setup_and_settle", ccx_s / (r.setup_s + r.settle_s)},
                             {"vs_c3d4_mean_mm", mean_mm},
                             {"vs_c3d4_max_mm", max_mm}});
    }
    if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_user_mesh: %s\n", e.what());
    return 1;
  }
}
