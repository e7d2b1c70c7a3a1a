#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "breast_sim/core/image/distance_transform.h"

using namespace breast_sim::core;

TEST(DistanceTransform, MatchesBruteForceOnRandomAnisotropicMasks) {
  std::mt19937 rng(7);
  for (int trial = 0; trial < 6; ++trial) {
    SCOPED_TRACE("trial " + std::to_string(trial));
    const Eigen::Vector3i size(5 + trial, 9 - trial / 2, 4 + 2 * trial);
    const Eigen::Vector3d spacing(0.5 + 0.3 * trial, 1.0, 2.0 - 0.2 * trial);
    std::vector<std::uint8_t> mask(size.prod());
    std::bernoulli_distribution on(trial == 0 ? 0.01 : 0.08 * trial);
    for (auto& m : mask) m = on(rng);
    mask[0] = 1;  // never empty
    const auto fast = euclideanDistanceTransform(mask, size, spacing);
    const auto slow = bruteForceDistanceTransform(mask, size, spacing);
    ASSERT_EQ(fast.size(), slow.size());
    for (size_t i = 0; i < fast.size(); ++i) ASSERT_NEAR(fast[i], slow[i], 1e-4 * (1 + slow[i])) << "voxel " << i;
  }
}

TEST(DistanceTransform, SinglePointGivesEuclideanDistanceInSpacingUnits) {
  const Eigen::Vector3i size(7, 6, 5);
  std::vector<std::uint8_t> mask(size.prod(), 0);
  mask[3 + 7 * (2 + 6 * 1)] = 1;  // voxel (3, 2, 1)
  const Eigen::Vector3d spacing(0.5, 1.0, 3.0);
  const auto d = euclideanDistanceTransform(mask, size, spacing);
  const double expected = std::sqrt(std::pow(0.5 * (6 - 3), 2) + std::pow(1.0 * (0 - 2), 2) + std::pow(3.0 * (4 - 1), 2));
  EXPECT_NEAR(d[6 + 7 * (0 + 6 * 4)], expected, 1e-5);
  EXPECT_EQ(d[3 + 7 * (2 + 6 * 1)], 0.0f);
}

TEST(DistanceTransform, EmptyMaskIsInfiniteEverywhere) {
  const Eigen::Vector3i size(3, 3, 3);
  const auto d = euclideanDistanceTransform(std::vector<std::uint8_t>(27, 0), size, Eigen::Vector3d::Ones());
  for (float v : d) EXPECT_TRUE(std::isinf(v));
}

// The feature transform's site is a nearest one: its distance equals the brute-force distance (ties
// may pick either site), and the distances it returns equal the distance transform's.
TEST(FeatureTransform, NearestSiteMatchesBruteForceDistances) {
  std::mt19937 rng(11);
  for (int trial = 0; trial < 5; ++trial) {
    SCOPED_TRACE("trial " + std::to_string(trial));
    const Eigen::Vector3i size(6 + trial, 8 - trial / 2, 5 + trial);
    const Eigen::Vector3d spacing(0.7 + 0.2 * trial, 1.0, 1.6 - 0.2 * trial);
    std::vector<std::uint8_t> mask(size.prod());
    std::bernoulli_distribution on(0.01 + 0.04 * trial);
    for (auto& m : mask) m = on(rng);
    mask[size.prod() / 2] = 1;
    std::vector<float> distance;
    const auto feature = euclideanFeatureTransform(mask, size, spacing, &distance);
    const auto slow = bruteForceDistanceTransform(mask, size, spacing);
    const auto fast = euclideanDistanceTransform(mask, size, spacing);
    auto position = [&](long i) {
      const long nx = size.x(), nxy = nx * size.y();
      return Eigen::Vector3d(spacing.x() * (i % nx), spacing.y() * ((i / nx) % size.y()), spacing.z() * (i / nxy));
    };
    for (long i = 0; i < size.prod(); ++i) {
      ASSERT_GE(feature[i], 0);
      ASSERT_TRUE(mask[feature[i]]) << "voxel " << i << " points to a voxel outside the mask";
      ASSERT_NEAR((position(i) - position(feature[i])).norm(), slow[i], 1e-4 * (1 + slow[i])) << "voxel " << i;
      ASSERT_EQ(distance[i], fast[i]);
    }
  }
  const auto none = euclideanFeatureTransform(std::vector<std::uint8_t>(8, 0), Eigen::Vector3i(2, 2, 2), Eigen::Vector3d::Ones());
  for (auto f : none) EXPECT_EQ(f, -1);
}

