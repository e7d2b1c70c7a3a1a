#pragma once
/// @file point_embedding.h
/// Points (lesions, landmarks) embedded in a tetrahedral mesh by barycentric coordinates, so they
/// follow any displacement field of the mesh.

#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// A named point of interest in the prone image (a lesion).
struct Lesion {
  std::string name;
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();  ///< prone position, patient space [m]
  double radius_m = 0.0;                                 ///< extent for mesh refinement [m]; 0 = a point
};

/// The containing tetrahedron and barycentric weights of one point.
struct EmbeddedPoint {
  int tet = -1;
  Eigen::Vector4d weights = Eigen::Vector4d::Zero();  ///< barycentric, sum to 1, all ≥ 0 inside
  double outside_distance_m = 0.0;  ///< 0 inside; for a point snapped from outside, its distance [m]
};

/// Embeds points in a mesh's rest configuration and evaluates them on displacement fields.
class PointEmbedding {
 public:
  PointEmbedding() = default;

  /// Locates each point in the mesh (uniform-grid search over element bounds, O(#T + #P)).
  /// @param mesh       the rest mesh
  /// @param points_m   #P×3 points [m]
  /// @param names      #P names used in error messages (may be empty)
  /// @param snap_tolerance_m  a point outside the mesh by at most this much is moved to the closest
  ///        point of the mesh surface (the meshed surface approximates the image's); 0 = must be inside
  /// @throws std::invalid_argument naming the point, its position in mm and its distance from the
  ///         mesh when it lies outside by more than the tolerance.
  PointEmbedding(const TetMesh& mesh, const Points& points_m, const std::vector<std::string>& names = {},
                 double snap_tolerance_m = 0.0);

  int size() const { return static_cast<int>(points_.size()); }
  const std::vector<EmbeddedPoint>& points() const { return points_; }

  /// Displacement of every point interpolated from nodal displacements.
  /// @param nodal_displacement_m  #N×3 [m]
  /// @return #P×3 [m]
  /// @throws std::invalid_argument when the field has fewer rows than the mesh has nodes.
  Points interpolate(const Points& nodal_displacement_m) const;

  /// Positions of the points for nodal positions (rest + displacement) [m]: #P×3.
  Points positions(const Points& nodal_positions_m) const;

 private:
  Tets tets_;  // copy of the connectivity (small) so the embedding is self-contained
  std::vector<EmbeddedPoint> points_;
};

/// Barycentric coordinates of p in tetrahedron (a, b, c, d) (positions in [m]).
Eigen::Vector4d barycentricCoordinates(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                       const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                       const Eigen::Vector3d& d);

}  // namespace breast_sim::core
