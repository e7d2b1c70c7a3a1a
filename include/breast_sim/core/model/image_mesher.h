#pragma once
/// @file image_mesher.h
/// Tetrahedral meshing of the breast tissue in a label image with CGAL Mesh_3.

#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// A point of interest around which the mesh is refined (a lesion).
struct RefinementPoint {
  Eigen::Vector3d position_m;   ///< [m], patient space of the image
  double radius_m = 0.0;        ///< the lesion's radius [m]; elements are small within radius + grading
};

/// How fine the mesh is and where. Sizes are CGAL's cell-size bound: the circumradius of a tetrahedron [m].
/// "Model no more than a scene needs": the mesh is coarse inside, finer at the skin (where surface
/// distance is measured and morphing forces act) and near lesions (where position error matters).
struct MeshingOptions {
  /// When > 0, the interior size is chosen so that the tissue mesh has about this many tetrahedra
  /// (within ±25%; up to `max_size_iterations` meshing passes); `interior_size_m` is then ignored.
  int target_elements = 0;
  double interior_size_m = 6e-3;         ///< element size deep inside the tissue [m]
  double skin_size_factor = 0.5;         ///< element size at the skin = factor × interior size
  double grading_distance_m = 15e-3;     ///< distance from the skin over which the size grows to interior [m]
  double lesion_size_factor = 0.35;      ///< element size inside a lesion's neighbourhood = factor × interior
  double lesion_grading_distance_m = 15e-3; ///< distance from a lesion over which the size grows [m]
  double facet_angle_deg = 25.0;         ///< lower bound on surface triangle angles [degrees]
  /// Surface approximation bound [m]; 0 = automatic: max(0.5 voxel, 0.1 × skin size).
  double facet_distance_m = 0.0;
  double cell_radius_edge_ratio = 2.5;   ///< CGAL shape bound (≥ 2 keeps the refinement terminating)
  bool perturb = true;                   ///< CGAL sliver perturbation
  bool exude = true;                     ///< CGAL sliver exudation
  int max_size_iterations = 3;           ///< meshing passes allowed to meet target_elements
  /// Tissue components that do not touch the chest wall and hold less than this fraction of the
  /// tissue volume are dropped: segmentation islands would float free in a simulation.
  double min_island_volume_fraction = 0.01;
  /// Rejects inputs that would need more than this many tetrahedra (protects a node from a typo).
  int max_elements = 3'000'000;
  /// Seed of CGAL's random generator (initial points, refinement order, sliver perturbation). CGAL
  /// seeds its default generator from the clock, so without a fixed seed the same image gave
  /// different meshes from one run to the next (measured 3189 vs 3387 nodes); with it, the same
  /// image and options give the same mesh, node for node, in any process.
  unsigned random_seed = 1;

  /// @throws std::invalid_argument naming the option, its value and the accepted range.
  void validate() const;
};

/// What the mesher did.
struct MeshingReport {
  double seconds = 0.0;           ///< wall time of all meshing passes [s]
  int passes = 0;                 ///< CGAL runs (more than one when fitting target_elements)
  double interior_size_m = 0.0;   ///< interior size used in the last pass [m]
  double skin_size_m = 0.0;       ///< skin size used in the last pass [m]
  double facet_distance_m = 0.0;  ///< surface approximation bound used [m]
  long tissue_voxels = 0;         ///< voxels of breast tissue in the image
  double voxel_volume_m3 = 0.0;   ///< tissue volume counted in voxels [m³]
  int num_chest_wall_faces = 0;   ///< boundary faces against the chest wall
  int num_skin_faces = 0;         ///< boundary faces against air
  /// Boundary faces with neither air nor chest wall just outside (tissue cut by the image border,
  /// or thin tissue folds); they are counted as chest wall (fixed), since a cut is no free skin.
  int num_undecided_faces = 0;
  int num_components = 0;         ///< connected tissue components CGAL meshed
  int dropped_components = 0;     ///< floating islands removed (see min_island_volume_fraction)
  double dropped_volume_m3 = 0.0; ///< their volume [m³]
};

/// Meshes the breast tissue of a label image.
///
/// The domain is the union of tissue labels (fat, fibroglandular, skin, lesion); the chest wall and
/// air are outside. Each boundary face is classified by the labels found 0.5–1.5 voxels outside it:
/// chest wall → node set "chest_wall", air → "skin" (nodes on the rim between the two are in both);
/// a face with neither (tissue cut by the image border) counts as chest wall and as undecided.
/// Element region labels are the TissueClass (as int) of the image at the element, sampled at the
/// centroid and four inner points (majority); internal tissue interfaces are not meshed conformingly,
/// so that fibroglandular strands finer than the elements do not force tiny elements. Nodes and
/// tetrahedra come out in Morton order (mesh/tet_mesh.h, mortonOrdered).
/// @param image   label image (patient space, metres)
/// @param labels  which label values are which tissue
/// @param refine_at  lesion points to refine around (may be empty)
/// @param report  filled when not null
/// @throws std::invalid_argument on invalid options or an image without tissue;
///         std::runtime_error when CGAL yields no tetrahedra (say which size was tried).
TetMesh meshLabelImage(const LabelImage& image, const TissueLabels& labels,
                       const std::vector<RefinementPoint>& refine_at, const MeshingOptions& options,
                       MeshingReport* report = nullptr);

}  // namespace breast_sim::core
