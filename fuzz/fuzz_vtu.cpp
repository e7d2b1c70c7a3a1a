// Fuzz target: the VTK XML (.vtu) unstructured-grid reader: ASCII, inline binary and appended data,
// compressed or not, with its point and cell fields.
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/mesh/mesh_io.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("vtu", {"mesh.vtu"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] {
    breast_sim::core::MeshFields fields;
    breast_sim::core::readVtkUnstructured(path, 1e-3, &fields);
  });
  return 0;
}
