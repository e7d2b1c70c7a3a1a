#include "breast_sim/core/image/label_image.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <climits>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <type_traits>

#include <Eigen/LU>
#include <Eigen/SVD>
#include <zlib.h>

#include "breast_sim/core/image/image_io_detail.h"

namespace breast_sim::core {

// ---------------------------------------------------------------------------------------------------
// LabelImage

LabelImage::LabelImage(const Eigen::Vector3i& size_in, const Eigen::Vector3d& spacing_in,
                       const Eigen::Vector3d& origin_in, std::uint16_t fill)
    : size(size_in), spacing_m(spacing_in), origin_m(origin_in) {
  if ((size.array() < 0).any()) {
    std::ostringstream msg;
    msg << "LabelImage: size (" << size.transpose() << ") has a negative entry";
    throw std::invalid_argument(msg.str());
  }
  std::int64_t count = 0;
  if (!image_io::checkedVoxelCount(size, count)) {
    throw std::invalid_argument("LabelImage: size " + image_io::voxelCountText(size) +
                                ", more than the " + std::to_string(image_io::kMaxVoxels) +
                                " (2^31) a label image may hold");
  }
  labels.assign(static_cast<std::size_t>(count), fill);
}

Eigen::Vector3d LabelImage::indexToPhysical(const Eigen::Vector3d& ijk) const {
  return origin_m + direction * spacing_m.cwiseProduct(ijk);
}

Eigen::Vector3d LabelImage::physicalToIndex(const Eigen::Vector3d& p_m) const {
  // The general inverse rather than a transpose, so that a hand-built, not yet validated
  // direction still gives the inverse of indexToPhysical.
  const Eigen::Matrix3d to_physical = direction * spacing_m.asDiagonal();
  return to_physical.inverse() * (p_m - origin_m);
}

std::uint16_t LabelImage::labelAt(const Eigen::Vector3d& p_m, std::uint16_t outside) const {
  const Eigen::Vector3d q = physicalToIndex(p_m);
  if (!q.allFinite()) return outside;
  const Eigen::Vector3d r = (q.array() + 0.5).floor().matrix();
  // Compare as doubles first: a far-away point must not overflow the int conversion.
  if ((r.array() < 0.0).any() || r.x() >= size.x() || r.y() >= size.y() || r.z() >= size.z()) {
    return outside;
  }
  return at(static_cast<int>(r.x()), static_cast<int>(r.y()), static_cast<int>(r.z()));
}

void LabelImage::validate() const {
  std::ostringstream msg;
  msg << "LabelImage: ";
  if ((size.array() < 1).any()) {
    msg << "size (" << size.transpose() << ") has an entry below 1";
    throw std::invalid_argument(msg.str());
  }
  // Counted without overflow: a wrapped product could otherwise match a short label vector and
  // let at() read past it.
  std::int64_t count = 0;
  if (!image_io::checkedVoxelCount(size, count)) {
    msg << "size " << image_io::voxelCountText(size) << ", more than the "
        << image_io::kMaxVoxels << " (2^31) a label image may hold";
    throw std::invalid_argument(msg.str());
  }
  if (labels.size() != static_cast<std::uint64_t>(count)) {
    msg << labels.size() << " labels for " << image_io::voxelCountText(size)
        << "; expected one label per voxel";
    throw std::invalid_argument(msg.str());
  }
  if (!spacing_m.allFinite() || (spacing_m.array() <= 0.0).any()) {
    msg << "spacing (" << spacing_m.transpose() << ") m must be finite and positive";
    throw std::invalid_argument(msg.str());
  }
  if (!origin_m.allFinite()) {
    msg << "origin (" << origin_m.transpose() << ") m is not finite";
    throw std::invalid_argument(msg.str());
  }
  const double error = (direction.transpose() * direction - Eigen::Matrix3d::Identity())
                           .cwiseAbs()
                           .maxCoeff();
  if (!direction.allFinite() || !(error <= 1e-6)) {
    msg << "direction columns are not orthonormal (|DᵀD − I| = " << error << "); direction =\n"
        << direction;
    throw std::invalid_argument(msg.str());
  }
}

// ---------------------------------------------------------------------------------------------------
// Dispatch

LabelImage readLabelImage(const std::string& path) {
  using namespace image_io;
  LabelImage image;
  if (endsWith(path, ".nrrd") || endsWith(path, ".nhdr")) {
    image = readNrrd(path);
  } else if (endsWith(path, ".mha") || endsWith(path, ".mhd")) {
    image = readMetaImage(path);
  } else if (endsWith(path, ".nii") || endsWith(path, ".nii.gz")) {
    image = readNifti(path);
  } else {
    fail(path, "unknown extension; expected .nrrd, .nhdr, .mha, .mhd, .nii or .nii.gz");
  }
  try {
    image.validate();
  } catch (const std::invalid_argument& e) {
    // The readers check each field, so this is a reader bug or a corner they missed; still name
    // the file.
    fail(path, e.what());
  }
  return image;
}

void writeLabelImage(const std::string& path, const LabelImage& image) {
  using namespace image_io;
  image.validate();
  if (endsWith(path, ".nrrd") || endsWith(path, ".nhdr")) {
    writeNrrd(path, image);
  } else if (endsWith(path, ".mha") || endsWith(path, ".mhd")) {
    writeMetaImage(path, image);
  } else if (endsWith(path, ".nii") || endsWith(path, ".nii.gz")) {
    writeNifti(path, image);
  } else {
    fail(path, "unknown extension; expected .nrrd, .nhdr, .mha, .mhd, .nii or .nii.gz");
  }
}

// ---------------------------------------------------------------------------------------------------
// Shared by the readers and writers

namespace image_io {

void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

bool checkedVoxelCount(const Eigen::Vector3i& size, std::int64_t& count) {
  if ((size.array() < 0).any()) return false;
  // Each factor is below 2^31, so each partial product stays below 2^62 as long as the previous
  // one was within the limit.
  std::int64_t n = static_cast<std::int64_t>(size.x()) * size.y();
  if (n > kMaxVoxels) return false;
  n *= size.z();
  if (n > kMaxVoxels) return false;
  count = n;
  return true;
}

std::string voxelCountText(const Eigen::Vector3i& size) {
  std::ostringstream s;
  s << size.x() << "×" << size.y() << "×" << size.z();
  const std::int64_t ab = static_cast<std::int64_t>(size.x()) * size.y();  // |ab| < 2^62
  const std::int64_t c = size.z();
  if (ab >= 0 && c >= 0 && (c == 0 || ab <= std::numeric_limits<std::int64_t>::max() / c)) {
    s << " = " << ab * c;
  } else {
    s.precision(3);
    s << " ≈ " << static_cast<double>(ab) * static_cast<double>(c);
  }
  s << " voxels";
  return s.str();
}

std::int64_t requireVoxelCount(const Eigen::Vector3i& size, const std::string& path,
                               const std::string& field, const std::string& value) {
  std::int64_t count = 0;
  if (!checkedVoxelCount(size, count)) {
    fail(path, "header field '" + field + "' is " + quoted(value) + ": " + voxelCountText(size) +
                   ", more than the " + std::to_string(kMaxVoxels) +
                   " (2^31) a label image may hold; crop or downsample the image");
  }
  return count;
}

std::size_t scalarSize(ScalarType type) {
  switch (type) {
    case ScalarType::kUint8:
    case ScalarType::kInt8: return 1;
    case ScalarType::kUint16:
    case ScalarType::kInt16: return 2;
    case ScalarType::kUint32:
    case ScalarType::kInt32:
    case ScalarType::kFloat32: return 4;
    case ScalarType::kUint64:
    case ScalarType::kInt64:
    case ScalarType::kFloat64: return 8;
  }
  return 0;
}

const char* scalarName(ScalarType type) {
  switch (type) {
    case ScalarType::kUint8: return "uint8";
    case ScalarType::kInt8: return "int8";
    case ScalarType::kUint16: return "uint16";
    case ScalarType::kInt16: return "int16";
    case ScalarType::kUint32: return "uint32";
    case ScalarType::kInt32: return "int32";
    case ScalarType::kUint64: return "uint64";
    case ScalarType::kInt64: return "int64";
    case ScalarType::kFloat32: return "float";
    case ScalarType::kFloat64: return "double";
  }
  return "?";
}

std::string toLower(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

std::string trim(const std::string& s) {
  const char* ws = " \t\r\n\f\v";
  const std::size_t b = s.find_first_not_of(ws);
  if (b == std::string::npos) return {};
  const std::size_t e = s.find_last_not_of(ws);
  return s.substr(b, e - b + 1);
}

bool endsWith(const std::string& s, const std::string& suffix) {
  if (s.size() < suffix.size()) return false;
  return toLower(s.substr(s.size() - suffix.size())) == toLower(suffix);
}

std::vector<std::string> splitWords(const std::string& s) {
  std::vector<std::string> words;
  std::istringstream in(s);
  std::string w;
  while (in >> w) words.push_back(w);
  return words;
}

bool parseDouble(const std::string& s, double& value) {
  const std::string t = trim(s);
  if (t.empty()) return false;
  char* end = nullptr;
  errno = 0;
  value = std::strtod(t.c_str(), &end);
  return end == t.c_str() + t.size() && errno != ERANGE;
}

bool parseLong(const std::string& s, long& value) {
  const std::string t = trim(s);
  if (t.empty()) return false;
  char* end = nullptr;
  errno = 0;
  value = std::strtol(t.c_str(), &end, 10);
  return end == t.c_str() + t.size() && errno != ERANGE;
}

std::string quoted(const std::string& s) {
  std::string out = s.substr(0, 60);
  for (char& c : out) {
    if (static_cast<unsigned char>(c) < 32 || static_cast<unsigned char>(c) > 126) c = '?';
  }
  return "'" + out + (s.size() > 60 ? "…'" : "'");
}

std::string formatNumber(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.15g", v);
  if (std::strtod(buf, nullptr) != v) std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

std::string readFileBytes(const std::string& path) {
  if (path.find('\0') != std::string::npos) fail(path, "the file name holds a NUL byte");
  // A folder or a device opens like a file but has no size to read (a folder's "size" can be 2^63).
  std::error_code ec;
  const auto status = std::filesystem::status(path, ec);
  if (!ec && std::filesystem::is_directory(status)) fail(path, "is a folder, not a file");
  if (!ec && std::filesystem::exists(status) && !std::filesystem::is_regular_file(status)) {
    fail(path, "is not a regular file (a device, a pipe or a socket)");
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot open for reading (") + std::strerror(errno) + ")");
  in.seekg(0, std::ios::end);
  const std::streamoff n = in.tellg();
  if (n < 0) fail(path, "cannot determine the file size");
  in.seekg(0, std::ios::beg);
  std::string bytes(static_cast<std::size_t>(n), '\0');
  if (n > 0 && !in.read(bytes.data(), n)) fail(path, "read error");
  return bytes;
}

bool isGzip(const std::string& bytes) {
  return bytes.size() >= 2 && static_cast<unsigned char>(bytes[0]) == 0x1f &&
         static_cast<unsigned char>(bytes[1]) == 0x8b;
}

void writeFileBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) fail(path, std::string("cannot open for writing (") + std::strerror(errno) + ")");
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  out.close();
  if (!out) fail(path, "write error (disk full?)");
}

std::string siblingPath(const std::string& header_path, const std::string& name) {
  // A name with a NUL byte would be cut there by the operating system and name another file (the
  // header's own folder, for a name that starts with one).
  const bool control = std::any_of(name.begin(), name.end(), [](char c) {
    return static_cast<unsigned char>(c) < 32 && c != '\t';
  });
  if (name.empty() || control) {
    fail(header_path, "the data file name " + quoted(name) + " is empty or holds control characters");
  }
  const std::filesystem::path p(name);
  if (p.is_absolute()) return name;
  return (std::filesystem::path(header_path).parent_path() / p).string();
}

std::string stemOf(const std::string& path, const std::string& ext) {
  const std::string file = std::filesystem::path(path).filename().string();
  return file.substr(0, file.size() - std::min(ext.size(), file.size()));
}

std::string inflateBytes(const char* data, std::size_t n, std::size_t max_bytes,
                         const std::string& path) {
  z_stream zs{};
  // 15 + 32: accept a zlib or a gzip header (MetaImage writes zlib, NRRD gzip).
  if (inflateInit2(&zs, 15 + 32) != Z_OK) fail(path, "cannot initialise zlib");
  // The buffer grows with what the stream really produces (doubling), never to the size a header
  // claims: a short stream that claims gigabytes costs what it decodes to (deflate expands at most
  // 1032:1).
  std::string out(std::min(max_bytes, std::max<std::size_t>(std::size_t{1} << 20, 4 * n)), '\0');
  std::size_t consumed = 0;
  std::size_t produced = 0;
  constexpr std::size_t kChunk = 1u << 30;  // zlib counts in 32-bit unsigned
  while (produced < max_bytes) {
    if (produced == out.size()) out.resize(std::min(max_bytes, 2 * out.size()));
    const std::size_t in_chunk = std::min(n - consumed, kChunk);
    const std::size_t out_chunk = std::min(out.size() - produced, kChunk);
    zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data + consumed));
    zs.avail_in = static_cast<uInt>(in_chunk);
    zs.next_out = reinterpret_cast<Bytef*>(out.data() + produced);
    zs.avail_out = static_cast<uInt>(out_chunk);
    const int ret = inflate(&zs, Z_NO_FLUSH);
    consumed += in_chunk - zs.avail_in;
    produced += out_chunk - zs.avail_out;
    if (ret == Z_STREAM_END) {
      // Concatenated gzip members (pigz, `cat a.gz b.gz`) decode as one stream, as gunzip does.
      if (consumed + 2 <= n && static_cast<unsigned char>(data[consumed]) == 0x1f &&
          static_cast<unsigned char>(data[consumed + 1]) == 0x8b) {
        inflateReset(&zs);
        continue;
      }
      break;
    }
    if (ret == Z_OK) continue;
    if (ret == Z_BUF_ERROR && consumed < n) continue;  // output was full; it grows above
    if (ret == Z_BUF_ERROR) break;                     // input ended early: caller counts bytes
    const std::string msg = zs.msg != nullptr ? zs.msg : zError(ret);
    inflateEnd(&zs);
    fail(path, "compressed data is corrupt (zlib: " + msg + ")");
  }
  inflateEnd(&zs);
  out.resize(produced);
  return out;
}

std::string deflateBytes(const std::string& data, Wrapper wrapper) {
  z_stream zs{};
  const int window = wrapper == Wrapper::kGzip ? 15 + 16 : 15;
  if (deflateInit2(&zs, Z_DEFAULT_COMPRESSION, Z_DEFLATED, window, 8, Z_DEFAULT_STRATEGY) != Z_OK) {
    throw std::runtime_error("deflateBytes: cannot initialise zlib");
  }
  std::string out(deflateBound(&zs, static_cast<uLong>(data.size())) + 64, '\0');
  std::size_t consumed = 0;
  std::size_t produced = 0;
  constexpr std::size_t kChunk = 1u << 30;
  int ret = Z_OK;
  while (ret != Z_STREAM_END) {
    if (produced == out.size()) out.resize(2 * out.size());
    const std::size_t in_chunk = std::min(data.size() - consumed, kChunk);
    const std::size_t out_chunk = std::min(out.size() - produced, kChunk);
    zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data.data() + consumed));
    zs.avail_in = static_cast<uInt>(in_chunk);
    zs.next_out = reinterpret_cast<Bytef*>(out.data() + produced);
    zs.avail_out = static_cast<uInt>(out_chunk);
    const bool last = consumed + in_chunk == data.size();
    ret = deflate(&zs, last ? Z_FINISH : Z_NO_FLUSH);
    consumed += in_chunk - zs.avail_in;
    produced += out_chunk - zs.avail_out;
    if (ret == Z_STREAM_ERROR) {
      deflateEnd(&zs);
      throw std::runtime_error("deflateBytes: zlib stream error");
    }
  }
  deflateEnd(&zs);
  out.resize(produced);
  return out;
}

