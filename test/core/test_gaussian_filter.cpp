// Separable Gaussian / derivative-of-Gaussian filter against a brute-force 3-D correlation, its
// derivatives against finite differences, trilinear sampling, and parameter checks.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include <Eigen/Geometry>

#include "breast_sim/core/image/gaussian_filter.h"

using namespace breast_sim::core;

namespace {

ScalarImage randomImage(const Eigen::Vector3i& size, const Eigen::Vector3d& spacing, unsigned seed) {
  ScalarImage im;
  im.geometry.size = size;
  im.geometry.spacing_m = spacing;
  im.geometry.origin_m = {0.01, -0.02, 0.003};
  im.values.resize(im.geometry.numVoxels());
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  for (float& v : im.values) v = u(rng);
  return im;
}

double maxAbsDiff(const std::vector<float>& a, const std::vector<float>& b) {
  double d = 0;
  for (size_t i = 0; i < a.size(); ++i) d = std::max(d, std::abs(double(a[i]) - b[i]));
  return d;
}

double maxAbs(const std::vector<float>& a) {
  double d = 0;
  for (float v : a) d = std::max(d, std::abs(double(v)));
  return d;
}

}  // namespace

TEST(GaussianKernel, SumsAndFirstMomentAreExact) {
  for (double s : {0.4, 1.0, 2.0, 3.7}) {
    const auto k0 = gaussianKernel1d(s, 0);
    const auto k1 = gaussianKernel1d(s, 1);
    const int r = static_cast<int>(k0.size() / 2);
    EXPECT_EQ(r, std::max(1, static_cast<int>(std::ceil(4 * s))));
    double sum = 0, m1 = 0, s1 = 0;
    for (int t = -r; t <= r; ++t) {
      sum += k0[t + r];
      m1 += t * k1[t + r];
      s1 += k1[t + r];
      EXPECT_NEAR(k0[t + r], k0[r - t], 1e-15);
    }
    EXPECT_NEAR(sum, 1.0, 1e-12);
    EXPECT_NEAR(m1, 1.0, 1e-12);
    EXPECT_NEAR(s1, 0.0, 1e-12);
  }
}

// The separable filter equals the direct 3-D correlation for every derivative order, anisotropic
// spacing, including the clamped border.
TEST(GaussianFilter, SeparableEqualsBruteForce3dCorrelation) {
  const ScalarImage im = randomImage({13, 9, 11}, {1e-3, 1.5e-3, 0.8e-3}, 7);
  const double sigma = 2e-3;
  for (const Eigen::Vector3i& order : {Eigen::Vector3i(0, 0, 0), Eigen::Vector3i(1, 0, 0), Eigen::Vector3i(0, 1, 0),
                                      Eigen::Vector3i(0, 0, 1), Eigen::Vector3i(1, 1, 0)}) {
    const ScalarImage fast = gaussianFilter(im, sigma, order, 3.0);
    const ScalarImage slow = bruteForceGaussianFilter(im, sigma, order, 3.0);
    const double scale = std::max(1.0, maxAbs(slow.values));
    EXPECT_LT(maxAbsDiff(fast.values, slow.values), 2e-6 * scale) << order.transpose();
  }
}

// The gradient (seven shared passes) equals the three single-derivative filters, rotated into the
// patient frame by the grid direction.
TEST(GaussianFilter, GradientEqualsPartialDerivativesRotatedByTheDirection) {
  ScalarImage im = randomImage({12, 10, 8}, {1e-3, 1.2e-3, 0.9e-3}, 3);
  im.geometry.direction = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const VectorImage g = gaussianGradient(im, 1.5e-3);
  const ScalarImage di = bruteForceGaussianFilter(im, 1.5e-3, {1, 0, 0});
  const ScalarImage dj = bruteForceGaussianFilter(im, 1.5e-3, {0, 1, 0});
  const ScalarImage dk = bruteForceGaussianFilter(im, 1.5e-3, {0, 0, 1});
  double worst = 0, scale = 0;
  for (long v = 0; v < im.geometry.numVoxels(); ++v) {
    const Eigen::Vector3d ref = im.geometry.direction * Eigen::Vector3d(di.values[v], dj.values[v], dk.values[v]);
    worst = std::max(worst, (Eigen::Vector3d(g.x[v], g.y[v], g.z[v]) - ref).norm());
    scale = std::max(scale, ref.norm());
  }
  EXPECT_LT(worst, 2e-6 * scale);
}

