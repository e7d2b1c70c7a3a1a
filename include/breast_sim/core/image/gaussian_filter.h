#pragma once
/// @file gaussian_filter.h
/// Scalar and vector images on a voxel grid placed in patient space, separable Gaussian smoothing
/// and derivative-of-Gaussian filtering (O(#voxels · kernel width), parallel with OpenMP), and
/// trilinear sampling of scalar and vector fields at physical points.
///
/// Used for the chest-wall normal field of sliding (seed section 2.4: a 3-D derivative of Gaussian,
/// σ = 2 mm, over the chest-wall mask) and reusable for the gradient of a distance field (surface
/// morphing, seed section 2.5).

#include <cstdint>
#include <set>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"

namespace breast_sim::core {

/// Where a voxel grid lies in patient space, as LabelImage:
///   p = origin_m + direction · diag(spacing_m) · (i, j, k)ᵀ   [m]
/// with i fastest in memory (index = i + size.x·(j + size.y·k)).
struct ImageGeometry {
  Eigen::Vector3i size{0, 0, 0};                            ///< voxels along i, j, k
  Eigen::Vector3d spacing_m{1e-3, 1e-3, 1e-3};              ///< voxel size along i, j, k [m]
  Eigen::Vector3d origin_m{0, 0, 0};                        ///< centre of voxel (0,0,0) [m]
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity();  ///< orthonormal columns: axes i, j, k

  /// The geometry of a label image.
  static ImageGeometry of(const LabelImage& image);
  long numVoxels() const { return static_cast<long>(size.x()) * size.y() * size.z(); }
  long index(int i, int j, int k) const {
    return i + static_cast<long>(size.x()) * (j + static_cast<long>(size.y()) * k);
  }
  /// Continuous voxel index of a physical point [m] (direction⁻¹ = directionᵀ).
  Eigen::Vector3d physicalToIndex(const Eigen::Vector3d& p_m) const {
    return (direction.transpose() * (p_m - origin_m)).cwiseQuotient(spacing_m);
  }
  /// Physical point [m] of a continuous voxel index.
  Eigen::Vector3d indexToPhysical(const Eigen::Vector3d& ijk) const {
    return origin_m + direction * ijk.cwiseProduct(spacing_m);
  }
  /// @throws std::invalid_argument for a size entry < 1, a non-positive or non-finite spacing, a
  ///         non-finite origin or a direction whose columns are not orthonormal within 1e-6.
  void validate() const;
};

/// A scalar field on a voxel grid (float voxels; any unit).
struct ScalarImage {
  ImageGeometry geometry;
  std::vector<float> values;  ///< geometry.numVoxels() values, i fastest
};

/// A vector field on a voxel grid, components in the patient frame (x, y, z), stored as three
/// planes (structure of arrays, so the filters stream each component).
struct VectorImage {
  ImageGeometry geometry;
  std::vector<float> x, y, z;  ///< geometry.numVoxels() values each, i fastest
};

/// 1 where the label image has one of `labels`, else 0, on the image's grid.
/// @throws std::invalid_argument if the image fails LabelImage::validate().
ScalarImage labelMask(const LabelImage& image, const std::set<std::uint16_t>& labels);

/// Sampled 1-D Gaussian kernel of standard deviation sigma_voxels [voxels], truncated at
/// radius = ceil(truncate_sigmas · sigma_voxels) taps (at least 1), for correlation
/// out[j] = Σ_t k[t + radius] · in[j + t].
///  - order 0: G(t) / Σ G (sums to 1: constants are kept exactly);
///  - order 1: t·G(t) / Σ t²·G(t) (a derivative per voxel: exact on linear data, Σ t·k = 1).
/// @throws std::invalid_argument for sigma_voxels ≤ 0 or not finite, order not 0 or 1,
///         truncate_sigmas < 1 or > 10.
std::vector<double> gaussianKernel1d(double sigma_voxels, int order, double truncate_sigmas = 4.0);

/// Separable Gaussian filter with per-axis derivative orders: the image smoothed with a Gaussian of
/// standard deviation sigma_m [m] (per axis sigma_m / spacing voxels) and differentiated
/// derivative_order[a] ∈ {0, 1} times along index axis a; a derivative is per metre along that axis
/// (unit of the input per m). Three 1-D passes; voxels beyond the border repeat the border voxel
/// (clamp), so a derivative is biased within the kernel radius of the border. Parallel over lines.
/// @throws std::invalid_argument for sigma_m ≤ 0 or not finite, an order not 0 or 1, a bad
///         truncation (as gaussianKernel1d), an invalid geometry or a value count that does not match.
ScalarImage gaussianFilter(const ScalarImage& image, double sigma_m,
                           const Eigen::Vector3i& derivative_order = Eigen::Vector3i::Zero(),
                           double truncate_sigmas = 4.0);

/// Gradient of the Gaussian-smoothed image in the patient frame [unit of the input per m]:
/// ∇(G_σ * f), from seven 1-D passes (the smoothing passes are shared between the three partial
/// derivatives), then rotated by the grid direction. Same border rule and throws as gaussianFilter.
VectorImage gaussianGradient(const ScalarImage& image, double sigma_m, double truncate_sigmas = 4.0);

/// O(#voxels · (2r+1)³) reference of gaussianFilter: direct 3-D correlation with the product of the
/// three 1-D kernels, evaluated here from the formulas (not from gaussianKernel1d), clamped border.
/// For tests only.
ScalarImage bruteForceGaussianFilter(const ScalarImage& image, double sigma_m,
                                     const Eigen::Vector3i& derivative_order = Eigen::Vector3i::Zero(),
                                     double truncate_sigmas = 4.0);

/// Trilinear interpolation of a scalar image at a physical point [m]. Points outside the grid of
/// voxel centres are clamped onto it (the border value continues). Exact on fields linear in the
/// voxel index inside the grid.
double sampleTrilinear(const ScalarImage& image, const Eigen::Vector3d& p_m);
/// Trilinear interpolation of each component of a vector image (same rules).
Eigen::Vector3d sampleTrilinear(const VectorImage& image, const Eigen::Vector3d& p_m);
/// Whether p lies within the grid of voxel centres (where sampling does not clamp).
bool insideGrid(const ImageGeometry& geometry, const Eigen::Vector3d& p_m);

}  // namespace breast_sim::core
