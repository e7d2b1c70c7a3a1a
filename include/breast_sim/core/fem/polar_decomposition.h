#pragma once
/// @file polar_decomposition.h
/// The rotation of a deformation gradient, robust on degenerate and inverted elements.

#include <Eigen/Core>

namespace breast_sim::core {

/// Rotation R (det R = +1) closest to the deformation gradient F.
///
/// For well-conditioned F with det F > 0 this is the orthogonal polar factor, computed by Higham's
/// scaled Newton iteration R ← ½(γR + R⁻ᵀ/γ) (a few 3×3 inverses; 2–3× faster than an SVD). For
/// det F ≤ 0 (inverted or collapsed elements) or when the iteration does not converge, it falls
/// back to the SVD F = U Σ Vᵀ with the reflection fix of Irving et al. 2004: the sign of the
/// singular vector of the smallest singular value is flipped so that R = U Vᵀ is a rotation.
Eigen::Matrix3d rotationOf(const Eigen::Matrix3d& F);

/// The SVD path of rotationOf alone (the slow reference in tests).
Eigen::Matrix3d rotationOfBySvd(const Eigen::Matrix3d& F);

}  // namespace breast_sim::core
