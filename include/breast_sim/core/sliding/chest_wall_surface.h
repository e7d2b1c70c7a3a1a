#pragma once
/// @file chest_wall_surface.h
/// The chest wall as seen by sliding (seed section 2.4): a dense normal field and a level set from
/// the chest-wall mask of the segmentation, with no analytic model of the wall.
///
/// The mask M (1 in the wall, 0 elsewhere) is smoothed with a Gaussian of standard deviation σ
/// (2 mm by default): S = G_σ * M, and its gradient ∇S comes from a 3-D derivative-of-Gaussian
/// filter (image/gaussian_filter.h). Both are sampled trilinearly at any point.
///  - Outward normal (from the wall into the breast): n = −∇S / |∇S|.
///  - Surface: the iso-surface S = 1/2. Near a wall that is flat on the scale of σ, S equals
///    Φ(−h/σ) with h the signed distance to the surface (positive outside the wall, in the tissue)
///    and Φ the standard normal distribution function; so h(p) = −σ Φ⁻¹(S(p)) is used as the signed
///    distance. It is exact for a planar wall thicker than ~4σ and, for a wall of curvature radius
///    R, off by O(σ²/R) (0.01 mm at σ = 2 mm, R = 200 mm); it saturates at |h| ≈ 3.7σ, where S
///    reaches 1e-4 or 1 − 1e-4 (beyond that the field carries no information).
///  - Projection: Newton steps on h along ∇h = σ |∇S| / φ(Φ⁻¹(S)) · n (φ the normal density): h
///    is nearly linear along the normal, so two or three steps reach 1e-6 m.

#include <cstdint>
#include <set>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"

namespace breast_sim::core {

/// Standard normal quantile Φ⁻¹(p) for p in (0, 1) (Acklam's rational approximation refined by one
/// Halley step: relative error ≈ 1e-15). @throws std::invalid_argument for p outside (0, 1).
double normalQuantile(double p);

/// How the chest-wall field is computed.
struct ChestWallFieldOptions {
  double sigma_m = 2e-3;           ///< σ of the Gaussian [m] (seed: 2 mm, ~twice the MRI in-plane voxel)
  double truncate_sigmas = 4.0;    ///< kernel radius in σ, [1, 10]
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Result of projecting a point onto a level of the chest-wall signed distance.
struct WallProjection {
  Eigen::Vector3d point_m = Eigen::Vector3d::Zero();  ///< the projected point [m]
  double residual_m = 0.0;  ///< |h(point) − target| after the last step [m]
  int iterations = 0;
  bool converged = false;   ///< residual ≤ tolerance (else point is the last iterate)
};

/// The smoothed chest-wall mask and its gradient on the label image's grid.
class ChestWallSurface {
 public:
  /// @param image       the segmentation (any geometry: rotated, anisotropic)
  /// @param wall_labels label values of the chest wall (TissueLabels::chest_wall)
  /// @throws std::invalid_argument for invalid options or image, no wall label given, or a mask
  ///         without any wall voxel (names the labels).
  ChestWallSurface(const LabelImage& image, const std::set<std::uint16_t>& wall_labels,
                   const ChestWallFieldOptions& options = {});

  const ChestWallFieldOptions& options() const { return options_; }
  const ScalarImage& smoothedMask() const { return smoothed_; }
  const VectorImage& maskGradient() const { return gradient_; }  ///< ∇S [1/m]
  double precomputeSeconds() const { return precompute_seconds_; }

  /// S(p) in [0, 1]: 1 deep in the wall, 1/2 on its surface.
  double smoothedMaskAt(const Eigen::Vector3d& p_m) const { return sampleTrilinear(smoothed_, p_m); }
  /// Unit outward normal at p (wall → breast); zero where |∇S| vanishes (far from the wall).
  Eigen::Vector3d normal(const Eigen::Vector3d& p_m) const;
  /// Signed distance h(p) to the wall surface [m], positive outside the wall (see the file comment);
  /// saturates at ±3.72σ.
  double signedDistance(const Eigen::Vector3d& p_m) const;
  /// h and its gradient ∇h [-] at p (∇h ≈ the outward normal with |∇h| ≈ 1 near the surface).
  double signedDistance(const Eigen::Vector3d& p_m, Eigen::Vector3d& gradient) const;
  /// Moves p along ∇h onto the level h = target_m [m] by Newton steps.
  /// @param tolerance_m  stop when |h − target| ≤ this [m]
  WallProjection project(const Eigen::Vector3d& p_m, double target_m = 0.0, int max_iterations = 8,
                         double tolerance_m = 1e-7) const;
  /// Distance from p to the nearest face of the segmentation's grid (the centres of its outer voxels)
  /// [m], negative outside the grid. The smoothing clamps the image at its border, so within about σ
  /// of a face the levels that meet it run straight on out of the image: there the field describes
  /// the image's edge, not the wall.
  double borderDistance(const Eigen::Vector3d& p_m) const;

 private:
  ChestWallFieldOptions options_;
  ScalarImage smoothed_;
  VectorImage gradient_;
  double precompute_seconds_ = 0.0;
};

}  // namespace breast_sim::core