bool hostIsBigEndian() {
  const std::uint16_t one = 1;
  unsigned char first = 0;
  std::memcpy(&first, &one, 1);
  return first == 0;
}

namespace {

std::string formatValue(double v) {
  std::ostringstream s;
  s.precision(12);
  s << v;
  return s.str();
}

[[noreturn]] void badLabel(const std::string& path, const Eigen::Vector3i& size, long n,
                           const std::string& value) {
  const long sx = size.x();
  const long sy = size.y();
  std::ostringstream msg;
  msg << "voxel (" << n % sx << ", " << (n / sx) % sy << ", " << n / (sx * sy) << ") holds "
      << value << "; labels must be integers in [0, 65535]";
  fail(path, msg.str());
}

template <typename T>
void decodeTyped(const char* bytes, bool swap, const Eigen::Vector3i& size, const std::string& path,
                 std::vector<std::uint16_t>& labels, double slope, double inter) {
  const long n = static_cast<long>(size.x()) * size.y() * size.z();
  labels.resize(static_cast<std::size_t>(n));
  const bool scaled = !(slope == 1.0 && inter == 0.0);
  if constexpr (std::is_same_v<T, std::uint8_t>) {
    if (!scaled) {
      const auto* src = reinterpret_cast<const std::uint8_t*>(bytes);
      std::copy(src, src + n, labels.begin());
      return;
    }
  }
  if constexpr (std::is_same_v<T, std::uint16_t>) {
    if (!scaled && !swap) {
      std::memcpy(labels.data(), bytes, static_cast<std::size_t>(n) * 2);
      return;
    }
  }
  for (long v = 0; v < n; ++v) {
    const T x = loadValue<T>(bytes + static_cast<std::size_t>(v) * sizeof(T), swap);
    if (scaled || std::is_floating_point_v<T>) {
      const double d = scaled ? static_cast<double>(x) * slope + inter : static_cast<double>(x);
      if (!(d >= 0.0 && d <= 65535.0 && d == std::floor(d))) badLabel(path, size, v, formatValue(d));
      labels[v] = static_cast<std::uint16_t>(d);
    } else if constexpr (std::is_same_v<T, std::uint64_t>) {
      if (x > 65535u) badLabel(path, size, v, std::to_string(x));
      labels[v] = static_cast<std::uint16_t>(x);
    } else if constexpr (std::is_integral_v<T>) {
      const std::int64_t w = x;
      if (w < 0 || w > 65535) badLabel(path, size, v, std::to_string(w));
      labels[v] = static_cast<std::uint16_t>(w);
    }
  }
}

}  // namespace

