#pragma once
/// @file image_io_detail.h
/// Internal functions shared by the label-image readers and writers (label_image.cpp, nrrd_io.cpp,
/// metaimage_io.cpp, nifti_io.cpp). Not part of the public API: include label_image.h instead.

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/image/scalar_image_io.h"

namespace breast_sim::core::image_io {

/// Throws std::runtime_error("<path>: <what>").
[[noreturn]] void fail(const std::string& path, const std::string& what);

// ---- size -----------------------------------------------------------------------------------------
/// Most voxels a LabelImage may have: 2^31 (4 GiB of uint16 labels). Every reader and
/// LabelImage::validate() check it, so that no voxel count or byte count can overflow.
constexpr std::int64_t kMaxVoxels = std::int64_t{1} << 31;
/// size.x·size.y·size.z computed without overflow. false when an entry is negative or the product
/// exceeds kMaxVoxels (`count` is then left as it was).
bool checkedVoxelCount(const Eigen::Vector3i& size, std::int64_t& count);
/// "7×5×3 = 105 voxels" for a message; exact up to 2^63, beyond it "… ≈ 1.84e+19 voxels".
std::string voxelCountText(const Eigen::Vector3i& size);
/// The readers' check, before anything is allocated: the voxel count of `size` (entries ≥ 1), or
/// fail(path, "header field '<field>' is <value>: a×b×c = N voxels, more than the 2147483648 (2^31)
/// a label image may hold; …").
std::int64_t requireVoxelCount(const Eigen::Vector3i& size, const std::string& path,
                               const std::string& field, const std::string& value);

/// Voxel value types found in image files.
enum class ScalarType { kUint8, kInt8, kUint16, kInt16, kUint32, kInt32, kUint64, kInt64, kFloat32,
                        kFloat64 };
/// Bytes per value.
std::size_t scalarSize(ScalarType type);
/// "uint8", "int16", "float", … (for messages).
const char* scalarName(ScalarType type);

// ---- text -----------------------------------------------------------------------------------------
std::string toLower(std::string s);
std::string trim(const std::string& s);
/// Case-insensitive suffix test.
bool endsWith(const std::string& s, const std::string& suffix);
/// Whitespace-separated tokens.
std::vector<std::string> splitWords(const std::string& s);
/// Whole-string number parses; false on any trailing character or an empty string.
bool parseDouble(const std::string& s, double& value);
bool parseLong(const std::string& s, long& value);
/// A header value quoted for an error message: at most 60 characters, non-printable ones as '?'.
std::string quoted(const std::string& s);
/// Shortest round-trip-safe decimal text of v (up to 15 significant digits, so 0.5 prints "0.5").
std::string formatNumber(double v);

// ---- files ----------------------------------------------------------------------------------------
/// Whole file as bytes. @throws via fail() when it cannot be opened or read, is a folder or a
/// device, or its name holds a NUL byte.
std::string readFileBytes(const std::string& path);
/// Whether bytes start with the gzip magic 1f 8b.
bool isGzip(const std::string& bytes);
/// Writes bytes, replacing the file. @throws via fail().
void writeFileBytes(const std::string& path, const std::string& bytes);
/// `name` relative to the directory of `header_path`, unless `name` is absolute.
/// @throws via fail() naming the header when `name` is empty or holds a control character.
std::string siblingPath(const std::string& header_path, const std::string& name);
/// File name without directory and without `ext` (which `path` is known to end with).
std::string stemOf(const std::string& path, const std::string& ext);

// ---- compression ----------------------------------------------------------------------------------
/// Inflates a gzip or zlib stream (detected from its header; concatenated gzip members are
/// followed). Stops after `max_bytes` output bytes; the buffer grows with the output, so memory
/// follows what the stream decodes to, not `max_bytes`. A stream that ends early returns what was
/// decoded (the caller reports the byte counts); corrupt data throws via fail() naming `path`.
std::string inflateBytes(const char* data, std::size_t n, std::size_t max_bytes,
                         const std::string& path);
enum class Wrapper { kGzip, kZlib };
/// Deflates at zlib's default level with a gzip or zlib wrapper.
std::string deflateBytes(const std::string& data, Wrapper wrapper);

// ---- voxel values ---------------------------------------------------------------------------------
/// Converts size.prod() binary values to labels (value · slope + inter when slope ≠ 1 or
/// inter ≠ 0). @throws via fail() naming the value and voxel (i, j, k) when a value is not an
/// integer in [0, 65535].
void decodeLabels(const char* bytes, ScalarType type, bool big_endian, const Eigen::Vector3i& size,
                  const std::string& path, std::vector<std::uint16_t>& labels, double slope = 1.0,
                  double inter = 0.0);
/// Parses size.prod() whitespace- (or comma-) separated numbers into labels, with the checks of
/// decodeLabels and a count check.
void decodeAsciiLabels(const char* begin, const char* end, const Eigen::Vector3i& size,
                       const std::string& path, std::vector<std::uint16_t>& labels);
/// The count check of ASCII voxel data, before anything is allocated: `count` values need at least
/// a digit and a separator each (the last none). @throws via fail() when the text is too short.
void requireAsciiRoom(const char* begin, const char* end, long count, const std::string& path);
/// Calls take(index, value) for each of the `count` whitespace- (or comma-) separated numbers of
/// [begin, end). @throws via fail() for text that is not a number, and for more or fewer values.
void forEachAsciiValue(const char* begin, const char* end, long count, const std::string& path,
                       const std::function<void(long index, double value)>& take);
/// uint8 when every label is ≤ 255, else uint16.
ScalarType narrowestLabelType(const LabelImage& image);
/// Labels as little-endian uint8 or uint16 bytes.
std::string encodeLabels(const LabelImage& image, ScalarType type);
bool hostIsBigEndian();
/// The value of type T at p, its bytes reversed when `swap`.
template <typename T>
T loadValue(const char* p, bool swap) {
  T v;
  if (!swap) {
    std::memcpy(&v, p, sizeof(T));
  } else {
    char b[sizeof(T)];
    for (std::size_t i = 0; i < sizeof(T); ++i) b[i] = p[sizeof(T) - 1 - i];
    std::memcpy(&v, b, sizeof(T));
  }
  return v;
}

// ---- geometry -------------------------------------------------------------------------------------
/// Splits axis vectors (columns, any length unit) into lengths and an orthonormal direction
/// (re-orthonormalised to machine precision). Returns false when the axes are not orthogonal
/// within 1e-4 (cosine); throws via fail() naming `what` when an axis is zero or not finite.
bool splitAxes(const Eigen::Matrix3d& axes, const std::string& path, const std::string& what,
               Eigen::Vector3d& lengths, Eigen::Matrix3d& direction);
/// Largest |cosine| between two axis columns, and which pair.
double largestAxisCosine(const Eigen::Matrix3d& axes, int& a, int& b);
/// MetaImage/ITK "AnatomicalOrientation" letters of an LPS direction ("RAI" for identity), or
/// "???" when an axis is oblique.
std::string anatomicalOrientation(const Eigen::Matrix3d& direction);

// ---- formats --------------------------------------------------------------------------------------
/// Where the NRRD and MetaImage readers deliver what they read, so that one parser per format serves
/// label images (readLabelImage) and intensity images (readScalarImageFile).
struct VoxelSink {
  /// Called once the header is read, before anything it claims is allocated, with the shape it
  /// gives and, when that is not a 3-D image of one value per voxel, the header field that says so
  /// (e.g. "header field 'dimension' is 2"; empty otherwise). Throws to refuse the file; a shape
  /// that is not a volume is refused after it in any case.
  std::function<void(const ImageFileShape& shape, const std::string& not_a_volume)> shape;
  /// size.prod() binary values of `type` in the byte order `big_endian`, starting at `bytes`.
  std::function<void(const char* bytes, ScalarType type, bool big_endian, const Eigen::Vector3i& size)> binary;
  /// size.prod() values of the header's `type` as text in [begin, end) (not yet counted).
  std::function<void(const char* begin, const char* end, ScalarType type, const Eigen::Vector3i& size)> ascii;
};
/// Read a file: its geometry into `grid` (labels left empty), its values into `sink`.
void readNrrd(const std::string& path, LabelImage& grid, const VoxelSink& sink);
void readMetaImage(const std::string& path, LabelImage& grid, const VoxelSink& sink);
/// The sink of readLabelImage: a 3-D image of one value per voxel, whose values decode into
/// `image.labels` (decodeLabels, decodeAsciiLabels).
VoxelSink labelSink(const std::string& path, LabelImage& image);
/// The label images of the two formats.
LabelImage readNrrd(const std::string& path);
void writeNrrd(const std::string& path, const LabelImage& image);
LabelImage readMetaImage(const std::string& path);
void writeMetaImage(const std::string& path, const LabelImage& image);
LabelImage readNifti(const std::string& path);
void writeNifti(const std::string& path, const LabelImage& image);

}  // namespace breast_sim::core::image_io
