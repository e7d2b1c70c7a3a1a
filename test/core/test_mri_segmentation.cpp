// The prone MRI segmentation (mri/mri_segmentation.h) on synthetic T1 images of the VICTRE phantom
// whose contrast, bias, noise and blur differ from the image the defaults were set on; the chest-wall
// field the sliding stage builds from it; lesions; the settings map; and the errors.
#include <cmath>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <omp.h>
#include <yaml-cpp/yaml.h>

#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/segmentation_metrics.h"
#include "breast_sim/core/mri/synthetic_mri.h"
#include "breast_sim/core/sliding/chest_wall_surface.h"
#include "mri_test_images.h"
#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::messageOf;
using breast_sim::test::smallImageParams;
using breast_sim::test::TempDir;
using breast_sim::test::victreLps;

namespace {

// Centres of the faces between chest wall and breast tissue [m].
std::vector<Eigen::Vector3d> wallFaces(const LabelImage& l) {
  const TissueLabels map;
  std::vector<Eigen::Vector3d> out;
  for (int k = 0; k + 1 < l.size.z(); ++k)
    for (int j = 0; j + 1 < l.size.y(); ++j)
      for (int i = 0; i + 1 < l.size.x(); ++i)
        for (int a = 0; a < 3; ++a) {
          Eigen::Vector3i q(i, j, k);
          ++q[a];
          const TissueClass c0 = map.classify(l.at(i, j, k)), c1 = map.classify(l.at(q.x(), q.y(), q.z()));
          const bool wall0 = c0 == TissueClass::kChestWall, wall1 = c1 == TissueClass::kChestWall;
          const bool tissue0 = map.isTissue(l.at(i, j, k)), tissue1 = map.isTissue(l.at(q.x(), q.y(), q.z()));
          if ((wall0 && tissue1) || (wall1 && tissue0))
            out.push_back(l.indexToPhysical(0.5 * (Eigen::Vector3d(i, j, k) + q.cast<double>())));
        }
  return out;
}

// One image (seed 5) for the tests that are not about contrast, rendered once.
const SyntheticMri& sharedImage() {
  static const SyntheticMri mri = renderSyntheticT1(victreLps(), TissueLabels{}, smallImageParams(5));
  return mri;
}

}  // namespace

TEST(MriSegmentation, MeetsTheTargetsOnImagesItWasNotTunedOn) {
  // The defaults were set on the default image (seed 1); these differ in every knob.
  const std::vector<std::pair<std::string, std::function<void(SyntheticMriParams&)>>> variants = {
      {"dense gland, muscle brighter, strong bias, noisy",
       [](SyntheticMriParams& p) {
         p.signal.fibroglandular = 560, p.signal.muscle = 470, p.bias_amplitude = 0.45, p.noise_sigma = 40;
       }},
      {"faint gland, dark muscle, 2 mm blur, short bias wavelength, strong noise",
       [](SyntheticMriParams& p) {
         p.signal.fibroglandular = 320, p.signal.muscle = 240, p.blur_fwhm_mm = 2.0, p.bias_wavelength_mm = 120,
         p.bias_amplitude = 0.3, p.noise_sigma = 60;
       }},
      {"bright skin, little noise, sharp, no ribs",
       [](SyntheticMriParams& p) {
         p.signal.skin = 780, p.noise_sigma = 8, p.blur_fwhm_mm = 0.8, p.rib_radius_mm = 0, p.rib_cortex_mm = 0;
       }}};
  std::uint64_t seed = 11;
  for (const auto& [name, set] : variants) {
    SCOPED_TRACE(name);
    SyntheticMriParams p = smallImageParams(seed++);
    set(p);
    const SyntheticMri mri = renderSyntheticT1(victreLps(), TissueLabels{}, p);
    const MriSegmentation seg = segmentProneMri(mri.image);
    const SegmentationScores s = scoreSegmentation(seg.labels, TissueLabels{}, mri.truth, TissueLabels{});
    EXPECT_GE(s.score("breast").dice, 0.95);
    EXPECT_GE(s.score("chest_wall").dice, 0.95);
    EXPECT_GE(s.score("fat").dice, 0.9);
    EXPECT_LE(s.boundary.mean_mm, 1.5);
    EXPECT_LE(s.boundary.p95_mm, 3.0);
    EXPECT_GT(seg.report.boundary_coverage, 0.8);
  }
}

