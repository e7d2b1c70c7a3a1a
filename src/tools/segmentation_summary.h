#pragma once
// The summary of an MRI segmentation as breast_sim_segment prints it and both it and breast_sim_run
// write it (JSON): the input, the levels, the chest wall's coverage, volumes per class, the nipples, the
// seconds per stage and, against a ground truth, the Dice per class and the boundary distances.
#include <cstdio>
#include <string>

#include <nlohmann/json.hpp>

#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/segmentation_metrics.h"

namespace breast_sim::tools {

/// The summary as JSON: input (path, format, series UID, size, spacing [mm], read seconds), volumes per
/// class [ml], levels, nipples [mm], the chest wall's coverage, seconds per stage and, with `scores`,
/// `truth` (path, Dice per class, boundary mean / p95 / max [mm]).
inline nlohmann::json segmentationJson(const core::MriVolume& mri, const core::MriSegmentation& seg, double read_seconds,
                                       const core::SegmentationScores* scores, const std::string& truth_path) {
  const core::ImageGeometry& g = mri.image.geometry;
  const core::SegmentationReport& r = seg.report;
  nlohmann::json j;
  j["input"] = {{"path", mri.info.path},
                {"format", mri.info.format},
                {"series_uid", mri.info.series_uid},
                {"size", {g.size.x(), g.size.y(), g.size.z()}},
                {"spacing_mm", {1e3 * g.spacing_m.x(), 1e3 * g.spacing_m.y(), 1e3 * g.spacing_m.z()}},
                {"read_seconds", read_seconds}};
  const char* names[6] = {"air", "fat", "fibroglandular", "skin", "lesion", "chest_wall"};
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
  if (scores) {
    nlohmann::json dice;
    for (const core::ClassScore& c : scores->classes) dice[c.name] = c.dice;
    j["truth"] = {{"path", truth_path},
                  {"dice", dice},
                  {"boundary_mean_mm", scores->boundary.mean_mm},
                  {"boundary_p95_mm", scores->boundary.p95_mm},
                  {"boundary_max_mm", scores->boundary.max_mm}};
  }
  return j;
}

/// The scores in one line: "Dice breast 0.985 fat 0.966 ...; chest-wall boundary mean 0.28 mm, p95 1.58 mm, max 7.00 mm".
inline std::string scoresLine(const core::SegmentationScores& scores) {
  std::string line = "Dice";
  char buf[96];
  for (const core::ClassScore& c : scores.classes) {
    std::snprintf(buf, sizeof buf, " %s %.3f", c.name.c_str(), c.dice);
    line += buf;
  }
  std::snprintf(buf, sizeof buf, "; chest-wall boundary mean %.2f mm, p95 %.2f mm, max %.2f mm", scores.boundary.mean_mm,
                scores.boundary.p95_mm, scores.boundary.max_mm);
  return line + buf;
}

/// Prints the summary: the input, the segmentation's levels and seconds, the chest wall, the volumes,
/// the nipples and, with `scores`, the Dice and the boundary distances against `truth_path`.
inline void printSegmentationSummary(const core::MriVolume& mri, const core::MriSegmentation& seg, double read_seconds,
                                     const core::SegmentationScores* scores, const std::string& truth_path) {
  const core::ImageGeometry& g = mri.image.geometry;
  const core::SegmentationReport& r = seg.report;
  std::printf("%s (%s%s): %d x %d x %d voxels of %.2f x %.2f x %.2f mm, read in %.2f s\n", mri.info.path.c_str(),
              mri.info.format.c_str(), mri.info.series_uid.empty() ? "" : (", series " + mri.info.series_uid).c_str(),
              g.size.x(), g.size.y(), g.size.z(), 1e3 * g.spacing_m.x(), 1e3 * g.spacing_m.y(), 1e3 * g.spacing_m.z(),
              read_seconds);
  std::printf("segmented in %.2f s (bias %.2f, tissue %.2f, chest wall %.2f, labels %.2f): fat level %.0f, background %.0f "
              "+- %.0f, body threshold %.0f, fat threshold %.0f, bias field %.2f-%.2f\n",
              r.seconds_total, r.seconds_bias, r.seconds_tissue, r.seconds_boundary, r.seconds_labels, r.fat_level,
              r.noise_level, r.noise_spread, r.body_threshold, r.fat_threshold, r.bias_min, r.bias_max);
  std::printf("chest wall: %d of %d breast columns measured (%.0f %%), %d candidates rejected by the fit\n", r.measured_columns,
              r.breast_columns, 100.0 * r.boundary_coverage, r.rejected_candidates);
  std::printf("volumes [ml]: fat %.1f, fibroglandular %.1f, skin %.1f, lesion %.1f, chest wall %.1f\n", r.volume_ml[1],
              r.volume_ml[2], r.volume_ml[3], r.volume_ml[4], r.volume_ml[5]);
  std::string nipples;
  for (const Eigen::Vector3d& n : r.nipples_m) {
    char buf[96];
    std::snprintf(buf, sizeof buf, "%s[%.1f, %.1f, %.1f]", nipples.empty() ? "" : ", ", 1e3 * n.x(), 1e3 * n.y(), 1e3 * n.z());
    nipples += buf;
  }
  std::printf("nipples (the apex of each breast) [mm]: %s\n", nipples.c_str());
  if (scores) std::printf("against %s: %s\n", truth_path.c_str(), scoresLine(*scores).c_str());
}

}  // namespace breast_sim::tools
