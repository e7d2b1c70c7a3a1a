// NIfTI-1 reader and writer, parsing the 348-byte header directly
// (https://nifti.nimh.nih.gov/pub/dist/src/niftilib/nifti1.h).
//
// Why not vtkNIFTIImageReader: it reverses the slice order when qfac = −1 and adjusts its QForm/
// SForm matrices to match, factors pixdim out of the sform, and leaves the RAS→LPS conversion
// and the sform/qform choice to the caller. Reading the header ourselves keeps voxel (i, j, k) of
// the file as voxel (i, j, k) of the LabelImage and the geometry rules in one place.

#include <cmath>
#include <cstring>
#include <string>

#include <Eigen/Geometry>

#include "breast_sim/core/image/image_io_detail.h"

namespace breast_sim::core::image_io {
namespace {

constexpr std::size_t kHeaderSize = 348;
constexpr std::size_t kDataOffset = 352;  // header + the 4-byte "no extension" flag

// Byte offsets of the NIfTI-1 header fields we use.
constexpr std::size_t kDim = 40;           // short[8]
constexpr std::size_t kIntentCode = 68;    // short
constexpr std::size_t kDatatype = 70;      // short
constexpr std::size_t kBitpix = 72;        // short
constexpr std::size_t kPixdim = 76;        // float[8]
constexpr std::size_t kVoxOffset = 108;    // float
constexpr std::size_t kSclSlope = 112;     // float
constexpr std::size_t kSclInter = 116;     // float
constexpr std::size_t kXyztUnits = 123;    // char
constexpr std::size_t kDescrip = 148;      // char[80]
constexpr std::size_t kQformCode = 252;    // short
constexpr std::size_t kSformCode = 254;    // short
constexpr std::size_t kQuaternB = 256;     // float b, c, d
constexpr std::size_t kQoffsetX = 268;     // float x, y, z
constexpr std::size_t kSrowX = 280;        // float[4] × 3 rows
constexpr std::size_t kMagic = 344;        // char[4]

constexpr int kIntentLabel = 1002;  // NIFTI_INTENT_LABEL

/// Reads fields of a header in either byte order.
class HeaderView {
 public:
  HeaderView(const std::string& bytes, bool swap) : bytes_(bytes), swap_(swap) {}
  std::int16_t i16(std::size_t offset) const { return load<std::int16_t>(offset); }
  std::int32_t i32(std::size_t offset) const { return load<std::int32_t>(offset); }
  double f32(std::size_t offset) const { return load<float>(offset); }
  std::uint8_t u8(std::size_t offset) const {
    return static_cast<std::uint8_t>(bytes_[offset]);
  }

 private:
  template <typename T>
  T load(std::size_t offset) const {
    char b[sizeof(T)];
    std::memcpy(b, bytes_.data() + offset, sizeof(T));
    if (swap_) {
      for (std::size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(b[i], b[sizeof(T) - 1 - i]);
    }
    T v;
    std::memcpy(&v, b, sizeof(T));
    return v;
  }
  const std::string& bytes_;
  bool swap_;
};

std::int32_t byteSwapped(std::int32_t v) {
  std::uint32_t u;
  std::memcpy(&u, &v, 4);
  u = (u >> 24) | ((u >> 8) & 0xff00u) | ((u << 8) & 0xff0000u) | (u << 24);
  std::int32_t out;
  std::memcpy(&out, &u, 4);
  return out;
}

bool niftiType(int datatype, ScalarType& type) {
  switch (datatype) {
    case 2: type = ScalarType::kUint8; return true;
    case 4: type = ScalarType::kInt16; return true;
    case 8: type = ScalarType::kInt32; return true;
    case 16: type = ScalarType::kFloat32; return true;
    case 64: type = ScalarType::kFloat64; return true;
    case 256: type = ScalarType::kInt8; return true;
    case 512: type = ScalarType::kUint16; return true;
    case 768: type = ScalarType::kUint32; return true;
    case 1024: type = ScalarType::kInt64; return true;
    case 1280: type = ScalarType::kUint64; return true;
    default: return false;
  }
}

/// The header's writer: little-endian fields into a 352-byte buffer.
class HeaderWriter {
 public:
  HeaderWriter() : bytes_(kDataOffset, '\0') {}
  void i16(std::size_t offset, int v) { store(offset, static_cast<std::int16_t>(v)); }
  void i32(std::size_t offset, int v) { store(offset, static_cast<std::int32_t>(v)); }
  void f32(std::size_t offset, double v) { store(offset, static_cast<float>(v)); }
  void text(std::size_t offset, const char* s, std::size_t n) { std::memcpy(&bytes_[offset], s, n); }
  const std::string& bytes() const { return bytes_; }