// On a linear field the smoothing keeps it and the derivative is its slope per metre (exact away
// from the border), in the patient frame for a rotated grid; the derivative also matches central
// finite differences of the smoothed image on a random one.
TEST(GaussianFilter, DerivativeOfLinearFieldIsItsSlopeAndMatchesFiniteDifferences) {
  ImageGeometry g;
  g.size = {30, 28, 26};
  g.spacing_m = {1e-3, 0.7e-3, 1.3e-3};
  g.origin_m = {-0.01, 0.02, 0.0};
  g.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0, 1, 1).normalized()).toRotationMatrix();
  const Eigen::Vector3d slope(30.0, -12.0, 7.0);  // per m
  ScalarImage lin;
  lin.geometry = g;
  lin.values.resize(g.numVoxels());
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i)
        lin.values[g.index(i, j, k)] = static_cast<float>(1.0 + slope.dot(g.indexToPhysical(Eigen::Vector3d(i, j, k))));
  const double sigma = 1.5e-3;
  const ScalarImage smooth = gaussianFilter(lin, sigma);
  const VectorImage grad = gaussianGradient(lin, sigma);
  int checked = 0;
  // Kernel radii ceil(4σ/h): 6, 9 and 5 voxels; only where the kernel does not reach the border.
  for (int k = 5; k < g.size.z() - 5; ++k)
    for (int j = 9; j < g.size.y() - 9; ++j)
      for (int i = 6; i < g.size.x() - 6; ++i) {
        const long v = g.index(i, j, k);
        ASSERT_NEAR(smooth.values[v], lin.values[v], 2e-5);
        ASSERT_LT((Eigen::Vector3d(grad.x[v], grad.y[v], grad.z[v]) - slope).norm(), 1e-3 * slope.norm());
        ++checked;
      }
  EXPECT_GT(checked, 1000);

  // Finite differences: ∂/∂i of the smoothed image ≈ (S[i+1] − S[i−1]) / 2h. Both are smooth, so the
  // central difference error is O(h²/σ²) of the derivative's scale.
  ScalarImage rnd = randomImage({24, 20, 18}, {1e-3, 1e-3, 1e-3}, 11);
  const double s2 = 3e-3;
  const ScalarImage S = gaussianFilter(rnd, s2);
  const ScalarImage Di = gaussianFilter(rnd, s2, {1, 0, 0});
  const ScalarImage Dk = gaussianFilter(rnd, s2, {0, 0, 1});
  double err = 0, scale = 0;
  const ImageGeometry& h = rnd.geometry;
  for (int k = 1; k < 17; ++k)
    for (int j = 1; j < 19; ++j)
      for (int i = 1; i < 23; ++i) {
        const double fdi = (S.values[h.index(i + 1, j, k)] - S.values[h.index(i - 1, j, k)]) / 2e-3;
        const double fdk = (S.values[h.index(i, j, k + 1)] - S.values[h.index(i, j, k - 1)]) / 2e-3;
        err = std::max({err, std::abs(fdi - Di.values[h.index(i, j, k)]), std::abs(fdk - Dk.values[h.index(i, j, k)])});
        scale = std::max({scale, std::abs(fdi), std::abs(fdk)});
      }
  EXPECT_GT(scale, 1.0);
  EXPECT_LT(err, 0.1 * scale);
}

