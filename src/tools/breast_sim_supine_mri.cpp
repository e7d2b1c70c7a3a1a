// breast_sim_supine_mri: the simulated supine MRI (seed Figure 4e) from a prone MRI and a deformed
// model written by breast_sim_run (supine.vtu or supine_gravity.vtu: deformed node positions [m] and
// the point array displacement_mm), by mri/supine_resampling.h; writes the supine image (NIfTI or
// NRRD), optionally the labels carried along, and cross-sections of prone and supine.
#include <cstdio>
#include <iostream>
#include <sstream>
#include <stdexcept>
#include <string>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mri/mri_cross_sections.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/supine_resampling.h"
#include "mri_tool_args.h"

using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_supine_mri PRONE --deformed MODEL.vtu --out SUPINE [--labels LABELS] [--out-labels FILE]
                             [--png FILE] [--margin-mm 10] [--spacing-mm X,Y,Z] [--series-uid UID]

Resamples a prone MRI into the deformed configuration of a model (include/breast_sim/core/mri/supine_resampling.h).
  PRONE               the prone MRI: NIfTI, NRRD, MetaImage or a DICOM folder, in the model's patient space
  --deformed FILE     a deformed model from breast_sim_run (.vtu/.vtk): deformed node positions [m] and the
                      point array displacement_mm (supine.vtu, supine_gravity.vtu)
  --out SUPINE        the simulated supine image: .nii, .nii.gz, .nrrd or .mha
  --labels LABELS     the prone labels (e.g. breast_sim_segment's): carried along by nearest neighbour, and
                      the chest wall kept where the body leaves it
  --out-labels FILE   write the carried labels (.nrrd, .nii.gz, ...)
  --png FILE          cross-sections of the prone and the supine image
  --margin-mm 10      air around the deformed model's bounding box [mm]
  --spacing-mm X,Y,Z  voxel size of the supine grid [mm] (default: the prone image's)
  --series-uid UID    the DICOM series to read when the folder holds several
)";

Eigen::Vector3d parseTriple(const std::string& text, const std::string& option) {
  Eigen::Vector3d v;
  char c1 = 0, c2 = 0;
  std::istringstream in(text);
  if (!(in >> v.x() >> c1 >> v.y() >> c2 >> v.z()) || c1 != ',' || c2 != ',')
    throw std::invalid_argument(option + " needs X,Y,Z, got '" + text + "'");
  return v;
}

}  // namespace

int main(int argc, char** argv) try {
  std::string prone_path, deformed_path, out, labels_path, out_labels, png, series_uid;
  SupineResampleOptions options;
  breast_sim::tools::Arguments args(argc, argv, kUsage);
  while (args.next()) {
    const std::string& a = args.option();
    if (args.help()) return 0;
    if (a == "--deformed") deformed_path = args.value();
    else if (a == "--out") out = args.value();
    else if (a == "--labels") labels_path = args.value();
    else if (a == "--out-labels") out_labels = args.value();
    else if (a == "--png") png = args.value();
    else if (a == "--series-uid") series_uid = args.value();
    else if (a == "--margin-mm") options.margin_m = std::stod(args.value()) * 1e-3;
    else if (a == "--spacing-mm") options.spacing_m = parseTriple(args.value(), a) * 1e-3;
    else if (args.positional() && prone_path.empty()) prone_path = a;
    else args.unknown();
  }
  if (prone_path.empty() || deformed_path.empty() || out.empty())
    throw std::invalid_argument(std::string("give PRONE, --deformed MODEL and --out SUPINE\n") + kUsage);
  if (!out_labels.empty() && labels_path.empty()) throw std::invalid_argument("--out-labels needs --labels");

  MriReadOptions read_options;
  read_options.series_uid = series_uid;
  const MriVolume prone = readMriVolume(prone_path, read_options);
  LabelImage labels;
  if (!labels_path.empty()) labels = readLabelImage(labels_path);
  MeshFields fields;
  const TetMesh deformed = readVtkUnstructured(deformed_path, 1.0, &fields);
  const MeshField* displacement = nullptr;
  for (const MeshField& f : fields.point_data)
    if (f.name == "displacement_mm") displacement = &f;
  if (!displacement || displacement->values.cols() != 3)
    throw std::runtime_error(deformed_path + ": no point array displacement_mm with 3 components; give a deformed model "
                                             "written by breast_sim_run (supine.vtu or supine_gravity.vtu)");
  const Points u = displacement->values * 1e-3;
  const TetMesh rest(deformed.nodes() - u, deformed.tets(), deformed.regionLabels());
  const ImageGeometry grid = supineGrid(prone.image.geometry, deformed.nodes(), options);
  const SupineImages supine = resampleToSupine(rest, u, &prone.image, labels_path.empty() ? nullptr : &labels, grid, options);
  writeMriVolume(out, supine.image);
  if (!out_labels.empty()) writeLabelImage(out_labels, supine.labels);
  if (!png.empty()) {
    MriSectionRow a, b;
    a.title = "prone MRI " + prone_path;
    a.image = &prone.image;
    a.labels = labels_path.empty() ? nullptr : &labels;
    b.title = "simulated supine MRI (" + deformed_path + ")";
    b.image = &supine.image;
    b.labels = labels_path.empty() ? nullptr : &supine.labels;
    writeMriCrossSections(png, {a, b});
  }
  std::printf("supine grid %d x %d x %d voxels of %.2f x %.2f x %.2f mm; %ld voxels in the body (%d tetrahedra); resampled in "
              "%.2f s; wrote %s%s%s%s%s\n",
              grid.size.x(), grid.size.y(), grid.size.z(), 1e3 * grid.spacing_m.x(), 1e3 * grid.spacing_m.y(),
              1e3 * grid.spacing_m.z(), supine.body_voxels, rest.numTets(), supine.seconds, out.c_str(),
              out_labels.empty() ? "" : ", ", out_labels.c_str(), png.empty() ? "" : ", ", png.c_str());
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "breast_sim_supine_mri: %s\n", e.what());
  return 2;
}
