#pragma once
/// @file mri_case.h
/// A case that starts from a patient's prone T1 MRI (the case file's `mri:` map): the MRI is read
/// (mri_volume.h), segmented into the labels the mesher takes (mri_segmentation.h, the `segmentation:`
/// map) with the case's lesions painted in, optionally scored against a ground truth, and, when one
/// breast of two is simulated, the other held as chest wall. loadModelCase (model/model_case.h) turns
/// it into a ModelCase whose image is these labels; after a run, simulatedSupineMri resamples the
/// prone MRI into the deformed model (seed Figure 4e).
///
/// Patient space is the MRI's, LPS (x towards the patient's left, y posterior, z superior); lengths
/// in metres inside, in millimetres in the case file.

#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/point_embedding.h"  // Lesion
#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/segmentation_metrics.h"
#include "breast_sim/core/mri/supine_resampling.h"

namespace breast_sim::core {

/// The `mri:` map of a case file (paths absolute, nothing read yet).
struct MriCaseSource {
  std::string path;        ///< the prone MRI: a NIfTI, NRRD or MetaImage file, or a DICOM folder (or one file of the series)
  std::string series_uid;  ///< DICOM: the series to read when the folder holds several; "" = the folder's only series
  /// Which breast is simulated: both (every breast the segmentation finds), or the patient's left
  /// (+x of the midline) or right; the other side of the sagittal midplane is held as chest wall.
  enum class Breasts { kBoth, kLeft, kRight };
  Breasts breasts = Breasts::kBoth;
  /// x of the sagittal midplane [m] (LPS) for breasts left or right; NaN = midway between the nipples
  /// of the two largest breasts the segmentation finds.
  double midline_x_m = std::numeric_limits<double>::quiet_NaN();
  std::string lesion_labels;  ///< a label image of the lesions (non-zero voxels, any grid in the MRI's space); "" = none
  std::string truth;          ///< a ground-truth label image on the MRI's grid (default label values); "" = none
};

/// "both", "left" or "right".
const char* breastsName(MriCaseSource::Breasts b);

/// Reads the `mri:` map of a case file (relative paths against the file's folder), without reading
/// any image. Keys: path (required), series_uid, breasts, midline_x_mm (a number or `auto`),
/// lesion_labels, truth.
/// @throws std::runtime_error naming the file, the key and what is expected.
MriCaseSource loadMriCaseSource(const std::string& yaml_path);

/// An MRI case read and segmented.
struct MriCase {
  MriCaseSource source;
  SegmentationSettings settings;  ///< the case's `segmentation:` map
  MriVolume volume;               ///< the prone MRI as read
  MriSegmentation segmentation;   ///< the segmentation of the whole image (lesions painted)
  /// The model's labels on the MRI's grid (segmentationLabel values): the segmentation, and for one
  /// breast of two the other side's tissue turned into chest wall.
  LabelImage labels;
  std::vector<Eigen::Vector3d> nipples_m;  ///< the nipples of the simulated breast(s) [m]
  double midline_x_m = std::numeric_limits<double>::quiet_NaN();  ///< the midplane used (left or right) [m]
  /// The lesions of the lesion label image: each connected piece (6-neighbours) of one label value
  /// within the breast, at its centroid with the radius of a sphere of its volume; named
  /// "label_<value>", or "label_<value>_<k>" when the value has several pieces (largest first).
  std::vector<Lesion> image_lesions;
  std::optional<SegmentationScores> scores;  ///< against `truth`, when given
  double read_seconds = 0.0;                 ///< reading the MRI [s]
};

/// Reads and segments the MRI case of a case file: the `mri:` and `segmentation:` maps and the
/// `lesions:` points (painted as spheres, checked to lie in the breast).
/// @param stage  called with "segmentation" when the MRI is read and its segmentation starts (a node
///               reports it); may be empty
/// @throws std::runtime_error naming the case file and the MRI and saying what to fix: an image that
///         cannot be read (not an image, 2-D, a series with a missing slice, …), an image with no
///         breast or no chest wall in it, a lesion outside the breast, a breast side without a breast
///         or a midline, a truth on another grid.
MriCase loadMriCase(const std::string& yaml_path, const std::function<void(const std::string&)>& stage = {});

/// Any case file as loadModelCase (model/model_case.h) reads it, and an `mri:` case too: its MRI read
/// and segmented (loadMriCase), the labels the case's image, the nipples and the prone gravity
/// direction from the segmentation, the lesion label image's lesions after the listed ones.
/// @param stage  called with "reading" and, for an MRI case, "segmentation" as each starts; may be empty
/// @throws std::runtime_error as loadModelCase and loadMriCase do.
ModelCase loadModelCaseWithMri(const std::string& yaml_path, const std::function<void(const std::string&)>& stage = {});

/// The simulated supine MRI of an MRI case: the prone MRI and the model's labels resampled
/// (supine_resampling.h) into the rest mesh moved by `displacement`, on the supine grid of the
/// deformed nodes (supineGrid, the prone spacing, `options.margin_m` around).
/// @param rest_mesh     the model's mesh at rest, nodes [m] in the MRI's patient space
/// @param displacement  #N×3 [m]
/// @throws std::invalid_argument as resampleToSupine does.
SupineImages simulatedSupineMri(const MriCase& mri, const TetMesh& rest_mesh, const Points& displacement,
                                const SupineResampleOptions& options = {});

}  // namespace breast_sim::core
