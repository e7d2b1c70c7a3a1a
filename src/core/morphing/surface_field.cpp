#include "breast_sim/core/morphing/surface_field.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
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
  rebuild(target, region_m, options);
}

void SurfaceVectorField::rebuild(const TargetSurface& target, const Eigen::AlignedBox3d& region_m,
                                 const SurfaceFieldOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  target.validate();
  options.validate();
  // Forget the previous surface: element_ is 0 everywhere again (the old sites are within it).
  for (std::int32_t s : sites_) element_[s] = 0;
  sites_.clear();
  surface_voxels_ = 0;

  // The grid (see SurfaceFieldOptions).
  Eigen::AlignedBox3d box = region_m;
  for (Eigen::Index v = 0; v < target.vertices_m.rows(); ++v) box.extend(Eigen::Vector3d(target.vertices_m.row(v)));
  box.min().array() -= options.margin_m;
  box.max().array() += options.margin_m;
  const Eigen::Vector3d extent = box.sizes();
  h_ = std::max(options.voxel_size_m, extent.maxCoeff() / (options.max_voxels_per_axis - 1));
  for (int c = 0; c < 3; ++c)
    size_[c] = std::clamp(static_cast<int>(std::ceil(extent[c] / h_)) + 1, 2, std::max(2, options.max_voxels_per_axis));
  origin_ = box.min();
  const int nx = size_.x(), ny = size_.y(), nz = size_.z();
  const long nxy = static_cast<long>(nx) * ny, n = nxy * nz;
  feature_.resize(n);  // every voxel is written by the feature transform
  element_.resize(n);  // all zero when fresh, and rebuilds leave it all zero but at the surface
  target_ = target;

  // Rasterise: every voxel whose centre lies within half a voxel diagonal of the surface keeps the
  // triangle nearest to its centre (a cloud: each point goes to its voxel, which keeps the point
  // nearest to its centre). Elements are binned by the slices k they reach, in index order, so
  // every slice is owned by one thread and ties go to the lower index as in a serial sweep.
  const bool cloud = target.isPointCloud();
  const long num_elements = cloud ? target.vertices_m.rows() : target.triangles.rows();
  const double reach = 0.5 * std::sqrt(3.0) * h_ * 1.0001;
  auto index = [&](double x, int c, bool up) {
    const double t = (x - origin_[c]) / h_;
    return std::clamp(static_cast<int>(up ? std::ceil(t) : std::floor(t)), 0, size_[c] - 1);
  };
  auto nearest = [&](double x, int c) {
    return std::clamp(static_cast<int>(std::lround((x - origin_[c]) / h_)), 0, size_[c] - 1);
  };
  auto vertex = [&](long f, int corner) -> Eigen::Vector3d {
    return target.vertices_m.row(target.triangles(f, corner)).transpose();
  };
  std::vector<int> k_first(num_elements), k_last(num_elements);
  std::vector<long> bin_begin(nz + 1, 0);
  for (long e = 0; e < num_elements; ++e) {
    if (cloud) {
      k_first[e] = k_last[e] = nearest(target.vertices_m(e, 2), 2);
    } else {
      const double z0 = std::min({vertex(e, 0).z(), vertex(e, 1).z(), vertex(e, 2).z()});
      const double z1 = std::max({vertex(e, 0).z(), vertex(e, 1).z(), vertex(e, 2).z()});
      k_first[e] = index(z0 - reach, 2, true);
      k_last[e] = index(z1 + reach, 2, false);
    }
    for (int k = k_first[e]; k <= k_last[e]; ++k) ++bin_begin[k + 1];
  }
  for (int k = 0; k < nz; ++k) bin_begin[k + 1] += bin_begin[k];
  std::vector<std::int32_t> bin(bin_begin[nz]);
  {
    std::vector<long> fill(bin_begin.begin(), bin_begin.end() - 1);
    for (long e = 0; e < num_elements; ++e)
      for (int k = k_first[e]; k <= k_last[e]; ++k) bin[fill[k]++] = static_cast<std::int32_t>(e);
  }
  std::vector<std::vector<std::int32_t>> slice_sites(nz);
  std::int32_t* const element = element_.data();
#pragma omp parallel
  {
    std::vector<float> best_d2(nxy, std::numeric_limits<float>::infinity());  // of this slice
    std::vector<std::int32_t> touched;
#pragma omp for schedule(dynamic, 2)
    for (int k = 0; k < nz; ++k) {
      std::int32_t* slice = element + k * nxy;
      touched.clear();
      auto offer = [&](long m, std::int32_t e, double d2) {
        if (d2 < best_d2[m]) {
          if (std::isinf(best_d2[m])) touched.push_back(static_cast<std::int32_t>(m));
          best_d2[m] = static_cast<float>(d2);
          slice[m] = e + 1;
        }
      };
      const double z = origin_.z() + h_ * k;
      for (long b = bin_begin[k]; b < bin_begin[k + 1]; ++b) {
        const std::int32_t e = bin[b];
        if (cloud) {
          const Eigen::Vector3d p = target.vertices_m.row(e).transpose();
          const int i = nearest(p.x(), 0), j = nearest(p.y(), 1);
          offer(i + static_cast<long>(nx) * j, e, (Eigen::Vector3d(origin_.x() + h_ * i, origin_.y() + h_ * j, z) - p).squaredNorm());
          continue;
        }
        const Eigen::Vector3d a = vertex(e, 0), bb = vertex(e, 1), c = vertex(e, 2);
        const Eigen::Vector3d lo = a.cwiseMin(bb).cwiseMin(c).array() - reach;
        const Eigen::Vector3d hi = a.cwiseMax(bb).cwiseMax(c).array() + reach;
        // Voxels farther than `reach` from the triangle's plane are farther from the triangle.
        Eigen::Vector3d normal = (bb - a).cross(c - a);
        const double area2 = normal.norm();
        normal = area2 > 0 ? Eigen::Vector3d(normal / area2) : Eigen::Vector3d::Zero();
        const double plane_reach = reach * (1 + 1e-9);
        const int i0 = index(lo.x(), 0, true), i1 = index(hi.x(), 0, false);
        for (int j = index(lo.y(), 1, true); j <= index(hi.y(), 1, false); ++j) {
          const double y = origin_.y() + h_ * j;
          const double plane0 = normal.y() * (y - a.y()) + normal.z() * (z - a.z()) + normal.x() * (origin_.x() - a.x());
          for (int i = i0; i <= i1; ++i) {
            if (std::abs(plane0 + normal.x() * h_ * i) > plane_reach) continue;
            const Eigen::Vector3d p(origin_.x() + h_ * i, y, z);
            const double d2 = (p - closestPointOnTriangle(p, a, bb, c)).squaredNorm();
            if (d2 <= reach * reach) offer(i + static_cast<long>(nx) * j, e, d2);
          }
        }
      }
      std::sort(touched.begin(), touched.end());
      std::vector<std::int32_t>& out = slice_sites[k];
      out.resize(touched.size());
      for (size_t t = 0; t < touched.size(); ++t) {
        best_d2[touched[t]] = std::numeric_limits<float>::infinity();
        out[t] = static_cast<std::int32_t>(k * nxy + touched[t]);
      }
    }
  }
  size_t total = 0;
  for (const auto& s : slice_sites) total += s.size();
  sites_.reserve(total);
  for (const auto& s : slice_sites) sites_.insert(sites_.end(), s.begin(), s.end());
  if (sites_.empty()) throw std::invalid_argument("SurfaceVectorField: the target surface reaches no voxel of the grid");
  // Voxel units: exact integer squared distances, the same features for any h.
  euclideanFeatureTransformOfSites(sites_, size_, Eigen::Vector3d::Ones(), feature_.data());
  surface_voxels_ = static_cast<int>(sites_.size());
  seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

Eigen::Vector3d SurfaceVectorField::vectorToSurface(const Eigen::Vector3d& p_m) const {
  if (surface_voxels_ == 0) throw std::logic_error("SurfaceVectorField::vectorToSurface: the last rebuild failed; rebuild first");
  // The voxel cell around p (clamped into the grid) and its eight corners' candidates.
  const Eigen::Vector3d t = (p_m - origin_) / h_;
  int i0[3];
  for (int c = 0; c < 3; ++c)
    i0[c] = std::min(static_cast<int>(std::clamp(t[c], 0.0, static_cast<double>(size_[c] - 1))), size_[c] - 2);
  const long nx = size_.x(), nxy = nx * size_.y();
  const int nyv = size_.y(), nzv = size_.z();
  std::int32_t voxels[8];
  int nv = 0;
  double best = std::numeric_limits<double>::infinity();
  Eigen::Vector3d best_q = p_m;
  auto offer = [&](const Eigen::Vector3d& q) {
    const double d2 = (q - p_m).squaredNorm();
    if (d2 < best) {  // strictly closer: of equal candidates the first offered wins
      best = d2;
      best_q = q;
    }
  };
  // Neighbouring voxels share their nearest triangle, so candidates repeat (up to 8 × 27 of them):
  // each triangle's closest point is computed once, its index kept in a small open-addressing set
  // (more slots than candidates, so it never fills). A point cloud's candidates skip the set: a
  // point's distance costs less than the look-up.
  constexpr int kSlots = 256;
  std::int32_t seen[kSlots];
  const bool cloud = target_.isPointCloud();
  if (!cloud) std::fill(seen, seen + kSlots, -1);
  auto consider = [&](std::int32_t e) {
    if (e < 0) return;
    if (cloud) {
      offer(target_.vertices_m.row(e).transpose());
      return;
    }
    for (unsigned h = (static_cast<std::uint32_t>(e) * 2654435761u) >> 24;; h = (h + 1) & (kSlots - 1)) {
      if (seen[h] == e) return;
      if (seen[h] < 0) {
        seen[h] = e;
        break;
      }
    }
    offer(closestPointOnTriangle(p_m, target_.vertices_m.row(target_.triangles(e, 0)).transpose(),
                                 target_.vertices_m.row(target_.triangles(e, 1)).transpose(),
                                 target_.vertices_m.row(target_.triangles(e, 2)).transpose()));
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
          consider(element_[di + nx * dj + nxy * dk] - 1);
  }
  return best_q - p_m;
}

}  // namespace breast_sim::core
