// Fuzz target: the MetaImage reader, local data (.mha) or a separate data file named 'data' (the
// input's second part).
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/image/label_image.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("metaimage", {"image.mha", "data"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] { breast_sim::core::readLabelImage(path); });
  return 0;
}
