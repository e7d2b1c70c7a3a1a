// breast_sim_segment: automatic segmentation of a prone T1 breast MRI (a file or a DICOM folder) into
// the labels a case's `image:` map takes by default (mri/mri_segmentation.h); writes the labels, a PNG
// of cross-sections with the segmentation outlined and a JSON summary.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/mri_cross_sections.h"
#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/segmentation_metrics.h"
#include "mri_tool_args.h"

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

  const ImageGeometry& g = mri.image.geometry;
  const SegmentationReport& r = seg.report;
  std::printf("%s (%s%s): %d x %d x %d voxels of %.2f x %.2f x %.2f mm, read in %.2f s\n", in.c_str(), mri.info.format.c_str(),
              mri.info.series_uid.empty() ? "" : (", series " + mri.info.series_uid).c_str(), g.size.x(), g.size.y(), g.size.z(),
              1e3 * g.spacing_m.x(), 1e3 * g.spacing_m.y(), 1e3 * g.spacing_m.z(), read_s);
  std::printf("segmented in %.2f s (bias %.2f, tissue %.2f, chest wall %.2f, labels %.2f): fat level %.0f, background %.0f "
              "+- %.0f, body threshold %.0f, fat threshold %.0f, bias field %.2f-%.2f\n",
              r.seconds_total, r.seconds_bias, r.seconds_tissue, r.seconds_boundary, r.seconds_labels, r.fat_level,
              r.noise_level, r.noise_spread, r.body_threshold, r.fat_threshold, r.bias_min, r.bias_max);
  std::printf("chest wall: %d of %d breast columns measured (%.0f %%), %d candidates rejected by the fit\n", r.measured_columns,
              r.breast_columns, 100.0 * r.boundary_coverage, r.rejected_candidates);
  const char* names[6] = {"air", "fat", "fibroglandular", "skin", "lesion", "chest_wall"};
  std::printf("volumes [ml]: fat %.1f, fibroglandular %.1f, skin %.1f, lesion %.1f, chest wall %.1f\n", r.volume_ml[1],
              r.volume_ml[2], r.volume_ml[3], r.volume_ml[4], r.volume_ml[5]);
  std::string nipples;
  for (const Eigen::Vector3d& n : r.nipples_m) {
    char buf[96];
    std::snprintf(buf, sizeof buf, "%s[%.1f, %.1f, %.1f]", nipples.empty() ? "" : ", ", 1e3 * n.x(), 1e3 * n.y(), 1e3 * n.z());
    nipples += buf;
  }
  std::printf("nipples (the apex of each breast) [mm]: %s\n", nipples.c_str());
  nlohmann::json j;
  j["input"] = {{"path", in},
                {"format", mri.info.format},
                {"series_uid", mri.info.series_uid},
                {"size", {g.size.x(), g.size.y(), g.size.z()}},
                {"spacing_mm", {1e3 * g.spacing_m.x(), 1e3 * g.spacing_m.y(), 1e3 * g.spacing_m.z()}},
                {"read_seconds", read_s}};
  nlohmann::json volumes;
  for (int c = 1; c < 6; ++c) volumes[names[c]] = r.volume_ml[c];
  j["volumes_ml"] = volumes;
  j["levels"] = {{"fat_level", r.fat_level}, {"background_level", r.noise_level}, {"background_spread", r.noise_spread},
                 {"body_threshold", r.body_threshold}, {"fat_threshold", r.fat_threshold},
                 {"bias_min", r.bias_min}, {"bias_max", r.bias_max}};
  nlohmann::json nipple_list = nlohmann::json::array();
  for (const Eigen::Vector3d& n : r.nipples_m) nipple_list.push_back({1e3 * n.x(), 1e3 * n.y(), 1e3 * n.z()});
  j["nipples_mm"] = nipple_list;
  j["chest_wall"] = {{"breast_columns", r.breast_columns}, {"measured_columns", r.measured_columns},
                     {"coverage", r.boundary_coverage}, {"rejected_candidates", r.rejected_candidates}};
  j["seconds"] = {{"bias_correction", r.seconds_bias}, {"tissue", r.seconds_tissue}, {"chest_wall", r.seconds_boundary},
                  {"labels", r.seconds_labels}, {"total", r.seconds_total}};
  j["outputs"] = {{"labels", out}, {"png", png}};
  if (!truth_path.empty()) {
    const SegmentationScores s = scoreSegmentation(seg.labels, TissueLabels{}, readLabelImage(truth_path), TissueLabels{});
    nlohmann::json dice;
    std::printf("against %s: Dice", truth_path.c_str());
    for (const ClassScore& c : s.classes) {
      dice[c.name] = c.dice;
      std::printf(" %s %.3f", c.name.c_str(), c.dice);
    }
    std::printf("; chest-wall boundary mean %.2f mm, p95 %.2f mm, max %.2f mm\n", s.boundary.mean_mm, s.boundary.p95_mm,
                s.boundary.max_mm);
    j["truth"] = {{"path", truth_path},
                  {"dice", dice},
                  {"boundary_mean_mm", s.boundary.mean_mm},
                  {"boundary_p95_mm", s.boundary.p95_mm},
                  {"boundary_max_mm", s.boundary.max_mm}};
  }
  std::ofstream(json_path) << j.dump(2) << '\n';
  std::printf("wrote %s, %s, %s\n", out.c_str(), png.c_str(), json_path.c_str());
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "breast_sim_segment: %s\n", e.what());
  return 2;
}