TEST(TrilinearSampling, ExactOnLinearScalarAndVectorFieldsAndClampsOutside) {
  ImageGeometry g;
  g.size = {7, 6, 5};
  g.spacing_m = {2e-3, 1e-3, 3e-3};
  g.origin_m = {0.1, -0.05, 0.02};
  g.direction = Eigen::AngleAxisd(-0.7, Eigen::Vector3d(1, -1, 2).normalized()).toRotationMatrix();
  const Eigen::Vector3d a(5.0, -3.0, 2.0), b(-1.0, 4.0, 0.5);
  ScalarImage s;
  VectorImage v;
  s.geometry = v.geometry = g;
  for (int k = 0; k < 5; ++k)
    for (int j = 0; j < 6; ++j)
      for (int i = 0; i < 7; ++i) {
        const Eigen::Vector3d p = g.indexToPhysical(Eigen::Vector3d(i, j, k));
        s.values.push_back(static_cast<float>(0.25 + a.dot(p)));
        v.x.push_back(static_cast<float>(a.dot(p)));
        v.y.push_back(static_cast<float>(b.dot(p)));
        v.z.push_back(static_cast<float>(1.0 - p.x()));
      }
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (int n = 0; n < 200; ++n) {
    const Eigen::Vector3d ijk(u(rng) * 6, u(rng) * 5, u(rng) * 4);
    const Eigen::Vector3d p = g.indexToPhysical(ijk);
    ASSERT_TRUE(insideGrid(g, p));
    EXPECT_NEAR(sampleTrilinear(s, p), 0.25 + a.dot(p), 2e-6);
    const Eigen::Vector3d w = sampleTrilinear(v, p);
    EXPECT_NEAR(w.x(), a.dot(p), 2e-6);
    EXPECT_NEAR(w.y(), b.dot(p), 2e-6);
    EXPECT_NEAR(w.z(), 1.0 - p.x(), 2e-6);
  }
  // Outside: the value at the clamped index.
  const Eigen::Vector3d out = g.indexToPhysical(Eigen::Vector3d(-3.0, 2.5, 9.0));
  EXPECT_FALSE(insideGrid(g, out));
  const Eigen::Vector3d clamped = g.indexToPhysical(Eigen::Vector3d(0.0, 2.5, 4.0));
  EXPECT_NEAR(sampleTrilinear(s, out), 0.25 + a.dot(clamped), 2e-6);
}

TEST(GaussianFilter, LabelMaskMarksTheLabels) {
  LabelImage li({4, 3, 2}, {1e-3, 1e-3, 1e-3}, {0, 0, 0}, 0);
  li.at(1, 2, 1) = 40;
  li.at(3, 0, 0) = 41;
  li.at(0, 0, 0) = 1;
  const ScalarImage m = labelMask(li, {40, 41});
  EXPECT_EQ(m.values[li.index(1, 2, 1)], 1.0f);
  EXPECT_EQ(m.values[li.index(3, 0, 0)], 1.0f);
  EXPECT_EQ(m.values[li.index(0, 0, 0)], 0.0f);
  double sum = 0;
  for (float x : m.values) sum += x;
  EXPECT_EQ(sum, 2.0);
}

TEST(GaussianFilter, BadParametersAreNamedWithTheirRange) {
  const ScalarImage im = randomImage({5, 5, 5}, {1e-3, 1e-3, 1e-3}, 1);
  auto message = [](auto&& f) {
    try {
      f();
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("(no error)");
  };
  EXPECT_NE(message([&] { gaussianFilter(im, 0.0); }).find("sigma_m = 0"), std::string::npos);
  EXPECT_NE(message([&] { gaussianFilter(im, 1e-3, {2, 0, 0}); }).find("order = 2"), std::string::npos);
  EXPECT_NE(message([&] { gaussianFilter(im, 1e-3, {0, 0, 0}, 0.5); }).find("truncate_sigmas = 0.5"), std::string::npos);
  ScalarImage wrong = im;
  wrong.values.pop_back();
  EXPECT_NE(message([&] { gaussianGradient(wrong, 1e-3); }).find("124 values"), std::string::npos);
  ScalarImage sheared = im;
  sheared.geometry.direction(0, 1) = 0.1;
  EXPECT_THROW(gaussianFilter(sheared, 1e-3), std::invalid_argument);
}
