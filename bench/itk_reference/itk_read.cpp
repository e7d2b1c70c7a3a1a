// itk_read.h: ITK's ImageIO of each format, created by name, and its DICOM series reading.
#include "itk_read.h"

#include <stdexcept>

#include <itkGDCMImageIO.h>
#include <itkGDCMSeriesFileNames.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageSeriesReader.h>
#include <itkMetaImageIO.h>
#include <itkNiftiImageIO.h>
#include <itkNrrdImageIO.h>

namespace breast_sim::bench {

namespace {

bool endsWith(const std::string& s, const std::string& end) {
  return s.size() >= end.size() && s.compare(s.size() - end.size(), end.size(), end) == 0;
}

using Image = itk::Image<float, 3>;

ItkVolume fromImage(const Image& image) {
  ItkVolume out;
  for (int d = 0; d < 3; ++d) {
    out.size[d] = static_cast<long>(image.GetLargestPossibleRegion().GetSize()[d]);
    out.spacing_mm[d] = image.GetSpacing()[d];
    out.origin_mm[d] = image.GetOrigin()[d];
    for (int r = 0; r < 3; ++r) out.direction[3 * r + d] = image.GetDirection()[r][d];
  }
  const float* values = image.GetBufferPointer();
  out.values.assign(values, values + out.size[0] * out.size[1] * out.size[2]);
  return out;
}

}  // namespace

ItkVolume itkReadFloat(const std::string& path) {
  itk::ImageIOBase::Pointer io;
  if (endsWith(path, ".nrrd")) io = itk::NrrdImageIO::New();
  else if (endsWith(path, ".mha")) io = itk::MetaImageIO::New();
  else if (endsWith(path, ".nii") || endsWith(path, ".nii.gz")) io = itk::NiftiImageIO::New();
  else throw std::runtime_error(path + ": not .nrrd, .mha, .nii or .nii.gz");
  auto reader = itk::ImageFileReader<Image>::New();
  reader->SetImageIO(io);
  reader->SetFileName(path);
  try {
    reader->Update();
  } catch (const itk::ExceptionObject& e) {
    throw std::runtime_error(path + ": " + e.GetDescription());
  }
  return fromImage(*reader->GetOutput());
}

ItkVolume itkReadDicomFolder(const std::string& folder) {
  auto names = itk::GDCMSeriesFileNames::New();
  names->SetUseSeriesDetails(false);
  auto reader = itk::ImageSeriesReader<Image>::New();
  reader->SetImageIO(itk::GDCMImageIO::New());
  try {
    names->SetDirectory(folder);
    const std::vector<std::string> uids = names->GetSeriesUIDs();
    if (uids.size() != 1) throw std::runtime_error(folder + ": not one DICOM series");
    reader->SetFileNames(names->GetFileNames(uids.front()));
    reader->Update();
  } catch (const itk::ExceptionObject& e) {
    throw std::runtime_error(folder + ": " + e.GetDescription());
  }
  return fromImage(*reader->GetOutput());
}

}  // namespace breast_sim::bench
