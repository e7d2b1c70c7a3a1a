#pragma once
/// @file segmentation_metrics.h
/// How good a segmentation is against a ground truth on the same grid: Dice per tissue class and the
/// distance between the two chest-wall boundaries.

#include <string>
#include <vector>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// Dice = 2 |A ∩ B| / (|A| + |B|) of one class (1 when both are empty).
struct ClassScore {
  std::string name;     ///< "fat", "fibroglandular", "skin", "lesion", "chest_wall", "breast" (= the four tissues)
  long truth_voxels = 0, result_voxels = 0, overlap_voxels = 0;
  double dice = 1.0;
};

/// Distances between the chest-wall boundaries [mm]. A boundary is the set of centres of the voxel
/// faces between a chest-wall voxel and a breast-tissue voxel (its 6-neighbour). Each face centre of
/// one boundary is taken to the nearest face centre of the other; `mean_mm`, `p95_mm` and `max_mm` pool
/// both directions (the average symmetric surface distance and its 95th percentile).
struct BoundaryDistance {
  double mean_mm = 0.0, p95_mm = 0.0, max_mm = 0.0;
  double result_to_truth_mean_mm = 0.0, truth_to_result_mean_mm = 0.0;
  long result_faces = 0, truth_faces = 0;
};

struct SegmentationScores {
  std::vector<ClassScore> classes;  ///< breast, fat, fibroglandular, skin, lesion, chest_wall
  BoundaryDistance boundary;
  /// The score of a class by name. @throws std::out_of_range for an unknown name.
  const ClassScore& score(const std::string& name) const;
};

/// Scores `result` against `truth`, each read with its own label map.
/// @throws std::invalid_argument when the grids differ (size, or spacing, origin or direction by more
///         than 1e-6 m or 1e-6), or when either has no chest-wall boundary face.
SegmentationScores scoreSegmentation(const LabelImage& result, const TissueLabels& result_labels, const LabelImage& truth,
                                     const TissueLabels& truth_labels);

}  // namespace breast_sim::core