void decodeLabels(const char* bytes, ScalarType type, bool big_endian, const Eigen::Vector3i& size,
                  const std::string& path, std::vector<std::uint16_t>& labels, double slope,
                  double inter) {
  const bool swap = scalarSize(type) > 1 && big_endian != hostIsBigEndian();
  switch (type) {
    case ScalarType::kUint8:
      return decodeTyped<std::uint8_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kInt8:
      return decodeTyped<std::int8_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kUint16:
      return decodeTyped<std::uint16_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kInt16:
      return decodeTyped<std::int16_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kUint32:
      return decodeTyped<std::uint32_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kInt32:
      return decodeTyped<std::int32_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kUint64:
      return decodeTyped<std::uint64_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kInt64:
      return decodeTyped<std::int64_t>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kFloat32:
      return decodeTyped<float>(bytes, swap, size, path, labels, slope, inter);
    case ScalarType::kFloat64:
      return decodeTyped<double>(bytes, swap, size, path, labels, slope, inter);
  }
}

void requireAsciiRoom(const char* begin, const char* end, long count, const std::string& path) {
  // Each value takes a digit and a separator (the last none): checked before the values are
  // allocated, so a header cannot claim 2^31 values over a few bytes of text.
  const std::size_t most = (static_cast<std::size_t>(end - begin) + 1) / 2;
  if (static_cast<std::size_t>(count) > most) {
    fail(path, "ASCII voxel data is truncated: expected " + std::to_string(count) + " values, but its " +
                   std::to_string(end - begin) + " bytes hold at most " + std::to_string(most));
  }
}

