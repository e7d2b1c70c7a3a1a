#pragma once
/// @file dicom_series.h
/// One DICOM series as an MRI volume, from the scans of its files (dicom_scan.h); private to src/core/mri.

#include <string>
#include <vector>

#include "breast_sim/core/mri/dicom_scan.h"
#include "breast_sim/core/mri/mri_volume.h"

namespace breast_sim::core {

/// Checks every slice's attributes (dicom_scan.h lists what is read), then the series: one size,
/// orientation and pixel spacing, positions on one line along the slice normal, evenly spaced (within
/// `tolerance` of the median gap), at most `max_voxels`; then reads the voxels slice by slice, sorted
/// along the normal. Geometry: the first slice's position, the row and column directions and their
/// normal, PixelSpacing and the median gap [mm → m]. `folder` and `uid` name the series in messages.
/// @throws std::runtime_error naming the file or the series and the fix (readMriVolume lists them).
MriVolume readDicomSeries(const std::string& folder, const std::string& uid, std::vector<DicomFileScan> slices,
                          long max_voxels, double tolerance);

}  // namespace breast_sim::core
