// Whether tracking holds the lesions where the clouds put them, over minutes: the phantom is
// precomputed, then fed scans of its own precomputed skin (the anterior-facing part, area-uniform
// samples, Gaussian noise, a breathing motion of the anterior skin), tracked as the node tracks them
// (GuardedTracker: SurfaceTracker with the node's parameters and the tracking monitor). The truth is
// known: the lesions should stay at their precomputed positions up to the breathing's share. With
// --slide-mm the scanned skin is slid along the chest wall (lateral, x) by that much, reached over
// --slide-frames frames, from --slide-start on: a drift the monitor must catch. Prints per block of
// frames the largest lesion error from the precomputed positions, the chest-wall drift, the model's
// drift, the seen skin's residual, frames taken back and frames whose lesions were valid:
//   bench_tracking_drift [--case FILE] [--settings FILE] [--target-elements N] [--frames N] [--rate-hz R] [--breath-mm A]
//                        [--points N] [--noise-mm S] [--slide-mm D] [--slide-start K] [--slide-frames K]
//                        [--block N] [--no-icp] [--solver-tol T] [--json FILE]
// (--no-icp: without the rigid pre-alignment, so that the monitor alone has to catch the slide;
// --solver-tol: a tracking frame's PCG tolerance, TrackerOptions::solver_relative_tolerance.)
// docs/tracking.md.
#include <fstream>
#include <iomanip>
#include <iostream>

#include <nlohmann/json.hpp>
#include <ros/package.h>
#include <ros/time.h>

#include "../bench_util.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/tracker_simulation.h"
#include "breast_sim/ros_interface/tracking_monitor.h"

using namespace breast_sim;


