// Latency of one tracker frame, from a PointCloud2 arriving to the updated mesh and lesion messages
// serialized for publishing, done exactly as the node does it (ros_interface::GuardedTracker: the tracker and its monitor), without
// a ROS master:
//   bench_tracking_latency [--case FILE] [--target-elements N] [--points N] [--frames N]
//                          [--field-voxels-mm 1,2,3] [--loop-voxels-mm 0,2] [--iterations K] [--no-icp]
//                          [--pcl-reference] [--solver-tol T] [--json FILE]
// Prints (1) the distance-field rebuild time per voxel size for one decimated cloud and (2) per loop
// voxel size (0 = the case's setting) the median and 95th percentile of every stage and of the whole
// frame, the rate reached (1 / mean frame time) and on how many frames the ICP correction was applied.
// --pcl-reference adds, per loop voxel size, the same frames with PCL's outlier removal, ICP and
// kd-tree (TrackerOptions::pcl_reference, the slow reference) from the same precomputed state, so the
// two are compared in the same run. --solver-tol sets TrackerOptions::solver_relative_tolerance (the
// per-frame PCG tolerance; default the node's, 0 = the case's own).
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>

#include <nlohmann/json.hpp>
#include <ros/package.h>
#include <ros/serialization.h>
#include <ros/time.h>

#include "../bench_util.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

using namespace breast_sim;
using bench::Clock;
using bench::since;

namespace {
double p95(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(std::ceil(0.95 * static_cast<double>(v.size()))) - 1)];
}
template <typename M>
size_t serialize(const M& m) {
  return ros::serialization::serializeMessage(m).num_bytes;
}
}  // namespace

