#pragma once
/// @file mri_segmentation.h
/// Automatic segmentation of a T1-weighted prone breast MRI into the labels the mesher takes: air,
/// fat, fibroglandular tissue, skin (optional), lesion (from the user) and the chest wall: the
/// pectoral muscle and everything posterior to its anterior boundary (seed section 2.1: deformable
/// against fixed tissue, after [WFFH11]: L. Wang, K. Filippatos, O. Friman, H. Hahn, "Fully automated
/// segmentation of the pectoralis muscle boundary in breast MR images", SPIE Medical Imaging 2011).
///
/// How (every threshold and size is a SegmentationSettings field):
///  1. N4 bias correction [Tustison 2010] (ITK) on the image shrunk by n4_shrink_factor, within its
///     voxels above Otsu's threshold; a light Gaussian smoothing against noise.
///  2. The fat level F: the median of the voxels brighter than 0.6 × the 99.5th percentile (fat is the
///     brightest tissue of a T1 breast image). Body: voxels ≥ body_threshold × F, and at least
///     body_noise_margin spreads above the background's noise (its most frequent value below that,
///     the spread from the values below it). Fat against dense tissue: Otsu's threshold (ITK) within
///     the body.
///  3. Breast fat: the connected components (ITK) of the fat mask with at least
///     min_fat_component_share of the largest's voxels. Fat behind the chest wall (rib marrow) is not
///     connected to it.
///  4. The chest-wall boundary as a height field over the coronal plane: along each column of the grid
///     axis nearest the anterior direction, from anterior to posterior, the first voxel after the
///     column's last breast fat where a run of body voxels without breast fat at least
///     chest_wall_min_thickness_mm deep begins; placed at sub-voxel precision where the intensity
///     crosses the fat threshold (or, after air, the body threshold). Columns where dense tissue lies
///     directly on the muscle give a boundary too far anterior: a robust smooth fit (a median over
///     boundary_median_window_mm, then Gaussian normalized convolution of boundary_smoothing_mm with
///     candidates farther than boundary_outlier_mm from the fit rejected, three times) removes them and
///     fills columns without a candidate. The fitted surface is smooth (a Gaussian-smoothed height
///     field), so the sliding stage's normal field (sliding/chest_wall_surface.h) sees no voxel steps
///     beyond the label image's own.
///  5. Labels: posterior of the surface: chest wall; anterior: the body (holes filled, components of at
///     least min_component_share of the largest kept) split into fat and fibroglandular tissue by
///     Otsu's threshold within it (a voxel on the body's surface, darkened by partial volume with the
///     air, is fat unless all the tissue behind it is dense); the outer skin_thickness_mm of the body
///     is skin; lesions painted last.
/// \note Assumes a T1-weighted image without fat suppression (fat brightest), prone (the breasts hang
/// anterior of the chest wall, along prone_gravity_direction), with the chest wall within the field of
/// view. Not supported: fat-suppressed or subtraction images, supine images.

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/model/point_embedding.h"  // Lesion
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// Every threshold and size of the segmentation; the case file's `segmentation:` map (lengths in mm).
struct SegmentationSettings {
  /// Chest wall → nipple in the image's patient space (anterior in LPS); the boundary is searched
  /// along the grid axis nearest it, which must be within 45°.
  Eigen::Vector3d prone_gravity_direction{0.0, -1.0, 0.0};
  bool bias_correction = true;          ///< N4 before anything else
  int n4_shrink_factor = 4;             ///< N4 works on the image shrunk by this per axis, in [1, 16]
  int n4_fitting_levels = 3;            ///< B-spline levels, in [1, 8]
  int n4_iterations = 50;               ///< iterations per level at most, in [1, 1000]
  double n4_spline_distance_mm = 100.0; ///< control-point spacing of the first level [mm], in [10, 1000]
  double smoothing_sigma_mm = 0.6;      ///< Gaussian against noise before the thresholds [mm]; 0 = none
  double body_threshold = 0.2;          ///< body: voxels ≥ this × the fat level, in (0, 1) ...
  /// ... and at least this many spreads of the background's noise above its level, in [0, 100]
  double body_noise_margin = 6.0;
  double min_fat_component_share = 0.1; ///< fat components of at least this share of the largest are breast fat
  double chest_wall_min_thickness_mm = 5.0;  ///< a chest wall is at least this deep behind the breast [mm]
  double boundary_median_window_mm = 30.0;   ///< robust first fit: median over this square of columns [mm]
  double boundary_smoothing_mm = 3.0;   ///< σ of the boundary's Gaussian fit over the coronal plane [mm], > 0
  double boundary_outlier_mm = 3.0;     ///< candidates farther than this from the fit are rejected [mm]
  double min_boundary_coverage = 0.5;   ///< share of the breast's columns that must give a boundary, in [0, 1]
  double min_component_share = 0.05;    ///< body components anterior of the wall of at least this share of the largest are kept
  double skin_thickness_mm = 0.0;       ///< outer layer of the body labelled skin [mm]; 0 = no skin class
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Reads the `segmentation:` map of a case file (absent keys keep the defaults; an absent map gives
/// the defaults). Keys are the field names above.
/// @throws std::runtime_error naming the file, the key and what is expected.
SegmentationSettings loadSegmentationSettings(const std::string& yaml_path);

/// The `lesions:` list of a case file ({name, position_mm: [x, y, z], radius_mm}, patient space, mm),
/// without reading its tissue source; empty when the file has none.
/// @throws std::runtime_error naming the file, the key and what is expected.
std::vector<Lesion> loadCaseLesions(const std::string& yaml_path);

/// Lesions to paint into the segmentation (the intensity image does not show them reliably).
struct LesionMarks {
  /// Points in the image's patient space [m]; a sphere of radius_m is painted (radius 0: only checked).
  std::vector<Lesion> points;
  /// A label image of the user's (any grid in the same patient space): its non-zero voxels are lesion,
  /// taken by nearest neighbour at each voxel centre. Empty (size 0) = none.
  LabelImage label_image;
};

/// The chest-wall boundary as a height field along one grid axis (the anterior-posterior one).
struct ChestWallBoundary {
  int axis = 1;              ///< the grid axis the columns run along
  /// +1: the index along `axis` increases anteriorly; −1: posteriorly.
  int anterior_sign = -1;
  int u_axis = 0, v_axis = 2;  ///< the two other grid axes (u < v)
  Eigen::Vector2i size{0, 0};  ///< columns along u, v
  /// Per column (u fastest): the boundary's continuous index along `axis`; voxels posterior of it are
  /// chest wall.
  std::vector<float> index;
  /// Per column: 1 where the column gave an accepted candidate, 0 where the fit filled it in.
  std::vector<std::uint8_t> measured;
  /// Whether the voxel (i, j, k) lies posterior of the boundary.
  bool posterior(const Eigen::Vector3i& ijk) const;
};

/// What the segmentation found and how long it took.
struct SegmentationReport {
  double fat_level = 0.0;         ///< F, in bias-corrected image units
  double body_threshold = 0.0;    ///< absolute, same units
  double noise_level = 0.0;       ///< the background's most frequent value (air, lung), same units
  double noise_spread = 0.0;      ///< the spread of the background below that level, same units
  double fat_threshold = 0.0;     ///< Otsu within the breast, same units
  double bias_min = 1.0, bias_max = 1.0;  ///< range of the estimated bias field within the body
  int breast_columns = 0;         ///< columns holding breast fat
  int measured_columns = 0;       ///< of those, with an accepted boundary candidate
  int rejected_candidates = 0;    ///< candidates the robust fit rejected
  double boundary_coverage = 0.0; ///< measured / breast columns
  double volume_ml[6] = {0, 0, 0, 0, 0, 0};  ///< per TissueClass (air, fat, fibroglandular, skin, lesion, chest wall)
  /// Per breast (body piece anterior of the wall, largest first): its nipple, the centroid of its voxels
  /// within 2 mm of its most anterior one (the apex of a prone, pendant breast) [m].
  std::vector<Eigen::Vector3d> nipples_m;
  double seconds_bias = 0, seconds_tissue = 0, seconds_boundary = 0, seconds_labels = 0, seconds_total = 0;
};

struct MriSegmentation {
  /// Labels on the image's grid with the default label values (TissueLabels' first values: air 0,
  /// fat 1, fibroglandular 29, skin 2, lesion 200, chest wall 40), so a case's `image:` map reads it
  /// with its defaults.
  LabelImage labels;
  ChestWallBoundary boundary;
  SegmentationReport report;
};

/// Segments a prone T1 breast MRI (see the file comment).
/// @throws std::invalid_argument for invalid settings or image; std::runtime_error naming what failed:
///         no bright (fat) tissue, an image axis more than 45° from the anterior direction, too few
///         columns with a chest-wall boundary (names the slices: "no chest-wall boundary found in
///         slices 40–80 …: is this a breast MRI in prone position?"), a lesion outside the breast.
MriSegmentation segmentProneMri(const ScalarImage& image, const SegmentationSettings& settings = {},
                                const LesionMarks& lesions = {});

/// The label value the segmentation writes for each tissue class (air, fat, fibroglandular, skin,
/// lesion, chest wall).
std::uint16_t segmentationLabel(TissueClass c);

}  // namespace breast_sim::core
