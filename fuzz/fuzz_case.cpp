// Fuzz target: YAML case files with their base: chains (the input's parts are case.yaml, b1.yaml,
// b2.yaml and b3.yaml) and the readers of their maps: phantom: (every parameter and its checks),
// image: and mesh: (read against a small label image image.nrrd and a 12 mm box mesh mesh.vtu that
// the target writes beside them), lesions: and meshing:.
#include <cstddef>
#include <cstdint>
#include <string>

#include "../src/core/util/yaml_fields.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "fuzz_files.h"

namespace {

using namespace breast_sim::core;

/// The files a case may name besides its bases.
void writeCompanions(const breast_sim::fuzz::FuzzFiles& files) {
  LabelImage image(Eigen::Vector3i(7, 5, 3), Eigen::Vector3d::Constant(4e-3), Eigen::Vector3d::Zero(), 1);
  for (int i = 0; i < 7; ++i) image.at(i, 0, 0) = 40;  // a chest-wall row
  image.at(3, 2, 1) = 2;
  writeLabelImage(files.path("image.nrrd"), image);
  const TetMesh box = makeBoxMesh(Eigen::Vector3i(2, 2, 2), Eigen::Vector3d::Constant(12e-3));
  writeTetMesh(files.path("mesh.vtu"), box);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("case", {"case.yaml", "b1.yaml", "b2.yaml", "b3.yaml"});
  static const bool companions = (writeCompanions(files), true);
  (void)companions;
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] {
    double snap_m = 0.0;
    loadMeshingOptions(path, &snap_m);
    const YAML::Node root = yaml_fields::loadFile(path);
    // A phantom case's model is the generated phantom (seconds of work, not reading): its
    // parameters are what the file holds.
    if (yaml_fields::caseSource(root, path) == "phantom") {
      loadPhantomParams(path);
    } else {
      loadModelCase(path);
    }
  });
  return 0;
}
