// Meshing benchmark: time, element count and quality of the phantom model for target sizes from 5k
// to 300k tetrahedra. Prints a table; --json FILE writes the same figures.
//   bench_meshing [--case config/phantom_default.yaml] [--targets 5000,20000,...] [--json FILE]
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"

using namespace breast_sim::core;

int main(int argc, char** argv) {
  std::string case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  std::string json_path;
  std::vector<int> targets = {5000, 10000, 20000, 47895, 99390, 158340, 313335};
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i], v = argv[i + 1];
    if (k == "--case") case_file = v;
    else if (k == "--json") json_path = v;
    else if (k == "--targets") {
      targets.clear();
      std::stringstream ss(v);
      for (std::string t; std::getline(ss, t, ',');) targets.push_back(std::stoi(t));
    } else {
      std::fprintf(stderr, "unknown option %s\nusage: bench_meshing [--case FILE] [--targets N,N,...] [--json FILE]\n", k.c_str());
      return 2;
    }
  }
  const auto t0 = std::chrono::steady_clock::now();
  ModelCase base = loadModelCase(case_file);
  const double t_image = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const double analytic = base.phantom ? base.phantom->prone_volume_m3 : 0.0;
  std::printf("case %s: label image %dx%dx%d, built in %.2f s\n", base.name.c_str(), base.image.size.x(),
              base.image.size.y(), base.image.size.z(), t_image);
  std::printf("%9s %9s %8s %7s %9s %9s %8s %8s %7s %8s %6s\n", "target", "tets", "nodes", "passes", "mesh[s]",
              "size[mm]", "minDih", "meanDih", "maxAR", "slivers", "dV[%]");
  nlohmann::json rows = nlohmann::json::array();
  for (int target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = target;
    const auto t1 = std::chrono::steady_clock::now();
    const SimulationModel m = buildSimulationModel(c);
    const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
    const double dv = analytic > 0 ? 100.0 * (m.mesh.volume() / analytic - 1.0) : 0.0;
    std::printf("%9d %9d %8d %7d %9.2f %9.2f %8.1f %8.1f %7.2f %8d %+6.2f\n", target, m.mesh.numTets(),
                m.mesh.numNodes(), m.meshing.passes, secs, m.meshing.interior_size_m * 1e3,
                m.quality.min_dihedral_deg, m.quality.mean_min_dihedral_deg, m.quality.max_aspect_ratio,
                m.quality.num_dihedral_below_10deg, dv);
    std::fflush(stdout);
    rows.push_back({{"target", target}, {"tets", m.mesh.numTets()}, {"nodes", m.mesh.numNodes()},
                    {"passes", m.meshing.passes}, {"seconds", secs}, {"interior_size_mm", m.meshing.interior_size_m * 1e3},
                    {"min_dihedral_deg", m.quality.min_dihedral_deg}, {"mean_min_dihedral_deg", m.quality.mean_min_dihedral_deg},
                    {"max_aspect_ratio", m.quality.max_aspect_ratio}, {"slivers_below_10deg", m.quality.num_dihedral_below_10deg},
                    {"inverted", m.quality.num_inverted}, {"volume_error_percent", dv}});
  }
  if (!json_path.empty()) {
    nlohmann::json out = {{"benchmark", "meshing"}, {"case", base.name}, {"image_seconds", t_image}, {"rows", rows}};
    std::ofstream(json_path) << out.dump(2) << '\n';
  }
  return 0;
}
