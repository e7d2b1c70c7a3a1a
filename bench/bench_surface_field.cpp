// bench_surface_field: how long the morphing target's distance field takes to build, by grid size,
// and how exact its vectors are against the exact closest-point distance (SurfaceDistance: CGAL's
// AABB tree, whose build and query time it prints first), on the phantom's supine target.
// Target: <= 0.2 s for a 256^3 grid on 2 cores (seed: 2-4 s).
// "build" constructs a new field each time (fresh grid memory: page faults); "rebuild" refills the
// same object (SurfaceVectorField::rebuild reuses its grids, as a tracker streaming clouds would).
// Both are wall times (median over the repeats) and, in "cpu", the process CPU time of a rebuild.
//
//   bench_surface_field [--sizes 64,128,192,256] [--repeats 3] [--samples 20000] [--json FILE]
#include <cstdio>
#include <ctime>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/morphing/surface_field.h"
#include "breast_sim/core/morphing/target_surface.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

int main(int argc, char** argv) {
  std::vector<double> sizes = {64, 128, 192, 256};
  int repeats = 3, samples = 20000;
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--sizes") sizes = parseList(next());
    else if (a == "--repeats") repeats = std::stoi(next());
    else if (a == "--samples") samples = std::stoi(next());
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_surface_field [--sizes 64,128,256] [--repeats N] [--samples N] [--json FILE]\n");
      return 2;
    }
  }
  const Phantom ph = generatePhantom(PhantomParams{});
  const TargetSurface target = skinTarget(ph.supine_surface);
  const auto te = Clock::now();
  const SurfaceDistance exact(target);
  const double exact_build_s = since(te);
  // The region the model moves in: the prone and supine shapes' box.
  Eigen::AlignedBox3d region;
  for (Eigen::Index v = 0; v < ph.prone_surface.vertices_m.rows(); ++v) region.extend(Eigen::Vector3d(ph.prone_surface.vertices_m.row(v)));
  // Sample points within 10 mm of the target (where morphing works): target samples pushed along random directions.
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const Points base = surfaceSamples(target);
  std::vector<Eigen::Vector3d> pts;
  for (int s = 0; s < samples; ++s) {
    const Eigen::Vector3d d(u(rng), u(rng), u(rng));
    pts.push_back(base.row(s % base.rows()).transpose() + 10e-3 * std::abs(u(rng)) * d.normalized());
  }
  Points pts_m(static_cast<Eigen::Index>(pts.size()), 3);
  for (size_t s = 0; s < pts.size(); ++s) pts_m.row(static_cast<Eigen::Index>(s)) = pts[s].transpose();
  const auto tx = Clock::now();
  const Eigen::VectorXd exact_d = exact.distances(pts_m);  // all threads, as the pipeline's metrics query
  const double exact_query_us = since(tx) / static_cast<double>(pts.size()) * 1e6;
  std::printf("Exact closest points (SurfaceDistance, CGAL AABB tree): build %.1f ms, %.2f us per point over %zu points "
              "on %d threads\n",
              exact_build_s * 1e3, exact_query_us, pts.size(), omp_get_max_threads());

  std::printf("Distance field of the phantom's supine target (%ld triangles), build time and accuracy\n",
              static_cast<long>(target.triangles.rows()));
  std::printf("%-10s %-16s %-10s %-12s %-12s %-12s %-12s %-14s %-14s\n", "grid", "voxels", "h [mm]", "build [s]", "rebuild [s]", "cpu b/r [s]", "query [us]",
              "mean err [um]", "max err [um]");
  nlohmann::json rows = nlohmann::json::array();
  for (double n : sizes) {
    SurfaceFieldOptions o;
    o.voxel_size_m = 1e-9;  // the cap decides: n voxels along the longest axis
    o.max_voxels_per_axis = static_cast<int>(n);
    std::vector<double> t, tbc;
    std::unique_ptr<SurfaceVectorField> f;
    for (int r = 0; r < repeats; ++r) {
      f.reset();  // the old field's memory goes back to the system first
      const double c0 = cpuSeconds();
      const auto t0 = Clock::now();
      f = std::make_unique<SurfaceVectorField>(target, region, o);
      t.push_back(since(t0));
      tbc.push_back(cpuSeconds() - c0);
    }
    // Rebuilding the same object reuses its grid storage (a tracker streaming clouds does this).
    std::vector<double> tr, tc;
    for (int r = 0; r < repeats; ++r) {
      const double c0 = cpuSeconds();
      const auto t0 = Clock::now();
      f->rebuild(target, region, o);
      tr.push_back(since(t0));
      tc.push_back(cpuSeconds() - c0);
    }
    const auto tq = Clock::now();
    double sum = 0, mx = 0;
    for (size_t s = 0; s < pts.size(); ++s) {
      const double e = std::abs(f->vectorToSurface(pts[s]).norm() - exact_d[static_cast<Eigen::Index>(s)]);
      sum += e;
      mx = std::max(mx, e);
    }
    const double query_us = since(tq) / static_cast<double>(pts.size()) * 1e6;
    const Eigen::Vector3i sz = f->size();
    const long voxels = static_cast<long>(sz.x()) * sz.y() * sz.z();
    char grid[48];
    std::snprintf(grid, sizeof grid, "%dx%dx%d", sz.x(), sz.y(), sz.z());
    std::printf("%-10.0f %-16ld %-10.3f %-12.3f %-12.3f %5.3f/%-6.3f %-12.2f %-14.2f %-14.2f   (%s)\n", n, voxels, f->voxelSize() * 1e3, median(t),
                median(tr), median(tbc), median(tc), query_us, sum / static_cast<double>(pts.size()) * 1e6, mx * 1e6, grid);
    rows.push_back({{"max_voxels_per_axis", n}, {"grid", {sz.x(), sz.y(), sz.z()}}, {"voxels", voxels},
                    {"voxel_size_mm", f->voxelSize() * 1e3}, {"build_seconds_median", median(t)}, {"build_seconds", t},
                    {"rebuild_seconds_median", median(tr)}, {"rebuild_seconds", tr},
                    {"build_cpu_seconds_median", median(tbc)}, {"rebuild_cpu_seconds_median", median(tc)},
                    {"query_us", query_us}, {"mean_error_um", sum / static_cast<double>(pts.size()) * 1e6},
                    {"max_error_um", mx * 1e6}});
  }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"bench", "surface_field"}, {"repeats", repeats}, {"samples", samples},
                                               {"threads", omp_get_max_threads()},
                                               {"exact_build_seconds", exact_build_s},
                                               {"exact_query_us", exact_query_us}, {"rows", rows}}
                                    .dump(2)
                             << '\n';
  return 0;
}