TEST(MriSegmentation, ItsChestWallGivesTheSlidingStageTheTruthsNormals) {
  const SyntheticMri& mri = sharedImage();
  const MriSegmentation seg = segmentProneMri(mri.image);
  const ChestWallSurface from_segmentation(seg.labels, {segmentationLabel(TissueClass::kChestWall)});
  const ChestWallSurface from_truth(mri.truth, TissueLabels{}.chest_wall);
  std::vector<double> angles, distances;
  for (const Eigen::Vector3d& p : wallFaces(mri.truth)) {
    const Eigen::Vector3d a = from_segmentation.normal(p), b = from_truth.normal(p);
    if (a.norm() < 0.5 || b.norm() < 0.5) continue;
    angles.push_back(std::acos(std::clamp(a.dot(b), -1.0, 1.0)) * 180.0 / M_PI);
    distances.push_back(std::abs(from_segmentation.signedDistance(p) - from_truth.signedDistance(p)));
  }
  ASSERT_GT(angles.size(), 1000u);
  std::sort(angles.begin(), angles.end());
  double mean_angle = 0, mean_distance = 0;
  for (double a : angles) mean_angle += a / angles.size();
  for (double d : distances) mean_distance += d / distances.size();
  EXPECT_LT(mean_angle, 5.0);
  EXPECT_LT(angles[static_cast<std::size_t>(0.95 * angles.size())], 15.0);
  EXPECT_LT(mean_distance, 0.5e-3);
  // The boundary is a smooth height field: neighbouring columns differ by less than two voxels.
  const ChestWallBoundary& b = seg.boundary;
  float jump = 0;
  for (int v = 0; v < b.size.y(); ++v)
    for (int u = 0; u + 1 < b.size.x(); ++u) jump = std::max(jump, std::abs(b.index[u + 1 + b.size.x() * v] - b.index[u + b.size.x() * v]));
  for (int v = 0; v + 1 < b.size.y(); ++v)
    for (int u = 0; u < b.size.x(); ++u) jump = std::max(jump, std::abs(b.index[u + b.size.x() * (v + 1)] - b.index[u + b.size.x() * v]));
  EXPECT_LT(jump, 2.0f);
  // One breast, its nipple at the VICTRE phantom's (README: (82.2, 0.1, −25.3) mm in its own axes).
  ASSERT_EQ(seg.report.nipples_m.size(), 1u);
  EXPECT_LT((seg.report.nipples_m[0] - victreToLpsRotation() * Eigen::Vector3d(82.2e-3, 0.1e-3, -25.3e-3)).norm(), 3e-3);
}

TEST(MriSegmentation, DoesNotDependOnTheThreadCount) {
  const SyntheticMri& mri = sharedImage();
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  const MriSegmentation one = segmentProneMri(mri.image);
  omp_set_num_threads(std::max(2, threads));
  const MriSegmentation many = segmentProneMri(mri.image);
  omp_set_num_threads(threads);
  EXPECT_EQ(one.labels.labels, many.labels.labels);
  EXPECT_EQ(one.boundary.index, many.boundary.index);
}

