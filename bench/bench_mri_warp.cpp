// bench_mri_warp: the simulated supine MRI (mri/supine_resampling.h). The phantom's model (default case,
// 20k elements) under a smooth displacement of up to ~25 mm carries a synthetic T1 image of the
// phantom and its labels into a supine grid of 256^3 voxels (target: at most 1 s on this 2-core
// machine), and, on a small grid, the fast rasterisation beside its slow reference (the same voxels,
// and the speed-up).
//
//   bench_mri_warp [--case FILE] [--target-elements N] [--size N] [--repeats N] [--json FILE]
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/material/stability_map.h"  // defaultPhantomCasePath
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/mri/supine_resampling.h"
#include "breast_sim/core/mri/synthetic_mri.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

// A supine-like displacement: the breast flattens towards the wall and shifts laterally and up,
// more the farther it hangs from the wall (y < 0 is anterior) [m].
Points displacementOf(const TetMesh& mesh) {
  Points u(mesh.numNodes(), 3);
  for (int n = 0; n < mesh.numNodes(); ++n) {
    const Eigen::Vector3d x = mesh.nodes().row(n).transpose();
    const double depth = std::max(0.0, -x.y());  // distance anterior of the wall [m]
    u.row(n) << 0.15 * depth + 4e-3 * std::sin(30 * x.z()), 0.3 * depth, 0.1 * depth * std::cos(20 * x.x());
  }
  return u;
}

ImageGeometry gridOfSize(const ImageGeometry& prone, const Points& deformed, int n, double margin_m) {
  SupineResampleOptions o;
  o.margin_m = margin_m;
  const Eigen::Matrix<double, Eigen::Dynamic, 3> q = (deformed.rowwise() - prone.origin_m.transpose()) * prone.direction;
  for (int a = 0; a < 3; ++a) o.spacing_m[a] = (q.col(a).maxCoeff() - q.col(a).minCoeff() + 2 * margin_m) / (n - 2);
  return supineGrid(prone, deformed, o);
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_path = defaultPhantomCasePath(), json_path;
  int target = 20000, size = 256, repeats = 5;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--case") case_path = next();
    else if (a == "--target-elements") target = std::stoi(next());
    else if (a == "--size") size = std::stoi(next());
    else if (a == "--repeats") repeats = std::stoi(next());
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_mri_warp [--case FILE] [--target-elements N] [--size N] [--repeats N] [--json FILE]\n");
      return 2;
    }
  }
  ModelCase c = loadModelCase(case_path);
  c.meshing.target_elements = target;
  const SimulationModel model = buildSimulationModel(c);
  const SyntheticMri prone = renderSyntheticT1(c.image, c.labels, SyntheticMriParams{});
  const Points u = displacementOf(model.mesh);
  const Points deformed = model.mesh.nodes() + u;
  std::printf("Simulated supine MRI: %s, %d tetrahedra, displacement up to %.1f mm, prone image %d x %d x %d, %d threads\n",
              case_path.c_str(), model.mesh.numTets(), 1e3 * u.rowwise().norm().maxCoeff(), prone.image.geometry.size.x(),
              prone.image.geometry.size.y(), prone.image.geometry.size.z(), omp_get_max_threads());

  nlohmann::json rows = nlohmann::json::array();
  std::printf("%-14s %-12s %-12s %-12s %-12s %-12s\n", "grid", "body voxels", "image [s]", "cpu [s]", "+labels [s]", "cpu [s]");
  for (int n : {size}) {
    const ImageGeometry grid = gridOfSize(prone.image.geometry, deformed, n, 10e-3);
    std::vector<double> t_image, c_image, t_both, c_both;
    long body = 0;
    for (int r = 0; r < repeats; ++r) {
      double c0 = cpuSeconds();
      const SupineImages a = resampleToSupine(model.mesh, u, &prone.image, nullptr, grid);
      c_image.push_back(cpuSeconds() - c0);
      t_image.push_back(a.seconds);
      c0 = cpuSeconds();
      const SupineImages b = resampleToSupine(model.mesh, u, &prone.image, &prone.truth, grid);
      c_both.push_back(cpuSeconds() - c0);
      t_both.push_back(b.seconds);
      body = b.body_voxels;
    }
    char name[48];
    std::snprintf(name, sizeof name, "%dx%dx%d", grid.size.x(), grid.size.y(), grid.size.z());
    std::printf("%-14s %-12ld %-12.3f %-12.3f %-12.3f %-12.3f\n", name, body, median(t_image), median(c_image), median(t_both),
                median(c_both));
    rows.push_back({{"grid", {grid.size.x(), grid.size.y(), grid.size.z()}},
                    {"spacing_mm", {1e3 * grid.spacing_m.x(), 1e3 * grid.spacing_m.y(), 1e3 * grid.spacing_m.z()}},
                    {"body_voxels", body},
                    {"image_seconds_median", median(t_image)},
                    {"image_seconds", t_image},
                    {"image_cpu_seconds_median", median(c_image)},
                    {"image_and_labels_seconds_median", median(t_both)},
                    {"image_and_labels_seconds", t_both},
                    {"image_and_labels_cpu_seconds_median", median(c_both)}});
  }
  // The reference on a small grid: the same voxels, and how much slower.
  const ImageGeometry small = gridOfSize(prone.image.geometry, deformed, 48, 10e-3);
  const SupineImages fast = resampleToSupine(model.mesh, u, &prone.image, &prone.truth, small);
  const SupineImages slow = resampleToSupineReference(model.mesh, u, &prone.image, &prone.truth, small);
  const bool same = fast.image.values == slow.image.values && fast.labels.labels == slow.labels.labels;
  std::printf("(wall times; cpu = process CPU time, all threads; load average when run: %.2f)\n", loadAverage());
  std::printf("\nreference on %dx%dx%d: %.3f s against %.4f s (%.0fx), voxels %s\n", small.size.x(), small.size.y(), small.size.z(),
              slow.seconds, fast.seconds, slow.seconds / fast.seconds, same ? "identical" : "DIFFERENT");
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"bench", "mri_warp"},
                                               {"case", case_path},
                                               {"tetrahedra", model.mesh.numTets()},
                                               {"threads", omp_get_max_threads()},
                                               {"load_average", loadAverage()},
                                               {"rows", rows},
                                               {"reference", {{"grid", {small.size.x(), small.size.y(), small.size.z()}},
                                                              {"reference_seconds", slow.seconds},
                                                              {"fast_seconds", fast.seconds},
                                                              {"identical", same}}}}
                                    .dump(2)
                             << '\n';
  return same ? 0 : 1;
}
