// Fuzz target: the Abaqus / CalculiX .inp reader (nodes, C3D4 elements, node and element sets).
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/mesh/mesh_io.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("inp", {"mesh.inp"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] { breast_sim::core::readTetMesh(path, 1e-3); });
  return 0;
}
