#include "breast_sim/core/image/distance_transform.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace breast_sim::core {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// 1-D squared distance transform of f (sampled at spacing h) into d, using the lower envelope of
// parabolas. v, z are scratch buffers of size n and n+1.
void edt1d(const double* f, double* d, int n, double h, int* v, double* z) {
  int k = 0;
  int first = 0;
  while (first < n && !std::isfinite(f[first])) ++first;
  if (first == n) {
    for (int q = 0; q < n; ++q) d[q] = kInf;
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
      // Intersection of the parabolas rooted at p and q, in index units. z[0] = −∞ stops the loop.
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
  }
}

// As edt1d, and fin/fout carry each sample's nearest site: fout[q] = fin[the parabola that wins at q].
void edt1dFeature(const double* f, const std::int32_t* fin, double* d, std::int32_t* fout, int n, double h, int* v,
                  double* z) {
  int k = 0;
  int first = 0;
  while (first < n && !std::isfinite(f[first])) ++first;
  if (first == n) {
    for (int q = 0; q < n; ++q) {
      d[q] = kInf;
      fout[q] = -1;
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
    fout[q] = fin[v[k]];
  }
}

void checkMask(const char* who, const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size) {
  if ((size.array() <= 0).any()) throw std::invalid_argument(std::string(who) + ": every size must be positive");
  if (static_cast<long>(mask.size()) != static_cast<long>(size.x()) * size.y() * size.z())
    throw std::invalid_argument(std::string(who) + ": mask has " + std::to_string(mask.size()) + " voxels, size gives " +
                                std::to_string(static_cast<long>(size.x()) * size.y() * size.z()));
}

}  // namespace

std::vector<std::int32_t> euclideanFeatureTransform(const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
                                                    const Eigen::Vector3d& spacing, std::vector<float>* distance) {
  checkMask("euclideanFeatureTransform", mask, size);
  const int nx = size.x(), ny = size.y(), nz = size.z();
  const long nxy = static_cast<long>(nx) * ny;
  const long n = nxy * nz;
  if (n > std::numeric_limits<std::int32_t>::max())
    throw std::invalid_argument("euclideanFeatureTransform: " + std::to_string(n) + " voxels do not fit 32-bit indices");
  std::vector<double> g(n);
  std::vector<std::int32_t> feature(n);
  for (long i = 0; i < n; ++i) {
    g[i] = mask[i] ? 0.0 : kInf;
    feature[i] = mask[i] ? static_cast<std::int32_t>(i) : -1;
  }
  const int nmax = std::max(nx, std::max(ny, nz));
  auto pass = [&](int axis) {
    const int len = axis == 0 ? nx : axis == 1 ? ny : nz;
    const long stride = axis == 0 ? 1 : axis == 1 ? nx : nxy;
    const long lines = n / len;
#pragma omp parallel
    {
      std::vector<double> f(nmax), d(nmax), z(nmax + 1);
      std::vector<int> v(nmax);
      std::vector<std::int32_t> fin(nmax), fout(nmax);
#pragma omp for schedule(static)
      for (long line = 0; line < lines; ++line) {
        long base;
        if (axis == 0) base = line * nx;
        else if (axis == 1) base = (line / nx) * nxy + (line % nx);
        else base = line;
        for (int q = 0; q < len; ++q) {
          f[q] = g[base + q * stride];
          fin[q] = feature[base + q * stride];
        }
        edt1dFeature(f.data(), fin.data(), d.data(), fout.data(), len, spacing[axis], v.data(), z.data());
        for (int q = 0; q < len; ++q) {
          g[base + q * stride] = d[q];
          feature[base + q * stride] = fout[q];
        }
      }
    }
  };
  pass(0);
  pass(1);
  pass(2);
  if (distance) {
    distance->resize(n);
    for (long i = 0; i < n; ++i) (*distance)[i] = static_cast<float>(std::sqrt(g[i]));
  }
  return feature;
}

std::vector<float> euclideanDistanceTransform(const std::vector<std::uint8_t>& mask,
                                              const Eigen::Vector3i& size,
                                              const Eigen::Vector3d& spacing) {
  checkMask("euclideanDistanceTransform", mask, size);
  const int nx = size.x(), ny = size.y(), nz = size.z();
  const long nxy = static_cast<long>(nx) * ny;
  const long n = nxy * nz;
  std::vector<double> g(n);
  for (long i = 0; i < n; ++i) g[i] = mask[i] ? 0.0 : kInf;
  const int nmax = std::max(nx, std::max(ny, nz));

  // Pass along each axis in turn; lines are independent, so parallel over them.
  auto pass = [&](int axis) {
    const int len = axis == 0 ? nx : axis == 1 ? ny : nz;
    const long stride = axis == 0 ? 1 : axis == 1 ? nx : nxy;
    const long lines = n / len;
#pragma omp parallel
    {
      std::vector<double> f(nmax), d(nmax), z(nmax + 1);
      std::vector<int> v(nmax);
#pragma omp for schedule(static)
      for (long line = 0; line < lines; ++line) {
        long base;
        if (axis == 0) base = line * nx;
        else if (axis == 1) base = (line / nx) * nxy + (line % nx);
        else base = line;
        for (int q = 0; q < len; ++q) f[q] = g[base + q * stride];
        edt1d(f.data(), d.data(), len, spacing[axis], v.data(), z.data());
        for (int q = 0; q < len; ++q) g[base + q * stride] = d[q];
      }
    }
  };
  pass(0);
  pass(1);
  pass(2);
  std::vector<float> out(n);
  for (long i = 0; i < n; ++i) out[i] = static_cast<float>(std::sqrt(g[i]));
  return out;
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
