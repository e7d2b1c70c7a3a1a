// How far dropped tracker clouds move the tracked lesions: the node drops a cloud when its tracking
// thread has not taken the one before (newest wins), so the clouds it tracks depend on the machine's
// load. This study tracks the recorded bag's clouds offline, as the navigation rostest's reference
// does (the core's SurfaceTracker with the node's default parameters, gravity following the table
// with the node's update rule, clouds in single precision in the tracker frame put into the model
// frame at their time), once with every cloud and once per drop set, from the same precomputed
// state, and prints per set the largest lesion difference from the all-cloud run over the frames
// [mm], the difference after the last frame, and the frames that reverted (time-step reversal):
//   bench_tracking_drops [--case FILE] [--settings FILE|case] [--target-elements N] [--field-voxel-mm V]
//                        [--clouds N] [--drops "1,26;0,3,6"] [--json FILE]
// The defaults are the navigation rostest's (test/ros/navigation.test): the phantom at 3000 target
// elements, test/data/navigation_settings.yaml (CHOLMOD, morphing stopped at 80 steps), a 3 mm
// field, the bag's 100 clouds at 10 Hz; "--settings case" takes the case file's own settings.
// docs/tracking.md, "Dropped clouds".
#include <fstream>
#include <iomanip>
#include <iostream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>
#include <ros/package.h>
#include <ros/time.h>

#include "../bench_util.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/node_params.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

using namespace breast_sim;

namespace {

/// One offline tracking run from `precomputed`, skipping the clouds in `drop`.
ros_interface::OfflineTrackingRun track(core::ProneToSupinePipeline& p, const core::PipelineState& precomputed,
                                        const core::ModelCase& c, const ros_interface::NodeParams& node, int clouds,
                                        const std::set<int>& drop) {
  std::vector<bool> tracked(static_cast<size_t>(clouds), true);
  for (int k : drop)
    if (k >= 0 && k < clouds) tracked[static_cast<size_t>(k)] = false;
  return ros_interface::trackRecordingOffline(p, precomputed, c, node.tracker, node.monitor, node.gravity_update_threshold_deg, clouds,
                                              10.0, tracked);
}

double maxDistanceMm(const core::Points& a, const core::Points& b) { return 1e3 * (a - b).rowwise().norm().maxCoeff(); }

std::vector<std::set<int>> parseDrops(const std::string& text) {
  std::vector<std::set<int>> sets;
  std::stringstream all(text);
  std::string one;
  while (std::getline(all, one, ';')) {
    std::set<int> s;
    for (double v : bench::parseList(one)) s.insert(static_cast<int>(v));
    if (!s.empty()) sets.push_back(s);
  }
  return sets;
}

}  // namespace