void forEachAsciiValue(const char* begin, const char* end, long count, const std::string& path,
                       const std::function<void(long index, double value)>& take) {
  const std::string text(begin, end);  // NUL-terminated for strtod
  const char* p = text.c_str();
  const char* stop = p + text.size();
  long found = 0;
  for (;;) {
    while (p < stop && (std::isspace(static_cast<unsigned char>(*p)) || *p == ',')) ++p;
    if (p >= stop) break;
    char* after = nullptr;
    const double d = std::strtod(p, &after);
    if (after == p) {
      fail(path, "ASCII voxel data: value " + std::to_string(found + 1) + " ('" +
                     std::string(p, std::min<std::size_t>(20, stop - p)) + "') is not a number");
    }
    if (found == count) {
      fail(path, "ASCII voxel data has more than the expected " + std::to_string(count) + " values");
    }
    take(found++, d);
    p = after;
  }
  if (found < count) {
    fail(path, "ASCII voxel data is truncated: expected " + std::to_string(count) + " values, found " +
                   std::to_string(found));
  }
}

void decodeAsciiLabels(const char* begin, const char* end, const Eigen::Vector3i& size,
                       const std::string& path, std::vector<std::uint16_t>& labels) {
  const long n = static_cast<long>(size.x()) * size.y() * size.z();
  requireAsciiRoom(begin, end, n, path);
  labels.resize(static_cast<std::size_t>(n));
  forEachAsciiValue(begin, end, n, path, [&](long index, double d) {
    if (!(d >= 0.0 && d <= 65535.0 && d == std::floor(d))) badLabel(path, size, index, formatValue(d));
    labels[index] = static_cast<std::uint16_t>(d);
  });
}

