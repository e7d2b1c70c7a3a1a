#include "breast_sim/core/sliding/chest_wall_surface.h"

#include <algorithm>
#include <limits>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace breast_sim::core {

namespace {
constexpr double kSaturation = 1e-4;  // S is clamped to [kSaturation, 1 − kSaturation]
constexpr double kInvSqrt2Pi = 0.39894228040143267794;
}  // namespace

double normalQuantile(double p) {
  if (!(p > 0.0 && p < 1.0)) {
    std::ostringstream s;
    s << "normalQuantile: p = " << p << " is invalid: expected a probability in (0, 1)";
    throw std::invalid_argument(s.str());
  }
  static const double a[] = {-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
                             1.383577518672690e+02,  -3.066479806614716e+01, 2.506628277459239e+00};
  static const double b[] = {-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
                             6.680131188771972e+01,  -1.328068155288572e+01};
  static const double c[] = {-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
                             -2.549732539343734e+00, 4.374664141464968e+00,  2.938163982698783e+00};
  static const double d[] = {7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
                             3.754408661907416e+00};
  const double lo = 0.02425;
  double x;
  if (p < lo) {
    const double q = std::sqrt(-2.0 * std::log(p));
    x = (((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) /
        ((((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0);
  } else if (p <= 1.0 - lo) {
    const double q = p - 0.5, r = q * q;
    x = (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * q /
        (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0);
  } else {
    const double q = std::sqrt(-2.0 * std::log1p(-p));
    x = -(((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) /
        ((((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0);
  }
  // One Halley step on Φ(x) − p.
  const double e = 0.5 * std::erfc(-x / std::sqrt(2.0)) - p;
  const double u = e * std::sqrt(2.0 * M_PI) * std::exp(0.5 * x * x);
  return x - u / (1.0 + 0.5 * x * u);
}

void ChestWallFieldOptions::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "chest-wall field '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(sigma_m > 0) || !std::isfinite(sigma_m) || sigma_m > 0.05)
    bad("sigma_m", sigma_m, "(0, 0.05] m, e.g. 0.002 (2 mm)");
  if (!(truncate_sigmas >= 1 && truncate_sigmas <= 10)) bad("truncate_sigmas", truncate_sigmas, "[1, 10]");
}

ChestWallSurface::ChestWallSurface(const LabelImage& image, const std::set<std::uint16_t>& wall_labels,
                                   const ChestWallFieldOptions& options)
    : options_(options) {
  options_.validate();
  if (wall_labels.empty()) throw std::invalid_argument("ChestWallSurface: no chest-wall label given");
  const auto t0 = std::chrono::steady_clock::now();
  const ScalarImage mask = labelMask(image, wall_labels);
  bool any = false;
  for (float v : mask.values)
    if (v > 0) {
      any = true;
      break;
    }
  if (!any) {
    std::ostringstream s;
    s << "ChestWallSurface: the image has no voxel with a chest-wall label (labels:";
    for (auto l : wall_labels) s << ' ' << l;
    s << ")";
    throw std::invalid_argument(s.str());
  }
  smoothed_ = gaussianFilter(mask, options_.sigma_m, Eigen::Vector3i::Zero(), options_.truncate_sigmas);
  gradient_ = gaussianGradient(mask, options_.sigma_m, options_.truncate_sigmas);
  precompute_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

Eigen::Vector3d ChestWallSurface::normal(const Eigen::Vector3d& p_m) const {
  const Eigen::Vector3d g = sampleTrilinear(gradient_, p_m);
  const double n = g.norm();
  // |∇S| peaks at 1/(σ√(2π)) on a planar surface; below 1e-9 of that there is no direction.
  if (!(n > 1e-9 * kInvSqrt2Pi / options_.sigma_m)) return Eigen::Vector3d::Zero();
  return -g / n;
}

double ChestWallSurface::borderDistance(const Eigen::Vector3d& p_m) const {
  const ImageGeometry& g = smoothed_.geometry;
  const Eigen::Vector3d c = g.physicalToIndex(p_m);
  double d = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) d = std::min({d, c[a] * g.spacing_m[a], (g.size[a] - 1 - c[a]) * g.spacing_m[a]});
  return d;
}

double ChestWallSurface::signedDistance(const Eigen::Vector3d& p_m) const {
  const double s = std::clamp(smoothedMaskAt(p_m), kSaturation, 1.0 - kSaturation);
  return -options_.sigma_m * normalQuantile(s);
}

double ChestWallSurface::signedDistance(const Eigen::Vector3d& p_m, Eigen::Vector3d& gradient) const {
  const double s_raw = smoothedMaskAt(p_m);
  const double s = std::clamp(s_raw, kSaturation, 1.0 - kSaturation);
  const double q = normalQuantile(s);
  const double pdf = kInvSqrt2Pi * std::exp(-0.5 * q * q);
  // h = −σ Φ⁻¹(S): ∇h = −σ ∇S / φ(Φ⁻¹(S)); zero where S is saturated (clamped).
  gradient = (s_raw == s) ? Eigen::Vector3d(-options_.sigma_m / pdf * sampleTrilinear(gradient_, p_m))
                          : Eigen::Vector3d::Zero();
  return -options_.sigma_m * q;
}

WallProjection ChestWallSurface::project(const Eigen::Vector3d& p_m, double target_m, int max_iterations,
                                         double tolerance_m) const {
  WallProjection r;
  r.point_m = p_m;
  Eigen::Vector3d g;
  double h = signedDistance(r.point_m, g);
  r.residual_m = std::abs(h - target_m);
  // A Newton step longer than the field's reach is not trusted; halve steps that do not reduce |h − t|.
  const double max_step = 2.0 * options_.sigma_m;
  while (r.residual_m > tolerance_m && r.iterations < max_iterations) {
    const double g2 = g.squaredNorm();
    if (!(g2 > 1e-12)) break;  // saturated or flat: no direction
    Eigen::Vector3d step = -(h - target_m) / g2 * g;
    if (step.norm() > max_step) step *= max_step / step.norm();
    ++r.iterations;
    bool improved = false;
    for (int halvings = 0; halvings < 6; ++halvings) {
      Eigen::Vector3d gq;
      const Eigen::Vector3d q = r.point_m + step;
      const double hq = signedDistance(q, gq);
      if (std::abs(hq - target_m) < r.residual_m) {
        r.point_m = q;
        h = hq;
        g = gq;
        r.residual_m = std::abs(hq - target_m);
        improved = true;
        break;
      }
      step *= 0.5;
    }
    if (!improved) break;
  }
  r.converged = r.residual_m <= tolerance_m;
  return r;
}

}  // namespace breast_sim::core
