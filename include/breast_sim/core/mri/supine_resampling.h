#pragma once
/// @file supine_resampling.h
/// The simulated supine MRI (seed Figure 4e): the prone image resampled into the deformed
/// configuration of the model. Each voxel centre y of the supine grid that lies in a deformed
/// tetrahedron (nodes X_a + u_a) takes barycentric coordinates λ there; its prone point is
/// X = Σ λ_a X_a (the displacement field is linear in each element, so this is its exact inverse), where
/// the prone image is read trilinearly and the prone labels by nearest neighbour.
///
/// Voxels in no deformed tetrahedron: where the prone labels (if given) say chest wall at the same
/// point, the prone voxel stays (the model holds the chest wall still and the tissue slides on it);
/// everywhere else the air value (and label 0).
///
/// A voxel in several tetrahedra (on a shared face, or where inverted elements overlap) takes the one
/// of lowest index, in the fast path and in the reference alike; both compute λ by the same
/// expression, so they agree bit for bit. Results do not depend on the thread count.

#include <cstdint>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

struct SupineResampleOptions {
  double margin_m = 10e-3;                  ///< around the deformed model's bounding box [m], ≥ 0
  /// Voxel size of the supine grid [m]; a zero component takes the prone image's spacing on that axis.
  Eigen::Vector3d spacing_m = Eigen::Vector3d::Zero();
  float air_value = 0.0f;                   ///< intensity outside the body
  long max_voxels = 1L << 28;               ///< a larger supine grid is an error
  TissueLabels label_map;                   ///< which prone labels are chest wall
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// The supine grid: the prone image's axes (direction), covering the deformed nodes' bounding box in
/// those axes plus the margin, with the chosen spacing; its voxel centres lie on the prone grid's
/// lattice when the spacings are equal (so a zero displacement reproduces the prone voxels).
/// @throws std::invalid_argument for invalid options, no nodes, or more than max_voxels voxels.
ImageGeometry supineGrid(const ImageGeometry& prone, const Points& deformed_m, const SupineResampleOptions& options = {});

/// What the resampling produced.
struct SupineImages {
  ScalarImage image;      ///< the simulated supine image (empty values when no prone image was given)
  LabelImage labels;      ///< the prone labels carried along (empty when none were given)
  long body_voxels = 0;   ///< voxels inside a deformed tetrahedron
  double seconds = 0.0;
};

/// Resamples the prone image and/or labels into the deformed configuration on `grid` (see the file
/// comment). Fast path: each deformed tetrahedron is rasterised over the voxels of its bounding box,
/// the supine slices shared out among threads, each slice's tetrahedra taken in index order.
/// @param mesh          the rest (prone) mesh, nodes [m] in the prone image's patient space
/// @param displacement  #N×3 displacement of each node [m]
/// @param prone_image   may be null (then `labels` must not be)
/// @param prone_labels  may be null
/// @throws std::invalid_argument for mismatched sizes, non-finite displacements, both inputs null, or
///         invalid images.
SupineImages resampleToSupine(const TetMesh& mesh, const Points& displacement, const ScalarImage* prone_image,
                              const LabelImage* prone_labels, const ImageGeometry& grid,
                              const SupineResampleOptions& options = {});

/// The slow reference of resampleToSupine: for every voxel, every tetrahedron in index order until one
/// holds it. O(#voxels × #tetrahedra): for tests on small grids.
SupineImages resampleToSupineReference(const TetMesh& mesh, const Points& displacement, const ScalarImage* prone_image,
                                       const LabelImage* prone_labels, const ImageGeometry& grid,
                                       const SupineResampleOptions& options = {});

}  // namespace breast_sim::core
