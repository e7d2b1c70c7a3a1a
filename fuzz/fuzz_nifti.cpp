// Fuzz target: the NIfTI-1 reader, plain or gzip-compressed (the file is named .nii.gz; the reader
// takes both).
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/image/label_image.h"
#include "fuzz_files.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("nifti", {"image.nii.gz"});
  const std::string path = files.write(data, size);
  breast_sim::fuzz::expectCleanError(files, [&] { breast_sim::core::readLabelImage(path); });
  return 0;
}