int main(int argc, char** argv) {
  ros::Time::init();
  std::string case_file = ros::package::getPath("breast_sim") + "/config/phantom_default.yaml", settings_file, json_path;
  int target = 5000, frames = 3000, points = 2500, slide_start = -1, slide_frames = 20, block = 300;
  double rate_hz = 10.0, breath_mm = 2.0, noise_mm = 0.5, slide_mm = 0.0;
  bool icp = true;
  double solver_tol = ros_interface::TrackerOptions{}.solver_relative_tolerance;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string { return i + 1 < argc ? argv[++i] : ""; };
    if (a == "--case") case_file = next();
    else if (a == "--settings") settings_file = next();
    else if (a == "--target-elements") target = std::stoi(next());
    else if (a == "--frames") frames = std::stoi(next());
    else if (a == "--rate-hz") rate_hz = std::stod(next());
    else if (a == "--breath-mm") breath_mm = std::stod(next());
    else if (a == "--points") points = std::stoi(next());
    else if (a == "--noise-mm") noise_mm = std::stod(next());
    else if (a == "--slide-mm") slide_mm = std::stod(next());
    else if (a == "--slide-start") slide_start = std::stoi(next());
    else if (a == "--slide-frames") slide_frames = std::stoi(next());
    else if (a == "--block") block = std::stoi(next());
    else if (a == "--no-icp") icp = false;
    else if (a == "--solver-tol") solver_tol = std::stod(next());
    else if (a == "--json") json_path = next();
    else {
      std::cerr << "bench_tracking_drift: unknown option '" << a << "'\n";
      return 2;
    }
  }
  if (slide_mm != 0 && slide_start < 0) slide_start = frames / 2;
  try {
    core::ModelCase c = core::loadModelCase(case_file);
    c.meshing.target_elements = target;
    const core::SimulationModel model = core::buildSimulationModel(c);
    core::PipelineSettings settings = core::loadPipelineSettings(settings_file.empty() ? case_file : settings_file);
    settings.morphing.field.voxel_size_m = 0.003;  // the node's field_voxel_size_m
    core::ProneToSupinePipeline p(c, model, settings);
    p.run();
    std::cout << "precomputed: gravity " << p.gravityReport().steps << " + sliding " << p.slidingReport().steps
              << " + morphing " << p.morphingReport().steps << " steps, pulled skin to target mean "
              << 1e3 * p.morphingReport().surface_mean_m << " mm, p95 " << 1e3 * p.morphingReport().surface_p95_m << " mm\n";
    const core::Points x0 = p.positions(), l0 = p.lesionPositions();
    const std::vector<int>& wall = model.mesh.nodeSet(core::node_sets::kChestWall);
    ros_interface::SkinScanner scanner(x0, core::skinTriangles(model.mesh, model.mesh.nodeSet(core::node_sets::kSkin)), 1);
    ros_interface::TrackerOptions options;  // the node's defaults (config/node.yaml)
    options.icp.enabled = icp;
    options.solver_relative_tolerance = solver_tol;
    ros_interface::GuardedTracker tracker(options);
    tracker.start(p);
    std::cout << "bench_tracking_drift: " << model.mesh.numTets() << " elements, " << frames << " frames at " << rate_hz
              << " Hz, " << points << " points, breathing " << breath_mm << " mm, noise " << noise_mm << " mm";
    if (!icp) std::cout << ", no ICP";
    std::cout << ", PCG tolerance per frame " << solver_tol;
    if (slide_mm != 0) std::cout << ", scan slid " << slide_mm << " mm along the wall from frame " << slide_start;
    std::cout << "\n  frames        lesion err max [mm]  wall drift max [mm]  model drift max [mm]  seen mean [mm]"
                 "  taken back  valid\n";
    nlohmann::json out = {{"elements", model.mesh.numTets()}, {"frames", frames}, {"rate_hz", rate_hz},
                          {"breath_mm", breath_mm}, {"noise_mm", noise_mm}, {"slide_mm", slide_mm},
                          {"slide_start", slide_start}, {"solver_relative_tolerance", solver_tol},
                          {"blocks", nlohmann::json::array()}};
    double worst_valid = 0, worst = 0;
    int first_invalid_after_slide = -1, taken_back_total = 0, valid_total = 0;
    double err = 0, wall_drift = 0, model_drift = 0, seen = 0;
    int seen_n = 0, taken = 0, valid = 0, in_block = 0;
    for (int k = 0; k < frames; ++k) {
      const double t = k / rate_hz;
      double slide = 0;
      if (slide_mm != 0 && k >= slide_start) slide = 1e-3 * slide_mm * std::min(1.0, (k - slide_start + 1.0) / slide_frames);
      const core::Points cloud =
          scanner.scan(points, 1e-3 * breath_mm * std::sin(2 * M_PI * t / 4.0), Eigen::Vector3d(slide, 0, 0), 1e-3 * noise_mm);
      const ros_interface::GuardedFrame f = tracker.frame(p, cloud);
      const core::Points x = p.positions();
      const double e = (p.lesionPositions() - l0).rowwise().norm().maxCoeff();
      double wd = 0;
      for (int n : wall) wd = std::max(wd, (x.row(n) - x0.row(n)).norm());
      err = std::max(err, e);
      worst = std::max(worst, e);
      if (f.valid) worst_valid = std::max(worst_valid, slide_mm != 0 && k >= slide_start ? 0.0 : e);
      wall_drift = std::max(wall_drift, wd);
      model_drift = std::max(model_drift, (x.colwise().mean() - x0.colwise().mean()).norm());
      if (k < 3 || k % 500 == 0)
        std::cout << "    frame " << k << ": ICP " << (f.track.icp_applied ? "applied" : f.track.icp_note) << ", RMS "
                  << 1e3 * f.track.icp_rms_m << " mm, inliers " << f.track.icp_inlier_fraction << "\n";
      if (f.track.seen_mean_m >= 0) {
        seen += f.track.seen_mean_m;
        ++seen_n;
      }
      taken += f.restored;
      valid += f.valid;
      if (slide_mm != 0 && k >= slide_start && !f.valid && first_invalid_after_slide < 0) first_invalid_after_slide = k - slide_start;
      if (++in_block == block || k == frames - 1) {
        std::cout << "  " << std::setw(5) << k + 1 - in_block << "-" << std::setw(5) << std::left << k << std::right
                  << std::fixed << std::setprecision(3) << std::setw(16) << 1e3 * err << std::setw(21) << 1e3 * wall_drift
                  << std::setw(22) << 1e3 * model_drift << std::setw(16) << (seen_n ? 1e3 * seen / seen_n : -1.0)
                  << std::setw(12) << taken << std::setw(7) << valid << "\n";
        out["blocks"].push_back({{"first", k + 1 - in_block}, {"last", k}, {"lesion_error_max_mm", 1e3 * err},
                                 {"wall_drift_max_mm", 1e3 * wall_drift}, {"model_drift_max_mm", 1e3 * model_drift},
                                 {"seen_mean_mm", seen_n ? 1e3 * seen / seen_n : -1.0}, {"taken_back", taken},
                                 {"valid", valid}, {"frames", in_block}});
        taken_back_total += taken;
        valid_total += valid;
        err = wall_drift = model_drift = seen = 0;
        seen_n = taken = valid = in_block = 0;
      }
    }
    std::cout << "  all: lesion error max " << std::setprecision(3) << 1e3 * worst << " mm; while valid (before any slide) "
              << 1e3 * worst_valid << " mm; " << taken_back_total << " frames taken back, " << valid_total << " of "
              << frames << " valid";
    if (slide_mm != 0) std::cout << "; lesions invalid " << first_invalid_after_slide << " frames after the slide began";
    std::cout << "\n";
    out["lesion_error_max_mm"] = 1e3 * worst;
    out["lesion_error_max_valid_mm"] = 1e3 * worst_valid;
    out["taken_back"] = taken_back_total;
    out["valid_frames"] = valid_total;
    out["invalid_after_slide_frames"] = first_invalid_after_slide;
    if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  } catch (const std::exception& e) {
    std::cerr << "bench_tracking_drift: " << e.what() << "\n";
    return 2;
  }
  return 0;
}
