#pragma once
/// @file surface_field.h
/// A dense vector field pointing from any point to the nearest point of a target surface, scaled by
/// the distance (seed section 2.5): the surface is rasterised into a 3-D grid, each surface voxel
/// keeps the triangle (or cloud point) nearest to its centre, and an exact Euclidean feature
/// transform (linear time) hands every voxel its nearest surface voxel. A sample at p takes the
/// nearest surface voxels of the eight surrounding voxels, the triangles of those and of their 26
/// neighbours as candidates, and returns the exact vector to the nearest candidate point,
/// so it is exact wherever the nearest triangle is among the candidates (always within a few voxels
/// of the surface, where morphing works) and continuous with the distance. The seed smooths a
/// distance image with a derivative-of-Gaussian filter instead; the exact candidates need no
/// smoothing and make sub-voxel surface distances possible at 1 mm voxels.

#include <cstdint>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/morphing/target_surface.h"

namespace breast_sim::core {

struct SurfaceFieldOptions {
  double voxel_size_m = 1e-3;       ///< grid spacing h [m]; made coarser if max_voxels_per_axis demands
  double margin_m = 0.02;           ///< the grid covers the region and the target plus this [m]
  int max_voxels_per_axis = 256;    ///< cap per axis (256³ = 16.8 M voxels)
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

class SurfaceVectorField {
 public:
  /// @param region_m  the space the model will move in (e.g. its bounding box); the grid covers it,
  ///        the target and the margin
  /// @throws std::invalid_argument as TargetSurface::validate and SurfaceFieldOptions::validate.
  SurfaceVectorField(const TargetSurface& target, const Eigen::AlignedBox3d& region_m,
                     const SurfaceFieldOptions& options = {});

  /// Vector from p to the nearest target point [m] (trilinear; outside the grid, clamped to it and
  /// continued by the offset to the grid).
  Eigen::Vector3d vectorToSurface(const Eigen::Vector3d& p_m) const;

  const Eigen::Vector3i& size() const { return size_; }
  double voxelSize() const { return h_; }
  const Eigen::Vector3d& origin() const { return origin_; }  ///< centre of voxel (0, 0, 0) [m]
  int numSurfaceVoxels() const { return surface_voxels_; }
  double buildSeconds() const { return seconds_; }

 private:
  Eigen::Vector3d origin_;
  double h_ = 0.0;
  Eigen::Vector3i size_;
  TargetSurface target_;
  std::vector<std::int32_t> feature_;  // per voxel: the nearest surface voxel (linear index)
  std::vector<std::int32_t> element_;  // per voxel: its triangle (or point) index if a surface voxel, else −1
  int surface_voxels_ = 0;
  double seconds_ = 0.0;
};

}  // namespace breast_sim::core
