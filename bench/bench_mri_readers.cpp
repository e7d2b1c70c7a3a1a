// bench_mri_readers: the readers of MRI volumes and label images against ITK's own readers on the same
// files. readMriVolume reads NRRD and MetaImage with the core's parsers (image/scalar_image_io.h) and
// NIfTI with ITK; readLabelImage reads all three with the core's parsers. Files: the VICTRE phantom's
// 1 mm and 0.5 mm label NRRDs, a 256 x 256 x 160 label volume as gzip NRRD, gzip NIfTI and raw NIfTI,
// and a 256 x 256 x 160 synthetic T1 image (float) as gzip NRRD and compressed MetaImage. Each row
// checks that readMriVolume gives ITK's grid and voxels, and prints median read times and their ratio.
// Then a 160-slice DICOM series: readMriVolume (the core's DICOM reader), the walk of every file it
// starts with (scanDicomFolder), and ITK with GDCM.
//
//   bench_mri_readers [--phantom FILE] [--fine FILE] [--repeats N] [--json FILE]
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/dicom_scan.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/synthetic_mri.h"
#include "itk_reference/itk_read.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

// readMriVolume's grid and voxels equal ITK's: spacing to `spacing_m`, positions to `position_m` (NIfTI
// stores float; DICOM positions have 6 significant digits, and ITK takes the slice spacing from the
// first two slices where readMriVolume takes the median gap).
bool sameAsItk(const MriVolume& a, const ItkVolume& b, double spacing_m = 1e-9, double position_m = 1e-7) {
  const ImageGeometry& g = a.image.geometry;
  for (int d = 0; d < 3; ++d) {
    if (g.size[d] != b.size[d] || std::abs(g.spacing_m[d] - 1e-3 * b.spacing_mm[d]) > spacing_m ||
        std::abs(g.origin_m[d] - 1e-3 * b.origin_mm[d]) > position_m)
      return false;
    for (int r = 0; r < 3; ++r)
      if (std::abs(g.direction(r, d) - b.direction[3 * r + d]) > 1e-6) return false;
  }
  return a.image.values == b.values;
}

}  // namespace

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
  // The large volumes: the synthetic T1 image of the phantom on a 256 x 256 x 160 grid and its truth labels.
  const std::filesystem::path dir = std::filesystem::temp_directory_path() / "breast_sim_bench_mri_readers";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  SyntheticMriParams p;
  p.size_voxels = Eigen::Vector3i(256, 256, 160);
  const SyntheticMri t1 = renderSyntheticT1(victrePhantomInLps(readLabelImage(phantom_path)), TissueLabels{}, p);
  struct File {
    std::string label, path;
    bool labels;  // a label image: readLabelImage reads it too
  };
  std::vector<File> files = {{"VICTRE 1 mm, gzip NRRD", phantom_path, true}};
  if (std::filesystem::exists(fine_path)) files.push_back({"VICTRE 0.5 mm, gzip NRRD", fine_path, true});
  for (const auto& [label, name] : {std::pair<std::string, std::string>{"256x256x160, gzip NRRD", "large.nrrd"},
                                    {"256x256x160, gzip NIfTI", "large.nii.gz"},
                                    {"256x256x160, raw NIfTI", "large.nii"}}) {
    writeLabelImage((dir / name).string(), t1.truth);
    files.push_back({label, (dir / name).string(), true});
  }
  for (const auto& [label, name] : {std::pair<std::string, std::string>{"T1 256x256x160, gzip NRRD", "t1.nrrd"},
                                    {"T1 256x256x160, MetaImage", "t1.mha"}}) {
    writeMriVolume((dir / name).string(), t1.image);
    files.push_back({label, (dir / name).string(), false});
  }

  std::printf("Reading volumes: readMriVolume (float voxels; NRRD and MetaImage by the core, NIfTI by ITK) and "
              "readLabelImage (uint16) against ITK's readers (float), median of %d, %d threads\n",
              repeats, omp_get_max_threads());
  std::printf("%-26s %-9s %-9s %-9s %-13s %-12s %-10s %-10s %s\n", "file", "voxels", "size [MB]", "reader", "MRI read [s]",
              "labels [s]", "ITK [s]", "ITK/MRI", "same voxels");
  nlohmann::json rows = nlohmann::json::array();
  bool all_same = true;
  for (const File& f : files) {
    std::vector<double> mri_s, labels_s, itk_s;
    MriVolume a;
    ItkVolume b;
    for (int r = 0; r < repeats; ++r) {
      auto t0 = Clock::now();
      a = readMriVolume(f.path);
      mri_s.push_back(since(t0));
      if (f.labels) {
        t0 = Clock::now();
        const LabelImage l = readLabelImage(f.path);
        labels_s.push_back(since(t0));
      }
      t0 = Clock::now();
      b = itkReadFloat(f.path);
      itk_s.push_back(since(t0));
    }
    const bool same = sameAsItk(a, b);
    all_same = all_same && same;
    const std::string reader = a.info.format == "NIfTI" ? "ITK" : "core";
    const double mb = static_cast<double>(std::filesystem::file_size(f.path)) / 1e6;
    const std::string labels_text = f.labels ? std::to_string(median(labels_s)).substr(0, 6) : "-";
    std::printf("%-26s %-9ld %-9.2f %-9s %-13.4f %-12s %-10.4f %-10.2f %s\n", f.label.c_str(), a.image.geometry.numVoxels(), mb,
                reader.c_str(), median(mri_s), labels_text.c_str(), median(itk_s), median(itk_s) / median(mri_s), same ? "yes" : "NO");
    nlohmann::json row = {{"file", f.label},       {"path", f.path},
                          {"voxels", a.image.geometry.numVoxels()},
                          {"megabytes", mb},        {"mri_reader", reader},
                          {"mri_seconds_median", median(mri_s)}, {"mri_seconds", mri_s},
                          {"itk_seconds_median", median(itk_s)}, {"itk_seconds", itk_s},
                          {"itk_over_mri", median(itk_s) / median(mri_s)}, {"same_voxels", same}};
    if (f.labels) row["labels_seconds_median"] = median(labels_s), row["labels_seconds"] = labels_s;
    rows.push_back(row);
  }

  // A DICOM series of the T1 image: readMriVolume, the walk of every file it starts with, and ITK with GDCM.
  const std::string series = (dir / "dicom").string();
  writeDicomSeries(series, t1.image);
  std::vector<double> read_s, scan_s, itk_dicom_s;
  MriVolume dicom;
  ItkVolume itk_dicom;
  for (int r = 0; r < repeats; ++r) {
    auto t0 = Clock::now();
    const DicomFolder found = scanDicomFolder(series);
    scan_s.push_back(since(t0));
    t0 = Clock::now();
    dicom = readMriVolume(series);
    read_s.push_back(since(t0));
    t0 = Clock::now();
    itk_dicom = itkReadDicomFolder(series);
    itk_dicom_s.push_back(since(t0));
    if (found.series.size() != 1 || dicom.info.files != p.size_voxels.z()) {
      std::fprintf(stderr, "the DICOM series did not read as %d slices\n", p.size_voxels.z());
      return 1;
    }
  }
  const bool dicom_same = sameAsItk(dicom, itk_dicom, 1e-6, 1e-6);
  all_same = all_same && dicom_same;
  std::printf("\nDICOM series, %d files: readMriVolume %.4f s (of it the walk of every file, scanDicomFolder, %.4f s: "
              "%.1f %%); ITK with GDCM %.4f s (%.2f x); same voxels: %s\n",
              p.size_voxels.z(), median(read_s), median(scan_s), 100.0 * median(scan_s) / median(read_s), median(itk_dicom_s),
              median(itk_dicom_s) / median(read_s), dicom_same ? "yes" : "NO");
  std::printf("(load average when run: %.2f)\n", loadAverage());
  std::filesystem::remove_all(dir);
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"bench", "mri_readers"}, {"repeats", repeats}, {"threads", omp_get_max_threads()},
                                               {"load_average", loadAverage()}, {"rows", rows},
                                               {"dicom", {{"files", p.size_voxels.z()},
                                                          {"read_seconds_median", median(read_s)}, {"read_seconds", read_s},
                                                          {"scan_seconds_median", median(scan_s)}, {"scan_seconds", scan_s},
                                                          {"itk_seconds_median", median(itk_dicom_s)},
                                                          {"itk_seconds", itk_dicom_s}, {"same_voxels", dicom_same}}}}
                                    .dump(2)
                             << '\n';
  return all_same ? 0 : 1;
}
