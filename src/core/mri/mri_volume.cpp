// mri_volume.h: which reader takes which input, our image types on the ITK bridge's plain ones (ITK's
// part is in mri_volume_itk.cpp), and the checks that need no ITK. NRRD and MetaImage are read by the
// core's own parsers (scalar_image_io.h): ITK's NrrdIO and MetaIO leak memory on malformed files, and
// ours read the same files faster (docs/mri.md). DICOM is read by the core too (dicom_scan.h says why
// GDCM is not). ITK reads NIfTI, its header checked first.
#include "breast_sim/core/mri/mri_volume.h"

#include <cctype>
#include <cmath>
#include <filesystem>
#include <sstream>
#include <stdexcept>
#include <system_error>
#include <utility>

#include <Eigen/Dense>

#include "breast_sim/core/image/scalar_image_io.h"
#include "breast_sim/core/mri/dicom_scan.h"
#include "dicom_series.h"
#include "grid_conversion.h"

namespace breast_sim::core {

namespace {

[[noreturn]] void fail(const std::string& path, const std::string& what) { throw std::runtime_error(path + ": " + what); }

// A direction matrix from a file, made exactly orthonormal when it is within float precision of it
// (NIfTI stores it as float); a sheared grid is an error.
Eigen::Matrix3d orthonormalDirection(const std::string& path, const Eigen::Matrix3d& d) {
  const double err = (d.transpose() * d - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (err <= 1e-6) return d;
  if (!(err <= 1e-3)) {
    std::ostringstream s;
    s << "the voxel axes are not orthogonal (largest entry of |D^T D - I| = " << err
      << "): a sheared grid (e.g. gantry tilt) is not supported; resample it onto an orthogonal grid first";
    fail(path, s.str());
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(d, Eigen::ComputeFullU | Eigen::ComputeFullV);
  return svd.matrixU() * svd.matrixV().transpose();
}

void checkImage(const ScalarImage& image, const char* who) {
  image.geometry.validate();
  if (static_cast<long>(image.values.size()) != image.geometry.numVoxels())
    throw std::invalid_argument(std::string(who) + ": " + std::to_string(image.values.size()) + " values for a grid of " +
                                std::to_string(image.geometry.numVoxels()) + " voxels");
}

// UIDs "2.25.<decimal>" (ISO/IEC 9834-8: a UID from a 128-bit number), here from a 64-bit hash of the
// seed and a tag, so a series written twice from the same seed has the same UIDs.
std::string derivedUid(std::uint64_t seed, std::uint64_t tag) {
  std::uint64_t z = seed * 0x9E3779B97F4A7C15ULL + tag * 0xBF58476D1CE4E5B9ULL + 0x94D049BB133111EBULL;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  z ^= z >> 31;
  return "2.25." + std::to_string(z);
}

}  // namespace

namespace itk_bridge {

void checkVolumeSize(const std::string& path, const std::vector<long>& sizes, long max_voxels) {
  std::string text;
  for (std::size_t d = 0; d < sizes.size(); ++d) text += (d ? " x " : "") + std::to_string(sizes[d]);
  if (sizes.size() < 3 || sizes[2] <= 1)
    fail(path, "a 2-D image (" + text +
                   " voxels); the MRI must be a 3-D volume: give the folder of the whole DICOM series or a 3-D "
                   "NIfTI/NRRD export");
  for (std::size_t d = 3; d < sizes.size(); ++d)
    if (sizes[d] > 1)
      fail(path, "a " + std::to_string(sizes.size()) + "-D image (" + text +
                     " voxels: several volumes, e.g. a time series); give one 3-D volume (export a single time point)");
  // Overflow-safe: stop multiplying once past the cap.
  long voxels = 1;
  for (int d = 0; d < 3; ++d) {
    if (sizes[d] < 1) fail(path, "the header gives a size of " + std::to_string(sizes[d]) + " voxels along axis " + std::to_string(d));
    if (voxels > max_voxels / sizes[d])
      fail(path, "the header gives " + std::to_string(sizes[0]) + " x " + std::to_string(sizes[1]) + " x " +
                     std::to_string(sizes[2]) + " voxels, more than the " + std::to_string(max_voxels) +
                     " accepted (MriReadOptions::max_voxels); a damaged header, or crop or resample the volume first");
    voxels *= sizes[d];
  }
}

}  // namespace itk_bridge

namespace {

const char* kFormats = "NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd) or a folder of DICOM files";

bool endsWithLower(const std::string& path, const std::string& end) {
  if (path.size() < end.size()) return false;
  for (std::size_t i = 0; i < end.size(); ++i)
    if (std::tolower(static_cast<unsigned char>(path[path.size() - end.size() + i])) != end[i]) return false;
  return true;
}

// ITK's names of the voxel types, so that MriVolumeInfo::pixel_type reads the same for every format.
std::string itkTypeName(const std::string& ours) {
  static const std::pair<const char*, const char*> kNames[] = {
      {"uint8", "unsigned_char"}, {"int8", "char"}, {"uint16", "unsigned_short"}, {"int16", "short"},
      {"uint32", "unsigned_int"}, {"int32", "int"}, {"uint64", "unsigned_long_long"}, {"int64", "long_long"}};
  for (const auto& [a, b] : kNames)
    if (ours == a) return b;
  return ours;  // float, double
}

// A NRRD or MetaImage file through the core's parser, with the MRI's checks on its header's shape.
MriVolume readOwnFormat(const std::string& path, long max_voxels) {
  ScalarImageFile file = readScalarImageFile(path, [&](const ImageFileShape& shape) {
    if (shape.components != 1)
      fail(path, "voxels of " + std::to_string(shape.components) +
                     " components; the MRI must be a scalar (magnitude) image: export the magnitude, not RGB, vector or "
                     "complex data");
    itk_bridge::checkVolumeSize(path, shape.sizes, max_voxels);
  });
  MriVolume out;
  out.image = std::move(file.image);
  out.info.format = file.format;
  out.info.pixel_type = itkTypeName(file.value_type);
  return out;
}

// A volume ITK read: its grid in mm checked and converted.
MriVolume fromBridge(const std::string& path, itk_bridge::Volume v) {
  MriVolume out;
  ImageGeometry& g = out.image.geometry;
  g = geometryOf(v.grid);
  for (int d = 0; d < 3; ++d) {
    if (!(g.spacing_m[d] > 0) || !std::isfinite(g.spacing_m[d]))
      fail(path, "the voxel spacing along axis " + std::to_string(d) + " is " + std::to_string(v.grid.spacing_mm[d]) +
                     " mm; it must be a positive number");
  }
  if (!g.origin_m.allFinite()) fail(path, "the origin is not a finite point");
  out.image.values = std::move(v.values);
  out.info.format = v.format;
  out.info.pixel_type = v.pixel_type;
  return out;
}

// The images of a DICOM folder: the series `uid`, or the only one.
MriVolume readDicomFolder(const std::string& folder, std::string uid, const MriReadOptions& options) {
  const DicomFolder found = scanDicomFolder(folder);
  if (found.series.empty())
    fail(folder, std::string("no DICOM image in this folder (DICOM Part 10 files: a 128-byte preamble, then 'DICM'); "
                             "give a folder holding one DICOM series, or a file in ") + kFormats);
  const auto listSeries = [&] {
    std::string s;
    for (const auto& [u, files] : found.series) s += "\n  " + u + " (" + std::to_string(files.size()) + " files)";
    return s;
  };
  if (uid.empty()) {
    if (found.series.size() > 1)
      fail(folder, "holds " + std::to_string(found.series.size()) + " DICOM series; name the one to read by its series UID "
                   "(MriReadOptions::series_uid, --series-uid):" + listSeries());
    uid = found.series.begin()->first;
  }
  const auto it = found.series.find(uid);
  if (it == found.series.end()) fail(folder, "holds no DICOM series with UID " + uid + "; the series here are:" + listSeries());
  return readDicomSeries(folder, uid, it->second, options.max_voxels, options.slice_spacing_tolerance);
}

MriVolume readAnyVolume(const std::string& path, const MriReadOptions& options) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (!fs::exists(path, ec))
    fail(path, "no such file or folder; check the path (a relative path is read from the working directory)");
  if (fs::is_directory(path, ec)) return readDicomFolder(path, options.series_uid, options);
  for (const char* e : {".nrrd", ".nhdr", ".mha", ".mhd"})
    if (endsWithLower(path, e)) return readOwnFormat(path, options.max_voxels);
  if (itk_bridge::isNifti(path)) return fromBridge(path, itk_bridge::readNifti(path, options.max_voxels));
  const DicomFileScan scan = scanDicomFile(path);
  if (scan.is_dicom && scan.has_pixel_data) {
    // One file of a series: read its folder, the series it belongs to unless another is named.
    const fs::path parent = fs::path(path).parent_path();
    return readDicomFolder(parent.empty() ? "." : parent.string(),
                           options.series_uid.empty() ? scan.series_uid : options.series_uid, options);
  }
  if (scan.is_dicom)
    fail(path, "a DICOM file without an image (no Pixel Data, e.g. a DICOMDIR or a report); give an image file of the "
               "series or its folder");
  fail(path, std::string("not an image of a supported format; give ") + kFormats);
}

}  // namespace

MriVolume readMriVolume(const std::string& path, const MriReadOptions& options) {
  if (options.max_voxels < 1) throw std::invalid_argument("MriReadOptions::max_voxels must be at least 1");
  if (!(options.slice_spacing_tolerance > 0 && options.slice_spacing_tolerance < 1))
    throw std::invalid_argument("MriReadOptions::slice_spacing_tolerance must be in (0, 1)");
  MriVolume out = readAnyVolume(path, options);
  ImageGeometry& g = out.image.geometry;
  g.direction = orthonormalDirection(path, g.direction);
  for (long i = 0; i < static_cast<long>(out.image.values.size()); ++i)
    if (!std::isfinite(out.image.values[i])) {
      const long x = i % g.size.x(), y = (i / g.size.x()) % g.size.y(), z = i / (static_cast<long>(g.size.x()) * g.size.y());
      fail(path, "voxel (" + std::to_string(x) + ", " + std::to_string(y) + ", " + std::to_string(z) +
                     ") is not a finite number; the MRI must hold finite intensities");
    }
  out.info.path = path;
  return out;
}

void writeMriVolume(const std::string& path, const ScalarImage& image) {
  checkImage(image, "writeMriVolume");
  itk_bridge::writeVolume(path, bridgeGrid(image.geometry), image.values);
}

void writeDicomSeries(const std::string& folder, const ScalarImage& image, const DicomSeriesOptions& options) {
  checkImage(image, "writeDicomSeries");
  itk_bridge::DicomTags tags;
  tags.study_uid = options.study_uid.empty() ? derivedUid(options.uid_seed, 1) : options.study_uid;
  tags.series_uid = options.series_uid.empty() ? derivedUid(options.uid_seed, 2) : options.series_uid;
  tags.frame_uid = derivedUid(options.uid_seed, 3);
  tags.description = options.series_description;
  tags.patient_name = options.patient_name;
  tags.patient_id = options.patient_id;
  tags.series_number = options.series_number;
  itk_bridge::writeDicom(folder, bridgeGrid(image.geometry), image.values, tags);
}

LabelImage labelImageLike(const ScalarImage& image, std::uint16_t fill) {
  LabelImage out;
  out.size = image.geometry.size;
  out.spacing_m = image.geometry.spacing_m;
  out.origin_m = image.geometry.origin_m;
  out.direction = image.geometry.direction;
  out.labels.assign(static_cast<std::size_t>(image.geometry.numVoxels()), fill);
  return out;
}

ScalarImage scalarImageLike(const LabelImage& labels, float fill) {
  ScalarImage out;
  out.geometry = ImageGeometry::of(labels);
  out.values.assign(static_cast<std::size_t>(out.geometry.numVoxels()), fill);
  return out;
}

}  // namespace breast_sim::core
