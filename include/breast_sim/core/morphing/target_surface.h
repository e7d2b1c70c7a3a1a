#pragma once
/// @file target_surface.h
/// The measured surface a model is morphed to (seed section 2.5): a triangle mesh or a point cloud,
/// and exact surface-distance metrics between a model's skin and it.

#include <memory>
#include <string>
#include <vector>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

struct PhantomSurface;  // model/phantom.h

/// A target surface [m]: triangles, or a point cloud when `triangles` is empty.
struct TargetSurface {
  Points vertices_m;   ///< #V×3 [m]
  Triangles triangles; ///< #F×3 (empty: a point cloud)
  bool isPointCloud() const { return triangles.rows() == 0; }
  /// @throws std::invalid_argument naming the problem: no vertices, a non-finite vertex, an index
  ///         out of range.
  void validate() const;
};

/// The skin faces of a phantom surface (the base on the chest wall is left out).
TargetSurface skinTarget(const PhantomSurface& surface);

/// Reads a surface through VTK, by extension: .obj, .stl, .ply, .vtp, .vtk (polydata); polygons are
/// triangulated; a file without polygons is read as a point cloud.
/// @param length_unit_m  metres per file unit (1e-3 for a file in mm)
/// @throws std::runtime_error naming the file and what is wrong.
TargetSurface readTargetSurface(const std::string& path, double length_unit_m = 1.0);

/// Distances between a set of points and a surface [m]: mean, 95th percentile, max.
struct DistanceStats {
  double mean_m = 0.0, p95_m = 0.0, max_m = 0.0;
  int count = 0;
};

/// Mean, 95th percentile (the ⌈0.95 n⌉-th smallest) and max of a list of distances [m].
DistanceStats distanceStats(std::vector<double> distances_m);

/// Exact closest-point distances to a triangle surface (CGAL's AABB tree; a point cloud target
/// measures to its nearest point, VTK's static point locator). Build once, query many times;
/// thread-safe queries.
class SurfaceDistance {
 public:
  /// @throws std::invalid_argument as TargetSurface::validate.
  explicit SurfaceDistance(const TargetSurface& surface);
  ~SurfaceDistance();
  SurfaceDistance(SurfaceDistance&&) noexcept;
  SurfaceDistance& operator=(SurfaceDistance&&) noexcept;
  /// Distance [m] and, if wanted, the closest point of the surface.
  double distance(const Eigen::Vector3d& p_m, Eigen::Vector3d* closest_m = nullptr) const;
  /// The distance [m] of every `points_m` row, in parallel: the same values as distance() row by row.
  Eigen::VectorXd distances(const Points& points_m) const;
  /// Statistics of the distances of all `points_m` rows.
  DistanceStats stats(const Points& points_m) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Points spread over a triangle surface: the vertices its triangles use and the centroids of its
/// triangles (a point cloud is returned as it is; vertices no triangle uses are not on the surface
/// and left out). Used to measure target → model distances with area coverage.
Points surfaceSamples(const TargetSurface& surface);

/// How far [m] from the model's chest-wall surface a target sample may lie and still count as the
/// target's chest-wall part (see surfaceMatch): about one element of the finest models, so a target's
/// base on the wall is left out while its skin, and any skin that misses the model's, is not.
inline constexpr double kTargetChestWallTolerance_m = 2e-3;

/// Surface distance both ways between a model's skin (boundary triangles touching `skin_nodes` with
/// all three nodes, at positions `x_m`) and the part of a target that should match it. A target may
/// include its base on the chest wall (a closed phantom surface, a segmentation); the model's skin
/// does not, so target samples on the chest wall would count as misses of up to the breast's radius.
/// A target sample is left out of target → skin when it lies within `chest_wall_tolerance_m` of the
/// model's chest-wall surface (boundary faces whose three nodes are in the mesh's "chest_wall" node
/// set, at `x_m`) and nearer to it than to the skin. A rule on distances, so it serves triangle and
/// point-cloud targets alike; a mesh without chest-wall faces leaves every sample in.
struct SurfaceMatch {
  DistanceStats model_to_target;  ///< skin vertices and face centroids → the whole target
  DistanceStats target_to_model;  ///< target samples off the chest wall → skin surface (count = kept)
  int target_samples = 0;         ///< target samples in all (surfaceSamples)
  int target_on_chest_wall = 0;   ///< of those, left out as the target's chest-wall part
};
/// @throws std::invalid_argument when the model has no skin triangles.
SurfaceMatch surfaceMatch(const TetMesh& mesh, const Points& x_m, const std::vector<int>& skin_nodes,
                          const SurfaceDistance& target, const TargetSurface& target_surface,
                          double chest_wall_tolerance_m = kTargetChestWallTolerance_m);

/// The skin triangles of a mesh: boundary faces whose three nodes are all in `skin_nodes`.
Triangles skinTriangles(const TetMesh& mesh, const std::vector<int>& skin_nodes);

}  // namespace breast_sim::core
