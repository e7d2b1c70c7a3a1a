#pragma once
/// @file distance_transform.h
/// Exact Euclidean distance and feature (nearest-site) transforms of a voxel grid, in linear time.
///
/// The transform is separable [Felzenszwalb & Huttenlocher 2012; Meijster et al. 2000]: along i
/// each voxel takes the nearest site of its own line; along j and then k each line's squared
/// distances are the lower envelope of parabolas h²(q − p)² + g(p) rooted at the line's samples.
/// Squared distances are never stored: a sample's g is recomputed from the site it carries (its
/// offset in the axes already done), so only the int32 site index travels between passes. A line
/// along j (k) holds a finite sample exactly at the rows (slices) that contain a site, the same for
/// every line, so each envelope is built over those samples only and evaluated at every voxel.
/// The i and j passes run slice by slice (a slice stays in cache); the k pass gathers blocks of 16
/// neighbouring lines so every cache line read is used whole. Parallel over slices / line blocks.

#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace breast_sim::core {

/// Exact Euclidean distance from every voxel centre to the nearest voxel centre where `mask` is
/// non-zero, with anisotropic voxel spacing (O(#voxels), parallel).
/// @param mask     size.prod() flags, i fastest (as LabelImage)
/// @param size     voxels along i, j, k
/// @param spacing  voxel size along i, j, k (any unit; the result is in the same unit)
/// @return size.prod() distances; 0 on the mask; +infinity everywhere if the mask is empty
/// @throws std::invalid_argument if a size or spacing is not positive, the mask has another length,
///         or the grid has more than 2³¹ − 1 voxels
std::vector<float> euclideanDistanceTransform(const std::vector<std::uint8_t>& mask,
                                              const Eigen::Vector3i& size,
                                              const Eigen::Vector3d& spacing);

/// The nearest mask voxel of every voxel (its linear index, i fastest), by the same separable
/// algorithm (an exact nearest site; among equally near sites any one, deterministically).
/// @param distance  when not null, set to the distances as euclideanDistanceTransform gives them
/// @return size.prod() indices; −1 everywhere if the mask is empty
/// @throws std::invalid_argument as euclideanDistanceTransform
std::vector<std::int32_t> euclideanFeatureTransform(const std::vector<std::uint8_t>& mask, const Eigen::Vector3i& size,
                                                    const Eigen::Vector3d& spacing, std::vector<float>* distance = nullptr);

/// The feature transform of a sparse set of sites into caller-owned storage (no allocation of
/// grid size; for rebuilding a field again and again in the same buffer).
/// @param sites    linear indices (i fastest) of the site voxels, strictly ascending
/// @param size     voxels along i, j, k
/// @param spacing  voxel size along i, j, k (only ratios matter)
/// @param feature  size.prod() writable entries; every one is set to the index of a nearest site,
///                 or to −1 everywhere when `sites` is empty. Its previous content is irrelevant.
/// @throws std::invalid_argument if a size or spacing is not positive, the grid has more than
///         2³¹ − 1 voxels, or a site is out of range or out of order
void euclideanFeatureTransformOfSites(const std::vector<std::int32_t>& sites, const Eigen::Vector3i& size,
                                      const Eigen::Vector3d& spacing, std::int32_t* feature);

/// O(#voxels × #mask) reference of euclideanDistanceTransform, for tests only.
std::vector<float> bruteForceDistanceTransform(const std::vector<std::uint8_t>& mask,
                                               const Eigen::Vector3i& size,
                                               const Eigen::Vector3d& spacing);

}  // namespace breast_sim::core
