// Fuzz target: the MRI reader (readMriVolume: the core's DICOM reader) on a folder of DICOM files: the
// input's parts are the slices IM00001.dcm … IM00004.dcm (as writeDicomSeries names them), and the
// folder is read as a series (sorting, spacing and acquisition checks included).
#include <cstddef>
#include <cstdint>

#include "fuzz_mri.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static breast_sim::fuzz::FuzzFiles files("mri_dicom", {"IM00001.dcm", "IM00002.dcm", "IM00003.dcm", "IM00004.dcm"});
  files.write(data, size);
  breast_sim::fuzz::readMri(files, files.dir().string());
  return 0;
}
