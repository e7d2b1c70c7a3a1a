// bench_morphing: how fast the morphing stage of the pipeline reaches its tolerance, by time step and
// gain, and what it costs per step; on the phantom. Two targets:
//   stretched  the model's own skin stretched anteriorly (reachable with the wall fixed: isolates the
//              morphing loop from sliding);
//   supine     the phantom's supine target after the gravity stage (needs sliding to be reachable).
//
//   bench_morphing [--elements 8000] [--target stretched|supine] [--stretch 1.08] [--dts 0.033,0.1,0.33]
//                  [--gains 10,20,40] [--max-steps 200] [--sliding] [--json FILE]
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

int main(int argc, char** argv) {
  int elements = 8000, max_steps = 200;
  std::string target = "stretched", json_path;
  double stretch = 1.08;
  bool sliding = false;
  std::vector<double> dts = {0.033, 0.1, 0.33}, gains = {10, 20, 40};
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--elements") elements = std::stoi(next());
    else if (a == "--target") target = next();
    else if (a == "--stretch") stretch = std::stod(next());
    else if (a == "--dts") dts = parseList(next());
    else if (a == "--gains") gains = parseList(next());
    else if (a == "--max-steps") max_steps = std::stoi(next());
    else if (a == "--sliding") sliding = true;
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_morphing [--elements N] [--target stretched|supine] [--stretch F] [--dts LIST] "
                           "[--gains LIST (Pa/mm)] [--max-steps N] [--sliding] [--json FILE]\n");
      return 2;
    }
  }
  if (target != "stretched" && target != "supine") {
    std::fprintf(stderr, "--target must be stretched or supine, got '%s'\n", target.c_str());
    return 2;
  }
  ModelCase c = loadModelCase(std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml");
  c.meshing.target_elements = elements;
  const SimulationModel m = buildSimulationModel(c);
  std::printf("Morphing convergence on the phantom (%d elements, target %s%s)\n", m.mesh.numTets(), target.c_str(),
              sliding ? ", sliding" : ", wall fixed");
  std::printf("%-8s %-12s %-7s %-10s %-9s %-11s %-11s %-10s %-10s %-9s %-9s\n", "dt [s]", "gain [Pa/mm]", "steps",
              "converged", "reversed", "mean [mm]", "p95 [mm]", "vol [%]", "inverted", "time [s]", "ms/step");
  nlohmann::json rows = nlohmann::json::array();
  for (double dt : dts)
    for (double gain : gains) {
      PipelineSettings s;
      s.simulation.sliding = sliding;
      s.morphing.time_step_s = dt;
      s.morphing.forces.gain_pa_per_m = gain * 1e3;
      s.morphing.max_steps = max_steps;
      if (target == "stretched") {
        s.simulation.gravity_mps2 = 0.0;
        s.morphing.target = "";
      }
      ProneToSupinePipeline pipe(c, m, s);
      if (target == "stretched") {
        TargetSurface t;
        t.vertices_m = m.mesh.nodes();
        t.vertices_m.col(1) *= stretch;
        t.triangles = skinTriangles(m.mesh, m.mesh.nodeSet(node_sets::kSkin));
        pipe.setTarget(t);
      } else {
        pipe.runGravity();
      }
      const StageReport r = pipe.runMorphing();
      const PipelineMetrics pm = pipe.metrics();
      std::printf("%-8.3g %-12.3g %-7d %-10s %-9ld %-11.3f %-11.3f %-10.2f %-10d %-9.2f %-9.1f\n", dt, gain, r.steps,
                  r.converged ? "yes" : "no", r.reversed_steps, pm.surface.model_to_target.mean_m * 1e3,
                  pm.surface.model_to_target.p95_m * 1e3, pm.volume_change_percent, pm.inverted_elements, r.seconds,
                  r.steps ? 1e3 * r.seconds / r.steps : 0.0);
      std::fflush(stdout);
      rows.push_back({{"time_step_s", dt}, {"gain_pa_per_mm", gain}, {"steps", r.steps}, {"converged", r.converged},
                      {"reversed_steps", r.reversed_steps}, {"skin_to_target_mean_mm", pm.surface.model_to_target.mean_m * 1e3},
                      {"skin_to_target_p95_mm", pm.surface.model_to_target.p95_m * 1e3},
                      {"target_skin_to_skin_mean_mm", pm.surface.target_to_model.mean_m * 1e3},
                      {"target_skin_to_skin_p95_mm", pm.surface.target_to_model.p95_m * 1e3},
                      {"volume_change_percent", pm.volume_change_percent}, {"inverted_elements", pm.inverted_elements},
                      {"seconds", r.seconds}});
    }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"bench", "morphing"}, {"elements", m.mesh.numTets()}, {"target", target},
                                               {"sliding", sliding}, {"rows", rows}}
                                    .dump(2)
                             << '\n';
  return 0;
}
