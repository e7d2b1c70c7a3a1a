#pragma once
/// @file polar_decomposition_detail.h
/// The lane arithmetic of rotationsOf(), inline so that a caller compiled for wider vectors (a
/// function with a GCC target attribute, CorotatedTetFem's AVX-512 element update) gets it
/// compiled for them too: the same source, so the same iteration and stopping rule per lane.
/// Not part of the API: call rotationsOf().

#include <cmath>

#include <Eigen/Dense>

#include "breast_sim/core/fem/polar_decomposition.h"

namespace breast_sim::core::detail {

/// rotationsOf() without its argument check (0 ≤ count ≤ kRotationBatch).
__attribute__((always_inline)) inline void rotationsOfLanes(const double* F, double* R, int count) {
  constexpr int W = kRotationBatch;
  // X[k·W + l]: entry k (column-major) of lane l's iterate; C its cofactor matrix. Unused lanes
  // iterate on the identity.
  alignas(64) double X[9 * W], C[9 * W];
  alignas(64) double det[W], gamma[W], change[W];
  // Per lane: 1 iterating, 0 converged (R holds the result), −1 for rotationOf() to decide.
  int state[W];
  for (int l = 0; l < W; ++l)
    for (int k = 0; k < 9; ++k) X[k * W + l] = l < count ? F[k * W + l] : (k % 4 == 0 ? 1.0 : 0.0);
  for (int l = 0; l < W; ++l) {
    const Eigen::Matrix3d Fl = Eigen::Matrix3d::NullaryExpr([&](Eigen::Index r, Eigen::Index c) { return X[(r + 3 * c) * W + l]; });
    const double s3 = Fl.squaredNorm() / 3.0;
    state[l] = l < count && Fl.determinant() > 1e-6 * s3 * std::sqrt(s3) ? 1 : -1;  // rotationOf's test
  }
  // rotationOf's iteration on all lanes in lock step. The arithmetic loops over l have no branch,
  // so they vectorise (a conditional expression would not: with the default -ftrapping-math GCC
  // does not if-convert floating-point code, and std::sqrt's errno check is a branch, hence the
  // square roots in a loop of their own, which vectorises where the file is built without errno
  // and -frounding-math, as the core's are: CMakeLists.txt). A lane's result is taken when it converges, at
  // rotationOf's iteration and stopping rule; the lanes iterate on regardless, discarded.
  for (int it = 0; it < 20; ++it) {
    for (int l = 0; l < W; ++l) {
      const double x0 = X[0 * W + l], x1 = X[1 * W + l], x2 = X[2 * W + l], x3 = X[3 * W + l], x4 = X[4 * W + l],
                   x5 = X[5 * W + l], x6 = X[6 * W + l], x7 = X[7 * W + l], x8 = X[8 * W + l];
      // Cofactor columns: col1 × col2, col2 × col0, col0 × col1.
      const double c0 = x4 * x8 - x5 * x7, c1 = x5 * x6 - x3 * x8, c2 = x3 * x7 - x4 * x6;
      C[0 * W + l] = c0, C[1 * W + l] = c1, C[2 * W + l] = c2;
      C[3 * W + l] = x7 * x2 - x8 * x1, C[4 * W + l] = x8 * x0 - x6 * x2, C[5 * W + l] = x6 * x1 - x7 * x0;
      C[6 * W + l] = x1 * x5 - x2 * x4, C[7 * W + l] = x2 * x3 - x0 * x5, C[8 * W + l] = x0 * x4 - x1 * x3;
      det[l] = x0 * c0 + x1 * c1 + x2 * c2;
    }
    if (it < 6) {
      // Frobenius-norm scaling γ = (‖X⁻¹‖/‖X‖)^½ (rotationOf's first 6 steps).
      for (int l = 0; l < W; ++l) {
        double cn = 0, xn = 0;
        for (int k = 0; k < 9; ++k) {
          cn += C[k * W + l] * C[k * W + l];
          xn += X[k * W + l] * X[k * W + l];
        }
        gamma[l] = cn / (det[l] * det[l] * xn);
      }
#pragma omp simd
      for (int l = 0; l < W; ++l) gamma[l] = std::sqrt(std::sqrt(gamma[l]));
    } else {
      for (int l = 0; l < W; ++l) gamma[l] = 1.0;
    }
    for (int l = 0; l < W; ++l) {
      const double a = 0.5 * gamma[l], b = 0.5 / (gamma[l] * det[l]);
      double ch = 0;
      for (int k = 0; k < 9; ++k) {
        const double x = X[k * W + l], next = a * x + b * C[k * W + l];
        ch += (next - x) * (next - x);
        X[k * W + l] = next;
      }
      change[l] = ch;
    }
    bool any = false;
    for (int l = 0; l < W; ++l) {
      if (state[l] != 1) continue;
      if (!(det[l] > 0)) {
        state[l] = -1;  // lost orientation
      } else if (change[l] < 1e-13) {
        state[l] = 0;
        for (int k = 0; k < 9; ++k) R[k * W + l] = X[k * W + l];
      } else {
        any = true;
      }
    }
    if (!any) break;
  }
  for (int l = 0; l < count; ++l) {
    if (state[l] == 0) continue;
    // Not converged, lost orientation or degenerate: rotationOf's own checks and SVD path.
    Eigen::Matrix3d Fl;
    for (int k = 0; k < 9; ++k) Fl.data()[k] = F[k * W + l];
    const Eigen::Matrix3d Rl = rotationOf(Fl);
    for (int k = 0; k < 9; ++k) R[k * W + l] = Rl.data()[k];
  }
}

}  // namespace breast_sim::core::detail
