#pragma once
/// @file cross_section.h
/// Orthogonal cross-sections of a tetrahedral mesh, drawn to PNG with OpenCV: the prone model and a
/// simulated (deformed) configuration side by side, cut by the same three patient-space planes, with
/// an optional target surface's outline and the lesions. What a reader checks first: is the shape
/// right, is anything folded, did the lesions go where the tissue went.
///
/// Each tetrahedron cut by a plane gives a convex triangle or quadrilateral, filled in its region's
/// colour (label 1 fat, 2 fibroglandular, 3 skin, 4 lesion); triangles of a surface cut by the plane
/// give line segments. Views follow radiological convention for LPS patient space: axial (plane
/// z = const) and coronal (y = const) show the patient's left on the image's right; sagittal
/// (x = const) shows anterior on the left; superior is up.

#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// One configuration to draw (a row of the figure).
struct CrossSectionConfiguration {
  std::string title;           ///< e.g. "prone (MRI)"
  const Points* positions_m = nullptr;  ///< node positions #N×3 [m] (the mesh's rest nodes if null)
  Points lesions_m;            ///< points to mark (#L×3 [m]); may be empty
  /// A surface to outline in this row (e.g. the supine target), vertices [m] and triangles; may be empty.
  Points outline_vertices_m;
  Triangles outline_triangles;
};

struct CrossSectionOptions {
  double pixel_size_m = 0.25e-3;   ///< [m] per pixel
  double margin_m = 10e-3;         ///< around the union of all configurations' bounding boxes [m]
  /// The three planes pass through this point [m]; NaN components = the centre of the first
  /// configuration's bounding box.
  Eigen::Vector3d centre_m = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Writes one PNG: one row per configuration, columns axial | coronal | sagittal, with a title, a
/// 1 cm scale bar and the plane positions in mm.
/// @throws std::invalid_argument for mismatched sizes; std::runtime_error if the file cannot be written.
void writeCrossSections(const std::string& png_path, const TetMesh& mesh,
                        const std::vector<CrossSectionConfiguration>& rows, const CrossSectionOptions& options = {});

/// The cut of one tetrahedron by the plane {p : p[axis] = value}: 0, 3 or 4 points [m], in order
/// around the convex polygon (the building block above, exposed for tests).
std::vector<Eigen::Vector3d> tetPlaneSection(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                             const Eigen::Vector3d& d, int axis, double value);

}  // namespace breast_sim::core
