// bench_mri_segmentation: the prone MRI segmentation (mri/mri_segmentation.h) on synthetic T1 images
// rendered from the VICTRE phantom (mri/synthetic_mri.h): its time on a 1 mm 256 x 256 x 160 volume
// (target: at most 10 s on this 2-core machine) and its accuracy over contrasts, bias fields, noise
// and blur it was not tuned on (the defaults were set on the default image, seed 1): Dice per class
// and the chest-wall boundary's mean and 95th-percentile distance to the truth (targets: breast
// tissue Dice >= 0.95, boundary mean <= 1.5 mm, p95 <= 3 mm).
//
//   bench_mri_segmentation [--phantom FILE] [--size X,Y,Z] [--repeats N] [--sweep] [--json FILE]
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/segmentation_metrics.h"
#include "breast_sim/core/mri/synthetic_mri.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

struct Case {
  std::string name;
  SyntheticMriParams params;
};

// The images of the sweep: one knob at a time away from the default, then combinations of them.
std::vector<Case> sweepCases() {
  std::vector<Case> cases;
  const auto add = [&](const std::string& name, auto change) {
    Case c{name, SyntheticMriParams{}};
    c.params.seed = 1000 + cases.size();
    change(c.params);
    cases.push_back(c);
  };
  add("default (tuned)", [](SyntheticMriParams& p) { p.seed = 1; });
  for (double g : {300.0, 550.0, 650.0, 750.0, 850.0})
    add("gland " + std::to_string(int(g)), [g](SyntheticMriParams& p) { p.signal.fibroglandular = g; });
  for (double m : {220.0, 450.0, 600.0, 750.0})
    add("muscle " + std::to_string(int(m)), [m](SyntheticMriParams& p) { p.signal.muscle = m; });
  for (double s : {350.0, 800.0}) add("skin " + std::to_string(int(s)), [s](SyntheticMriParams& p) { p.signal.skin = s; });
  for (double a : {0.0, 0.4, 0.6, 0.8, 1.0})
    add("bias " + std::to_string(a).substr(0, 4), [a](SyntheticMriParams& p) { p.bias_amplitude = a; });
  add("bias wavelength 100 mm", [](SyntheticMriParams& p) { p.bias_wavelength_mm = 100; });
  for (double n : {5.0, 40.0, 60.0, 80.0, 100.0, 120.0, 140.0, 160.0})
    add("noise " + std::to_string(int(n)), [n](SyntheticMriParams& p) { p.noise_sigma = n; });
  for (double b : {0.0, 2.0, 3.0, 4.0})
    add("blur " + std::to_string(b).substr(0, 3) + " mm", [b](SyntheticMriParams& p) { p.blur_fwhm_mm = b; });
  add("no ribs", [](SyntheticMriParams& p) { p.rib_radius_mm = 0, p.rib_cortex_mm = 0; });
  add("dense gland, strong bias", [](SyntheticMriParams& p) {
    p.signal.fibroglandular = 550, p.bias_amplitude = 0.45;
  });
  add("muscle brighter than gland, noisy", [](SyntheticMriParams& p) {
    p.signal.muscle = 500, p.signal.fibroglandular = 350, p.noise_sigma = 45;
  });
  add("dark muscle, noise 60", [](SyntheticMriParams& p) { p.signal.muscle = 240, p.noise_sigma = 60; });
  add("dark muscle, noise 100", [](SyntheticMriParams& p) { p.signal.muscle = 240, p.noise_sigma = 100; });
  add("low contrast, blur, bias", [](SyntheticMriParams& p) {
    p.signal.fibroglandular = 600, p.signal.muscle = 450, p.blur_fwhm_mm = 2.0, p.bias_amplitude = 0.35, p.noise_sigma = 35;
  });
  return cases;
}

}  // namespace