// The sparse-site entry point: every voxel gets a site at the brute-force distance, whatever the
// buffer held before, on grids with one-voxel axes too, and the same features as the mask version.
TEST(FeatureTransformOfSites, MatchesBruteForceAndTheMaskVersion) {
  std::mt19937 rng(23);
  const Eigen::Vector3i sizes[] = {{9, 7, 6}, {1, 8, 5}, {6, 1, 7}, {5, 6, 1}, {1, 1, 9}, {17, 3, 4}, {4, 5, 19}};
  int trial = 0;
  for (const Eigen::Vector3i& size : sizes) {
    SCOPED_TRACE("trial " + std::to_string(trial));
    const Eigen::Vector3d spacing(0.6 + 0.1 * trial, 1.0, 1.3 - 0.05 * trial);
    const long n = size.prod();
    std::vector<std::uint8_t> mask(n, 0);
    std::bernoulli_distribution on(0.02 + 0.03 * (trial % 4));
    for (auto& m : mask) m = on(rng);
    mask[(7 * trial + 3) % n] = 1;
    std::vector<std::int32_t> sites;
    for (long i = 0; i < n; ++i)
      if (mask[i]) sites.push_back(static_cast<std::int32_t>(i));
    std::vector<std::int32_t> feature(n, 123456789);  // garbage the transform must overwrite
    euclideanFeatureTransformOfSites(sites, size, spacing, feature.data());
    const auto slow = bruteForceDistanceTransform(mask, size, spacing);
    const auto from_mask = euclideanFeatureTransform(mask, size, spacing);
    auto position = [&](long i) {
      const long nx = size.x(), nxy = nx * size.y();
      return Eigen::Vector3d(spacing.x() * (i % nx), spacing.y() * ((i / nx) % size.y()), spacing.z() * (i / nxy));
    };
    for (long i = 0; i < n; ++i) {
      ASSERT_GE(feature[i], 0) << "voxel " << i;
      ASSERT_LT(feature[i], n) << "voxel " << i;
      ASSERT_TRUE(mask[feature[i]]) << "voxel " << i;
      ASSERT_NEAR((position(i) - position(feature[i])).norm(), slow[i], 1e-6 * (1 + slow[i])) << "voxel " << i;  // float reference
      ASSERT_EQ(feature[i], from_mask[i]) << "voxel " << i;
    }
    ++trial;
  }
}

// A lattice of sites is all ties: every voxel still gets a nearest one.
TEST(FeatureTransformOfSites, LatticeOfTiesGivesNearestSites) {
  const Eigen::Vector3i size(12, 10, 11);
  const Eigen::Vector3d spacing = Eigen::Vector3d::Ones();
  std::vector<std::uint8_t> mask(size.prod(), 0);
  std::vector<std::int32_t> sites;
  for (int k = 0; k < size.z(); k += 4)
    for (int j = 1; j < size.y(); j += 4)
      for (int i = 2; i < size.x(); i += 4) {
        const std::int32_t idx = i + size.x() * (j + size.y() * k);
        mask[idx] = 1;
        sites.push_back(idx);
      }
  std::vector<std::int32_t> feature(size.prod());
  euclideanFeatureTransformOfSites(sites, size, spacing, feature.data());
  std::vector<float> distance;
  euclideanFeatureTransform(mask, size, spacing, &distance);
  const auto slow = bruteForceDistanceTransform(mask, size, spacing);
  for (long i = 0; i < size.prod(); ++i) {
    ASSERT_TRUE(mask[feature[i]]);
    ASSERT_NEAR(distance[i], slow[i], 1e-6) << "voxel " << i;
  }
}

TEST(FeatureTransformOfSites, EmptyAndBadInput) {
  const Eigen::Vector3i size(3, 4, 5);
  std::vector<std::int32_t> feature(size.prod(), 7);
  euclideanFeatureTransformOfSites({}, size, Eigen::Vector3d::Ones(), feature.data());
  for (auto f : feature) EXPECT_EQ(f, -1);
  EXPECT_THROW(euclideanFeatureTransformOfSites({5, 3}, size, Eigen::Vector3d::Ones(), feature.data()), std::invalid_argument);
  EXPECT_THROW(euclideanFeatureTransformOfSites({4, 4}, size, Eigen::Vector3d::Ones(), feature.data()), std::invalid_argument);
  EXPECT_THROW(euclideanFeatureTransformOfSites({60}, size, Eigen::Vector3d::Ones(), feature.data()), std::invalid_argument);
  EXPECT_THROW(euclideanFeatureTransformOfSites({1}, Eigen::Vector3i(3, 0, 5), Eigen::Vector3d::Ones(), feature.data()),
               std::invalid_argument);
  EXPECT_THROW(euclideanFeatureTransformOfSites({1}, size, Eigen::Vector3d(1, 0, 1), feature.data()), std::invalid_argument);
}
