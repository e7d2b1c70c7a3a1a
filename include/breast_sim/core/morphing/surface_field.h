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
///
/// Build cost (seed: 2–4 s; issue target ≤ 0.2 s for 256 voxels per axis on 2 cores): the
/// rasterisation runs slice by slice in parallel (each slice owns its voxels, triangles are binned
/// by slice, the nearest-element bookkeeping is one slice-sized buffer per thread), the feature
/// transform starts from the sparse list of surface voxels and carries only int32 site indices, and
/// the two dense int32 grids (element, feature) are the only grid-sized storage. rebuild() reuses
/// that storage when the new grid fits it (a tracker streaming clouds rebuilds every frame): it then
/// touches no fresh memory and resets only the previous surface voxels.

#include <cstdint>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/image/grid_buffer.h"
#include "breast_sim/core/morphing/target_surface.h"

namespace breast_sim::core {

/// The grid of a SurfaceVectorField. It covers the region and the target, grown by margin_m on
/// every side (extent E_c along axis c). The spacing is h = max(voxel_size_m, max_c E_c /
/// (max_voxels_per_axis − 1)), the same along all axes, and axis c has ⌈E_c / h⌉ + 1 voxel centres:
/// the longest axis never gets more than max_voxels_per_axis, the others proportionally fewer
/// (e.g. 256 on the phantom gives 256 × 135 × 239 voxels at h = 0.82 mm).
struct SurfaceFieldOptions {
  double voxel_size_m = 1e-3;     ///< wanted grid spacing h [m]; made coarser if max_voxels_per_axis demands
  double margin_m = 0.02;         ///< the grid covers the region and the target plus this on every side [m]
  int max_voxels_per_axis = 256;  ///< cap on the voxel centres along the longest axis (and so along any axis)
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

class SurfaceVectorField {
 public:
  /// @param region_m  the space the model will move in (e.g. its bounding box); the grid covers it,
  ///        the target and the margin
  /// @throws std::invalid_argument as TargetSurface::validate and SurfaceFieldOptions::validate, or
  ///         when the target reaches no voxel.
  SurfaceVectorField(const TargetSurface& target, const Eigen::AlignedBox3d& region_m,
                     const SurfaceFieldOptions& options = {});

  /// Builds the field anew for another target (and region), as the constructor does, reusing the
  /// grid storage when the new grid has no more voxels than any grid built before by this object.
  /// The result equals a freshly constructed field's. Invalid input (TargetSurface::validate,
  /// SurfaceFieldOptions::validate) leaves the field unchanged; a target that reaches no voxel
  /// leaves it without a surface until the next successful rebuild.
  /// @throws std::invalid_argument as the constructor.
  void rebuild(const TargetSurface& target, const Eigen::AlignedBox3d& region_m, const SurfaceFieldOptions& options = {});

  /// Vector from p to the nearest target point [m] (trilinear; outside the grid, clamped to it and
  /// continued by the offset to the grid).
  /// @throws std::logic_error if the last rebuild found no surface voxel.
  Eigen::Vector3d vectorToSurface(const Eigen::Vector3d& p_m) const;

  const Eigen::Vector3i& size() const { return size_; }
  double voxelSize() const { return h_; }
  const Eigen::Vector3d& origin() const { return origin_; }  ///< centre of voxel (0, 0, 0) [m]
  int numSurfaceVoxels() const { return surface_voxels_; }
  /// Wall time of the last build or rebuild [s].
  double buildSeconds() const { return seconds_; }

 private:
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();
  double h_ = 0.0;
  Eigen::Vector3i size_ = Eigen::Vector3i::Zero();
  TargetSurface target_;
  GridBuffer<std::int32_t> feature_;  // per voxel: the nearest surface voxel (linear index)
  GridBuffer<std::int32_t> element_;  // all of its capacity: 1 + the voxel's triangle (or point) if a surface voxel, else 0
  std::vector<std::int32_t> sites_;            // the surface voxels, ascending (to reset element_ on rebuild)
  int surface_voxels_ = 0;
  double seconds_ = 0.0;
};

}  // namespace breast_sim::core