 private:
  template <typename T>
  void store(std::size_t offset, T v) {
    char b[sizeof(T)];
    std::memcpy(b, &v, sizeof(T));
    if (hostIsBigEndian()) {
      for (std::size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(b[i], b[sizeof(T) - 1 - i]);
    }
    std::memcpy(&bytes_[offset], b, sizeof(T));
  }
  std::string bytes_;
};

}  // namespace

LabelImage readNifti(const std::string& path) {
  const std::string stored = readFileBytes(path);
  // A .nii.gz is inflated in two steps: the header first, then exactly the bytes that header
  // describes. A stream that holds more is refused, so a small file cannot decompress into
  // whatever it likes (a decompression bomb).
  const bool gz = isGzip(stored);
  std::string file = gz ? inflateBytes(stored.data(), stored.size(), kHeaderSize, path) : stored;
  if (file.size() < kHeaderSize) {
    fail(path, "file has " + std::to_string(file.size()) +
                   " bytes (after decompression), fewer than a NIfTI-1 header's 348");
  }
  std::int32_t sizeof_hdr = 0;
  std::memcpy(&sizeof_hdr, file.data(), 4);
  bool swap = false;
  if (sizeof_hdr == 348) {
    swap = false;
  } else if (byteSwapped(sizeof_hdr) == 348) {
    swap = true;
  } else if (sizeof_hdr == 540 || byteSwapped(sizeof_hdr) == 540) {
    fail(path, "NIfTI-2 files are not supported; convert to NIfTI-1 (e.g. with 3D Slicer or nibabel)");
  } else {
    fail(path, "not a NIfTI-1 file: sizeof_hdr is " + std::to_string(sizeof_hdr) +
                   ", expected 348");
  }
  const HeaderView h(file, swap);
  const bool big_endian = swap != hostIsBigEndian();
  const std::string magic = file.substr(kMagic, 4);
  if (magic == std::string("ni1\0", 4)) {
    fail(path, "header-only NIfTI (.hdr/.img pair) is not supported; convert to a single .nii");
  }
  if (magic != std::string("n+1\0", 4)) {
    fail(path, "magic is not 'n+1' (an ANALYZE 7.5 file?); only single-file NIfTI-1 is supported");
  }

  // ---- size and type ----
  const int ndim = h.i16(kDim);
  if (ndim < 1 || ndim > 7) fail(path, "dim[0] is " + std::to_string(ndim) + ", expected 1 to 7");
  LabelImage image;
  image.size.setOnes();
  for (int d = 1; d <= ndim; ++d) {
    const int n = h.i16(kDim + 2 * d);
    if (n < 1) {
      fail(path, "dim[" + std::to_string(d) + "] is " + std::to_string(n) +
                     "; every dimension must be at least 1");
    }
    if (d <= 3) {
      image.size(d - 1) = n;
    } else if (n != 1) {
      fail(path, "dim[" + std::to_string(d) + "] is " + std::to_string(n) +
                     "; images with more than 3 dimensions (time, vectors) are not supported");
    }
  }
  const std::int64_t num_voxels =
      requireVoxelCount(image.size, path, "dim[1..3]",
                        std::to_string(image.size.x()) + " " + std::to_string(image.size.y()) +
                            " " + std::to_string(image.size.z()));
  ScalarType type = ScalarType::kUint8;
  const int datatype = h.i16(kDatatype);
  if (!niftiType(datatype, type)) {
    fail(path, "datatype " + std::to_string(datatype) +
                   " is not supported; use an integer or float scalar type");
  }
  const int bitpix = h.i16(kBitpix);
  if (bitpix != static_cast<int>(8 * scalarSize(type))) {
    fail(path, "bitpix is " + std::to_string(bitpix) + " but datatype " + std::to_string(datatype) +
                   " (" + scalarName(type) + ") has " + std::to_string(8 * scalarSize(type)) +
                   " bits");
  }
  // A float from the file: infinity or 1e30 must not reach the size_t conversion below (UB). A
  // compressed file decompresses to at most 1032 bytes per byte (deflate's limit).
  const double vox_offset = h.f32(kVoxOffset);
  const double most_bytes =
      gz ? 1032.0 * static_cast<double>(stored.size()) : static_cast<double>(file.size());
  if (!std::isfinite(vox_offset) || vox_offset < static_cast<double>(kHeaderSize) ||
      vox_offset > most_bytes || vox_offset != std::floor(vox_offset)) {
    fail(path, "vox_offset is " + formatNumber(vox_offset) +
                   "; expected an integer from 348 to the file size (" +
                   (gz ? "at most " + formatNumber(most_bytes) + " bytes after decompression"
                       : std::to_string(file.size()) + " bytes") +
                   ")");
  }
  double slope = h.f32(kSclSlope);
  double inter = h.f32(kSclInter);
  if (slope == 0.0 || !std::isfinite(slope)) {  // the standard: slope 0 means "no scaling"
    slope = 1.0;
    inter = 0.0;
  }
  if (!std::isfinite(inter)) inter = 0.0;

  // ---- geometry ----
  double scale = 1e-3;
  switch (h.u8(kXyztUnits) & 0x07) {
    case 0:  // unknown: mm, as every NIfTI tool assumes
    case 2: scale = 1e-3; break;
    case 1: scale = 1.0; break;
    case 3: scale = 1e-6; break;
    default: fail(path, "xyzt_units " + std::to_string(h.u8(kXyztUnits)) + " is not a length unit");
  }
  double pixdim[4];
  for (int d = 0; d < 4; ++d) pixdim[d] = h.f32(kPixdim + 4 * d);
  const auto voxelSize = [&](int d) {
    const double v = std::abs(pixdim[d]);
    if (std::isfinite(v) && v > 0.0) return v;
    if (image.size(d - 1) == 1) return 1.0;  // a flat axis may leave its size unset
    fail(path, "pixdim[" + std::to_string(d) + "] is " + formatNumber(pixdim[d]) +
                   "; voxel sizes must be finite and non-zero");
  };
  const int qform_code = h.i16(kQformCode);
  const int sform_code = h.i16(kSformCode);
  Eigen::Matrix3d axes;
  Eigen::Vector3d origin;
  bool ras = true;
  bool use_qform = qform_code > 0;
  if (sform_code > 0) {
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) axes(r, c) = h.f32(kSrowX + 16 * r + 4 * c);
      origin(r) = h.f32(kSrowX + 16 * r + 12);
    }
    if (!axes.allFinite() || !origin.allFinite()) fail(path, "sform (srow_x/y/z) is not finite");
    int a = 0;
    int b = 0;
    const double cosine = largestAxisCosine(axes, a, b);
    if (!(cosine <= 1e-4)) {
      // ITK also falls back to the qform when the sform is not a rigid grid.
      if (!use_qform) {
        fail(path, "sform axes " + std::to_string(a) + " and " + std::to_string(b) +
                       " are not orthogonal (cosine " + formatNumber(cosine) +
                       ") and there is no qform to fall back on; sheared grids are not supported");
      }
    } else {
      use_qform = false;
    }
  }
  if (use_qform) {
    const double b = h.f32(kQuaternB);
    const double c = h.f32(kQuaternB + 4);
    const double d = h.f32(kQuaternB + 8);
    if (!std::isfinite(b) || !std::isfinite(c) || !std::isfinite(d)) {
      fail(path, "qform quaternion (quatern_b/c/d) is not finite");
    }
    // a is implied by |q| = 1; float rounding can make 1 − b² − c² − d² slightly negative, in
    // which case a = 0 and (b, c, d) is renormalised (as nifti1_io.c does).
    double a2 = 1.0 - (b * b + c * c + d * d);
    Eigen::Quaterniond q;
    if (a2 < 1e-7) {
      const double n = std::sqrt(b * b + c * c + d * d);
      q = Eigen::Quaterniond(0.0, b / n, c / n, d / n);
    } else {
      q = Eigen::Quaterniond(std::sqrt(a2), b, c, d);
    }
    // qfac = pixdim[0]: −1 means the k axis is R's third column reversed (a left-handed grid).
    const double qfac = pixdim[0] < 0.0 ? -1.0 : 1.0;
    const Eigen::Vector3d step(voxelSize(1), voxelSize(2), qfac * voxelSize(3));
    axes = q.toRotationMatrix() * step.asDiagonal();
    origin << h.f32(kQoffsetX), h.f32(kQoffsetX + 4), h.f32(kQoffsetX + 8);
    if (!origin.allFinite()) fail(path, "qform offset (qoffset_x/y/z) is not finite");
  } else if (sform_code <= 0) {
    // "Method 1" (ANALYZE compatibility): no orientation in the file; taken as it is.
    ras = false;
    axes = Eigen::Vector3d(voxelSize(1), voxelSize(2), voxelSize(3)).asDiagonal();
    origin.setZero();
  }
  if (ras) {
    const Eigen::Vector3d flip(-1, -1, 1);
    axes = flip.asDiagonal() * axes;
    origin = flip.asDiagonal() * origin;
  }
  Eigen::Vector3d lengths;
  if (!splitAxes(axes, path, use_qform ? "qform" : "sform", lengths, image.direction)) {
    fail(path, "voxel axes are not orthogonal; sheared grids are not supported");
  }
  image.spacing_m = lengths * scale;
  image.origin_m = origin * scale;

