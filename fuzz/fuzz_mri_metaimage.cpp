// Fuzz target: the MRI reader (readMriVolume: the core's MetaImage parser, values as float) on a
// MetaImage file, attached (.mha) or with a detached data file named 'data' (the input's second part).
#include <cstddef>
#include <cstdint>

#include "fuzz_mri.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("mri_metaimage", {"image.mha", "data"});
  breast_sim::fuzz::readMri(files, files.write(data, size));
  return 0;
}
