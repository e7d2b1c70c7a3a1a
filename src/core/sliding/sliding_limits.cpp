// ChestWallSliding's limiting factors w_i = thickness factor × Gaussian factor (chest_wall_sliding.h):
// the tissue thickness by ray marching in the label image, and the seed's bimodal Gaussian in the
// chest-wall plane frame, centred at the nipples' foot points on the wall.
#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>

#include <Eigen/Geometry>

#include "../util/closest_point.h"

namespace breast_sim::core {

void ChestWallSliding::measureThickness(const LabelImage* labels, const TissueLabels& tissue) {
  const int n = static_cast<int>(rest_.rows());
  // Thickness: ray marching from the rest position along the rest normal through tissue.
  thickness_factor_ = Eigen::VectorXd::Ones(n);
  thickness_m_ = Eigen::VectorXd::Zero(n);
  if (settings_.thickness_limit) {
    const double step = 0.5 * labels->spacing_m.minCoeff();
    const double reach = (labels->spacing_m.cwiseProduct(labels->size.cast<double>())).norm();
    const double wall_skip = 3.0 * labels->spacing_m.maxCoeff();
#pragma omp parallel for schedule(dynamic, 64)
    for (int i = 0; i < n; ++i) {
      const Eigen::Vector3d x = rest_.row(i).transpose();
      const Eigen::Vector3d nrm = surface_->normal(x);
      if (nrm.isZero()) continue;
      double t = step;
      for (; t < reach; t += step) {
        const std::uint16_t l = labels->labelAt(x + t * nrm, 0);
        if (tissue.isTissue(l)) continue;
        if (t < wall_skip && tissue.classify(l) == TissueClass::kChestWall) continue;
        break;
      }
      thickness_m_[i] = t - 0.5 * step;
    }
    const double tmax = thickness_m_.maxCoeff();
    if (tmax > 0) thickness_factor_ = thickness_m_ / tmax;
  }
}

void ChestWallSliding::placeGaussian(const TetMesh& mesh, const std::vector<int>& slot,
                                     const std::vector<Eigen::Vector3d>& nipples_m, const Eigen::Vector3d& anterior) {
  const int n = static_cast<int>(rest_.rows());
  const BoundarySurface& b = mesh.boundary();
  // Chest-wall plane frame and the bimodal Gaussian.
  gaussian_factor_ = Eigen::VectorXd::Ones(n);
  const Eigen::Vector3d a = anterior.normalized();
  auto inPlane = [&](const Eigen::Vector3d& v) { return Eigen::Vector3d(v - v.dot(a) * a); };
  if (nipples_m.size() == 2 && inPlane(nipples_m[0] - nipples_m[1]).norm() > 1e-6) {
    plane_u_ = inPlane(nipples_m[0] - nipples_m[1]).normalized();
    plane_origin_ = 0.5 * (nipples_m[0] + nipples_m[1]);
  } else {
    // One nipple (or none): u along the patient x axis (or y, z if x is anterior) in the plane.
    for (const Eigen::Vector3d e : {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ()})
      if (inPlane(e).norm() > 0.5) {
        plane_u_ = inPlane(e).normalized();
        break;
      }
    if (!nipples_m.empty()) plane_origin_ = nipples_m[0];
  }
  plane_v_ = a.cross(plane_u_).normalized();
  if (settings_.gaussian_limit) {
    // Each mode is centred at the nipple's foot point on the wall: the closest point of the
    // all-sliding boundary triangles (or, without any, the closest sliding node).
    for (const Eigen::Vector3d& p : nipples_m) {
      Eigen::Vector3d best = rest_.row(0).transpose();
      double best_d = std::numeric_limits<double>::infinity();
      bool any_triangle = false;
      for (Eigen::Index f = 0; f < b.triangles.rows(); ++f) {
        const int a0 = b.triangles(f, 0), a1 = b.triangles(f, 1), a2 = b.triangles(f, 2);
        if (slot[a0] < 0 || slot[a1] < 0 || slot[a2] < 0) continue;
        any_triangle = true;
        const Eigen::Vector3d q = closestPointOnTriangle(p, mesh.nodes().row(a0).transpose(), mesh.nodes().row(a1).transpose(),
                                                    mesh.nodes().row(a2).transpose());
        const double d = (q - p).squaredNorm();
        if (d < best_d) {
          best_d = d;
          best = q;
        }
      }
      if (!any_triangle)
        for (int i = 0; i < n; ++i) {
          const double d = (rest_.row(i).transpose() - p).squaredNorm();
          if (d < best_d) {
            best_d = d;
            best = rest_.row(i).transpose();
          }
        }
      centre_points_.push_back(best);
      centres_.emplace_back((best - plane_origin_).dot(plane_u_), (best - plane_origin_).dot(plane_v_));
    }
    if (settings_.gaussian_sigma_m > 0) {
      gaussian_sigma_ = Eigen::Vector2d::Constant(settings_.gaussian_sigma_m);
    } else {
      // Extent of the sliding nodes closest to each nipple, along u and v (a breast's diameter).
      std::vector<Eigen::Vector2d> lo(centres_.size(), Eigen::Vector2d::Constant(1e300)),
          hi(centres_.size(), Eigen::Vector2d::Constant(-1e300));
      for (int i = 0; i < n; ++i) {
        const Eigen::Vector3d d = rest_.row(i).transpose() - plane_origin_;
        const Eigen::Vector2d uv(d.dot(plane_u_), d.dot(plane_v_));
        size_t best = 0;
        for (size_t k = 1; k < centres_.size(); ++k)
          if ((uv - centres_[k]).squaredNorm() < (uv - centres_[best]).squaredNorm()) best = k;
        lo[best] = lo[best].cwiseMin(uv);
        hi[best] = hi[best].cwiseMax(uv);
      }
      Eigen::Vector2d ext = Eigen::Vector2d::Zero();
      int count = 0;
      for (size_t k = 0; k < centres_.size(); ++k)
        if (hi[k].x() >= lo[k].x()) {
          ext += hi[k] - lo[k];
          ++count;
        }
      if (count == 0 || !(ext.minCoeff() > 0))
        throw std::invalid_argument("ChestWallSliding: cannot measure the breasts' extent for the Gaussian sigma; "
                                    "give gaussian_sigma_m > 0");
      gaussian_sigma_ = settings_.gaussian_sigma_fraction * ext / count;
    }
    for (int i = 0; i < n; ++i) gaussian_factor_[i] = gaussianWeight(rest_.row(i).transpose());
  }
}

double ChestWallSliding::gaussianWeight(const Eigen::Vector3d& p_m) const {
  if (centres_.empty()) return 1.0;
  const Eigen::Vector3d d = p_m - plane_origin_;
  const double u = d.dot(plane_u_), v = d.dot(plane_v_);
  double z = 0;
  for (const Eigen::Vector2d& c : centres_) {
    const double du = (u - c.x()) / gaussian_sigma_.x(), dv = (v - c.y()) / gaussian_sigma_.y();
    z += settings_.gaussian_amplitude * std::exp(-0.5 * (du * du + dv * dv));
  }
  return std::min(1.0, z);
}

}  // namespace breast_sim::core
