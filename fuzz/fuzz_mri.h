#pragma once
/// @file fuzz_mri.h
/// What the fuzz targets of the MRI reader (readMriVolume) share: the cap on the volume a header may
/// claim. The readers allocate the whole volume a header gives once readMriVolume has checked it against
/// MriReadOptions::max_voxels; the default (2^28 voxels, 1 GiB of float) is above libFuzzer's 512 MB
/// allocation limit, so the targets read with 2^22 voxels (16 MB of float), and a larger claim is the
/// reader's documented error. test_mri_volume checks the default cap on a header claiming 10^15 voxels.
#include <string>

#include "breast_sim/core/mri/mri_volume.h"
#include "fuzz_files.h"

namespace breast_sim::fuzz {

inline void readMri(const FuzzFiles& files, const std::string& path) {
  core::MriReadOptions options;
  options.max_voxels = 1L << 22;
  expectCleanError(files, [&] { core::readMriVolume(path, options); });
}

}  // namespace breast_sim::fuzz
