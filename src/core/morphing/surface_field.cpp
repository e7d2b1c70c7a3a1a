#include "breast_sim/core/morphing/surface_field.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/image/distance_transform.h"
#include "../util/closest_point.h"

namespace breast_sim::core {

void SurfaceFieldOptions::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "surface field '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(voxel_size_m > 0) || !std::isfinite(voxel_size_m)) bad("voxel_size_m", voxel_size_m, "> 0 m, e.g. 1e-3");
  if (!(margin_m >= 0) || !std::isfinite(margin_m)) bad("margin_m", margin_m, "≥ 0 m");
  if (max_voxels_per_axis < 4 || max_voxels_per_axis > 1024) bad("max_voxels_per_axis", max_voxels_per_axis, "4 … 1024");
}

SurfaceVectorField::SurfaceVectorField(const TargetSurface& target, const Eigen::AlignedBox3d& region_m,
                                       const SurfaceFieldOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  target.validate();
  options.validate();
  Eigen::AlignedBox3d box = region_m;
  for (Eigen::Index v = 0; v < target.vertices_m.rows(); ++v) box.extend(Eigen::Vector3d(target.vertices_m.row(v)));
  box.min().array() -= options.margin_m;
  box.max().array() += options.margin_m;
  const Eigen::Vector3d extent = box.sizes();
  h_ = std::max(options.voxel_size_m, extent.maxCoeff() / (options.max_voxels_per_axis - 1));
  for (int c = 0; c < 3; ++c) size_[c] = std::max(2, static_cast<int>(std::ceil(extent[c] / h_)) + 1);
  origin_ = box.min();
  const long nx = size_.x(), nxy = nx * size_.y(), n = nxy * size_.z();

  // Rasterise: every voxel whose centre lies within half a voxel diagonal of the surface keeps the
  // triangle nearest to its centre (a cloud: the point nearest to it).
  target_ = target;
  const double reach = 0.5 * std::sqrt(3.0) * h_ * 1.0001;
  std::vector<std::int32_t> element(n, -1);
  std::vector<float> best_d2(n, std::numeric_limits<float>::infinity());
  auto offer = [&](long i, int e, double d2) {
    if (d2 < best_d2[i]) {
      best_d2[i] = static_cast<float>(d2);
      element[i] = e;
    }
  };
  auto centre = [&](int i, int j, int k) { return Eigen::Vector3d(origin_ + h_ * Eigen::Vector3d(i, j, k)); };
  auto index = [&](const Eigen::Vector3d& p, int c, bool up) {
    const double t = (p[c] - origin_[c]) / h_;
    return std::clamp(static_cast<int>(up ? std::ceil(t) : std::floor(t)), 0, size_[c] - 1);
  };
  if (target.isPointCloud()) {
    for (Eigen::Index v = 0; v < target.vertices_m.rows(); ++v) {
      const Eigen::Vector3d p = target.vertices_m.row(v);
      int ijk[3];
      for (int c = 0; c < 3; ++c) ijk[c] = std::clamp(static_cast<int>(std::lround((p[c] - origin_[c]) / h_)), 0, size_[c] - 1);
      offer(ijk[0] + nx * ijk[1] + nxy * ijk[2], static_cast<int>(v), (centre(ijk[0], ijk[1], ijk[2]) - p).squaredNorm());
    }
  } else {
    for (Eigen::Index f = 0; f < target.triangles.rows(); ++f) {
      const Eigen::Vector3d a = target.vertices_m.row(target.triangles(f, 0));
      const Eigen::Vector3d b = target.vertices_m.row(target.triangles(f, 1));
      const Eigen::Vector3d c = target.vertices_m.row(target.triangles(f, 2));
      const Eigen::Vector3d lo = a.cwiseMin(b).cwiseMin(c).array() - reach;
      const Eigen::Vector3d hi = a.cwiseMax(b).cwiseMax(c).array() + reach;
      for (int k = index(lo, 2, true); k <= index(hi, 2, false); ++k)
        for (int j = index(lo, 1, true); j <= index(hi, 1, false); ++j)
          for (int i = index(lo, 0, true); i <= index(hi, 0, false); ++i) {
            const Eigen::Vector3d p = centre(i, j, k);
            const double d2 = (p - closestPointOnTriangle(p, a, b, c)).squaredNorm();
            if (d2 <= reach * reach) offer(i + nx * j + nxy * k, static_cast<int>(f), d2);
          }
    }
  }
  std::vector<std::uint8_t> mask(n);
  surface_voxels_ = 0;
  for (long i = 0; i < n; ++i) {
    mask[i] = element[i] >= 0;
    surface_voxels_ += mask[i];
  }
  if (surface_voxels_ == 0) throw std::invalid_argument("SurfaceVectorField: the target surface reaches no voxel of the grid");
  feature_ = euclideanFeatureTransform(mask, size_, Eigen::Vector3d::Constant(h_));
  element_ = std::move(element);
  seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

Eigen::Vector3d SurfaceVectorField::vectorToSurface(const Eigen::Vector3d& p_m) const {
  // The voxel cell around p (clamped into the grid) and its eight corners' candidates.
  const Eigen::Vector3d t = (p_m - origin_) / h_;
  int i0[3];
  for (int c = 0; c < 3; ++c)
    i0[c] = std::min(static_cast<int>(std::clamp(t[c], 0.0, static_cast<double>(size_[c] - 1))), size_[c] - 2);
  const long nx = size_.x(), nxy = nx * size_.y();
  const int nyv = size_.y(), nzv = size_.z();
  std::int32_t voxels[8], elements[64];
  int nv = 0, ne = 0;
  double best = std::numeric_limits<double>::infinity();
  Eigen::Vector3d best_q = p_m;
  auto consider = [&](std::int32_t e) {
    if (e < 0 || std::find(elements, elements + ne, e) != elements + ne) return;
    if (ne < 64) elements[ne++] = e;
    Eigen::Vector3d q;
    if (target_.isPointCloud()) {
      q = target_.vertices_m.row(e).transpose();
    } else {
      q = closestPointOnTriangle(p_m, target_.vertices_m.row(target_.triangles(e, 0)).transpose(),
                                 target_.vertices_m.row(target_.triangles(e, 1)).transpose(),
                                 target_.vertices_m.row(target_.triangles(e, 2)).transpose());
    }
    const double d2 = (q - p_m).squaredNorm();
    if (d2 < best) {
      best = d2;
      best_q = q;
    }
  };
  for (int corner = 0; corner < 8; ++corner) {
    const long idx = (i0[0] + (corner & 1)) + nx * (i0[1] + ((corner >> 1) & 1)) + nxy * (i0[2] + ((corner >> 2) & 1));
    const std::int32_t f = feature_[idx];
    if (std::find(voxels, voxels + nv, f) != voxels + nv) continue;
    voxels[nv++] = f;
    const int fi = static_cast<int>(f % nx), fj = static_cast<int>((f / nx) % nyv), fk = static_cast<int>(f / nxy);
    for (int dk = std::max(fk - 1, 0); dk <= std::min(fk + 1, nzv - 1); ++dk)
      for (int dj = std::max(fj - 1, 0); dj <= std::min(fj + 1, nyv - 1); ++dj)
        for (int di = std::max(fi - 1, 0); di <= std::min(fi + 1, static_cast<int>(nx) - 1); ++di)
          consider(element_[di + nx * dj + nxy * dk]);
  }
  return best_q - p_m;
}

}  // namespace breast_sim::core
