// The `mri:` case (mri/mri_case.h): the map's keys, reading and segmenting the MRI, the simulated
// breast side, the lesions of a lesion label image, the score against a truth, the supine MRI.
#include "breast_sim/core/mri/mri_case.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <stdexcept>

#include "../util/yaml_fields.h"
#include "grid_conversion.h"
#include "itk_bridge.h"
#include "label_lookup.h"

namespace breast_sim::core {
namespace {

using namespace yaml_fields;

std::string mm(double metres) {
  char b[32];
  std::snprintf(b, sizeof b, "%.1f mm", metres * 1e3);
  return b;
}

/// The lesions of the lesion label image: voxels of the MRI grid that the label image marks and the
/// segmentation painted as lesion, one lesion per connected piece of one label value.
std::vector<Lesion> lesionsOfLabelImage(const LabelImage& lesion_image, const LabelImage& labels) {
  const ImageGeometry g = ImageGeometry::of(labels);
  const std::uint16_t l_lesion = segmentationLabel(TissueClass::kLesion);
  const LabelLookup value_at(lesion_image);
  const long n = static_cast<long>(labels.labels.size());
  std::vector<std::uint16_t> value(static_cast<std::size_t>(n), 0);
  std::map<std::uint16_t, long> values;
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) {
        const long v = g.index(i, j, k);
        if (labels.labels[v] != l_lesion) continue;
        value[v] = value_at(g.indexToPhysical(Eigen::Vector3d(i, j, k)));
        if (value[v] != 0) ++values[value[v]];
      }
  std::vector<Lesion> out;
  const itk_bridge::Grid grid = bridgeGrid(g);
  const double voxel_m3 = g.spacing_m.prod();
  for (const auto& [label, count] : values) {
    std::vector<std::uint8_t> mask(static_cast<std::size_t>(n));
    for (long v = 0; v < n; ++v) mask[v] = value[v] == label;
    std::vector<long> sizes;
    const std::vector<std::int32_t> piece = itk_bridge::connectedComponents(grid, mask, false, &sizes);
    std::vector<Eigen::Vector3d> sum(sizes.size(), Eigen::Vector3d::Zero());
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const std::int32_t c = piece[g.index(i, j, k)];
          if (c > 0) sum[c - 1] += g.indexToPhysical(Eigen::Vector3d(i, j, k));
        }
    for (std::size_t c = 0; c < sizes.size(); ++c) {
      Lesion l;
      l.name = "label_" + std::to_string(label) + (sizes.size() > 1 ? "_" + std::to_string(c + 1) : "");
      l.position_m = sum[c] / static_cast<double>(sizes[c]);
      l.radius_m = std::cbrt(3.0 * static_cast<double>(sizes[c]) * voxel_m3 / (4.0 * M_PI));
      out.push_back(l);
    }
  }
  return out;
}

}  // namespace

const char* breastsName(MriCaseSource::Breasts b) {
  switch (b) {
    case MriCaseSource::Breasts::kLeft: return "left";
    case MriCaseSource::Breasts::kRight: return "right";
    default: return "both";
  }
}

MriCaseSource loadMriCaseSource(const std::string& yaml_path) {
  const YAML::Node root = loadFile(yaml_path);
  if (!root.IsMap() || !root["mri"]) fail(yaml_path, "mri", "missing: this is not an MRI case");
  const YAML::Node m = root["mri"];
  if (!m.IsMap()) fail(yaml_path, "mri", "expected a map {path, series_uid, breasts, midline_x_mm, lesion_labels, truth}");
  checkKeys(m, {"path", "series_uid", "breasts", "midline_x_mm", "lesion_labels", "truth"}, yaml_path, "mri");
  MriCaseSource s;
  if (!m["path"]) fail(yaml_path, "mri.path", "missing: give the prone MRI (NIfTI, NRRD, MetaImage or a DICOM folder)");
  s.path = pathBeside(yaml_path, text(m["path"], yaml_path, "mri.path"));
  if (s.path.empty()) fail(yaml_path, "mri.path", "empty: give the prone MRI (NIfTI, NRRD, MetaImage or a DICOM folder)");
  if (m["series_uid"]) s.series_uid = text(m["series_uid"], yaml_path, "mri.series_uid");
  if (m["breasts"]) {
    const std::string b = choice(m["breasts"], yaml_path, "mri.breasts", {"both", "left", "right"});
    s.breasts = b == "left" ? MriCaseSource::Breasts::kLeft : b == "right" ? MriCaseSource::Breasts::kRight
                                                                          : MriCaseSource::Breasts::kBoth;
  }
  if (m["midline_x_mm"] && !(m["midline_x_mm"].IsScalar() && m["midline_x_mm"].as<std::string>() == "auto"))
    s.midline_x_m = 1e-3 * numberIn(m["midline_x_mm"], yaml_path, "mri.midline_x_mm", -1e4, 1e4, false, false,
                                    "mm (or auto: midway between the two breasts' nipples)");
  if (m["lesion_labels"])
    s.lesion_labels = pathBeside(yaml_path, text(m["lesion_labels"], yaml_path, "mri.lesion_labels"));
  if (m["truth"]) s.truth = pathBeside(yaml_path, text(m["truth"], yaml_path, "mri.truth"));
  return s;
}

