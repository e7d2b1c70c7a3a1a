// bench_mri_readers: ITK's NIfTI and NRRD readers (through mri/mri_volume.h, voxels as float) against
// the hand-written label-image readers of core/image (readLabelImage, voxels as uint16) on the same
// files: the VICTRE phantom's 1 mm and 0.5 mm NRRDs and a 256 x 256 x 160 label volume written as
// gzip NRRD, gzip NIfTI and raw NIfTI. Each row checks that both give the same grid and voxels and
// prints the median read times and their ratio.
//
//   bench_mri_readers [--phantom FILE] [--fine FILE] [--repeats N] [--json FILE]
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/synthetic_mri.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

int main(int argc, char** argv) {
  const std::string source = BREAST_SIM_SOURCE_DIR_FOR_TOOLS;
  std::string phantom_path = source + "/test/data/victre_labels_1mm.nrrd";
  std::string fine_path = source + "/../shared/data/victre-phantom/breast_labels_0p5mm.nrrd";
  if (!std::filesystem::exists(fine_path)) fine_path = "/work/shared/data/victre-phantom/breast_labels_0p5mm.nrrd";
  std::string json_path;
  int repeats = 5;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--phantom") phantom_path = next();
    else if (a == "--fine") fine_path = next();
    else if (a == "--repeats") repeats = std::stoi(next());
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_mri_readers [--phantom FILE] [--fine FILE] [--repeats N] [--json FILE]\n");
      return 2;
    }
  }
  // The large volume: the synthetic image's truth labels on a 256 x 256 x 160 grid, in three encodings.
  const std::filesystem::path dir = std::filesystem::temp_directory_path() / "breast_sim_bench_mri_readers";
  std::filesystem::create_directories(dir);
  SyntheticMriParams p;
  p.size_voxels = Eigen::Vector3i(256, 256, 160);
  p.noise_sigma = 0;
  const LabelImage large = renderSyntheticT1(victrePhantomInLps(readLabelImage(phantom_path)), TissueLabels{}, p).truth;
  std::vector<std::pair<std::string, std::string>> files = {{"VICTRE 1 mm, gzip NRRD", phantom_path}};
  if (std::filesystem::exists(fine_path)) files.push_back({"VICTRE 0.5 mm, gzip NRRD", fine_path});
  for (const auto& [label, name] : {std::pair<std::string, std::string>{"256x256x160, gzip NRRD", "large.nrrd"},
                                    {"256x256x160, gzip NIfTI", "large.nii.gz"},
                                    {"256x256x160, raw NIfTI", "large.nii"}}) {
    writeLabelImage((dir / name).string(), large);
    files.push_back({label, (dir / name).string()});
  }

  std::printf("Reading label volumes: ITK (float voxels) against core/image (uint16 voxels), median of %d, %d threads\n", repeats,
              omp_get_max_threads());
  std::printf("%-26s %-12s %-10s %-12s %-12s %-10s %s\n", "file", "voxels", "size [MB]", "ours [s]", "ITK [s]", "ITK/ours",
              "same voxels");
  nlohmann::json rows = nlohmann::json::array();
  bool all_same = true;
  for (const auto& [label, path] : files) {
    std::vector<double> ours, itk;
    LabelImage a;
    MriVolume b;
    for (int r = 0; r < repeats; ++r) {
      auto t0 = Clock::now();
      a = readLabelImage(path);
      ours.push_back(since(t0));
      t0 = Clock::now();
      b = readMriVolume(path);
      itk.push_back(since(t0));
    }
    bool same = a.size == b.image.geometry.size && (a.spacing_m - b.image.geometry.spacing_m).cwiseAbs().maxCoeff() < 1e-9 &&
                (a.origin_m - b.image.geometry.origin_m).cwiseAbs().maxCoeff() < 1e-7 &&
                (a.direction - b.image.geometry.direction).cwiseAbs().maxCoeff() < 1e-6;
    for (std::size_t v = 0; same && v < a.labels.size(); ++v) same = static_cast<float>(a.labels[v]) == b.image.values[v];
    all_same = all_same && same;
    const double mb = static_cast<double>(std::filesystem::file_size(path)) / 1e6;
    std::printf("%-26s %-12ld %-10.2f %-12.4f %-12.4f %-10.2f %s\n", label.c_str(), a.numVoxels(), mb, median(ours), median(itk),
                median(itk) / median(ours), same ? "yes" : "NO");
    rows.push_back({{"file", label},
                    {"path", path},
                    {"voxels", a.numVoxels()},
                    {"megabytes", mb},
                    {"ours_seconds_median", median(ours)},
                    {"itk_seconds_median", median(itk)},
                    {"ours_seconds", ours},
                    {"itk_seconds", itk},
                    {"itk_over_ours", median(itk) / median(ours)},
                    {"same_voxels", same}});
  }
  std::printf("(load average when run: %.2f)\n", loadAverage());
  std::filesystem::remove_all(dir);
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"bench", "mri_readers"}, {"repeats", repeats}, {"threads", omp_get_max_threads()},
                                               {"load_average", loadAverage()}, {"rows", rows}}
                                    .dump(2)
                             << '\n';
  return all_same ? 0 : 1;
}