int main(int argc, char** argv) {
  ros::Time::init();
  std::string case_file, json_path;
  int target = 20000, points = 10000, frames = 60, iterations = 1;
  bool icp = true, pcl_reference = false;
  double solver_tol = ros_interface::TrackerOptions{}.solver_relative_tolerance;
  std::vector<double> field_voxels = {1, 2, 3}, loop_voxels = {0};
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string { return i + 1 < argc ? argv[++i] : ""; };
    if (a == "--case") case_file = next();
    else if (a == "--target-elements") target = std::stoi(next());
    else if (a == "--points") points = std::stoi(next());
    else if (a == "--frames") frames = std::stoi(next());
    else if (a == "--iterations") iterations = std::stoi(next());
    else if (a == "--field-voxels-mm") field_voxels = bench::parseList(next());
    else if (a == "--loop-voxels-mm") loop_voxels = bench::parseList(next());
    else if (a == "--no-icp") icp = false;
    else if (a == "--pcl-reference") pcl_reference = true;
    else if (a == "--solver-tol") solver_tol = std::stod(next());
    else if (a == "--json") json_path = next();
    else {
      std::cerr << "usage: bench_tracking_latency [--case FILE] [--target-elements N] [--points N] [--frames N]"
                   " [--field-voxels-mm 1,2,3] [--loop-voxels-mm 0,2] [--iterations K] [--no-icp]"
                   " [--pcl-reference] [--solver-tol T] [--json FILE]\n";
      return a == "--help" ? 0 : 2;
    }
  }
  if (case_file.empty()) case_file = ros::package::getPath("breast_sim") + "/config/phantom_default.yaml";
  nlohmann::json out;
  try {
    core::ModelCase c = core::loadModelCase(case_file);
    c.meshing.target_elements = target;
    auto t0 = Clock::now();
    const core::SimulationModel model = core::buildSimulationModel(c);
    const double mesh_s = since(t0);
    core::PipelineSettings settings = core::loadPipelineSettings(case_file);
    t0 = Clock::now();
    core::ProneToSupinePipeline pre(c, model, settings);
    pre.run();
    const double pre_s = since(t0);
    const core::PipelineState precomputed = pre.state();
    std::cout << "case " << c.name << ": " << model.mesh.numTets() << " tetrahedra, " << model.mesh.numNodes()
              << " nodes (meshed in " << mesh_s << " s); precomputation (gravity + morphing) " << pre_s << " s\n";
    out["tetrahedra"] = model.mesh.numTets();
    out["nodes"] = model.mesh.numNodes();
    out["precompute_s"] = pre_s;

    ros_interface::TrackerSimulationOptions so;
    so.points = points;
    ros_interface::TrackerSimulation sim(c, so);
    const Eigen::Isometry3d tracker_from_model0 = sim.worldFromTracker().inverse() * sim.worldFromModel(0.0);
    ros_interface::TrackerOptions to;
    to.icp.enabled = icp;
    to.iterations_per_frame = iterations;
    to.solver_relative_tolerance = solver_tol;

    // (1) Field rebuild per voxel size, for one decimated cloud over the model's reach.
    const core::Points filtered = ros_interface::filterCloud(sim.cloudInModel(0.0), to.filter);
    Eigen::AlignedBox3d region;
    const core::Points x = pre.positions();
    for (Eigen::Index i = 0; i < x.rows(); ++i) region.extend(x.row(i).transpose());
    core::TargetSurface cloud_target;
    cloud_target.vertices_m = filtered;
    std::cout << "\n(1) distance-field rebuild for one cloud: " << points << " points -> " << filtered.rows()
              << " after the " << 1e3 * to.filter.voxel_leaf_m << " mm voxel grid and outlier removal\n";
    std::cout << "  voxel[mm]        grid   build[ms]  (median of 5)   + SurfaceDistance[ms]\n";
    for (double v : field_voxels) {
      core::SurfaceFieldOptions fo = settings.morphing.field;
      fo.voxel_size_m = 1e-3 * v;
      std::vector<double> ts, ds;
      Eigen::Vector3i size;
      for (int r = 0; r < 5; ++r) {
        auto t1 = Clock::now();
        core::SurfaceVectorField f(cloud_target, region, fo);
        ts.push_back(since(t1));
        size = f.size();
        t1 = Clock::now();
        core::SurfaceDistance d(cloud_target);
        ds.push_back(since(t1));
      }
      std::cout << "  " << std::setw(9) << v << "  " << std::setw(3) << size.x() << "x" << size.y() << "x" << size.z()
                << std::setw(12) << std::fixed << std::setprecision(2) << 1e3 * bench::median(ts) << std::setw(25)
                << 1e3 * bench::median(ds) << "\n";
      out["field"].push_back({{"voxel_mm", v}, {"grid", {size.x(), size.y(), size.z()}},
                              {"build_ms", 1e3 * bench::median(ts)}, {"distance_ms", 1e3 * bench::median(ds)}});
    }

    // (2) Whole frames.
    std::cout << "\n(2) frames: " << points << "-point cloud in -> mesh + lesions serialized; " << iterations
              << " iteration(s) per frame, ICP " << (icp ? "on" : "off") << ", PCG tolerance per frame "
              << (solver_tol > 0 ? std::to_string(solver_tol) : std::string("of the case")) << ", " << frames
              << " frames (medians, p95) [ms]\n";
    std::cout << "  voxel[mm]  convert  filter     icp   field iterate  (PCG it.)  publish |   total    p95 |  rate[Hz]"
                 "  surf.mean[mm]  ICP applied  search (valid frames)\n";
    core::Points grid_final;  // final positions of the grid run, compared with the reference run
    for (double v : loop_voxels) for (const bool reference : {false, true}) {
      if (reference && !pcl_reference) continue;
      to.pcl_reference = reference;
      core::PipelineSettings s = settings;
      if (v > 0) s.morphing.field.voxel_size_m = 1e-3 * v;
      core::ProneToSupinePipeline p(c, model, s);
      p.restore(precomputed);
      ros_interface::GuardedTracker tracker(to, ros_interface::MonitorLimits{});  // the node's: tracker and monitor
      tracker.start(p);
      ros_interface::TrackerSimulation frame_sim(c, so);
      std::vector<double> conv, filt, icps, field, iter, pub, total, pcg;
      double last_mean = -1;
      int icp_applied = 0, valid_frames = 0;
      const core::StepTotals steps_before = p.simulator().totals();
      for (int k = 0; k < frames; ++k) {
        const double t = k / 30.0;
        const sensor_msgs::PointCloud2 msg =
            ros_interface::cloudToMessage(frame_sim.cloudInTracker(t), "tracker", ros::Time(100.0 + t));
        const Eigen::Isometry3d model_from_tracker = (sim.worldFromTracker().inverse() * sim.worldFromModel(t)).inverse();
        const auto f0 = Clock::now();
        const ros_interface::CloudPoints cp = ros_interface::pointsFromCloud(msg, 300000);
        const core::Points cloud = ros_interface::transformPoints(model_from_tracker, cp.points_m);
        const double conv_s = since(f0);
        const long pcg_before = p.simulator().totals().iterations;
        const ros_interface::GuardedFrame g = tracker.frame(p, cloud);
        const long pcg_frame = p.simulator().totals().iterations - pcg_before;
        const ros_interface::TrackResult& r = g.track;
        const auto p0 = Clock::now();
        const core::Points xs = p.positions();
        const core::Points lesions = model.lesion_embedding.positions(xs);
        size_t bytes = serialize(ros_interface::toMessage(model.mesh, xs - model.mesh.nodes(), "breast_model", msg.header.stamp));
        bytes += serialize(ros_interface::lesionsMessage(model.lesions, lesions, "breast_model", msg.header.stamp, g.valid, g.status));
        const double pub_s = since(p0);
        const double total_s = since(f0);
        (void)bytes;
        if (k < 3) continue;  // warm-up (first fields, ICP guess)
        conv.push_back(conv_s);
        filt.push_back(r.filter_s);
        icps.push_back(r.icp_s);
        field.push_back(r.field_s);
        iter.push_back(r.iterate_s);
        pub.push_back(pub_s);
        total.push_back(total_s);
        pcg.push_back(static_cast<double>(pcg_frame));
        last_mean = r.seen_mean_m;
        valid_frames += g.valid ? 1 : 0;
        icp_applied += r.icp_applied ? 1 : 0;
      }
      // Steps that solved with an earlier frame's matrix (tracking reuses it, DynamicSimulator::
      // setMatrixReuse) and reusing solves done again assembled.
      const core::StepTotals& steps_after = p.simulator().totals();
      const long reused = steps_after.reused_matrix - steps_before.reused_matrix;
      const long resolved = steps_after.resolved_assembled - steps_before.resolved_assembled;
      std::string search = reference ? "PCL (reference)" : "grid";
      double max_diff_mm = -1;
      if (!reference) {
        grid_final = p.positions();
      } else if (grid_final.rows() == p.positions().rows()) {
        max_diff_mm = 1e3 * (p.positions() - grid_final).rowwise().norm().maxCoeff();
        std::ostringstream note;
        note << ", final nodes " << max_diff_mm << " mm from the grid run's";
        search += note.str();
      }
      (void)tracker_from_model0;
      const double rate = 1.0 / bench::mean(total);
      std::cout << "  " << std::setw(9) << (v > 0 ? v : 1e3 * settings.morphing.field.voxel_size_m) << std::fixed
                << std::setprecision(2) << std::setw(9) << 1e3 * bench::median(conv) << std::setw(8)
                << 1e3 * bench::median(filt) << std::setw(8) << 1e3 * bench::median(icps) << std::setw(8)
                << 1e3 * bench::median(field) << std::setw(8) << 1e3 * bench::median(iter) << std::setw(11)
                << bench::median(pcg) << std::setw(9) << 1e3 * bench::median(pub) << " |" << std::setw(8)
                << 1e3 * bench::median(total) << std::setw(7)
                << 1e3 * p95(total) << " |" << std::setw(10) << rate << std::setw(15) << 1e3 * last_mean << std::setw(8)
                << icp_applied << "/" << std::setw(3) << std::left << total.size() << std::right << "  " << search << " ("
                << valid_frames << " valid), matrix reused in " << reused << " of " << frames
                << " frames, solved again " << resolved << "\n";
      out["frames"].push_back({{"voxel_mm", v > 0 ? v : 1e3 * settings.morphing.field.voxel_size_m},
                               {"convert_ms", 1e3 * bench::median(conv)}, {"filter_ms", 1e3 * bench::median(filt)},
                               {"icp_ms", 1e3 * bench::median(icps)}, {"field_ms", 1e3 * bench::median(field)},
                               {"iterate_ms", 1e3 * bench::median(iter)},
                               {"pcg_iterations_median", bench::median(pcg)}, {"publish_ms", 1e3 * bench::median(pub)},
                               {"total_median_ms", 1e3 * bench::median(total)}, {"total_p95_ms", 1e3 * p95(total)},
                               {"rate_hz", rate}, {"surface_mean_mm", 1e3 * last_mean},
                               {"icp_applied", icp_applied}, {"frames_timed", total.size()}, {"valid_frames", valid_frames},
                               {"search", reference ? "pcl" : "grid"}, {"max_diff_from_grid_mm", max_diff_mm},
                               {"solver_relative_tolerance", solver_tol}, {"frames", frames},
                               {"matrix_reused_frames", reused}, {"solved_again_assembled", resolved}});
    }
  } catch (const std::exception& e) {
    std::cerr << "bench_tracking_latency: " << e.what() << "\n";
    return 2;
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
