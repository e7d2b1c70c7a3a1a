#pragma once
/// @file mri_cross_sections.h
/// Orthogonal cross-sections of MRI volumes, with label maps outlined, drawn to one PNG with OpenCV:
/// what a reader checks first after a segmentation (does the outline follow the tissue, is the chest
/// wall where the muscle is) or a simulated supine MRI (beside the prone one).
///
/// One row per volume, columns axial | coronal | sagittal, cut by the same patient-space planes in every
/// row. Views follow radiological convention for LPS, as render/cross_section.h: axial (z = const) and
/// coronal (y = const) show the patient's left on the image's right, sagittal (x = const) anterior on
/// the left; superior is up, anterior up in the axial view. Intensities are trilinear, grey between the
/// 1st and 99.5th percentile of the row's volume; labels are taken by nearest neighbour and each
/// class's border is drawn in its colour (fat yellow, fibroglandular magenta, skin orange, lesion red,
/// chest wall cyan).

#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// One row of the figure.
struct MriSectionRow {
  std::string title;                     ///< e.g. "prone T1 (input)"
  const ScalarImage* image = nullptr;    ///< the volume (required)
  const LabelImage* labels = nullptr;    ///< outlined when given (any grid in the same patient space)
  TissueLabels label_map;                ///< which label values are which class (default: the defaults)
};

struct MriSectionOptions {
  double pixel_size_m = 0.5e-3;  ///< [m] per pixel, > 0
  /// The three planes pass through this point [m]; NaN components = the centre of the first row's
  /// labelled tissue (non-air, non-chest-wall), or of its volume when it has no labels.
  Eigen::Vector3d centre_m = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
};

/// Writes the PNG (the union of the rows' extents per view, at one scale), with titles, the plane
/// positions in mm and a 1 cm scale bar.
/// @throws std::invalid_argument for no rows, a row without image, an invalid image or a pixel size
///         giving more than 4096 pixels per panel side; std::runtime_error if the file cannot be written.
void writeMriCrossSections(const std::string& png_path, const std::vector<MriSectionRow>& rows,
                           const MriSectionOptions& options = {});

}  // namespace breast_sim::core
