#include "breast_sim/core/image/distance_transform.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace breast_sim::core {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr int kBlock = 16;  // lines gathered together in the k pass (16 int32 = one 64-byte cache line)

// Lower envelope of the parabolas h2·(q − pos[a])² + g[a], a = 0 … m−1 (pos strictly ascending,
// every g finite, m ≥ 1), evaluated at q = 0 … len−1: out[q·out_stride] = site[the lowest parabola
// at q]. fa holds g[a] + h2·pos[a]² on entry. Parabola v[t] is lowest from zn[t]/zd[t] on; the
// intersections stay fractions (cross-multiplied, no division on the critical path; with integer
// g and h2 = 1 every product is an exact integer). v (m), zn and zd (m + 1) are scratch.
inline void envelope(const int* pos, const double* fa, const std::int32_t* site, int m, int len, double h2, int* v,
                     double* zn, double* zd, std::int32_t* out, long out_stride) {
  int k = 0;
  v[0] = 0;
  for (int a = 1; a < m; ++a) {
    double num, den;
    while (true) {
      const int b = v[k];
      num = fa[a] - fa[b];
      den = 2.0 * h2 * (pos[a] - pos[b]);
      if (k > 0 && num * zd[k] <= zn[k] * den) {  // a's crossing with b is at or before b's start: b is hidden
        --k;
        continue;
      }
      break;
    }
    ++k;
    v[k] = a;
    zn[k] = num;
    zd[k] = den;
  }
  zn[k + 1] = kInf;
  zd[k + 1] = 1.0;
  k = 0;
  for (int q = 0; q < len; ++q) {
    while (zn[k + 1] < q * zd[k + 1]) ++k;
    out[q * out_stride] = site[v[k]];
  }
}

void checkGrid(const char* who, const Eigen::Vector3i& size, const Eigen::Vector3d& spacing) {
  if ((size.array() <= 0).any()) throw std::invalid_argument(std::string(who) + ": every size must be positive");
  if (!(spacing.array() > 0).all() || !spacing.allFinite())
    throw std::invalid_argument(std::string(who) + ": every spacing must be positive and finite");
  const long n = static_cast<long>(size.x()) * size.y() * size.z();
  if (n > std::numeric_limits<std::int32_t>::max())
    throw std::invalid_argument(std::string(who) + ": " + std::to_string(n) + " voxels do not fit 32-bit indices");
}

void checkMask(const char* who, const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
               const Eigen::Vector3d& spacing) {
  checkGrid(who, size, spacing);
  if (static_cast<long>(mask.size()) != static_cast<long>(size.x()) * size.y() * size.z())
    throw std::invalid_argument(std::string(who) + ": mask has " + std::to_string(mask.size()) + " voxels, size gives " +
                                std::to_string(static_cast<long>(size.x()) * size.y() * size.z()));
}

std::vector<std::int32_t> sitesOf(const std::vector<std::uint8_t>& mask) {
  std::vector<std::int32_t> sites;
  for (size_t i = 0; i < mask.size(); ++i)
    if (mask[i]) sites.push_back(static_cast<std::int32_t>(i));
  return sites;
}

// Exact distance from every voxel to its feature (+∞ where there is none).
std::vector<float> featureDistances(const std::vector<std::int32_t>& feature, const Eigen::Vector3i& size,
                                    const Eigen::Vector3d& spacing) {
  const long nx = size.x(), nxy = nx * size.y(), n = static_cast<long>(feature.size());
  std::vector<float> out(n);
#pragma omp parallel for schedule(static)
  for (long i = 0; i < n; ++i) {
    const long f = feature[i];
    if (f < 0) {
      out[i] = std::numeric_limits<float>::infinity();
      continue;
    }
    const double dx = spacing.x() * static_cast<double>(i % nx - f % nx);
    const double dy = spacing.y() * static_cast<double>((i / nx) % size.y() - (f / nx) % size.y());
    const double dz = spacing.z() * static_cast<double>(i / nxy - f / nxy);
    out[i] = static_cast<float>(std::sqrt(dx * dx + dy * dy + dz * dz));
  }
  return out;
}

}  // namespace

