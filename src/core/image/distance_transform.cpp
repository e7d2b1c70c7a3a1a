#include "breast_sim/core/image/distance_transform.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace breast_sim::core {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// 1-D squared distance transform of f (sampled at spacing h) into d, using the lower envelope of
// parabolas; v, z are scratch buffers of size n and n+1. When fin/fout are given they carry each
// sample's nearest site along: fout[q] = fin[the parabola that wins at q].
void edt1d(const double* f, const std::int32_t* fin, double* d, std::int32_t* fout, int n, double h, int* v,
                  double* z) {
  int k = 0;
  int first = 0;
  while (first < n && !std::isfinite(f[first])) ++first;
  if (first == n) {
    for (int q = 0; q < n; ++q) {
      d[q] = kInf;
      if (fout) fout[q] = -1;
    }
    return;
  }
  v[0] = first;
  z[0] = -kInf;
  z[1] = kInf;
  const double h2 = h * h;
  for (int q = first + 1; q < n; ++q) {
    if (!std::isfinite(f[q])) continue;
    double s;
    while (true) {
      const int p = v[k];
      s = ((f[q] + h2 * q * q) - (f[p] + h2 * p * p)) / (2.0 * h2 * (q - p));
      if (s <= z[k]) {
        --k;
        continue;
      }
      break;
    }
    ++k;
    v[k] = q;
    z[k] = s;
    z[k + 1] = kInf;
  }
  k = 0;
  for (int q = 0; q < n; ++q) {
    while (z[k + 1] < q) ++k;
    const double dq = h * (q - v[k]);
    d[q] = dq * dq + f[v[k]];
    if (fout) fout[q] = fin[v[k]];
  }
}

void checkMask(const char* who, const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size) {
  if ((size.array() <= 0).any()) throw std::invalid_argument(std::string(who) + ": every size must be positive");
  if (static_cast<long>(mask.size()) != static_cast<long>(size.x()) * size.y() * size.z())
    throw std::invalid_argument(std::string(who) + ": mask has " + std::to_string(mask.size()) + " voxels, size gives " +
                                std::to_string(static_cast<long>(size.x()) * size.y() * size.z()));
}

// The separable transform: squared distances g (0 on the mask, +∞ elsewhere on entry) and, when
// `feature` is given, the nearest site of each voxel, one pass along each axis in turn (lines are
// independent, so parallel over them).
void separableTransform(std::vector<double>& g, std::vector<std::int32_t>* feature, const Eigen::Vector3i& size,
                        const Eigen::Vector3d& spacing) {
  const int nx = size.x(), ny = size.y(), nz = size.z();
  const long nxy = static_cast<long>(nx) * ny;
  const long n = nxy * nz;
  const int nmax = std::max(nx, std::max(ny, nz));
  std::int32_t* feat = feature ? feature->data() : nullptr;
  for (int axis = 0; axis < 3; ++axis) {
    const int len = axis == 0 ? nx : axis == 1 ? ny : nz;
    const long stride = axis == 0 ? 1 : axis == 1 ? nx : nxy;
    const long lines = n / len;
#pragma omp parallel
    {
      std::vector<double> f(nmax), d(nmax), z(nmax + 1);
      std::vector<int> v(nmax);
      std::vector<std::int32_t> fin(feat ? nmax : 0), fout(feat ? nmax : 0);
#pragma omp for schedule(static)
      for (long line = 0; line < lines; ++line) {
        long base;
        if (axis == 0) base = line * nx;
        else if (axis == 1) base = (line / nx) * nxy + (line % nx);
        else base = line;
        for (int q = 0; q < len; ++q) f[q] = g[base + q * stride];
        if (feat)
          for (int q = 0; q < len; ++q) fin[q] = feat[base + q * stride];
        edt1d(f.data(), feat ? fin.data() : nullptr, d.data(), feat ? fout.data() : nullptr, len, spacing[axis],
              v.data(), z.data());
        for (int q = 0; q < len; ++q) g[base + q * stride] = d[q];
        if (feat)
          for (int q = 0; q < len; ++q) feat[base + q * stride] = fout[q];
      }
    }
  }
}

std::vector<float> roots(const std::vector<double>& g) {
  std::vector<float> out(g.size());
  for (size_t i = 0; i < g.size(); ++i) out[i] = static_cast<float>(std::sqrt(g[i]));
  return out;
}

}  // namespace

std::vector<std::int32_t> euclideanFeatureTransform(const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
                                                    const Eigen::Vector3d& spacing, std::vector<float>* distance) {
  checkMask("euclideanFeatureTransform", mask, size);
  const long n = static_cast<long>(mask.size());
  if (n > std::numeric_limits<std::int32_t>::max())
    throw std::invalid_argument("euclideanFeatureTransform: " + std::to_string(n) + " voxels do not fit 32-bit indices");
  std::vector<double> g(n);
  std::vector<std::int32_t> feature(n);
  for (long i = 0; i < n; ++i) {
    g[i] = mask[i] ? 0.0 : kInf;
    feature[i] = mask[i] ? static_cast<std::int32_t>(i) : -1;
  }
  separableTransform(g, &feature, size, spacing);
  if (distance) *distance = roots(g);
  return feature;
}

std::vector<float> euclideanDistanceTransform(const std::vector<std::uint8_t>& mask,
                                              const Eigen::Vector3i& size,
                                              const Eigen::Vector3d& spacing) {
  checkMask("euclideanDistanceTransform", mask, size);
  std::vector<double> g(mask.size());
  for (size_t i = 0; i < mask.size(); ++i) g[i] = mask[i] ? 0.0 : kInf;
  separableTransform(g, nullptr, size, spacing);
  return roots(g);
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