  // ---- voxel data ----
  const std::size_t offset = static_cast<std::size_t>(vox_offset);
  const std::size_t expected = static_cast<std::size_t>(num_voxels) * scalarSize(type);
  const std::string values = std::to_string(image.size.x()) + "×" + std::to_string(image.size.y()) +
                             "×" + std::to_string(image.size.z()) + " " + scalarName(type) + " values";
  if (gz) {
    const std::size_t needed = offset + expected;
    file = inflateBytes(stored.data(), stored.size(), needed + 1, path);
    if (file.size() > needed) {
      fail(path, "the gzip stream decompresses to more than the " + std::to_string(needed) +
                     " bytes its header describes (vox_offset " + std::to_string(offset) + " + " +
                     values + "); refused without inflating the rest (a decompression bomb?)");
    }
  }
  const std::size_t available = file.size() > offset ? file.size() - offset : 0;
  if (available < expected) {
    fail(path, "voxel data is truncated: expected " + std::to_string(expected) + " bytes (" + values +
                   " from byte " + std::to_string(offset) + (gz ? " after decompression" : "") +
                   "), found " + std::to_string(available));
  }
  decodeLabels(file.data() + offset, type, big_endian, image.size, path, image.labels, slope,
               inter);
  return image;
}

void writeNifti(const std::string& path, const LabelImage& image) {
  // dim[] is int16: a larger size would be silently truncated into another image.
  constexpr int kMaxDim = 32767;
  for (int a = 0; a < 3; ++a) {
    if (image.size(a) > kMaxDim) {
      fail(path, "size " + std::to_string(image.size.x()) + "×" + std::to_string(image.size.y()) +
                     "×" + std::to_string(image.size.z()) + ": axis " + "ijk"[a] + " has " +
                     std::to_string(image.size(a)) + " voxels, but NIfTI-1 stores sizes as 16-bit " +
                     "integers (at most " + std::to_string(kMaxDim) +
                     "); write .nrrd or .mha instead");
    }
  }
  const ScalarType type = narrowestLabelType(image);
  // NIfTI is RAS; our direction is LPS.
  const Eigen::Vector3d flip(-1, -1, 1);
  const Eigen::Matrix3d direction_ras = flip.asDiagonal() * image.direction;
  const Eigen::Vector3d origin_ras_mm = flip.asDiagonal() * image.origin_m * 1e3;
  const Eigen::Vector3d spacing_mm = image.spacing_m * 1e3;
  // The qform holds a proper rotation; a left-handed grid is expressed by qfac = −1, which
  // reverses the rotation's third column.
  const double qfac = direction_ras.determinant() < 0.0 ? -1.0 : 1.0;
  Eigen::Matrix3d rotation = direction_ras;
  rotation.col(2) *= qfac;
  Eigen::Quaterniond q(rotation);
  q.normalize();
  if (q.w() < 0.0) q.coeffs() *= -1.0;  // the file stores b, c, d and implies a ≥ 0
  const Eigen::Matrix3d sform = direction_ras * spacing_mm.asDiagonal();

  HeaderWriter h;
  h.i32(0, static_cast<int>(kHeaderSize));
  const int dims[8] = {3, image.size.x(), image.size.y(), image.size.z(), 1, 1, 1, 1};
  for (int d = 0; d < 8; ++d) h.i16(kDim + 2 * d, dims[d]);
  h.i16(kIntentCode, kIntentLabel);
  h.i16(kDatatype, type == ScalarType::kUint8 ? 2 : 512);
  h.i16(kBitpix, static_cast<int>(8 * scalarSize(type)));
  const double pixdim[8] = {qfac, spacing_mm.x(), spacing_mm.y(), spacing_mm.z(), 1, 1, 1, 1};
  for (int d = 0; d < 8; ++d) h.f32(kPixdim + 4 * d, pixdim[d]);
  h.f32(kVoxOffset, static_cast<double>(kDataOffset));
  h.f32(kSclSlope, 1.0);
  h.f32(kSclInter, 0.0);
  h.text(kXyztUnits, "\x02", 1);  // NIFTI_UNITS_MM
  const char descrip[] = "breast_sim label image";
  h.text(kDescrip, descrip, sizeof descrip - 1);
  h.i16(kQformCode, 1);  // NIFTI_XFORM_SCANNER_ANAT
  h.i16(kSformCode, 1);
  h.f32(kQuaternB, q.x());
  h.f32(kQuaternB + 4, q.y());
  h.f32(kQuaternB + 8, q.z());
  for (int r = 0; r < 3; ++r) {
    h.f32(kQoffsetX + 4 * r, origin_ras_mm(r));
    for (int c = 0; c < 3; ++c) h.f32(kSrowX + 16 * r + 4 * c, sform(r, c));
    h.f32(kSrowX + 16 * r + 12, origin_ras_mm(r));
  }
  h.text(kMagic, "n+1\0", 4);

  std::string bytes = h.bytes() + encodeLabels(image, type);
  if (endsWith(path, ".gz")) bytes = deflateBytes(bytes, Wrapper::kGzip);
  writeFileBytes(path, bytes);
}

}  // namespace breast_sim::core::image_io