int main(int argc, char** argv) {
  ros::Time::init();
  std::string case_file, settings_file, json_path;
  int target = 3000, clouds = 100;
  double field_voxel_mm = 3.0;
  // Single clouds and the sets the rostest's node dropped at 2× playback.
  std::string drops = "1;26;60;63;1,26,60,63;0,3,6,10,12,26,28,40,58,62;1,4,8,11,25,26,51,53,56;1,26,63,65,67,75,79,81,84";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string { return i + 1 < argc ? argv[++i] : ""; };
    if (a == "--case") case_file = next();
    else if (a == "--settings") settings_file = next();
    else if (a == "--target-elements") target = std::stoi(next());
    else if (a == "--field-voxel-mm") field_voxel_mm = std::stod(next());
    else if (a == "--clouds") clouds = std::stoi(next());
    else if (a == "--drops") drops = next();
    else if (a == "--json") json_path = next();
    else {
      std::cerr << "usage: bench_tracking_drops [--case FILE] [--settings FILE|case] [--target-elements N]"
                   " [--field-voxel-mm V] [--clouds N] [--drops \"1,26;0,3,6\"] [--json FILE]\n";
      return a == "--help" ? 0 : 2;
    }
  }
  const std::string pkg = ros::package::getPath("breast_sim");
  if (case_file.empty()) case_file = pkg + "/config/phantom_default.yaml";
  if (settings_file.empty()) settings_file = pkg + "/test/data/navigation_settings.yaml";
  if (settings_file == "case") settings_file = case_file;
  const std::vector<std::set<int>> sets = parseDrops(drops);
  nlohmann::json out;
  try {
    if (clouds < 1 || !(field_voxel_mm > 0)) throw std::invalid_argument("--clouds must be ≥ 1 and --field-voxel-mm > 0");
    core::ModelCase c = core::loadModelCase(case_file);
    c.meshing.target_elements = target;
    const core::SimulationModel model = core::buildSimulationModel(c);
    core::PipelineSettings settings = core::loadPipelineSettings(settings_file);
    settings.morphing.field.voxel_size_m = 1e-3 * field_voxel_mm;  // as the node's field_voxel_size_m
    core::ProneToSupinePipeline p(c, model, settings);
    auto t0 = bench::Clock::now();
    p.run();
    const double pre_s = bench::since(t0);
    const core::PipelineState precomputed = p.state();
    const core::Points lesions0 = p.lesionPositions();
    const core::StageReport& m = p.morphingReport();
    const ros_interface::NodeParams node;  // the node's defaults (config/node.yaml lists the same)
    std::cout << "case " << c.name << ", settings " << settings_file << ": " << model.mesh.numTets()
              << " tetrahedra; precomputation " << std::fixed << std::setprecision(2) << pre_s << " s, morphing "
              << m.steps << " steps, " << m.reversed_steps << " reverted\n";
    t0 = bench::Clock::now();
    const ros_interface::OfflineTrackingRun all = track(p, precomputed, c, node, clouds, {});
    const double run_s = bench::since(t0);
    std::cout << clouds << " clouds at 10 Hz, every one tracked: " << run_s << " s, " << all.reverted_frames
              << " frames reverted (" << all.reversals << " reversals); lesions end "
              << maxDistanceMm(all.lesions_m.back(), lesions0) << " mm from the precomputed positions\n\n";
    out["tetrahedra"] = model.mesh.numTets();
    out["settings"] = settings_file;
    out["precompute_s"] = pre_s;
    out["morphing_steps"] = m.steps;
    out["morphing_reverted_steps"] = m.reversed_steps;
    out["clouds"] = clouds;
    out["all"] = {{"reverted_frames", all.reverted_frames}, {"reversals", all.reversals},
                  {"end_from_precomputed_mm", maxDistanceMm(all.lesions_m.back(), lesions0)}};
    std::cout << "dropped clouds                          | n  | max diff[mm]  end diff[mm] | reverted frames\n";
    for (const std::set<int>& drop : sets) {
      const ros_interface::OfflineTrackingRun r = track(p, precomputed, c, node, clouds, drop);
      double worst = 0;
      for (int k = 0; k < clouds; ++k) worst = std::max(worst, maxDistanceMm(r.lesions_m[k], all.lesions_m[k]));
      const double end = maxDistanceMm(r.lesions_m.back(), all.lesions_m.back());
      std::string name;
      for (int k : drop) name += (name.empty() ? "" : ",") + std::to_string(k);
      std::cout << std::left << std::setw(40) << name.substr(0, 40) << std::right << "| " << std::setw(2) << drop.size()
                << " | " << std::setw(12) << std::setprecision(3) << worst << std::setw(14) << end << " | "
                << std::setw(6) << r.reverted_frames << "\n";
      out["drops"].push_back({{"dropped", std::vector<int>(drop.begin(), drop.end())},
                              {"max_diff_mm", worst},
                              {"end_diff_mm", end},
                              {"reverted_frames", r.reverted_frames},
                              {"reversals", r.reversals}});
    }
  } catch (const std::exception& e) {
    std::cerr << "bench_tracking_drops: " << e.what() << "\n";
    return 1;
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
