// Fuzz target: the TetGen reader: the input's first part is mesh.node, its second mesh.ele.
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/mesh/mesh_io.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("tetgen", {"mesh.node", "mesh.ele"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] { breast_sim::core::readTetMesh(path, 1e-3); });
  return 0;
}