void euclideanFeatureTransformOfSites(const std::vector<std::int32_t>& sites, const Eigen::Vector3i& size,
                                      const Eigen::Vector3d& spacing, std::int32_t* feature) {
  const char* who = "euclideanFeatureTransformOfSites";
  checkGrid(who, size, spacing);
  const int nx = size.x(), ny = size.y(), nz = size.z();
  const long nxy = static_cast<long>(nx) * ny, n = nxy * nz;
  const long num_sites = static_cast<long>(sites.size());
  for (long s = 0; s < num_sites; ++s)
    if (sites[s] < 0 || sites[s] >= n || (s > 0 && sites[s] <= sites[s - 1]))
      throw std::invalid_argument(std::string(who) + ": site " + std::to_string(s) + " = " + std::to_string(sites[s]) +
                                  " is out of range [0, " + std::to_string(n) + ") or not above the previous one");
  if (num_sites == 0) {
    std::fill(feature, feature + n, -1);
    return;
  }
  // Sites of each slice: sites[slice_begin[k] … slice_begin[k + 1]); the slices holding any.
  std::vector<long> slice_begin(nz + 1, 0);
  for (long s = 0; s < num_sites; ++s) ++slice_begin[sites[s] / nxy + 1];
  std::vector<int> full_slices;
  for (int k = 0; k < nz; ++k) {
    if (slice_begin[k + 1] > 0) full_slices.push_back(k);
    slice_begin[k + 1] += slice_begin[k];
  }
  const double hx2 = spacing.x() * spacing.x(), hy2 = spacing.y() * spacing.y(), hz2 = spacing.z() * spacing.z();
  const int nmax = std::max(nx, std::max(ny, nz));

  // Passes along i and j, slice by slice (slices without a site are left for the k pass to fill).
#pragma omp parallel
  {
    std::vector<int> rows(ny), v(nmax);
    std::vector<double> fa(nmax), zn(nmax + 1), zd(nmax + 1);
    std::vector<std::int32_t> site(nmax);
#pragma omp for schedule(dynamic, 1)
    for (long fs = 0; fs < static_cast<long>(full_slices.size()); ++fs) {
      const int k = full_slices[fs];
      std::int32_t* slice = feature + k * nxy;
      // i: each row with sites takes its nearest one (ties: the lower i).
      int num_rows = 0;
      for (long s = slice_begin[k]; s < slice_begin[k + 1];) {
        const long r0 = sites[s] - k * nxy;
        const int j = static_cast<int>(r0 / nx);
        std::int32_t* row = slice + static_cast<long>(j) * nx;
        const std::int32_t row_base = static_cast<std::int32_t>(k * nxy + static_cast<long>(j) * nx);
        long e = s;
        while (e < slice_begin[k + 1] && sites[e] < row_base + nx) ++e;
        int i = 0;
        for (long t = s; t < e; ++t) {
          const int c = sites[t] - row_base;
          const int last = t + 1 < e ? (c + (sites[t + 1] - row_base)) / 2 : nx - 1;  // midpoint to the next site
          for (; i <= last; ++i) row[i] = sites[t];
        }
        rows[num_rows++] = j;
        s = e;
      }
      // j: every column's finite samples are the rows just filled.
      for (int i = 0; i < nx; ++i) {
        for (int a = 0; a < num_rows; ++a) {
          const std::int32_t f = slice[static_cast<long>(rows[a]) * nx + i];
          const double di = i - (f - static_cast<std::int32_t>(k * nxy + static_cast<long>(rows[a]) * nx));
          fa[a] = hx2 * di * di + hy2 * rows[a] * rows[a];
          site[a] = f;
        }
        envelope(rows.data(), fa.data(), site.data(), num_rows, ny, hy2, v.data(), zn.data(), zd.data(), slice + i, nx);
      }
    }
  }

  // Pass along k, over blocks of kBlock neighbouring lines (consecutive i, then j).
  const int m = static_cast<int>(full_slices.size());
  const double inv_nx = 1.0 / nx;
  const long blocks = (nxy + kBlock - 1) / kBlock;
#pragma omp parallel
  {
    std::vector<std::int32_t> in(static_cast<size_t>(m) * kBlock), out(static_cast<size_t>(nz) * kBlock), site(m);
    std::vector<int> v(m);
    std::vector<double> fa(m), zn(m + 1), zd(m + 1);
#pragma omp for schedule(static)
    for (long blk = 0; blk < blocks; ++blk) {
      const long l0 = blk * kBlock;
      const int width = static_cast<int>(std::min<long>(kBlock, nxy - l0));
      for (int a = 0; a < m; ++a) {
        const std::int32_t* src = feature + full_slices[a] * nxy + l0;
        for (int b = 0; b < width; ++b) in[a * kBlock + b] = src[b];
      }
      for (int b = 0; b < width; ++b) {
        const long l = l0 + b;
        const int j = static_cast<int>(l / nx), i = static_cast<int>(l - static_cast<long>(j) * nx);
        for (int a = 0; a < m; ++a) {
          const std::int32_t f = in[a * kBlock + b];
          const long r = f - full_slices[a] * nxy;  // the site's place in its slice
          // r / nx exactly: (r + ½)/nx is at least ½/nx away from an integer, far beyond rounding.
          const int fj = static_cast<int>((static_cast<double>(r) + 0.5) * inv_nx);
          const double di = i - (r - static_cast<long>(fj) * nx), dj = j - fj;
          fa[a] = hx2 * di * di + hy2 * dj * dj + hz2 * full_slices[a] * full_slices[a];
          site[a] = f;
        }
        envelope(full_slices.data(), fa.data(), site.data(), m, nz, hz2, v.data(), zn.data(), zd.data(), out.data() + b, kBlock);
      }
      for (int q = 0; q < nz; ++q) {
        std::int32_t* dst = feature + q * nxy + l0;
        for (int b = 0; b < width; ++b) dst[b] = out[q * kBlock + b];
      }
    }
  }
}

