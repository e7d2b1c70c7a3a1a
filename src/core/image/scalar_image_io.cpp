// scalar_image_io.h: the NRRD and MetaImage parsers of the label images with a sink that keeps every
// value as float.

#include "breast_sim/core/image/scalar_image_io.h"

#include <cstdint>
#include <stdexcept>

#include "breast_sim/core/image/image_io_detail.h"

namespace breast_sim::core {

namespace {

using image_io::ScalarType;

template <typename T>
void toFloat(const char* bytes, bool swap, long n, float* out) {
  for (long v = 0; v < n; ++v)
    out[v] = static_cast<float>(image_io::loadValue<T>(bytes + static_cast<std::size_t>(v) * sizeof(T), swap));
}

void decodeFloats(const char* bytes, ScalarType type, bool big_endian, long n, float* out) {
  const bool swap = image_io::scalarSize(type) > 1 && big_endian != image_io::hostIsBigEndian();
  switch (type) {
    case ScalarType::kUint8: return toFloat<std::uint8_t>(bytes, swap, n, out);
    case ScalarType::kInt8: return toFloat<std::int8_t>(bytes, swap, n, out);
    case ScalarType::kUint16: return toFloat<std::uint16_t>(bytes, swap, n, out);
    case ScalarType::kInt16: return toFloat<std::int16_t>(bytes, swap, n, out);
    case ScalarType::kUint32: return toFloat<std::uint32_t>(bytes, swap, n, out);
    case ScalarType::kInt32: return toFloat<std::int32_t>(bytes, swap, n, out);
    case ScalarType::kUint64: return toFloat<std::uint64_t>(bytes, swap, n, out);
    case ScalarType::kInt64: return toFloat<std::int64_t>(bytes, swap, n, out);
    case ScalarType::kFloat32: return toFloat<float>(bytes, swap, n, out);
    case ScalarType::kFloat64: return toFloat<double>(bytes, swap, n, out);
  }
}

}  // namespace

ScalarImageFile readScalarImageFile(const std::string& path, const std::function<void(const ImageFileShape&)>& check) {
  using namespace image_io;
  ScalarImageFile out;
  LabelImage grid;  // the geometry; its labels stay empty
  std::vector<float>& values = out.image.values;
  VoxelSink sink;
  sink.shape = [&](const ImageFileShape& shape, const std::string&) {
    if (check) check(shape);
  };
  sink.binary = [&](const char* bytes, ScalarType type, bool big_endian, const Eigen::Vector3i& size) {
    const long n = static_cast<long>(size.x()) * size.y() * size.z();
    values.resize(static_cast<std::size_t>(n));
    decodeFloats(bytes, type, big_endian, n, values.data());
    out.value_type = scalarName(type);
  };
  sink.ascii = [&](const char* begin, const char* end, ScalarType type, const Eigen::Vector3i& size) {
    const long n = static_cast<long>(size.x()) * size.y() * size.z();
    requireAsciiRoom(begin, end, n, path);
    values.resize(static_cast<std::size_t>(n));
    forEachAsciiValue(begin, end, n, path, [&](long index, double value) { values[index] = static_cast<float>(value); });
    out.value_type = scalarName(type);
  };
  if (endsWith(path, ".nrrd") || endsWith(path, ".nhdr")) {
    readNrrd(path, grid, sink);
    out.format = "NRRD";
  } else if (endsWith(path, ".mha") || endsWith(path, ".mhd")) {
    readMetaImage(path, grid, sink);
    out.format = "MetaImage";
  } else {
    fail(path, "unknown extension; expected .nrrd, .nhdr, .mha or .mhd");
  }
  out.image.geometry = ImageGeometry::of(grid);
  try {
    out.image.geometry.validate();
  } catch (const std::invalid_argument& e) {
    fail(path, e.what());  // the readers check each field; still name the file
  }
  return out;
}

}  // namespace breast_sim::core
