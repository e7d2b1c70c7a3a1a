#pragma once
/// @file itk_read.h
/// ITK's own readers, the baseline bench_mri_readers measures the core's readers against: a NRRD,
/// MetaImage or NIfTI file read by that format's ImageIO, a DICOM series by GDCM, into a float image
/// (ITK converts the stored type). Plain types only: its source includes ITK's headers and no Eigen
/// (ITK ships its own).

#include <string>
#include <vector>

namespace breast_sim::bench {

/// A volume as ITK read it: sizes, spacing and origin [mm], direction row-major (direction[3 r + c]:
/// row r of axis c), float values with i fastest.
struct ItkVolume {
  long size[3] = {0, 0, 0};
  double spacing_mm[3] = {0, 0, 0};
  double origin_mm[3] = {0, 0, 0};
  double direction[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
  std::vector<float> values;
};

/// Reads `path` with itk::NrrdImageIO (.nrrd), itk::MetaImageIO (.mha) or itk::NiftiImageIO (.nii,
/// .nii.gz) into itk::Image<float, 3>.
/// @throws std::runtime_error naming the file for another extension or ITK's error.
ItkVolume itkReadFloat(const std::string& path);

/// Reads the one DICOM series of `folder` as ITK does: itk::GDCMSeriesFileNames lists and orders its
/// files, itk::ImageSeriesReader with itk::GDCMImageIO reads them into itk::Image<float, 3>.
/// @throws std::runtime_error naming the folder for ITK's error or a folder without one series.
ItkVolume itkReadDicomFolder(const std::string& folder);

}  // namespace breast_sim::bench
