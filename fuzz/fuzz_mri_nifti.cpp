// Fuzz target: the MRI reader (readMriVolume, ITK's NIfTI ImageIO) on a NIfTI-1 file, plain or
// gzip-compressed (named .nii.gz; ITK takes both).
#include <cstddef>
#include <cstdint>

#include "fuzz_mri.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("mri_nifti", {"image.nii.gz"});
  breast_sim::fuzz::readMri(files, files.write(data, size));
  return 0;
}
