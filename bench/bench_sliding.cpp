// Sliding benchmark (seed Table 1, column "up./sl."): the phantom under the supine load with its
// chest-wall nodes sliding, per step: the simulation step, the extra elastic-force evaluation the
// public API needs for the reaction forces, and the sliding update itself; plus the one-off normal
// field (3-D derivative of Gaussian over the chest-wall mask) and the set-up. Prints a table;
// --json FILE writes the same figures; --csv FILE writes the chest-wall nodes with their rest
// position, sliding vector and limiting weights (docs/sliding/plot_sliding.py draws it).
//   bench_sliding [--case FILE] [--targets 47895] [--steps 25] [--solver multigrid|cholmod]
//                 [--sigma-fraction F] [--no-gaussian] [--json FILE] [--csv FILE]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {
}  // namespace

int main(int argc, char** argv) {
  std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_two_breasts.yaml";
  std::vector<double> targets = {47895};
  int steps = 25;
  std::string json_path, csv_path, solver = "multigrid";
  double sigma_fraction = 0.25;
  bool gaussian = true;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--case") case_path = next();
    else if (a == "--targets") targets = parseList(next());
    else if (a == "--steps") steps = std::stoi(next());
    else if (a == "--solver") solver = next();
    else if (a == "--sigma-fraction") sigma_fraction = std::stod(next());
    else if (a == "--no-gaussian") gaussian = false;
    else if (a == "--json") json_path = next();
    else if (a == "--csv") csv_path = next();
    else {
      std::fprintf(stderr,
                   "usage: bench_sliding [--case FILE] [--targets 47895,...] [--steps 25] [--solver multigrid|cholmod]\n"
                   "                     [--sigma-fraction 0.25] [--no-gaussian] [--json FILE] [--csv FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(case_path);
  std::printf("sliding benchmark: %s, %d steps per size, %d threads\n", case_path.c_str(), steps, omp_get_max_threads());
  std::printf("%8s %7s %6s %6s | %9s %9s | %9s %9s %9s %7s | %8s %8s\n", "target", "tets", "nodes", "wall",
              "field[ms]", "setup[ms]", "step[ms]", "f_el[ms]", "slide[ms]", "sl/step", "slide_mm", "moving");
  nlohmann::json rows = nlohmann::json::array();
  for (double target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = static_cast<int>(target);
    const SimulationModel model = buildSimulationModel(c);
    SimulationSettings ss;
    ss.solver.kind = SolverSettings::kindFromName(solver);
    const Eigen::Vector3d g_prone = c.phantom ? c.phantom->gravity_prone_mps2
                                              : Eigen::Vector3d(9.81 * c.prone_gravity_direction.normalized());
    const Eigen::Vector3d g_supine = c.phantom ? c.phantom->gravity_supine_mps2 : Eigen::Vector3d(-g_prone);
    ss.dynamics.gravity_mps2 = g_supine - g_prone;
    SimulatorBuild b = buildSimulator(c, model, ss);
    DynamicSimulator& sim = *b.simulator;

    SlidingSettings s;
    s.gaussian_limit = gaussian;
    s.gaussian_sigma_fraction = sigma_fraction;
    auto t0 = Clock::now();
    auto surface = std::make_shared<const ChestWallSurface>(c.image, c.labels.chest_wall, s.field);
    const double field_s = since(t0);
    t0 = Clock::now();
    ChestWallSliding sl(model.mesh, model.mesh.nodeSet(node_sets::kChestWall), surface, s, &c.image, c.labels,
                        c.nipples_m, c.prone_gravity_direction);
    sl.attach(sim);
    const double setup_s = since(t0);

    std::vector<double> step_t, force_t, slide_t;
    SlidingStepStats last;
    for (int k = 0; k < steps; ++k) {
      const StepStats st = sim.step();
      step_t.push_back(st.total_seconds);
      last = sl.update(sim);
      force_t.push_back(last.force_seconds);
      slide_t.push_back(last.seconds);
    }
    const double step_ms = 1e3 * median(step_t), f_ms = 1e3 * median(force_t), sl_ms = 1e3 * median(slide_t);
    std::printf("%8.0f %7d %6d %6zu | %9.1f %9.1f | %9.2f %9.2f %9.3f %6.1f%% | %8.2f %8d\n", target,
                model.mesh.numTets(), model.mesh.numNodes(), sl.nodes().size(), 1e3 * field_s, 1e3 * setup_s, step_ms,
                f_ms, sl_ms, 100.0 * sl_ms / step_ms, 1e3 * last.max_slide_m, last.moving);
    rows.push_back({{"target_elements", static_cast<int>(target)},
                    {"tets", model.mesh.numTets()},
                    {"nodes", model.mesh.numNodes()},
                    {"wall_nodes", sl.nodes().size()},
                    {"held_nodes", sl.heldNodes()},
                    {"image_voxels", c.image.numVoxels()},
                    {"normal_field_ms", 1e3 * field_s},
                    {"sliding_setup_ms", 1e3 * setup_s},
                    {"step_median_ms", step_ms},
                    {"elastic_forces_median_ms", f_ms},
                    {"sliding_update_median_ms", sl_ms},
                    {"max_slide_mm", 1e3 * last.max_slide_m},
                    {"moving_nodes_last_step", last.moving},
                    {"stiffness_limited_last_step", last.stiffness_limited}});
    if (!csv_path.empty()) {
      std::ofstream f(csv_path);
      f << "node,x_mm,y_mm,z_mm,slide_x_mm,slide_y_mm,slide_z_mm,weight,gaussian,thickness_mm\n";
      const Points d = sl.slidingVectors();
      for (size_t i = 0; i < sl.nodes().size(); ++i) {
        const int v = sl.nodes()[i];
        f << v << ',' << 1e3 * model.mesh.nodes()(v, 0) << ',' << 1e3 * model.mesh.nodes()(v, 1) << ','
          << 1e3 * model.mesh.nodes()(v, 2) << ',' << 1e3 * d(v, 0) << ',' << 1e3 * d(v, 1) << ',' << 1e3 * d(v, 2)
          << ',' << sl.weights()[i] << ',' << sl.gaussianFactors()[i] << ',' << 1e3 * sl.tissueThickness()[i] << '\n';
      }
    }
  }
  std::printf("(median per step; slide = the sliding update without f_el; f_el = DynamicSimulator::elasticForces(),\n"
              " which the reaction forces need through the public API and step() recomputes)\n");
  if (!json_path.empty()) {
    nlohmann::json j = {{"case", case_path}, {"steps", steps}, {"threads", omp_get_max_threads()},
                        {"solver", solver}, {"rows", rows}};
    std::ofstream(json_path) << j.dump(2) << "\n";
  }
  return 0;
}
