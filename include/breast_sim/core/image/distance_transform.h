#pragma once
/// @file distance_transform.h
/// Exact Euclidean distance transform of a binary voxel mask, in linear time.

#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace breast_sim::core {

/// Exact Euclidean distance from every voxel centre to the nearest voxel centre where `mask` is
/// non-zero, with anisotropic voxel spacing [Felzenszwalb & Huttenlocher 2012: separable lower
/// envelope of parabolas; O(#voxels), parallel over lines].
/// @param mask     size.prod() flags, i fastest (as LabelImage)
/// @param size     voxels along i, j, k
/// @param spacing  voxel size along i, j, k (any unit; the result is in the same unit)
/// @return size.prod() distances; 0 on the mask; +infinity everywhere if the mask is empty
/// @throws std::invalid_argument if a size is not positive or the mask has another length
std::vector<float> euclideanDistanceTransform(const std::vector<std::uint8_t>& mask,
                                              const Eigen::Vector3i& size,
                                              const Eigen::Vector3d& spacing);

/// The nearest mask voxel of every voxel (its linear index, i fastest), by the same separable
/// algorithm carrying each parabola's site along (exact nearest site up to ties).
/// @param distance  when not null, set to the distances as euclideanDistanceTransform gives them
/// @return size.prod() indices; −1 everywhere if the mask is empty
/// @throws std::invalid_argument as euclideanDistanceTransform, or for more than 2³¹ − 1 voxels
std::vector<std::int32_t> euclideanFeatureTransform(const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
                                                    const Eigen::Vector3d& spacing, std::vector<float>* distance = nullptr);

/// O(#voxels × #mask) reference of euclideanDistanceTransform, for tests only.
std::vector<float> bruteForceDistanceTransform(const std::vector<std::uint8_t>& mask,
                                               const Eigen::Vector3i& size,
                                               const Eigen::Vector3d& spacing);

}  // namespace breast_sim::core
