// What a node (re)start spends before it can track: reading a case, meshing it, and building the
// pipeline (the solver's multigrid levels, meshed from the case's image, and the element set-up),
// the same steps as the node's ~load_case, at each element count. A restarted node that resumes a
// checkpoint skips the precomputation but not these (docs/ros.md, "Checkpoints and restart").
// Prints a table; --json FILE writes it too.
//   bench_model_build [--case FILE] [--elements 3000,20000] [--json FILE]
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

using namespace breast_sim;
using bench::Clock;
using bench::since;

int main(int argc, char** argv) {
  std::string case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  std::vector<double> elements = {3000, 20000};
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (k == "--case") case_file = bench::argValue(argc, argv, i);
    else if (k == "--elements") elements = bench::parseList(bench::argValue(argc, argv, i));
    else if (k == "--json") json_path = bench::argValue(argc, argv, i);
    else {
      std::fprintf(stderr, "usage: bench_model_build [--case FILE] [--elements 3000,20000] [--json FILE]\n");
      return 2;
    }
  }
  std::printf("case %s, load %.1f\n", case_file.c_str(), bench::loadAverage());
  std::printf("%10s %9s %9s %9s %12s %9s %9s\n", "target", "tets", "case s", "mesh s", "pipeline s", "levels s", "total s");
  nlohmann::json rows = nlohmann::json::array();
  for (double target : elements) {
    const auto t0 = Clock::now();
    core::ModelCase c = core::loadModelCase(case_file);
    if (!c.mesh) c.meshing.target_elements = static_cast<int>(target);
    const double case_s = since(t0);
    const auto t1 = Clock::now();
    const core::SimulationModel model = core::buildSimulationModel(c);
    const double mesh_s = since(t1);
    const auto t2 = Clock::now();
    const core::ProneToSupinePipeline pipeline(c, model, core::loadPipelineSettings(case_file));
    const double pipeline_s = since(t2);
    const double total_s = since(t0);
    std::printf("%10.0f %9d %9.2f %9.2f %12.2f %9.2f %9.2f\n", target, model.mesh.numTets(), case_s, mesh_s, pipeline_s,
                pipeline.build().hierarchy_seconds, total_s);
    rows.push_back({{"target_elements", target}, {"tets", model.mesh.numTets()}, {"case_s", case_s}, {"mesh_s", mesh_s},
                    {"pipeline_s", pipeline_s}, {"multigrid_levels_s", pipeline.build().hierarchy_seconds},
                    {"total_s", total_s}});
  }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "model_build"}, {"case", case_file},
                                               {"load_average", bench::loadAverage()}, {"rows", rows}}.dump(1)
                             << "\n";
  return 0;
}