TEST(MriSegmentation, LesionsArePaintedIntoTheBreastAndOutsideOnesAreErrors) {
  const SyntheticMri& mri = sharedImage();
  // A point lesion deep in the breast (40 mm anterior of the wall, in LPS), radius 5 mm, and a lesion
  // label image on another grid (0.5 mm) holding a 4 mm sphere 25 mm to its left: both become lesion.
  LesionMarks marks;
  const Eigen::Vector3d centre(-0.010, -0.040, -0.010), other(0.015, -0.040, -0.010);
  marks.points.push_back({"L1", centre, 5e-3});
  LabelImage& li = marks.label_image;
  li = LabelImage(Eigen::Vector3i(40, 40, 40), Eigen::Vector3d::Constant(0.5e-3), other - Eigen::Vector3d::Constant(10e-3));
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 40; ++j)
      for (int i = 0; i < 40; ++i)
        if ((li.indexToPhysical(Eigen::Vector3d(i, j, k)) - other).norm() <= 4e-3) li.at(i, j, k) = 7;
  const MriSegmentation seg = segmentProneMri(mri.image, {}, marks);
  EXPECT_EQ(seg.labels.labelAt(centre), segmentationLabel(TissueClass::kLesion));
  EXPECT_EQ(seg.labels.labelAt(other), segmentationLabel(TissueClass::kLesion));
  long near_centre = 0, near_other = 0;
  for (int k = 0; k < seg.labels.size.z(); ++k)
    for (int j = 0; j < seg.labels.size.y(); ++j)
      for (int i = 0; i < seg.labels.size.x(); ++i) {
        if (seg.labels.at(i, j, k) != segmentationLabel(TissueClass::kLesion)) continue;
        const Eigen::Vector3d p = seg.labels.indexToPhysical(Eigen::Vector3d(i, j, k));
        near_centre += (p - centre).norm() < 6e-3;
        near_other += (p - other).norm() < 6e-3;
      }
  EXPECT_NEAR(near_centre * 1e-3, 4.0 / 3.0 * M_PI * 0.125, 0.06);  // 0.52 ml
  EXPECT_NEAR(near_other * 1e-3, 4.0 / 3.0 * M_PI * 0.064, 0.04);   // 0.27 ml
  // In the air in front of the breast, in the chest wall, outside the image.
  // (The messages do not depend on the bias correction: left out to save time.)
  SegmentationSettings quick;
  quick.bias_correction = false;
  for (const auto& [where, p] : {std::pair<std::string, Eigen::Vector3d>{"air", {0.040, -0.080, 0.045}},
                                 {"chest wall", {-0.010, 0.020, -0.010}}}) {
    LesionMarks bad;
    bad.points.push_back({"L9", p, 3e-3});
    const std::string m = messageOf([&] { segmentProneMri(mri.image, quick, bad); });
    EXPECT_NE(m.find("lesion L9 at"), std::string::npos) << m;
    EXPECT_NE(m.find("lies in the " + where + ", not in the breast"), std::string::npos) << m;
  }
  LesionMarks far;
  far.points.push_back({"L8", Eigen::Vector3d(1.0, 0, 0), 3e-3});
  EXPECT_NE(messageOf([&] { segmentProneMri(mri.image, quick, far); }).find("lies outside the image"), std::string::npos);
}

TEST(MriSegmentation, ImagesThatAreNoProneBreastMriAreClearErrors) {
  const SyntheticMri& mri = sharedImage();
  // Anterior taken the wrong way round: no chest wall behind the breast.
  SegmentationSettings upside_down;
  upside_down.prone_gravity_direction = Eigen::Vector3d(0, 1, 0);
  std::string m = messageOf([&] { segmentProneMri(mri.image, upside_down); });
  EXPECT_NE(m.find("no chest-wall boundary found in slices"), std::string::npos) << m;
  EXPECT_NE(m.find("is this a breast MRI in prone position"), std::string::npos) << m;
  // An image of noise alone.
  ScalarImage noise = mri.image;
  for (std::size_t v = 0; v < noise.values.size(); ++v) noise.values[v] = static_cast<float>(20 + (v * 7919) % 13);
  m = messageOf([&] { segmentProneMri(noise); });
  EXPECT_TRUE(m.find("no breast tissue found") != std::string::npos || m.find("no chest-wall boundary") != std::string::npos) << m;
  // A grid whose axes are all 45 degrees or more from anterior.
  ScalarImage oblique = mri.image;
  const double a = M_PI / 4;
  Eigen::Matrix3d r;
  r << 1, 0, 0, 0, std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a);
  Eigen::Matrix3d q;
  q << std::cos(0.3), -std::sin(0.3), 0, std::sin(0.3), std::cos(0.3), 0, 0, 0, 1;
  oblique.geometry.direction = q * r;
  m = messageOf([&] { segmentProneMri(oblique); });
  EXPECT_NE(m.find("no grid axis of the image is within 45 deg of the anterior direction"), std::string::npos) << m;
}

