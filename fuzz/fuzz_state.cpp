// Fuzz target: the pipeline's binary state file reader.
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/pipeline/state_file.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("state", {"state.bin"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] { breast_sim::core::readStateFile(path); });
  return 0;
}
