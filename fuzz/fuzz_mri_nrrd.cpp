// Fuzz target: the MRI reader (readMriVolume: the core's NRRD parser, values as float) on an NRRD file,
// attached or with a detached data file named 'data' (the input's second part).
#include <cstddef>
#include <cstdint>

#include "fuzz_mri.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("mri_nrrd", {"image.nrrd", "data"});
  breast_sim::fuzz::readMri(files, files.write(data, size));
  return 0;
}