VoxelSink labelSink(const std::string& path, LabelImage& image) {
  VoxelSink sink;
  sink.shape = [path](const ImageFileShape&, const std::string& not_a_volume) {
    if (!not_a_volume.empty()) {
      fail(path, not_a_volume + "; only 3-D label images of one value per voxel are supported");
    }
  };
  sink.binary = [path, &image](const char* bytes, ScalarType type, bool big_endian, const Eigen::Vector3i& size) {
    decodeLabels(bytes, type, big_endian, size, path, image.labels);
  };
  sink.ascii = [path, &image](const char* begin, const char* end, ScalarType, const Eigen::Vector3i& size) {
    decodeAsciiLabels(begin, end, size, path, image.labels);
  };
  return sink;
}

ScalarType narrowestLabelType(const LabelImage& image) {
  const bool small = std::all_of(image.labels.begin(), image.labels.end(),
                                 [](std::uint16_t l) { return l <= 255; });
  return small ? ScalarType::kUint8 : ScalarType::kUint16;
}

std::string encodeLabels(const LabelImage& image, ScalarType type) {
  const std::size_t n = image.labels.size();
  if (type == ScalarType::kUint8) {
    std::string out(n, '\0');
    for (std::size_t v = 0; v < n; ++v) out[v] = static_cast<char>(image.labels[v]);
    return out;
  }
  std::string out(2 * n, '\0');
  for (std::size_t v = 0; v < n; ++v) {
    out[2 * v] = static_cast<char>(image.labels[v] & 0xff);
    out[2 * v + 1] = static_cast<char>(image.labels[v] >> 8);
  }
  return out;
}

