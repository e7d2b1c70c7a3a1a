#pragma once
/// @file error_metrics.h
/// How far a simulated displacement field is from a reference one (reference/calculix.h, or a fine
/// mesh of our own): nodal displacement error, lesion position error, distance between the deformed
/// surfaces, and the volume change of each.
///
/// On the same mesh the fields are compared node by node. Across meshes (a coarse model against a
/// fine reference) the reference displacement is interpolated at our nodes by barycentric
/// coordinates in the reference mesh's rest configuration (model/point_embedding.h); nodes of ours
/// slightly outside the reference mesh (the two meshes approximate the same image surface
/// differently) take the displacement of the closest point of the reference mesh. Lesions are
/// embedded in each mesh on its own, so their error includes how each mesh carries them.
///
/// Which nodes count: the nodal errors are over the free nodes (not in the fixed node set, whose
/// error is zero by construction and would dilute the mean). Units: errors in mm in the result
/// (the names say so), fields in m.

#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// The error of one field against a reference.
struct DisplacementErrors {
  int nodes_compared = 0;              ///< free nodes of our mesh
  double mean_mm = 0.0;                ///< mean nodal displacement error [mm]
  double rms_mm = 0.0;                 ///< root mean square [mm]
  double p95_mm = 0.0;                 ///< 95th percentile [mm]
  double max_mm = 0.0;                 ///< largest [mm]
  double max_displacement_mm = 0.0;    ///< our largest nodal displacement [mm]
  double reference_max_displacement_mm = 0.0;  ///< the reference's at our nodes [mm]
  /// Per lesion: distance between our and the reference's displaced lesion position [mm].
  std::vector<double> lesion_error_mm;
  double lesion_max_mm = 0.0;          ///< largest of them (0 with no lesion) [mm]
  /// From our deformed skin nodes to the reference's deformed boundary surface: mean and max [mm].
  double surface_distance_mean_mm = 0.0;
  double surface_distance_max_mm = 0.0;
  /// The same at rest (how far apart the two meshes' surfaces start; 0 on the same mesh) [mm].
  double rest_surface_distance_mean_mm = 0.0;
  double volume_change_percent = 0.0;            ///< ours, (V − V0)/V0 · 100 [%]
  double reference_volume_change_percent = 0.0;  ///< the reference's on its own mesh [%]
};

/// Reference displacement at arbitrary points: barycentric interpolation in the reference mesh's
/// rest configuration; points outside it by at most snap_tolerance_m take the value at the closest
/// point of the mesh surface.
/// @param reference_u_m  #N_ref×3 [m]
/// @param points_m       #P×3 rest positions [m]
/// @return #P×3 [m]
/// @throws std::invalid_argument (from PointEmbedding) naming a point farther outside.
Points transferDisplacement(const TetMesh& reference_mesh, const Points& reference_u_m, const Points& points_m,
                           double snap_tolerance_m = 5e-3);

/// Errors of u on `mesh` against u_ref on `reference_mesh` (which may be the same mesh: then the
/// comparison is node by node, no interpolation).
/// @param lesions_m  #L×3 lesion positions at rest [m] (may be empty)
/// @param fixed_node_set  nodes of `mesh` left out of the nodal errors ("" = none; a name the mesh
///        does not have is ignored)
/// @param skin_node_set   nodes of `mesh` whose surface distance is measured ("" or absent: all
///        boundary nodes)
/// @throws std::invalid_argument when a field's row count does not match its mesh.
DisplacementErrors compareDisplacements(const TetMesh& mesh, const Points& u_m, const TetMesh& reference_mesh,
                                        const Points& reference_u_m, const Points& lesions_m = Points(),
                                        const std::string& fixed_node_set = "chest_wall",
                                        const std::string& skin_node_set = "skin");

/// Unsigned distance from each point to a triangle surface [m] (exact closest points,
/// SurfaceDistance); infinite for every point when there are no triangles.
/// @param vertices_m #V×3 [m]; triangles index them
Eigen::VectorXd pointSurfaceDistance(const Points& points_m, const Points& vertices_m, const Triangles& triangles);

}  // namespace breast_sim::core
