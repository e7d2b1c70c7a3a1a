// Fuzz target: the legacy VTK (.vtk) unstructured-grid reader, ASCII and binary, with its point and
// cell fields.
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/mesh/mesh_io.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("vtk_legacy", {"mesh.vtk"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] {
    breast_sim::core::MeshFields fields;
    breast_sim::core::readVtkUnstructured(path, 1e-3, &fields);
  });
  return 0;
}