int main(int argc, char** argv) {
  std::string phantom_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/test/data/victre_labels_1mm.nrrd";
  std::string json_path;
  std::vector<double> size = {256, 256, 160};
  int repeats = 3;
  bool sweep = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--phantom") phantom_path = next();
    else if (a == "--size") size = parseList(next());
    else if (a == "--repeats") repeats = std::stoi(next());
    else if (a == "--sweep") sweep = true;
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_mri_segmentation [--phantom FILE] [--size X,Y,Z] [--repeats N] [--sweep] [--json FILE]\n");
      return 2;
    }
  }
  if (size.size() != 3) {
    std::fprintf(stderr, "--size needs X,Y,Z\n");
    return 2;
  }
  const LabelImage phantom = victrePhantomInLps(readLabelImage(phantom_path));
  const TissueLabels labels;
  nlohmann::json out = {{"bench", "mri_segmentation"}, {"phantom", phantom_path}, {"threads", omp_get_max_threads()}};

  // 1. Time on the large volume.
  SyntheticMriParams big;
  big.size_voxels = Eigen::Vector3i(static_cast<int>(size[0]), static_cast<int>(size[1]), static_cast<int>(size[2]));
  const SyntheticMri image = renderSyntheticT1(phantom, labels, big);
  std::printf("Segmentation time, %d x %d x %d voxels of %.1f mm, %d threads (median of %d)\n", image.image.geometry.size.x(),
              image.image.geometry.size.y(), image.image.geometry.size.z(), 1e3 * image.image.geometry.spacing_m.x(),
              omp_get_max_threads(), repeats);
  std::vector<double> total, cpu, bias, tissue, boundary, label;
  MriSegmentation seg;
  for (int r = 0; r < repeats; ++r) {
    const double c0 = cpuSeconds();
    seg = segmentProneMri(image.image);
    cpu.push_back(cpuSeconds() - c0);
    total.push_back(seg.report.seconds_total);
    bias.push_back(seg.report.seconds_bias);
    tissue.push_back(seg.report.seconds_tissue);
    boundary.push_back(seg.report.seconds_boundary);
    label.push_back(seg.report.seconds_labels);
  }
  const SegmentationScores big_scores = scoreSegmentation(seg.labels, labels, image.truth, labels);
  std::printf("%-10s %-10s %-10s %-10s %-12s %-10s | %-12s %-14s %-14s\n", "total [s]", "cpu [s]", "bias [s]", "tissue [s]",
              "boundary [s]", "labels [s]", "Dice breast", "boundary mean", "boundary p95");
  std::printf("%-10.2f %-10.2f %-10.2f %-10.2f %-12.2f %-10.2f | %-12.3f %-14.2f %-14.2f\n", median(total), median(cpu),
              median(bias), median(tissue), median(boundary), median(label), big_scores.score("breast").dice,
              big_scores.boundary.mean_mm, big_scores.boundary.p95_mm);
  std::printf("(wall times; cpu = process CPU time, all threads; load average when run: %.2f)\n\n", loadAverage());
  out["timing"] = {{"size", size},
                   {"seconds_total", total},
                   {"seconds_total_median", median(total)},
                   {"cpu_seconds_median", median(cpu)},
                   {"load_average", loadAverage()},
                   {"seconds_bias_median", median(bias)},
                   {"seconds_tissue_median", median(tissue)},
                   {"seconds_boundary_median", median(boundary)},
                   {"seconds_labels_median", median(label)},
                   {"dice_breast", big_scores.score("breast").dice},
                   {"boundary_mean_mm", big_scores.boundary.mean_mm},
                   {"boundary_p95_mm", big_scores.boundary.p95_mm}};

  // 2. Accuracy over images it was not tuned on.
  if (sweep) {
    std::printf("Accuracy over contrasts, bias, noise and blur (default grid: tissue + 10 mm, thorax 40 mm)\n");
    std::printf("%-36s %6s %6s %6s %6s %5s | %7s %7s %7s %7s | %6s %6s %6s | %5s\n", "image", "gland", "muscle", "bias",
                "noise", "blur", "breast", "fat", "gland", "wall", "mean", "p95", "max", "time");
    std::printf("%-36s %6s %6s %6s %6s %5s | %7s %7s %7s %7s | %6s %6s %6s | %5s\n", "", "[a.u.]", "[a.u.]", "", "[a.u.]", "[mm]",
                "Dice", "Dice", "Dice", "Dice", "[mm]", "[mm]", "[mm]", "[s]");
    nlohmann::json rows = nlohmann::json::array();
    for (const Case& c : sweepCases()) {
      const SyntheticMri img = renderSyntheticT1(phantom, labels, c.params);
      nlohmann::json row = {{"image", c.name},
                            {"fibroglandular", c.params.signal.fibroglandular},
                            {"muscle", c.params.signal.muscle},
                            {"skin", c.params.signal.skin},
                            {"bias_amplitude", c.params.bias_amplitude},
                            {"bias_wavelength_mm", c.params.bias_wavelength_mm},
                            {"noise_sigma", c.params.noise_sigma},
                            {"blur_fwhm_mm", c.params.blur_fwhm_mm},
                            {"seed", c.params.seed}};
      try {
        const MriSegmentation s = segmentProneMri(img.image);
        const SegmentationScores sc = scoreSegmentation(s.labels, labels, img.truth, labels);
        std::printf("%-36s %6.0f %6.0f %6.2f %6.0f %5.1f | %7.3f %7.3f %7.3f %7.3f | %6.2f %6.2f %6.2f | %5.2f\n", c.name.c_str(),
                    c.params.signal.fibroglandular, c.params.signal.muscle, c.params.bias_amplitude, c.params.noise_sigma,
                    c.params.blur_fwhm_mm, sc.score("breast").dice, sc.score("fat").dice, sc.score("fibroglandular").dice,
                    sc.score("chest_wall").dice, sc.boundary.mean_mm, sc.boundary.p95_mm, sc.boundary.max_mm,
                    s.report.seconds_total);
        row["dice"] = {{"breast", sc.score("breast").dice}, {"fat", sc.score("fat").dice},
                       {"fibroglandular", sc.score("fibroglandular").dice}, {"chest_wall", sc.score("chest_wall").dice}};
        row["boundary_mean_mm"] = sc.boundary.mean_mm;
        row["boundary_p95_mm"] = sc.boundary.p95_mm;
        row["boundary_max_mm"] = sc.boundary.max_mm;
        row["coverage"] = s.report.boundary_coverage;
        row["seconds"] = s.report.seconds_total;
      } catch (const std::exception& e) {
        std::printf("%-36s failed: %s\n", c.name.c_str(), e.what());
        row["error"] = e.what();
      }
      std::fflush(stdout);
      rows.push_back(row);
    }
    out["sweep"] = rows;
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
  return 0;
}
