// The chest-wall boundary's robust fit: a median for a first estimate that dense tissue lying on the
// muscle cannot pull (its candidates are a minority in a wide window), then rounds of Gaussian
// normalized convolution [Knutsson & Westin 1993] with the candidates far from the fit left out.
#include "chest_wall_boundary.h"

#include <algorithm>
#include <cmath>

namespace breast_sim::core::boundary_fit {

namespace {

// A Gaussian of sigma_px pixels truncated at 4 sigma, and at `limit` pixels (beyond the grid it has
// nothing to weigh).
std::vector<double> kernel(double sigma_px, int limit) {
  const int r = std::max(1, std::min(limit, static_cast<int>(std::ceil(4.0 * sigma_px))));
  std::vector<double> k(2 * r + 1);
  for (int t = -r; t <= r; ++t) k[t + r] = std::exp(-0.5 * t * t / (sigma_px * sigma_px));
  return k;
}

// One pass of a box of half-width h along u (axis 0) or v (axis 1), zero outside the grid.
void boxPass(const ColumnGrid& g, std::vector<double>& f, int axis, int h) {
  const int n = axis == 0 ? g.nu : g.nv, lines = axis == 0 ? g.nv : g.nu;
  const long stride = axis == 0 ? 1 : g.nu;
  std::vector<double> line(n), prefix(n + 1);
  for (int l = 0; l < lines; ++l) {
    const long base = axis == 0 ? static_cast<long>(g.nu) * l : l;
    prefix[0] = 0.0;
    for (int t = 0; t < n; ++t) prefix[t + 1] = prefix[t] + f[base + t * stride];
    const double w = 1.0 / (2 * h + 1);
    for (int t = 0; t < n; ++t) line[t] = w * (prefix[std::min(n, t + h + 1)] - prefix[std::max(0, t - h)]);
    for (int t = 0; t < n; ++t) f[base + t * stride] = line[t];
  }
}

// Separable Gaussian over the column grid, zero outside it (a normalized convolution divides the
// weights out, so the border needs no rule of its own). Wide kernels (the coarse levels of the gap
// filling) are three box passes of the same variance, whose cost does not grow with sigma. Serial: a
// few tens of thousands of columns.
std::vector<double> blur(const ColumnGrid& g, const std::vector<double>& f, double sigma_mm) {
  const double su = sigma_mm / g.du, sv = sigma_mm / g.dv;
  if (std::max(su, sv) > 6.0) {
    std::vector<double> out = f;
    for (int pass = 0; pass < 3; ++pass) {
      boxPass(g, out, 0, static_cast<int>(std::lround(0.5 * (std::sqrt(4.0 * su * su + 1.0) - 1.0))));
      boxPass(g, out, 1, static_cast<int>(std::lround(0.5 * (std::sqrt(4.0 * sv * sv + 1.0) - 1.0))));
    }
    return out;
  }
  const std::vector<double> ku = kernel(su, g.nu), kv = kernel(sv, g.nv);
  const int ru = static_cast<int>(ku.size() / 2), rv = static_cast<int>(kv.size() / 2);
  std::vector<double> tmp(f.size()), out(f.size());
  for (int v = 0; v < g.nv; ++v)
    for (int u = 0; u < g.nu; ++u) {
      double s = 0.0;
      for (int t = std::max(-ru, -u); t <= std::min(ru, g.nu - 1 - u); ++t) s += ku[t + ru] * f[u + t + static_cast<long>(g.nu) * v];
      tmp[u + static_cast<long>(g.nu) * v] = s;
    }
  for (int v = 0; v < g.nv; ++v)
    for (int u = 0; u < g.nu; ++u) {
      double s = 0.0;
      for (int t = std::max(-rv, -v); t <= std::min(rv, g.nv - 1 - v); ++t) s += kv[t + rv] * tmp[u + static_cast<long>(g.nu) * (v + t)];
      out[u + static_cast<long>(g.nu) * v] = s;
    }
  return out;
}

// Normalized convolution at sigma, blended into the one at 2 sigma where the candidates thin out, and
// so on up to the mean of all: h_k = (G_k*(w h) + λ h_{k+1}) / (G_k*(w) + λ).
std::vector<double> normalizedConvolution(const ColumnGrid& g, const std::vector<float>& h,
                                          const std::vector<std::uint8_t>& w, double sigma_mm) {
  const long n = g.count();
  double sum = 0.0;
  long count = 0;
  for (long c = 0; c < n; ++c)
    if (w[c]) sum += h[c], ++count;
  std::vector<double> coarse(n, count ? sum / static_cast<double>(count) : 0.0);
  if (!count) return coarse;
  std::vector<double> sigmas;
  const double extent = std::max(g.nu * g.du, g.nv * g.dv);
  for (double s = sigma_mm; s < 2.0 * extent; s *= 2.0) sigmas.push_back(s);
  std::vector<double> wh(n), ww(n);
  for (long c = 0; c < n; ++c) {
    ww[c] = w[c] ? 1.0 : 0.0;
    wh[c] = w[c] ? h[c] : 0.0;
  }
  constexpr double kBlend = 0.01;  // a column with this much weight within σ is half its own estimate
  for (auto it = sigmas.rbegin(); it != sigmas.rend(); ++it) {
    const std::vector<double> num = blur(g, wh, *it), den = blur(g, ww, *it);
    for (long c = 0; c < n; ++c) coarse[c] = (num[c] + kBlend * coarse[c]) / (den[c] + kBlend);
  }
  return coarse;
}

}  // namespace

std::vector<float> robustSmoothFit(const ColumnGrid& g, const std::vector<float>& height,
                                   std::vector<std::uint8_t>& accepted, const FitOptions& o, int* rejected) {
  const long n = g.count();
  const std::vector<std::uint8_t> candidates = accepted;
  const double tolerance = o.outlier_mm / o.height_mm;
  // First estimate: the median of the candidates in a window around each column.
  if (o.median_window_mm > 0) {
    const int ru = static_cast<int>(std::floor(0.5 * o.median_window_mm / g.du));
    const int rv = static_cast<int>(std::floor(0.5 * o.median_window_mm / g.dv));
    std::vector<std::uint8_t> keep(candidates);
#pragma omp parallel
    {
      std::vector<float> window;
#pragma omp for schedule(dynamic, 4)
      for (int v = 0; v < g.nv; ++v)
        for (int u = 0; u < g.nu; ++u) {
          const long c = u + static_cast<long>(g.nu) * v;
          if (!candidates[c]) continue;
          window.clear();
          for (int q = std::max(0, v - rv); q <= std::min(g.nv - 1, v + rv); ++q)
            for (int p = std::max(0, u - ru); p <= std::min(g.nu - 1, u + ru); ++p) {
              const long d = p + static_cast<long>(g.nu) * q;
              if (candidates[d]) window.push_back(height[d]);
            }
          std::nth_element(window.begin(), window.begin() + window.size() / 2, window.end());
          keep[c] = std::abs(height[c] - window[window.size() / 2]) <= tolerance;
        }
    }
    accepted = keep;
  }
  std::vector<double> fit = normalizedConvolution(g, height, accepted, o.sigma_mm);
  for (int round = 0; round < o.iterations; ++round) {
    for (long c = 0; c < n; ++c) accepted[c] = candidates[c] && std::abs(height[c] - fit[c]) <= tolerance;
    fit = normalizedConvolution(g, height, accepted, o.sigma_mm);
  }
  if (rejected) {
    *rejected = 0;
    for (long c = 0; c < n; ++c) *rejected += candidates[c] && !accepted[c];
  }
  return std::vector<float>(fit.begin(), fit.end());
}

}  // namespace breast_sim::core::boundary_fit
