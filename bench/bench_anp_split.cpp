// The average-nodal-pressure element's time step, three ways in one run: its stiffness split into
// the one-ring matrix and the rank-one sum over node stars (what the multigrid and Jacobi-PCG
// take), the same element with the assembled two-ring matrix, and the J − 1 co-rotated linear
// tetrahedra. Their steps are interleaved (one step of each in turn) so that all three see the same
// load on a shared machine; the table gives medians, the ratios to the J − 1 step, and a settle of
// each from the rest shape to the supine equilibrium (SettleOptions' defaults: 0.33 s steps). The phantom's supine load, the multigrid at the default tolerance.
//   bench_anp_split [--targets 20000,47895] [--steps 25] [--no-settle] [--json FILE]
#include <cstdio>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include <omp.h>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/anp_tet_fem.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/solver/multigrid.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

// The multigrid PCG with its rank-one capability hidden: the simulator then assembles the whole
// two-ring matrix, as for CHOLMOD.
class AssembledOnly : public LinearSolver {
 public:
  explicit AssembledOnly(std::unique_ptr<LinearSolver> s) : s_(std::move(s)) {}
  void analyzePattern(const SparseMatrix& A) override { s_->analyzePattern(A); }
  void factorize(const SparseMatrix& A) override { s_->factorize(A); }
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override { return s_->solve(b, x); }
  std::string name() const override { return s_->name(); }

 private:
  std::unique_ptr<LinearSolver> s_;
};

struct Variant {
  const char* name;
  std::unique_ptr<DynamicSimulator> sim;
  std::vector<double> total, assembly, setup, solve, iterations;
};

}  // namespace

int main(int argc, char** argv) {
  std::vector<double> targets = {20000, 47895};
  int steps = 25;
  bool settle_study = true;
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (k == "--targets") targets = parseList(argValue(argc, argv, i));
    else if (k == "--steps") steps = std::stoi(argValue(argc, argv, i));
    else if (k == "--no-settle") settle_study = false;
    else if (k == "--json") json_path = argValue(argc, argv, i);
    else {
      std::fprintf(stderr, "usage: bench_anp_split [--targets 20000,47895] [--steps 25] [--no-settle] [--json FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml");
  nlohmann::json out;
  out["threads"] = omp_get_max_threads();
  out["steps"] = steps;
  out["load_average_1min"] = loadAverage();
  std::printf("ANP split against ANP assembled and J - 1 linear tetrahedra: %d threads, %d interleaved steps of dt 0.033 s,\n"
              "supine gravity, multigrid-PCG to 1e-2; load average %.2f at the start (medians; ratio = step / J - 1 step)\n",
              omp_get_max_threads(), steps, loadAverage());
  std::printf("%8s %-15s | %8s %8s %8s %8s %6s %6s | %8s %6s %8s\n", "tets", "element", "step[ms]", "assem", "factor.",
              "solve", "iters", "ratio", "settle[s]", "steps", "umax[mm]");
  nlohmann::json rows = nlohmann::json::array();
  for (double target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = static_cast<int>(target);
    const SimulationModel model = buildSimulationModel(c);
    std::vector<Variant> variants;
    for (int v = 0; v < 3; ++v) {
      SimulationSettings s;
      s.dynamics.gravity_mps2 = c.phantom->gravity_supine_mps2;
      if (v == 0) {
        s.element = SimulationSettings::Element::kLinearTet;
        s.volume_term = CorotatedTetFem::VolumeTerm::kDeterminant;
      } else {
        s.element = SimulationSettings::Element::kAnpTet;
        s.anp_inversion_barrier = 0.3;
      }
      Variant var{v == 0 ? "J - 1 linear" : v == 1 ? "ANP split" : "ANP assembled", nullptr, {}, {}, {}, {}, {}};
      if (v < 2) {
        var.sim = std::move(buildSimulator(c, model, s).simulator);
      } else {
        // The same multigrid on the same coarse meshes, behind AssembledOnly.
        std::vector<TetMesh> meshes{model.mesh};
        for (TetMesh& m : buildCoarseMeshes(c, model, s.solver.coarsening)) meshes.push_back(std::move(m));
        MultigridOptions mg = s.solver.multigrid;
        mg.fine_eigenvalue_bound = 0.0;
        PcgOptions pcg;
        pcg.relative_tolerance = s.solver.relative_tolerance;
        pcg.max_iterations = s.solver.max_iterations;
        auto elements = std::make_unique<AnpTetFem>(model.mesh, s.material);
        elements->setInversionBarrier(s.anp_inversion_barrier);
        var.sim = std::make_unique<DynamicSimulator>(
            model.mesh, std::move(elements), s.material, s.dynamics,
            std::make_unique<AssembledOnly>(std::make_unique<MultigridPcgSolver>(MeshHierarchy(std::move(meshes)), pcg, mg)));
        var.sim->fixNodes(model.mesh.nodeSet(node_sets::kChestWall));
      }
      variants.push_back(std::move(var));
    }
    for (int k = 0; k < steps; ++k)
      for (Variant& v : variants) {
        const StepStats st = v.sim->step();
        if (k == 0) continue;  // the first step includes the solver's first set-up
        v.total.push_back(st.total_seconds);
        v.assembly.push_back(st.assembly_seconds);
        v.setup.push_back(st.setup_seconds);
        v.solve.push_back(st.solve.seconds);
        v.iterations.push_back(st.solve.iterations);
      }
    const double reference = median(variants[0].total);
    for (Variant& v : variants) {
      SettleResult r;
      if (settle_study) {  // from the rest shape, as the pipeline's settles start
        SimulationState rest;
        rest.displacement_m = rest.velocity_mps = Eigen::VectorXd::Zero(3 * model.mesh.numNodes());
        v.sim->restore(rest);
        r = settle(*v.sim, SettleOptions{});
      }
      std::printf("%8d %-15s | %8.1f %8.1f %8.1f %8.1f %6.1f %6.2f | %8.2f %6d %8.2f\n", model.mesh.numTets(), v.name,
                  1e3 * median(v.total), 1e3 * median(v.assembly), 1e3 * median(v.setup), 1e3 * median(v.solve),
                  mean(v.iterations), median(v.total) / reference, r.seconds, r.steps, 1e3 * r.max_displacement_m);
      rows.push_back({{"tets", model.mesh.numTets()},
                      {"element", v.name},
                      {"split", v.sim->splitStiffness()},
                      {"step_ms", 1e3 * median(v.total)},
                      {"assembly_ms", 1e3 * median(v.assembly)},
                      {"setup_ms", 1e3 * median(v.setup)},
                      {"solve_ms", 1e3 * median(v.solve)},
                      {"iterations", mean(v.iterations)},
                      {"ratio_to_linear", median(v.total) / reference},
                      {"settle_s", r.seconds},
                      {"settle_steps", r.steps},
                      {"settled", r.settled},
                      {"max_displacement_mm", 1e3 * r.max_displacement_m}});
    }
  }
  out["rows"] = rows;
  out["load_average_1min_end"] = loadAverage();
  std::printf("load average %.2f at the end\n", loadAverage());
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
