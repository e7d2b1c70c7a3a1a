// mri_volume.h: our image types on the ITK bridge's plain ones (the reading itself is in
// mri_volume_itk.cpp), and the checks that need no ITK.
#include "breast_sim/core/mri/mri_volume.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

#include <Eigen/Dense>

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

MriVolume readMriVolume(const std::string& path, const MriReadOptions& options) {
  if (options.max_voxels < 1) throw std::invalid_argument("MriReadOptions::max_voxels must be at least 1");
  if (!(options.slice_spacing_tolerance > 0 && options.slice_spacing_tolerance < 1))
    throw std::invalid_argument("MriReadOptions::slice_spacing_tolerance must be in (0, 1)");
  itk_bridge::Volume v =
      itk_bridge::readVolume(path, options.series_uid, options.max_voxels, options.slice_spacing_tolerance);
  MriVolume out;
  ImageGeometry& g = out.image.geometry;
  g = geometryOf(v.grid);
  for (int d = 0; d < 3; ++d) {
    if (!(g.spacing_m[d] > 0) || !std::isfinite(g.spacing_m[d]))
      fail(path, "the voxel spacing along axis " + std::to_string(d) + " is " + std::to_string(v.grid.spacing_mm[d]) +
                     " mm; it must be a positive number");
  }
  if (!g.origin_m.allFinite()) fail(path, "the origin is not a finite point");
  g.direction = orthonormalDirection(path, g.direction);
  out.image.values = std::move(v.values);
  for (long i = 0; i < static_cast<long>(out.image.values.size()); ++i)
    if (!std::isfinite(out.image.values[i])) {
      const long x = i % g.size.x(), y = (i / g.size.x()) % g.size.y(), z = i / (static_cast<long>(g.size.x()) * g.size.y());
      fail(path, "voxel (" + std::to_string(x) + ", " + std::to_string(y) + ", " + std::to_string(z) +
                     ") is not a finite number; the MRI must hold finite intensities");
    }
  out.info.path = path;
  out.info.format = v.format;
  out.info.series_uid = v.series_uid;
  out.info.series_description = v.series_description;
  out.info.files = v.files;
  out.info.pixel_type = v.pixel_type;
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
