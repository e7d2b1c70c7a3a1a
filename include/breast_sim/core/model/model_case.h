#pragma once
/// @file model_case.h
/// A case: where the tissue comes from (the built-in phantom, a label image, a mesh of the user's or a
/// prone MRI segmented automatically), its lesions and how to mesh it; and the simulation model built
/// from it.

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/image_mesher.h"
#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/model/tissue_labels.h"
#include "breast_sim/core/model/user_mesh.h"

namespace breast_sim::core {

struct Phantom;  // model/phantom.h
struct MriCase;  // mri/mri_case.h

/// Everything needed to build a simulation model.
struct ModelCase {
  std::string name;                        ///< case name (file stem)
  std::string source_path;                 ///< the YAML file it came from, if any
  /// The prone segmentation; for a mesh case, the label image made from the mesh (voxelizeModel).
  LabelImage image;
  TissueLabels labels;                     ///< which label values are which tissue
  std::vector<Lesion> lesions;             ///< lesions in the prone image [m]
  std::vector<Eigen::Vector3d> nipples_m;  ///< nipple points [m] (may be empty)
  /// Unit direction of gravity in the prone image (chest wall → nipple), patient space. Anterior,
  /// (0, −1, 0), for LPS images and the phantom; a case must give it for images whose space is not
  /// anatomical (e.g. the VICTRE phantom: +x).
  Eigen::Vector3d prone_gravity_direction{0.0, -1.0, 0.0};
  MeshingOptions meshing;
  double lesion_snap_tolerance_m = 2e-3;   ///< a lesion this close outside the mesh is snapped onto it [m]
  std::shared_ptr<const Phantom> phantom;  ///< set when the case is the software phantom
  /// Set when the case is a mesh of the user's (`mesh:`): the prepared mesh (readUserMesh), which
  /// buildSimulationModel takes instead of meshing the image.
  std::shared_ptr<const TetMesh> mesh;
  UserMeshSource mesh_source;              ///< where that mesh came from (path made absolute)
  UserMeshReport mesh_report;              ///< what preparing it found
  /// Set when the case is a prone MRI (`mri:`): the MRI, its segmentation (the case's image) and its
  /// scores, for the simulated supine MRI and the reports.
  std::shared_ptr<const MriCase> mri;
};

/// Voxels around a user's mesh in its label image [m]: room for the chest-wall field behind the wall
/// (it saturates 3.7 σ in, 7.4 mm at the default σ of 2 mm, and the Gaussian reaches 4 σ further).
inline constexpr double kUserMeshImageMarginM = 20e-3;

/// Loads a YAML case file. Top-level maps:
///  - exactly one of `phantom:` the software phantom's parameters (model/phantom.h),
///  - `image:` {path (relative to the YAML file), labels: {fat: [...], fibroglandular: [...], skin:
///    [...], lesion: [...], chest_wall: [...]}, nipples_mm: [[x, y, z], ...],
///    prone_gravity_direction: [x, y, z] (default [0, -1, 0], anterior in LPS)};
///  - `mesh:` {path (relative to the YAML file), units: m | mm, chest_wall: NODE_SET (default
///    "chest_wall"), skin: NODE_SET (default: the boundary off the wall), nipple: NODE_SET, regions:
///    {fat: [...], fibroglandular: [...], skin: [...], lesion: [...]} (element region labels),
///    voxel_size_mm (default 1), nipples_mm, prone_gravity_direction} (model/user_mesh.h); without
///    `lesions:` its pieces of lesion elements are the lesions (lesionsOfRegions);
///  - `mri:` {path (a file or a DICOM folder, relative to the YAML file), series_uid, breasts: both |
///    left | right, midline_x_mm, lesion_labels, truth} with the `segmentation:` map (mri/mri_case.h):
///    the MRI is read and segmented (with `read_mri` below; mri/mri_case.h, loadModelCaseWithMri), and
///    its labels (segmentationLabel values) are the case's image; nipples and the prone gravity
///    direction come from the segmentation, the lesions of a lesion label image follow the listed ones;
///  - `lesions:` optional list of {name, position_mm: [x, y, z], radius_mm} (LPS patient space, mm),
///    added to the phantom's own lesions;
///  - `meshing:` {target_elements, interior_size_mm, skin_size_factor, grading_distance_mm,
///    lesion_size_factor, lesion_grading_distance_mm, facet_angle_deg, facet_distance_mm,
///    cell_radius_edge_ratio, perturb, exude, lesion_snap_tolerance_mm}.
/// Other top-level maps are left to later stages (simulation, sliding, …).
/// @throws std::runtime_error naming the file, the key and what is expected.
ModelCase loadModelCase(const std::string& yaml_path);
/// Reads the tissue of an `mri:` case into `c` (image, nipples_m, prone_gravity_direction, mri): the
/// MRI module (mri/mri_case.h, loadModelCaseWithMri) passes it, since the model layer does not segment.
using MriSourceReader = std::function<void(const std::string& yaml_path, ModelCase& c)>;
/// The same, saying which stage runs: `stage` is called with "reading" (the case file and its image)
/// as it starts; `read_mri` reads an `mri:` case's tissue (without it such a case is an error naming
/// the file).
ModelCase loadModelCase(const std::string& yaml_path, const std::function<void(const std::string&)>& stage,
                        const MriSourceReader& read_mri = {});

/// The `meshing:` map of a case file alone (absent = the defaults of MeshingOptions), and its
/// lesion_snap_tolerance_mm [m] into *lesion_snap_tolerance_m; reads no image.
/// @throws std::runtime_error as loadModelCase does for that map.
MeshingOptions loadMeshingOptions(const std::string& yaml_path, double* lesion_snap_tolerance_m);

/// The simulation model: the tissue mesh with its node sets and the embedded lesions.
struct SimulationModel {
  TetMesh mesh;                  ///< node sets: chest_wall, skin, nipple (if nipples given)
  std::vector<Lesion> lesions;
  PointEmbedding lesion_embedding;
  MeshingReport meshing;
  QualityStats quality;
};

/// Meshes the case's image (or takes the case's own mesh) and embeds its lesions. The nipple node set
/// holds the skin node nearest each nipple point.
/// @throws as meshLabelImage and PointEmbedding do; messages name the case.
SimulationModel buildSimulationModel(const ModelCase& model_case);

}  // namespace breast_sim::core
