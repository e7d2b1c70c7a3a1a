#pragma once
/// @file label_image.h
/// A 3-D label image (segmentation) placed in patient space, and its file readers and writers.

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
/// \note `direction` may have determinant −1 (a left-handed voxel grid); its columns must be
/// orthonormal. Readers reject sheared grids.
/// \note At most 2^31 = 2147483648 voxels (4 GiB of labels). validate(), the constructor and the
/// readers reject larger sizes, naming them; the count is computed without overflow.
struct LabelImage {
  Eigen::Vector3i size{0, 0, 0};                        ///< voxels along i, j, k
  Eigen::Vector3d spacing_m{1e-3, 1e-3, 1e-3};          ///< voxel size along i, j, k [m]
  Eigen::Vector3d origin_m{0, 0, 0};                    ///< centre of voxel (0,0,0) [m]
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity(); ///< orthonormal columns: axes i, j, k
  std::vector<std::uint16_t> labels;                    ///< size.prod() labels

  LabelImage() = default;
  /// An image of `size` voxels, all `fill`, with identity direction.
  /// @param size       voxels along i, j, k (≥ 0)
  /// @param spacing_m  voxel size along i, j, k [m]
  /// @param origin_m   centre of voxel (0,0,0) [m]
  /// @throws std::invalid_argument when a size entry is negative or the image would have more
  ///         than 2^31 voxels.
  LabelImage(const Eigen::Vector3i& size, const Eigen::Vector3d& spacing_m,
             const Eigen::Vector3d& origin_m, std::uint16_t fill = 0);

  /// size.x·size.y·size.z.
  /// \pre The size has passed validate() (at most 2^31 voxels); for larger sizes the product can
  /// overflow.
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
  /// Continuous voxel index of a physical position [m]; the exact inverse of indexToPhysical.
  Eigen::Vector3d physicalToIndex(const Eigen::Vector3d& p_m) const;
  /// Label of the voxel containing p (nearest voxel centre), or `outside` beyond the image
  /// (more than half a voxel past the outer voxel centres) or when p is not finite.
  std::uint16_t labelAt(const Eigen::Vector3d& p_m, std::uint16_t outside = 0) const;

  /// Checks: every size entry ≥ 1, at most 2^31 voxels in all (counted without overflow),
  /// labels.size() equal to that count, spacing finite and > 0, origin finite, direction columns
  /// orthonormal within 1e-6.
  /// @throws std::invalid_argument when sizes, label count, spacing or direction are inconsistent.
  void validate() const;
};

/// Reads a label image, choosing the reader by extension (case-insensitive):
///  - NRRD `.nrrd` (attached header) and `.nhdr` (detached, `data file:` relative to the header).
///    Encodings raw, gzip and ascii; endian little and big; `space` left-posterior-superior,
///    right-anterior-superior, left-anterior-superior (converted to LPS), 3D-right-handed,
///    3D-left-handed, scanner-xyz or none (taken as they are); `space directions` (one column
///    vector per axis, spacing included) or else `spacings` (identity direction); `space origin`;
///    `space units` mm (default), m, cm or um; `line skip`, `byte skip` (−1 for raw data at the
///    end of the file). Not supported: bzip2 and hex encodings, multiple data files (LIST or
///    `%d` patterns), dimension ≠ 3.
///  - MetaImage `.mha` (ElementDataFile = LOCAL) and `.mhd` (separate data file, HeaderSize).
///    ElementType MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_INT, MET_UINT, MET_LONG,
///    MET_ULONG, MET_LONG_LONG, MET_ULONG_LONG, MET_FLOAT, MET_DOUBLE; CompressedData (zlib);
///    BinaryDataByteOrderMSB; BinaryData = False (ASCII values). Offset (or Position/Origin),
///    ElementSpacing (or ElementSize), TransformMatrix (or Rotation/Orientation) as ITK writes it:
///    the 9 numbers list axis i's direction first, then axis j's, then axis k's (that is, the
///    direction matrix column by column). Lengths in mm; coordinates taken as LPS (ITK's
///    convention); AnatomicalOrientation is ignored, as ITK does. Not supported: multiple data
///    files, ElementNumberOfChannels ≠ 1, NDims ≠ 3.
///  - NIfTI-1 `.nii` and `.nii.gz` (single file, either byte order). The sform is used when
///    sform_code > 0, else the qform (quaternion, qfac = pixdim[0] = −1 flips the k axis) when
///    qform_code > 0; both are RAS and converted to LPS. With both codes 0 (ANALYZE-style
///    "method 1") the grid is diag(pixdim) at origin 0, taken as it is. A sheared sform falls
///    back to the qform (as ITK does). xyzt_units mm (or unknown), m or µm; scl_slope/scl_inter
///    applied when slope ≠ 0. dim[0] may be 1…7 if dimensions 4 and above have size 1. Not
///    supported: NIfTI-2, .hdr/.img pairs, ANALYZE 7.5.
/// Voxel types: integers of 8 to 64 bits and floats; every value must be an integer in
/// [0, 65535]. Images of more than 2^31 voxels are rejected before their labels are allocated.
/// @throws std::runtime_error whose message starts with the path and says what is wrong (unknown
///         extension, unreadable file, malformed header field and its value, truncated data with
///         the expected and found byte counts, a non-integral or out-of-range label with its value
///         and voxel index, …).
LabelImage readLabelImage(const std::string& path);

/// Writes a label image; format by extension as for readLabelImage. Voxels are written as uint8
/// when every label is ≤ 255, else as uint16; lengths in mm.
///  - `.nrrd`: gzip data, space left-posterior-superior, space directions and space origin.
///    `.nhdr`: the same header beside a gzip data file `<stem>.raw.gz`.
///  - `.mha`: zlib-compressed local data, LPS TransformMatrix/Offset/ElementSpacing.
///    `.mhd`: the same header beside a compressed data file `<stem>.zraw`.
///  - `.nii` / `.nii.gz`: NIfTI-1 in RAS with qform_code = sform_code = 1 (scanner); qfac = −1
///    when the grid is left-handed in RAS; intent NIFTI_INTENT_LABEL. NIfTI-1 stores sizes as
///    16-bit integers: a size above 32767 is rejected (write NRRD or MetaImage instead).
/// \note NIfTI stores geometry as float32: positions come back to about 1e-7 relative.
/// @throws std::invalid_argument if the image fails validate();
///         std::runtime_error naming the file if it cannot be written, the extension is unknown,
///         or a size does not fit the format (NIfTI: above 32767, checked before writing).
void writeLabelImage(const std::string& path, const LabelImage& image);

}  // namespace breast_sim::core
