// Co-rotated FEM assembly benchmark: per-step cost of rotations + forces (update) and of the
// stiffness assembly, on phantom meshes of the seed paper's Table-1 sizes, and the whole assembly of
// a DynamicSimulator step (update + stiffness + mass diagonal, right-hand side and the elimination
// of the constrained DOFs: chest wall fixed, nipple targets) with a solver that does nothing, so
// the pose stays the same every step. "step overhead" is step assembly − update − assemble: what
// step() itself adds. Figures are minima over the repetitions: the least disturbed by other load
// on a shared machine (an OpenMP region whose second thread is descheduled waits for it).
// Prints a table; --json FILE writes the same figures. The linear solve is measured by bench_solvers.
//   bench_fem_assembly [--targets 47895,99390,...] [--reps 25] [--json FILE]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/model/model_case.h"

using namespace breast_sim::core;
using Clock = std::chrono::steady_clock;

namespace {
/// Leaves the velocity at zero: every step re-assembles the same pose.
class NullSolver : public LinearSolver {
 public:
  void analyzePattern(const SparseMatrix&) override {}
  void factorize(const SparseMatrix&) override {}
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override {
    x.setZero(b.size());
    return {0, 0.0, true, 0.0};
  }
  std::string name() const override { return "null"; }
};

double minimum(const std::vector<double>& v) { return v.empty() ? 0.0 : *std::min_element(v.begin(), v.end()); }
}  // namespace

int main(int argc, char** argv) {
  std::vector<int> targets = {47895, 99390, 158340, 313335};
  int reps = 25;
  std::string json_path;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i], v = argv[i + 1];
    if (k == "--targets") {
      targets.clear();
      std::stringstream ss(v);
      for (std::string t; std::getline(ss, t, ',');) targets.push_back(std::stoi(t));
    } else if (k == "--reps") reps = std::stoi(v);
    else if (k == "--json") json_path = v;
    else {
      std::fprintf(stderr, "usage: bench_fem_assembly [--targets N,...] [--reps R] [--json FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml");
  std::printf("threads %d, %d repetitions per size\n", omp_get_max_threads(), reps);
  std::printf("%9s %9s %12s %12s %12s %14s %14s %14s\n", "tets", "nodes", "update[ms]", "assemble[ms]", "sum[ms]",
              "ns/element", "step asm[ms]", "overhead[ms]");
  nlohmann::json rows = nlohmann::json::array();
  for (int target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = target;
    const SimulationModel model = buildSimulationModel(c);
    CorotatedTetFem fem(model.mesh, ElasticMaterial{});
    // A deformed pose (sag under gravity-like shear) so rotations are not trivial.
    Points x = model.mesh.nodes();
    for (int n = 0; n < x.rows(); ++n) x(n, 0) += 0.05 * x(n, 1) * x(n, 1);
    SparseMatrix A = fem.pattern().matrix();
    Eigen::VectorXd f;
    fem.update(x, f);  // warm-up
    std::vector<double> t_update, t_assemble, t_step;
    for (int r = 0; r < reps; ++r) {
      auto t0 = Clock::now();
      fem.update(x, f);
      auto t1 = Clock::now();
      std::fill(A.valuePtr(), A.valuePtr() + A.nonZeros(), 0.0);
      fem.addStiffness(1.0, A);
      auto t2 = Clock::now();
      t_update.push_back(std::chrono::duration<double>(t1 - t0).count());
      t_assemble.push_back(std::chrono::duration<double>(t2 - t1).count());
    }
    // The same pose through DynamicSimulator::step().
    DynamicsParams params;
    params.gravity_mps2 = {0, -9.81, 0};
    DynamicSimulator sim(model.mesh, std::make_unique<CorotatedTetFem>(model.mesh, ElasticMaterial{}), ElasticMaterial{},
                         params, std::make_unique<NullSolver>());
    sim.fixNodes(model.mesh.nodeSet("chest_wall"));
    if (model.mesh.nodeSets().count("nipple")) {
      const auto& nip = model.mesh.nodeSet("nipple");
      sim.setNodeTargets(nip, Points::Constant(static_cast<Eigen::Index>(nip.size()), 3, 1e-3));
    }
    SimulationState s0 = sim.state();
    for (int n = 0; n < x.rows(); ++n) s0.displacement_m.segment<3>(3 * n) = (x.row(n) - model.mesh.nodes().row(n)).transpose();
    sim.restore(s0);
    sim.step();  // warm-up
    for (int r = 0; r < reps; ++r) {
      sim.restore(s0);
      t_step.push_back(sim.step().assembly_seconds);
    }
    const double u_ms = 1e3 * minimum(t_update), a_ms = 1e3 * minimum(t_assemble), s_ms = 1e3 * minimum(t_step);
    const double ns = 1e6 * (u_ms + a_ms) / model.mesh.numTets();
    std::printf("%9d %9d %12.2f %12.2f %12.2f %14.1f %14.2f %14.2f\n", model.mesh.numTets(), model.mesh.numNodes(), u_ms,
                a_ms, u_ms + a_ms, ns, s_ms, s_ms - u_ms - a_ms);
    std::fflush(stdout);
    rows.push_back({{"tets", model.mesh.numTets()}, {"nodes", model.mesh.numNodes()}, {"update_ms", u_ms},
                    {"assemble_ms", a_ms}, {"ns_per_element", ns}, {"step_assembly_ms", s_ms},
                    {"step_overhead_ms", s_ms - u_ms - a_ms}});
  }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "fem_assembly"}, {"threads", omp_get_max_threads()},
                                               {"rows", rows}}.dump(2) << '\n';
  return 0;
}
