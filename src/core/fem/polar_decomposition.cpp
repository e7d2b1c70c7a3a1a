#include "breast_sim/core/fem/polar_decomposition.h"

#include <cmath>

#include <Eigen/Dense>
#include <Eigen/SVD>

namespace breast_sim::core {

Eigen::Matrix3d rotationOfBySvd(const Eigen::Matrix3d& F) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d U = svd.matrixU();
  Eigen::Matrix3d V = svd.matrixV();
  // Reflection fix: make U and V rotations; the smallest singular value takes the sign.
  if (U.determinant() < 0) U.col(2) *= -1.0;
  if (V.determinant() < 0) V.col(2) *= -1.0;
  return U * V.transpose();
}

Eigen::Matrix3d rotationOf(const Eigen::Matrix3d& F) {
  const double det = F.determinant();
  const double scale = F.squaredNorm();
  // Well-conditioned, positively oriented: Higham's scaled Newton iteration.
  if (det > 1e-6 * std::pow(scale / 3.0, 1.5)) {
    Eigen::Matrix3d R = F;
    for (int it = 0; it < 20; ++it) {
      const Eigen::Matrix3d Rinv_t = R.inverse().transpose();
      // Frobenius-norm scaling γ = (‖R⁻¹‖/‖R‖)^½ speeds up the first iterations.
      const double gamma = it < 6 ? std::sqrt(std::sqrt(Rinv_t.squaredNorm() / R.squaredNorm())) : 1.0;
      const Eigen::Matrix3d next = 0.5 * (gamma * R + Rinv_t / gamma);
      const double change = (next - R).squaredNorm();
      R = next;
      if (change < 1e-24) return R;
    }
    if ((R.transpose() * R - Eigen::Matrix3d::Identity()).squaredNorm() < 1e-20) return R;
  }
  return rotationOfBySvd(F);
}

}  // namespace breast_sim::core