double largestAxisCosine(const Eigen::Matrix3d& axes, int& a, int& b) {
  double worst = 0.0;
  a = 0;
  b = 1;
  for (int p = 0; p < 3; ++p) {
    for (int q = p + 1; q < 3; ++q) {
      const double c =
          std::abs(axes.col(p).dot(axes.col(q))) / (axes.col(p).norm() * axes.col(q).norm());
      if (c > worst) {
        worst = c;
        a = p;
        b = q;
      }
    }
  }
  return worst;
}

bool splitAxes(const Eigen::Matrix3d& axes, const std::string& path, const std::string& what,
               Eigen::Vector3d& lengths, Eigen::Matrix3d& direction) {
  for (int j = 0; j < 3; ++j) {
    lengths(j) = axes.col(j).norm();
    if (!std::isfinite(lengths(j)) || lengths(j) <= 0.0) {
      std::ostringstream msg;
      msg << what << ": axis " << j << " is (" << axes.col(j).transpose()
          << "); every axis needs a finite, non-zero vector";
      fail(path, msg.str());
    }
  }
  int a = 0;
  int b = 0;
  // Files store directions in float or in decimal text; 1e-4 admits their rounding and rejects
  // any real shear (1e-4 is 0.006°).
  if (largestAxisCosine(axes, a, b) > 1e-4) return false;
  const Eigen::Matrix3d unit = axes * lengths.cwiseInverse().asDiagonal();
  // Nearest orthonormal matrix (polar factor), so that validate()'s 1e-6 holds exactly.
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(unit, Eigen::ComputeFullU | Eigen::ComputeFullV);
  direction = svd.matrixU() * svd.matrixV().transpose();
  return true;
}

std::string anatomicalOrientation(const Eigen::Matrix3d& direction) {
  // ITK/MetaIO letters name where each axis comes *from* in LPS: +x runs from Right to Left, so
  // an axis along +x is "R"; the identity is "RAI".
  const char plus[3] = {'R', 'A', 'I'};
  const char minus[3] = {'L', 'P', 'S'};
  std::string letters;
  bool used[3] = {false, false, false};
  for (int j = 0; j < 3; ++j) {
    Eigen::Index m = 0;
    direction.col(j).cwiseAbs().maxCoeff(&m);
    if (used[m]) return "???";
    used[m] = true;
    letters += direction(m, j) > 0 ? plus[m] : minus[m];
  }
  return letters;
}

}  // namespace image_io
}  // namespace breast_sim::core
