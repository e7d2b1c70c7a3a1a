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

/// How many matrices rotationsOf() decomposes per call.
inline constexpr int kRotationBatch = 8;

/// rotationOf() of up to kRotationBatch matrices at once, in structure-of-arrays layout: entry (r, c)
/// of matrix l is F[(r + 3c)·kRotationBatch + l]; R is written the same way. Lanes ≥ count are
/// ignored (R there is unspecified).
///
/// One Higham iteration for one matrix is a chain of dependent operations (cross products, two square
/// roots, two divisions) that leaves the core mostly idle; here the same iteration runs on all lanes
/// in lock step, in loops over the lane the compiler vectorises, so the lanes' latencies overlap. A lane
/// that converged is frozen, so each lane takes exactly rotationOf()'s iterations and stopping rule;
/// lanes that need the SVD (det F ≤ 0, degenerate, lost orientation, no convergence) are handed to
/// rotationOf(). Equal to rotationOf() to round-off.
void rotationsOf(const double* F, double* R, int count);

}  // namespace breast_sim::core