std::vector<std::int32_t> euclideanFeatureTransform(const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
                                                    const Eigen::Vector3d& spacing, std::vector<float>* distance) {
  checkMask("euclideanFeatureTransform", mask, size, spacing);
  std::vector<std::int32_t> feature(mask.size());
  euclideanFeatureTransformOfSites(sitesOf(mask), size, spacing, feature.data());
  if (distance) *distance = featureDistances(feature, size, spacing);
  return feature;
}

std::vector<float> euclideanDistanceTransform(const std::vector<std::uint8_t>& mask,
                                              const Eigen::Vector3i& size,
                                              const Eigen::Vector3d& spacing) {
  checkMask("euclideanDistanceTransform", mask, size, spacing);
  std::vector<std::int32_t> feature(mask.size());
  euclideanFeatureTransformOfSites(sitesOf(mask), size, spacing, feature.data());
  return featureDistances(feature, size, spacing);
}

std::vector<float> bruteForceDistanceTransform(const std::vector<std::uint8_t>& mask,
                                               const Eigen::Vector3i& size,
                                               const Eigen::Vector3d& spacing) {
  const long n = static_cast<long>(size.prod());
  std::vector<Eigen::Vector3d> sites;
  for (int k = 0; k < size.z(); ++k)
    for (int j = 0; j < size.y(); ++j)
      for (int i = 0; i < size.x(); ++i)
        if (mask[i + static_cast<long>(size.x()) * (j + static_cast<long>(size.y()) * k)])
          sites.emplace_back(i * spacing.x(), j * spacing.y(), k * spacing.z());
  std::vector<float> out(n, std::numeric_limits<float>::infinity());
  for (int k = 0; k < size.z(); ++k)
    for (int j = 0; j < size.y(); ++j)
      for (int i = 0; i < size.x(); ++i) {
        const Eigen::Vector3d p(i * spacing.x(), j * spacing.y(), k * spacing.z());
        double best = std::numeric_limits<double>::infinity();
        for (const auto& s : sites) best = std::min(best, (p - s).squaredNorm());
        out[i + static_cast<long>(size.x()) * (j + static_cast<long>(size.y()) * k)] =
            static_cast<float>(std::sqrt(best));
      }
  return out;
}

}  // namespace breast_sim::core
