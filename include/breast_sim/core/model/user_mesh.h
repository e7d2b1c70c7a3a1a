#pragma once
/// @file user_mesh.h
/// A tetrahedral mesh of the user's own as the simulation model (a case's `mesh:` map): checked,
/// given the project's node sets and tissue classes, and turned into a label image so that every
/// stage written for an image (the chest-wall field of sliding, the multigrid's coarse meshes, the
/// thickness limit, the cross-section pictures) runs on it unchanged.

#include <map>
#include <string>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// Where a user's mesh is and how to read it (docs/case_files.md, `mesh:`).
struct UserMeshSource {
  std::string path;                 ///< .msh .vtu .vtk .node/.ele .inp
  double length_unit_m = 0.0;       ///< metres per file unit: 1 (m) or 1e-3 (mm); must be given
  std::string chest_wall_set = "chest_wall";  ///< node set of the tissue nodes on the chest wall
  std::string skin_set;             ///< node set of the skin; empty = every boundary face not on the wall
  std::string nipple_set;           ///< node set whose centroid is the nipple; empty = none
  /// Element region label in the file → tissue class (fat, fibroglandular, skin, lesion). Empty: the
  /// mesh must have a single region label, and it is fat.
  std::map<int, TissueClass> regions;
  double voxel_size_m = 1e-3;       ///< voxel size of the label image made from the mesh [m]
};

/// What preparing the mesh found and did.
struct UserMeshReport {
  int file_nodes = 0;               ///< nodes in the file
  int unused_nodes = 0;             ///< nodes no tetrahedron uses (dropped)
  int components = 0;               ///< connected pieces (tetrahedra sharing a node)
  int chest_wall_faces = 0;         ///< boundary faces with all three nodes on the chest wall
  int skin_faces = 0;               ///< the other boundary faces
  /// Typical element size: the 90th percentile of the circumradii of tetrahedra off the boundary
  /// (the quantity a mesher's size bound limits) [m]; the multigrid meshes its coarse levels at
  /// multiples of it.
  double interior_size_m = 0.0;
  double skin_size_m = 0.0;         ///< the same over tetrahedra with a skin face [m]
  double voxelize_seconds = 0.0;    ///< wall time of voxelizeModel [s]
};

/// Reads and prepares a user's mesh: unused nodes dropped, node sets "chest_wall" and "skin" (and
/// "nipple" when a nipple set is named) under the project's names, region labels mapped to tissue
/// classes (TissueClass as int), nodes and tetrahedra in Morton order.
/// @throws std::runtime_error naming the file and the fix when: the unit is not given or the mesh's
///         size is implausible for it (a breast spans 2 cm to 1 m); a named node set is missing (the
///         message lists those present), empty, or holds nodes off the boundary; the chest-wall set
///         covers no boundary face; a region label is not mapped (or several labels without a map);
///         a connected piece touches no chest-wall node (it would float free); the file is malformed
///         or its elements overlap (as readTetMesh and TetMesh report them).
TetMesh readUserMesh(const UserMeshSource& source, UserMeshReport* report = nullptr);

/// The lesions a prepared mesh segments: each connected piece of lesion elements (region label
/// TissueClass::kLesion; tetrahedra sharing a face) becomes a lesion "L1", "L2", … (in the order of
/// their first tetrahedron) at the piece's centroid, with the radius of the sphere of its volume [m].
/// Empty when the mesh has no lesion elements.
std::vector<Lesion> lesionsOfRegions(const TetMesh& mesh);

/// The label image of a prepared mesh (node sets chest_wall and skin, tissue-class regions), on an
/// axis-aligned grid of `voxel_size_m` covering the mesh plus `margin_m` on every side:
///  - a voxel whose centre lies in a tetrahedron takes the label of its tissue class (the first value
///    of that class in `labels`);
///  - a voxel outside the tissue is chest wall when it lies behind the chest-wall face nearest to it
///    (on the side its outward normal points to) and is no farther from the chest-wall faces than
///    from the skin faces (+ one voxel); so the wall continues flat past the rim of the mesh, and a
///    voxel in front of the skin is air. The rest is air.
/// So the chest-wall field's surface (sliding/chest_wall_surface.h) passes within about half a voxel
/// of the mesh's wall faces. Memory: 10 bytes per voxel while it runs (labels and two feature
/// transforms), 2 in the result; at most 2^26 voxels.
/// @throws std::invalid_argument when the mesh lacks the node sets, an element's region label is not
///         a tissue class (1–4), `labels` has no value for a class the mesh uses or for the chest
///         wall, the voxel size or margin is not positive, or the grid would exceed 2^26 voxels (the
///         message gives the voxel size to choose).
LabelImage voxelizeModel(const TetMesh& mesh, const TissueLabels& labels, double voxel_size_m, double margin_m);

}  // namespace breast_sim::core
