// Co-rotated FEM assembly benchmark: per-step cost of rotations + forces (update) and of the
// stiffness assembly, on phantom meshes of the seed paper's Table-1 sizes. Prints a table;
// --json FILE writes the same figures. The linear solve is measured by bench_solvers.
//   bench_fem_assembly [--targets 47895,99390,...] [--reps 25] [--json FILE]
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/model/model_case.h"

using namespace breast_sim::core;
using Clock = std::chrono::steady_clock;

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
  std::printf("%9s %9s %12s %12s %12s %14s\n", "tets", "nodes", "update[ms]", "assemble[ms]", "sum[ms]", "ns/element");
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
    double t_update = 0, t_assemble = 0;
    for (int r = 0; r < reps; ++r) {
      auto t0 = Clock::now();
      fem.update(x, f);
      auto t1 = Clock::now();
      std::fill(A.valuePtr(), A.valuePtr() + A.nonZeros(), 0.0);
      fem.addStiffness(1.0, A);
      auto t2 = Clock::now();
      t_update += std::chrono::duration<double>(t1 - t0).count();
      t_assemble += std::chrono::duration<double>(t2 - t1).count();
    }
    const double u_ms = 1e3 * t_update / reps, a_ms = 1e3 * t_assemble / reps;
    const double ns = 1e6 * (u_ms + a_ms) / model.mesh.numTets();
    std::printf("%9d %9d %12.2f %12.2f %12.2f %14.1f\n", model.mesh.numTets(), model.mesh.numNodes(), u_ms, a_ms,
                u_ms + a_ms, ns);
    std::fflush(stdout);
    rows.push_back({{"tets", model.mesh.numTets()}, {"nodes", model.mesh.numNodes()}, {"update_ms", u_ms},
                    {"assemble_ms", a_ms}, {"ns_per_element", ns}});
  }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "fem_assembly"}, {"threads", omp_get_max_threads()},
                                               {"rows", rows}}.dump(2) << '\n';
  return 0;
}