TEST(SegmentationSettings, TheDocumentedMapHoldsEveryKeyWithTheCodesDefault) {
  // docs/mri.md lists the `segmentation:` map with every key at its default.
  std::ifstream in(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../docs/mri.md");
  std::stringstream doc;
  doc << in.rdbuf();
  const std::string text = doc.str();
  const std::size_t start = text.find("```yaml\nsegmentation:\n");
  ASSERT_NE(start, std::string::npos) << "docs/mri.md has no ```yaml block starting with segmentation:";
  const std::size_t end = text.find("```", start + 8);
  ASSERT_NE(end, std::string::npos);
  const std::string block = text.substr(start + 8, end - start - 8);
  TempDir dir("breast_sim_segmentation_doc");
  const SegmentationSettings documented = loadSegmentationSettings(dir.write("doc.yaml", block));
  const SegmentationSettings code;
  EXPECT_EQ(documented.prone_gravity_direction, code.prone_gravity_direction);
  EXPECT_EQ(documented.bias_correction, code.bias_correction);
  EXPECT_EQ(documented.n4_shrink_factor, code.n4_shrink_factor);
  EXPECT_EQ(documented.n4_fitting_levels, code.n4_fitting_levels);
  EXPECT_EQ(documented.n4_iterations, code.n4_iterations);
  EXPECT_EQ(documented.n4_spline_distance_mm, code.n4_spline_distance_mm);
  EXPECT_EQ(documented.smoothing_sigma_mm, code.smoothing_sigma_mm);
  EXPECT_EQ(documented.body_threshold, code.body_threshold);
  EXPECT_EQ(documented.body_noise_margin, code.body_noise_margin);
  EXPECT_EQ(documented.min_fat_component_share, code.min_fat_component_share);
  EXPECT_EQ(documented.chest_wall_min_thickness_mm, code.chest_wall_min_thickness_mm);
  EXPECT_EQ(documented.boundary_median_window_mm, code.boundary_median_window_mm);
  EXPECT_EQ(documented.boundary_smoothing_mm, code.boundary_smoothing_mm);
  EXPECT_EQ(documented.boundary_outlier_mm, code.boundary_outlier_mm);
  EXPECT_EQ(documented.min_boundary_coverage, code.min_boundary_coverage);
  EXPECT_EQ(documented.min_component_share, code.min_component_share);
  EXPECT_EQ(documented.skin_thickness_mm, code.skin_thickness_mm);
  // Every key the reader takes is in the block (the reader refuses any other).
  EXPECT_EQ(YAML::Load(block)["segmentation"].size(), 17u);
}

TEST(SegmentationSettings, TheCaseFileMapIsReadAndCheckedKeyByKey) {
  TempDir dir("breast_sim_segmentation_settings");
  const std::string path = dir.write("case.yaml",
                                     "segmentation:\n  body_threshold: 0.25\n  boundary_smoothing_mm: 4\n  skin_thickness_mm: 1.5\n"
                                     "  prone_gravity_direction: [1, 0, 0]\n  bias_correction: false\n"
                                     "lesions:\n  - {name: A, position_mm: [1, 2, 3], radius_mm: 4}\n");
  const SegmentationSettings s = loadSegmentationSettings(path);
  EXPECT_EQ(s.body_threshold, 0.25);
  EXPECT_EQ(s.boundary_smoothing_mm, 4.0);
  EXPECT_EQ(s.skin_thickness_mm, 1.5);
  EXPECT_EQ(s.prone_gravity_direction, Eigen::Vector3d(1, 0, 0));
  EXPECT_FALSE(s.bias_correction);
  EXPECT_EQ(s.n4_iterations, SegmentationSettings{}.n4_iterations);
  const std::vector<Lesion> lesions = loadCaseLesions(path);
  ASSERT_EQ(lesions.size(), 1u);
  EXPECT_EQ(lesions[0].name, "A");
  EXPECT_NEAR((lesions[0].position_m - Eigen::Vector3d(1e-3, 2e-3, 3e-3)).norm(), 0.0, 1e-12);
  EXPECT_NEAR(lesions[0].radius_m, 4e-3, 1e-12);
  // Without the map: the defaults.
  EXPECT_EQ(loadSegmentationSettings(dir.write("plain.yaml", "image: {path: x.nrrd}\n")).body_threshold,
            SegmentationSettings{}.body_threshold);
  std::string m = messageOf([&] { loadSegmentationSettings(dir.write("typo.yaml", "segmentation:\n  body_treshold: 0.3\n")); });
  EXPECT_NE(m.find("body_treshold"), std::string::npos) << m;
  m = messageOf([&] { loadSegmentationSettings(dir.write("range.yaml", "segmentation:\n  body_threshold: 1.5\n")); });
  EXPECT_NE(m.find("segmentation.body_threshold"), std::string::npos) << m;
  EXPECT_NE(m.find("(0, 1)"), std::string::npos) << m;
  m = messageOf<std::invalid_argument>([] {
    SegmentationSettings bad;
    bad.boundary_outlier_mm = 0;
    bad.validate();
  });
  EXPECT_NE(m.find("segmentation.boundary_outlier_mm = 0"), std::string::npos) << m;
}
