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
