#pragma once
/// @file label_image.h
/// A 3-D label image (segmentation) placed in patient space.

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace breast_sim::core {

/// A 3-D image of integer labels with its geometry.
///
/// Physical position [m] of voxel centre (i, j, k):
///   p = origin_m + direction · diag(spacing_m) · (i, j, k)ᵀ
/// \note Patient coordinates are LPS (x towards the patient's left, y posterior, z superior), as
/// in DICOM, ITK and 3D Slicer's files. Readers convert RAS files (NIfTI, NRRD "right-anterior-
/// superior") to LPS by negating x and y. Files whose space is not anatomical ("3D-right-handed",
/// MetaImage) are taken as they are.
/// \note Voxel order: i fastest, then j, then k (index = i + size.x·(j + size.y·k)).
struct LabelImage {
  Eigen::Vector3i size{0, 0, 0};                        ///< voxels along i, j, k
  Eigen::Vector3d spacing_m{1e-3, 1e-3, 1e-3};          ///< voxel size along i, j, k [m]
  Eigen::Vector3d origin_m{0, 0, 0};                    ///< centre of voxel (0,0,0) [m]
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity(); ///< orthonormal columns: axes i, j, k
  std::vector<std::uint16_t> labels;                    ///< size.prod() labels

  LabelImage() = default;
  /// An image of `size` voxels, all `fill`.
  LabelImage(const Eigen::Vector3i& size, const Eigen::Vector3d& spacing_m,
             const Eigen::Vector3d& origin_m, std::uint16_t fill = 0);

  long numVoxels() const { return static_cast<long>(size.x()) * size.y() * size.z(); }
  long index(int i, int j, int k) const {
    return i + static_cast<long>(size.x()) * (j + static_cast<long>(size.y()) * k);
  }
  std::uint16_t at(int i, int j, int k) const { return labels[index(i, j, k)]; }
  std::uint16_t& at(int i, int j, int k) { return labels[index(i, j, k)]; }
  bool contains(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < size.x() && j < size.y() && k < size.z();
  }

  /// Physical position of a (possibly fractional) voxel index [m].
  Eigen::Vector3d indexToPhysical(const Eigen::Vector3d& ijk) const;
  /// Continuous voxel index of a physical position [m].
  Eigen::Vector3d physicalToIndex(const Eigen::Vector3d& p_m) const;
  /// Label of the voxel containing p (nearest voxel centre), or `outside` beyond the image.
  std::uint16_t labelAt(const Eigen::Vector3d& p_m, std::uint16_t outside = 0) const;

  /// @throws std::invalid_argument when sizes, spacing or direction are inconsistent.
  void validate() const;
};

/// Reads a label image, choosing the reader by extension: NIfTI (`.nii`, `.nii.gz`), NRRD (`.nrrd`,
/// `.nhdr`) or MetaImage (`.mha`, `.mhd`). Integer voxel types up to 16 bits (and float types
/// holding integral values) are accepted.
/// @throws std::runtime_error naming the file and what is wrong (unknown extension, malformed header,
///         truncated data, non-integral labels, …).
LabelImage readLabelImage(const std::string& path);

/// Writes a label image; format by extension as for readLabelImage (NRRD and MetaImage written
/// gzip-compressed, NIfTI with a qform/sform in RAS as the standard requires).
void writeLabelImage(const std::string& path, const LabelImage& image);

}  // namespace breast_sim::core
