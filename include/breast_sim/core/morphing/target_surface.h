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

/// Exact closest-point distances to a triangle surface (VTK's static cell locator; a point cloud
/// target measures to its nearest point). Build once, query many times; thread-safe queries.
class SurfaceDistance {
 public:
  /// @throws std::invalid_argument as TargetSurface::validate.
  explicit SurfaceDistance(const TargetSurface& surface);
  ~SurfaceDistance();
  SurfaceDistance(SurfaceDistance&&) noexcept;
  SurfaceDistance& operator=(SurfaceDistance&&) noexcept;
  /// Distance [m] and, if wanted, the closest point of the surface.
  double distance(const Eigen::Vector3d& p_m, Eigen::Vector3d* closest_m = nullptr) const;
  /// Statistics of the distances of all `points_m` rows.
  DistanceStats stats(const Points& points_m) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Points spread over a triangle surface: its vertices and the centroids of its triangles (a point
/// cloud is returned as it is). Used to measure target → model distances with area coverage.
Points surfaceSamples(const TargetSurface& surface);

/// Surface distance both ways between a model's skin (boundary triangles touching `skin_nodes` with
/// all three nodes, at positions `x_m`) and a target.
struct SurfaceMatch {
  DistanceStats model_to_target;  ///< skin vertices and face centroids → target
  DistanceStats target_to_model;  ///< target samples → skin surface
};
SurfaceMatch surfaceMatch(const TetMesh& mesh, const Points& x_m, const std::vector<int>& skin_nodes,
                          const SurfaceDistance& target, const TargetSurface& target_surface);

/// The skin triangles of a mesh: boundary faces whose three nodes are all in `skin_nodes`.
Triangles skinTriangles(const TetMesh& mesh, const std::vector<int>& skin_nodes);

}  // namespace breast_sim::core
