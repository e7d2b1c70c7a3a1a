// breast_sim_segment: automatic segmentation of a prone T1 breast MRI (a file or a DICOM folder) into
// the labels a case's `image:` map takes by default (mri/mri_segmentation.h); writes the labels, a PNG
// of cross-sections with the segmentation outlined and a JSON summary.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <optional>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/mri_cross_sections.h"
#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/segmentation_metrics.h"
#include "mri_tool_args.h"
#include "segmentation_summary.h"

using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_segment IN --out LABELS [--case CASE.yaml] [--series-uid UID]
                          [--lesion-labels FILE] [--png FILE] [--json FILE] [--truth LABELS]

Segments a prone T1-weighted breast MRI into air 0, fat 1, fibroglandular 29, skin 2, lesion 200 and chest
wall 40 (include/breast_sim/core/mri/mri_segmentation.h).
  IN                    NIfTI (.nii, .nii.gz), NRRD, MetaImage, or a DICOM folder (or one file of the series)
  --out LABELS          the labels: .nrrd, .nhdr, .nii, .nii.gz, .mha or .mhd
  --case CASE.yaml      its `segmentation:` map (every threshold and size, docs/mri.md) and `lesions:`
                        (points in the MRI's patient space, LPS mm, painted as spheres of radius_mm)
  --series-uid UID      the DICOM series to read when the folder holds several
  --lesion-labels FILE  a label image of the lesions (non-zero voxels) in the MRI's patient space
  --png FILE            cross-sections with the segmentation outlined (default: LABELS with .png)
  --json FILE           summary: volumes per class, nipples, levels, coverage, seconds (default: LABELS with .json)
  --truth LABELS        a ground truth on the MRI's grid (VICTRE label values): Dice per class and the
                        chest-wall boundary's distance to it, printed and in the summary
)";

std::string stemOf(const std::string& path) {
  for (const char* ext : {".nii.gz", ".nrrd", ".nhdr", ".nii", ".mha", ".mhd"}) {
    const std::string e = ext;
    if (path.size() > e.size() && path.compare(path.size() - e.size(), e.size(), e) == 0) return path.substr(0, path.size() - e.size());
  }
  return path;
}

}  // namespace

int main(int argc, char** argv) try {
  std::string in, out, case_path, series_uid, lesion_labels, png, json_path, truth_path;
  breast_sim::tools::Arguments args(argc, argv, kUsage);
  while (args.next()) {
    const std::string& a = args.option();
    if (args.help()) return 0;
    if (a == "--out") out = args.value();
    else if (a == "--case") case_path = args.value();
    else if (a == "--series-uid") series_uid = args.value();
    else if (a == "--lesion-labels") lesion_labels = args.value();
    else if (a == "--png") png = args.value();
    else if (a == "--json") json_path = args.value();
    else if (a == "--truth") truth_path = args.value();
    else if (args.positional() && in.empty()) in = a;
    else args.unknown();
  }
  if (in.empty() || out.empty()) throw std::invalid_argument(std::string("give IN and --out LABELS\n") + kUsage);
  if (png.empty()) png = stemOf(out) + ".png";
  if (json_path.empty()) json_path = stemOf(out) + ".json";

  const auto t0 = std::chrono::steady_clock::now();
  SegmentationSettings settings;
  LesionMarks lesions;
  if (!case_path.empty()) {
    settings = loadSegmentationSettings(case_path);
    lesions.points = loadCaseLesions(case_path);
  }
  if (!lesion_labels.empty()) lesions.label_image = readLabelImage(lesion_labels);
  MriReadOptions read_options;
  read_options.series_uid = series_uid;
  const MriVolume mri = readMriVolume(in, read_options);
  const double read_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const MriSegmentation seg = segmentProneMri(mri.image, settings, lesions);
  writeLabelImage(out, seg.labels);
  MriSectionRow row;
  row.title = "prone T1 " + std::filesystem::path(in).filename().string() + " with its segmentation";
  row.image = &mri.image;
  row.labels = &seg.labels;
  writeMriCrossSections(png, {row});

  std::optional<SegmentationScores> scores;
  if (!truth_path.empty())
    scores = scoreSegmentation(seg.labels, TissueLabels{}, readLabelImage(truth_path), TissueLabels{});
  const SegmentationScores* scored = scores ? &*scores : nullptr;
  breast_sim::tools::printSegmentationSummary(mri, seg, read_s, scored, truth_path);
  nlohmann::json j = breast_sim::tools::segmentationJson(mri, seg, read_s, scored, truth_path);
  j["outputs"] = {{"labels", out}, {"png", png}};
  std::ofstream(json_path) << j.dump(2) << '\n';
  std::printf("wrote %s, %s, %s\n", out.c_str(), png.c_str(), json_path.c_str());
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "breast_sim_segment: %s\n", e.what());
  return 2;
}
