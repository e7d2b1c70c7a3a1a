#pragma once
/// @file chest_wall_boundary.h
/// The chest-wall boundary's robust smooth fit over the coronal plane (private to src/core/mri): a
/// height field from scattered per-column candidates, with outliers rejected and gaps filled.

#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace breast_sim::core::boundary_fit {

/// A field over the nu × nv columns (u fastest) with pixel sizes du, dv [mm].
struct ColumnGrid {
  int nu = 0, nv = 0;
  double du = 1.0, dv = 1.0;
  long count() const { return static_cast<long>(nu) * nv; }
};

struct FitOptions {
  double median_window_mm = 30.0;  ///< robust first estimate: median of the candidates within this square
  double sigma_mm = 3.0;           ///< Gaussian of the normalized convolution
  double outlier_mm = 3.0;         ///< rejection distance, in the unit of the heights × `height_mm`
  double height_mm = 1.0;          ///< mm per unit of height (the voxel size along the columns)
  int iterations = 3;              ///< reject-and-refit rounds after the median
};

/// The fitted heights at every column. `accepted` (in: 1 where `height` holds a candidate) is set to
/// the candidates kept. Columns without candidates get a smooth continuation: a normalized convolution
/// at σ blended into the one at 2σ, 4σ, … (finally the mean), so the field has no seams.
/// @return nu·nv heights; all zero when there is no candidate at all.
std::vector<float> robustSmoothFit(const ColumnGrid& grid, const std::vector<float>& height,
                                   std::vector<std::uint8_t>& accepted, const FitOptions& options, int* rejected);

}  // namespace breast_sim::core::boundary_fit
