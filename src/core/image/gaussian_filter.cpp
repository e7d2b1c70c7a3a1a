#include "breast_sim/core/image/gaussian_filter.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

namespace breast_sim::core {

namespace {

[[noreturn]] void bad(const std::string& what, double value, const std::string& range) {
  std::ostringstream s;
  s << what << " = " << value << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

void checkImage(const ScalarImage& image, const char* who) {
  image.geometry.validate();
  if (static_cast<long>(image.values.size()) != image.geometry.numVoxels())
    throw std::invalid_argument(std::string(who) + ": the image has " + std::to_string(image.values.size()) +
                                " values, its size gives " + std::to_string(image.geometry.numVoxels()));
}

void checkSigma(double sigma_m, int order_x, int order_y, int order_z) {
  if (!(sigma_m > 0) || !std::isfinite(sigma_m)) bad("gaussian filter sigma_m", sigma_m, "a finite value > 0 [m], e.g. 0.002");
  for (int o : {order_x, order_y, order_z})
    if (o != 0 && o != 1) bad("gaussian filter derivative order", o, "0 or 1");
}

// One 1-D correlation pass along `axis` with a kernel of radius r (2r+1 taps), clamped border.
void pass(const std::vector<float>& in, std::vector<float>& out, const Eigen::Vector3i& size, int axis,
          const std::vector<double>& kernel) {
  const int nx = size.x(), ny = size.y(), nz = size.z();
  const int r = static_cast<int>(kernel.size() / 2);
  std::vector<float> k(kernel.begin(), kernel.end());
  out.resize(in.size());
  if (axis == 0) {
    const long lines = static_cast<long>(ny) * nz;
#pragma omp parallel
    {
      std::vector<float> buf(nx + 2 * r);
#pragma omp for schedule(static)
      for (long line = 0; line < lines; ++line) {
        const float* src = in.data() + line * nx;
        float* dst = out.data() + line * nx;
        for (int i = 0; i < r; ++i) buf[i] = src[0];
        std::copy(src, src + nx, buf.begin() + r);
        for (int i = 0; i < r; ++i) buf[nx + r + i] = src[nx - 1];
        for (int i = 0; i < nx; ++i) {
          float acc = 0.0f;
          const float* b = buf.data() + i;  // b[t + r] = in[i + t]
          for (int t = 0; t <= 2 * r; ++t) acc += k[t] * b[t];
          dst[i] = acc;
        }
      }
    }
    return;
  }
  // Axes j and k: each output row (fixed j, k) is a weighted sum of whole input rows, so the inner
  // loop runs over contiguous i and vectorises.
  const long rows = static_cast<long>(ny) * nz;
  const int len = axis == 1 ? ny : nz;
#pragma omp parallel for schedule(static)
  for (long row = 0; row < rows; ++row) {
    const int j = static_cast<int>(row % ny), kk = static_cast<int>(row / ny);
    float* dst = out.data() + row * nx;
    std::fill(dst, dst + nx, 0.0f);
    const int c = axis == 1 ? j : kk;
    for (int t = -r; t <= r; ++t) {
      const int q = std::clamp(c + t, 0, len - 1);
      const long src_row = axis == 1 ? (q + static_cast<long>(ny) * kk) : (j + static_cast<long>(ny) * q);
      const float* src = in.data() + src_row * nx;
      const float w = k[t + r];
      for (int i = 0; i < nx; ++i) dst[i] += w * src[i];
    }
  }
}

// Kernel of one axis, scaled to "per metre" for a derivative.
std::vector<double> axisKernel(const ImageGeometry& g, int axis, double sigma_m, int order, double truncate) {
  std::vector<double> k = gaussianKernel1d(sigma_m / g.spacing_m[axis], order, truncate);
  if (order == 1)
    for (double& w : k) w /= g.spacing_m[axis];
  return k;
}

}  // namespace

ImageGeometry ImageGeometry::of(const LabelImage& image) {
  ImageGeometry g;
  g.size = image.size;
  g.spacing_m = image.spacing_m;
  g.origin_m = image.origin_m;
  g.direction = image.direction;
  return g;
}

void ImageGeometry::validate() const {
  for (int a = 0; a < 3; ++a)
    if (size[a] < 1) bad("image size[" + std::to_string(a) + "]", size[a], "≥ 1 voxel");
  for (int a = 0; a < 3; ++a)
    if (!(spacing_m[a] > 0) || !std::isfinite(spacing_m[a]))
      bad("image spacing_m[" + std::to_string(a) + "]", spacing_m[a], "a finite voxel size > 0 [m]");
  if (!origin_m.allFinite()) bad("image origin_m norm", origin_m.norm(), "finite coordinates [m]");
  const double err = (direction.transpose() * direction - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (!(err <= 1e-6)) bad("image direction deviation from orthonormal", err, "≤ 1e-6 (orthonormal columns)");
}

ScalarImage labelMask(const LabelImage& image, const std::set<std::uint16_t>& labels) {
  image.validate();
  ScalarImage m;
  m.geometry = ImageGeometry::of(image);
  const long n = image.numVoxels();
  m.values.resize(n);
  bool lut[65536] = {};
  for (std::uint16_t l : labels) lut[l] = true;
#pragma omp parallel for schedule(static)
  for (long i = 0; i < n; ++i) m.values[i] = lut[image.labels[i]] ? 1.0f : 0.0f;
  return m;
}

std::vector<double> gaussianKernel1d(double sigma_voxels, int order, double truncate_sigmas) {
  if (!(sigma_voxels > 0) || !std::isfinite(sigma_voxels))
    bad("gaussianKernel1d sigma_voxels", sigma_voxels, "a finite value > 0 [voxels]");
  if (order != 0 && order != 1) bad("gaussianKernel1d order", order, "0 (smoothing) or 1 (first derivative)");
  if (!(truncate_sigmas >= 1.0 && truncate_sigmas <= 10.0))
    bad("gaussian filter truncate_sigmas", truncate_sigmas, "[1, 10] standard deviations");
  const int r = std::max(1, static_cast<int>(std::ceil(truncate_sigmas * sigma_voxels)));
  std::vector<double> k(2 * r + 1);
  double norm = 0.0;
  for (int t = -r; t <= r; ++t) {
    const double g = std::exp(-0.5 * t * t / (sigma_voxels * sigma_voxels));
    k[t + r] = order == 0 ? g : t * g;
    norm += order == 0 ? g : static_cast<double>(t) * t * g;
  }
  for (double& w : k) w /= norm;
  return k;
}

ScalarImage gaussianFilter(const ScalarImage& image, double sigma_m, const Eigen::Vector3i& derivative_order,
                           double truncate_sigmas) {
  checkImage(image, "gaussianFilter");
  checkSigma(sigma_m, derivative_order.x(), derivative_order.y(), derivative_order.z());
  const ImageGeometry& g = image.geometry;
  ScalarImage out;
  out.geometry = g;
  std::vector<float> tmp;
  pass(image.values, tmp, g.size, 0, axisKernel(g, 0, sigma_m, derivative_order.x(), truncate_sigmas));
  pass(tmp, out.values, g.size, 1, axisKernel(g, 1, sigma_m, derivative_order.y(), truncate_sigmas));
  pass(out.values, tmp, g.size, 2, axisKernel(g, 2, sigma_m, derivative_order.z(), truncate_sigmas));
  out.values.swap(tmp);
  return out;
}

VectorImage gaussianGradient(const ScalarImage& image, double sigma_m, double truncate_sigmas) {
  checkImage(image, "gaussianGradient");
  checkSigma(sigma_m, 0, 0, 0);
  const ImageGeometry& g = image.geometry;
  std::vector<double> k0[3], k1[3];
  for (int a = 0; a < 3; ++a) {
    k0[a] = axisKernel(g, a, sigma_m, 0, truncate_sigmas);
    k1[a] = axisKernel(g, a, sigma_m, 1, truncate_sigmas);
  }
  // Seven passes: G_x, D_x; G_x G_y, G_x D_y, D_x G_y; then along z.
  std::vector<float> gx, dx, gxgy, gxdy, dxgy;
  pass(image.values, gx, g.size, 0, k0[0]);
  pass(image.values, dx, g.size, 0, k1[0]);
  pass(gx, gxgy, g.size, 1, k0[1]);
  pass(gx, gxdy, g.size, 1, k1[1]);
  pass(dx, dxgy, g.size, 1, k0[1]);
  std::vector<float>().swap(gx);
  std::vector<float>().swap(dx);
  VectorImage out;
  out.geometry = g;
  std::vector<float> di, dj, dk;
  pass(dxgy, di, g.size, 2, k0[2]);
  pass(gxdy, dj, g.size, 2, k0[2]);
  pass(gxgy, dk, g.size, 2, k1[2]);
  // Index-axis derivatives (per metre along each axis) to the patient frame: ∇ = D · (∂_i, ∂_j, ∂_k).
  const Eigen::Matrix3f D = g.direction.cast<float>();
  if (D.isIdentity(1e-7f)) {
    out.x.swap(di);
    out.y.swap(dj);
    out.z.swap(dk);
    return out;
  }
  const long n = g.numVoxels();
  out.x.resize(n);
  out.y.resize(n);
  out.z.resize(n);
#pragma omp parallel for schedule(static)
  for (long v = 0; v < n; ++v) {
    const Eigen::Vector3f p = D * Eigen::Vector3f(di[v], dj[v], dk[v]);
    out.x[v] = p.x();
    out.y[v] = p.y();
    out.z[v] = p.z();
  }
  return out;
}

ScalarImage bruteForceGaussianFilter(const ScalarImage& image, double sigma_m, const Eigen::Vector3i& order,
                                     double truncate_sigmas) {
  checkImage(image, "bruteForceGaussianFilter");
  checkSigma(sigma_m, order.x(), order.y(), order.z());
  if (!(truncate_sigmas >= 1.0 && truncate_sigmas <= 10.0))
    bad("gaussian filter truncate_sigmas", truncate_sigmas, "[1, 10] standard deviations");
  const ImageGeometry& g = image.geometry;
  int r[3];
  std::vector<double> w[3];
  for (int a = 0; a < 3; ++a) {
    const double s = sigma_m / g.spacing_m[a];
    r[a] = std::max(1, static_cast<int>(std::ceil(truncate_sigmas * s)));
    // Normalisation from the formulas: Σ G (order 0) or Σ t² G (order 1), derivative per metre.
    double sum = 0;
    for (int t = -r[a]; t <= r[a]; ++t) {
      const double e = std::exp(-(t * t) / (2.0 * s * s));
      w[a].push_back(order[a] ? t * e : e);
      sum += order[a] ? double(t) * t * e : e;
    }
    for (double& x : w[a]) x /= sum * (order[a] ? g.spacing_m[a] : 1.0);
  }
  ScalarImage out;
  out.geometry = g;
  out.values.assign(image.values.size(), 0.0f);
  const Eigen::Vector3i& n = g.size;
  for (int k = 0; k < n.z(); ++k)
    for (int j = 0; j < n.y(); ++j)
      for (int i = 0; i < n.x(); ++i) {
        double acc = 0;
        for (int c = -r[2]; c <= r[2]; ++c)
          for (int b = -r[1]; b <= r[1]; ++b)
            for (int a = -r[0]; a <= r[0]; ++a) {
              const double weight = w[0][a + r[0]] * w[1][b + r[1]] * w[2][c + r[2]];
              acc += weight * image.values[g.index(std::clamp(i + a, 0, n.x() - 1), std::clamp(j + b, 0, n.y() - 1),
                                                   std::clamp(k + c, 0, n.z() - 1))];
            }
        out.values[g.index(i, j, k)] = static_cast<float>(acc);
      }
  return out;
}

namespace {

// The 8 corner indices and weights of trilinear interpolation at p (clamped to the grid).
struct Stencil {
  long idx[8];
  double w[8];
};

inline Stencil stencil(const ImageGeometry& g, const Eigen::Vector3d& p_m) {
  const Eigen::Vector3d c = g.physicalToIndex(p_m);
  int i0[3], i1[3];
  double f[3];
  for (int a = 0; a < 3; ++a) {
    const int n = g.size[a];
    double x = std::isfinite(c[a]) ? std::clamp(c[a], 0.0, static_cast<double>(n - 1)) : 0.0;
    int lo = std::min(static_cast<int>(std::floor(x)), std::max(n - 2, 0));
    i0[a] = lo;
    i1[a] = std::min(lo + 1, n - 1);
    f[a] = x - lo;
  }
  Stencil s;
  int m = 0;
  for (int dk = 0; dk < 2; ++dk)
    for (int dj = 0; dj < 2; ++dj)
      for (int di = 0; di < 2; ++di) {
        s.idx[m] = g.index(di ? i1[0] : i0[0], dj ? i1[1] : i0[1], dk ? i1[2] : i0[2]);
        s.w[m] = (di ? f[0] : 1 - f[0]) * (dj ? f[1] : 1 - f[1]) * (dk ? f[2] : 1 - f[2]);
        ++m;
      }
  return s;
}

}  // namespace

double sampleTrilinear(const ScalarImage& image, const Eigen::Vector3d& p_m) {
  const Stencil s = stencil(image.geometry, p_m);
  double v = 0;
  for (int m = 0; m < 8; ++m) v += s.w[m] * image.values[s.idx[m]];
  return v;
}

Eigen::Vector3d sampleTrilinear(const VectorImage& image, const Eigen::Vector3d& p_m) {
  const Stencil s = stencil(image.geometry, p_m);
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  for (int m = 0; m < 8; ++m) {
    v.x() += s.w[m] * image.x[s.idx[m]];
    v.y() += s.w[m] * image.y[s.idx[m]];
    v.z() += s.w[m] * image.z[s.idx[m]];
  }
  return v;
}

bool insideGrid(const ImageGeometry& geometry, const Eigen::Vector3d& p_m) {
  const Eigen::Vector3d c = geometry.physicalToIndex(p_m);
  for (int a = 0; a < 3; ++a)
    if (!(c[a] >= 0.0 && c[a] <= geometry.size[a] - 1)) return false;
  return true;
}

}  // namespace breast_sim::core