MriCase loadMriCase(const std::string& yaml_path, const std::function<void(const std::string&)>& stage) {
  MriCase c;
  c.source = loadMriCaseSource(yaml_path);
  c.settings = loadSegmentationSettings(yaml_path);
  LesionMarks marks;
  marks.points = loadCaseLesions(yaml_path);
  const MriCaseSource& s = c.source;
  if (!s.lesion_labels.empty()) {
    try {
      marks.label_image = readLabelImage(s.lesion_labels);
    } catch (const std::exception& e) {
      fail(yaml_path, "mri.lesion_labels", e.what());
    }
  }
  const auto t0 = std::chrono::steady_clock::now();
  try {
    MriReadOptions read;
    read.series_uid = s.series_uid;
    c.volume = readMriVolume(s.path, read);
  } catch (const std::exception& e) {
    fail(yaml_path, "mri.path", e.what());
  }
  c.read_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (stage) stage("segmentation");
  try {
    c.segmentation = segmentProneMri(c.volume.image, c.settings, marks);
  } catch (const std::exception& e) {
    fail(yaml_path, "mri", s.path + ": " + e.what());
  }
  if (!s.truth.empty()) {
    LabelImage truth;
    try {
      truth = readLabelImage(s.truth);
    } catch (const std::exception& e) {
      fail(yaml_path, "mri.truth", e.what());
    }
    try {
      c.scores = scoreSegmentation(c.segmentation.labels, TissueLabels{}, truth, TissueLabels{});
    } catch (const std::exception& e) {
      fail(yaml_path, "mri.truth", s.truth + ": " + e.what() + "; the truth must be a label image on the MRI's grid");
    }
  }

  // The simulated breast(s): the other side of the midplane is held as chest wall.
  c.labels = c.segmentation.labels;
  const std::vector<Eigen::Vector3d>& found = c.segmentation.report.nipples_m;
  c.nipples_m = found;
  if (s.breasts != MriCaseSource::Breasts::kBoth) {
    const std::string side = breastsName(s.breasts);
    const double sign = s.breasts == MriCaseSource::Breasts::kLeft ? 1.0 : -1.0;  // LPS: +x is the patient's left
    c.midline_x_m = s.midline_x_m;
    if (std::isnan(c.midline_x_m)) {
      if (found.size() < 2)
        fail(yaml_path, "mri.breasts",
             side + ": the segmentation of " + s.path + " found " + std::to_string(found.size()) +
                 " breast, so the midline between two breasts is unknown; give mri.midline_x_mm (the x of the "
                 "patient's sagittal midplane, LPS mm) or breasts: both");
      c.midline_x_m = 0.5 * (found[0].x() + found[1].x());
    }
    const auto kept = [&](const Eigen::Vector3d& p) { return sign * (p.x() - c.midline_x_m) > 0.0; };
    const ImageGeometry g = ImageGeometry::of(c.labels);
    const TissueLabels defaults;
    const std::uint16_t l_wall = segmentationLabel(TissueClass::kChestWall);
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          std::uint16_t& l = c.labels.labels[g.index(i, j, k)];
          if (defaults.isTissue(l) && !kept(g.indexToPhysical(Eigen::Vector3d(i, j, k)))) l = l_wall;
        }
    c.nipples_m.clear();
    for (const Eigen::Vector3d& n : found)
      if (kept(n)) c.nipples_m.push_back(n);
    if (c.nipples_m.empty())
      fail(yaml_path, "mri.breasts",
           side + ": no breast of " + s.path + " lies on the patient's " + side + " of the midline x = " + mm(c.midline_x_m) +
               " (LPS: the patient's left is +x); choose the other side, breasts: both, or mri.midline_x_mm");
    for (const Lesion& l : marks.points)
      if (!kept(l.position_m))
        fail(yaml_path, "lesions",
             "lesion " + l.name + " at x = " + mm(l.position_m.x()) + " lies in the breast the case does not simulate "
             "(mri.breasts: " + side + ", midline x = " + mm(c.midline_x_m) + "); simulate breasts: both or the other side");
  }
  if (marks.label_image.size.prod() > 0) {
    c.image_lesions = lesionsOfLabelImage(marks.label_image, c.labels);
    if (c.image_lesions.empty())
      fail(yaml_path, "mri.lesion_labels",
           "its lesions lie in the breast the case does not simulate (mri.breasts: " + std::string(breastsName(s.breasts)) +
               "); simulate breasts: both or the other side");
  }
  return c;
}

ModelCase loadModelCaseWithMri(const std::string& yaml_path, const std::function<void(const std::string&)>& stage) {
  ModelCase c = loadModelCase(yaml_path, stage, [&](const std::string& file, ModelCase& m) {
    auto mri = std::make_shared<MriCase>(loadMriCase(file, stage));
    m.image = mri->labels;
    m.nipples_m = mri->nipples_m;
    m.prone_gravity_direction = mri->settings.prone_gravity_direction.normalized();
    m.mri = std::move(mri);
  });
  // The lesion label image's lesions follow the listed ones.
  if (c.mri) c.lesions.insert(c.lesions.end(), c.mri->image_lesions.begin(), c.mri->image_lesions.end());
  return c;
}

SupineImages simulatedSupineMri(const MriCase& mri, const TetMesh& rest_mesh, const Points& displacement,
                                const SupineResampleOptions& options) {
  if (displacement.rows() != rest_mesh.numNodes())
    throw std::invalid_argument("simulatedSupineMri: " + std::to_string(displacement.rows()) + " displacements for " +
                                std::to_string(rest_mesh.numNodes()) + " nodes");
  const Points deformed = rest_mesh.nodes() + displacement;
  const ImageGeometry grid = supineGrid(mri.volume.image.geometry, deformed, options);
  return resampleToSupine(rest_mesh, displacement, &mri.volume.image, &mri.labels, grid, options);
}

}  // namespace breast_sim::core
