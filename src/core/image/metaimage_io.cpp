// MetaImage reader and writer (ITK's MetaIO: https://itk.org/Wiki/ITK/MetaIO/Documentation).

#include <climits>
#include <cmath>
#include <map>
#include <sstream>
#include <string>

#include "breast_sim/core/image/image_io_detail.h"

namespace breast_sim::core::image_io {
namespace {

bool metaType(const std::string& name, ScalarType& type) {
  // MetaIO's sizes: MET_LONG and MET_ULONG are 4 bytes on every platform (metaTypes.h).
  static const std::map<std::string, ScalarType> kTypes = {
      {"MET_UCHAR", ScalarType::kUint8},    {"MET_CHAR", ScalarType::kInt8},
      {"MET_USHORT", ScalarType::kUint16},  {"MET_SHORT", ScalarType::kInt16},
      {"MET_UINT", ScalarType::kUint32},    {"MET_INT", ScalarType::kInt32},
      {"MET_ULONG", ScalarType::kUint32},   {"MET_LONG", ScalarType::kInt32},
      {"MET_ULONG_LONG", ScalarType::kUint64}, {"MET_LONG_LONG", ScalarType::kInt64},
      {"MET_FLOAT", ScalarType::kFloat32},  {"MET_DOUBLE", ScalarType::kFloat64},
  };
  const auto it = kTypes.find(name);
  if (it == kTypes.end()) return false;
  type = it->second;
  return true;
}

/// A bound on NDims, so a header's per-axis lists stay short (NRRD allows 16 axes, as here).
constexpr long kMaxMetaDimension = 16;

const char* metaTypeName(ScalarType type) {
  return type == ScalarType::kUint8 ? "MET_UCHAR" : "MET_USHORT";
}

}  // namespace

void readMetaImage(const std::string& path, LabelImage& image, const VoxelSink& sink) {
  const std::string file = readFileBytes(path);

  // ---- header: "Key = Value" lines up to and including ElementDataFile ----
  std::map<std::string, std::string> fields;  // keys lower-cased
  std::size_t pos = 0;
  std::size_t data_begin = 0;
  bool found_data_file = false;
  int line_no = 0;
  while (pos < file.size()) {
    const std::size_t eol = file.find('\n', pos);
    const std::size_t line_end = eol == std::string::npos ? file.size() : eol;
    std::string line = file.substr(pos, line_end - pos);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    pos = eol == std::string::npos ? file.size() : eol + 1;
    ++line_no;
    if (trim(line).empty()) continue;
    const std::size_t eq = line.find('=');
    if (eq == std::string::npos) {
      fail(path, "header line " + std::to_string(line_no) + " " + quoted(line) +
                     " is not 'Key = Value'" +
                     (line_no == 1 ? " (is this a MetaImage file?)" : ""));
    }
    const std::string key = toLower(trim(line.substr(0, eq)));
    if (!fields.emplace(key, trim(line.substr(eq + 1))).second) {
      fail(path, "header field '" + trim(line.substr(0, eq)) + "' appears twice");
    }
    if (key == "elementdatafile") {
      found_data_file = true;
      data_begin = pos;
      break;  // MetaIO: ElementDataFile is the last field; LOCAL data starts on the next byte
    }
  }
  if (!found_data_file) {
    fail(path, "header has no 'ElementDataFile' field (it must be the last header line)");
  }
  const auto get = [&](const std::string& key) -> const std::string* {
    const auto it = fields.find(toLower(key));
    return it == fields.end() ? nullptr : &it->second;
  };
  const auto require = [&](const std::string& key) -> const std::string& {
    const std::string* v = get(key);
    if (v == nullptr) fail(path, "header field '" + key + "' is missing");
    return *v;
  };
  const auto boolean = [&](const std::string& key, bool fallback) {
    const std::string* v = get(key);
    if (v == nullptr) return fallback;
    const std::string b = toLower(*v);
    if (b == "true" || b == "1") return true;
    if (b == "false" || b == "0") return false;
    fail(path, "header field '" + key + "' is " + quoted(*v) + "; expected True or False");
  };
  if (const std::string* ot = get("ObjectType"); ot != nullptr && toLower(*ot) != "image") {
    fail(path, "header field 'ObjectType' is " + quoted(*ot) + "; expected Image");
  }
  long ndims = 0;
  if (!parseLong(require("NDims"), ndims) || ndims < 1 || ndims > kMaxMetaDimension) {
    fail(path, "header field 'NDims' is " + quoted(require("NDims")) + "; expected an integer from 1 to " +
                   std::to_string(kMaxMetaDimension));
  }
  // n numbers of a field; `alias` fields are tried in order after `key`.
  const auto numbers = [&](std::vector<std::string> keys, std::size_t n,
                           std::vector<double>& out) -> bool {
    for (const std::string& key : keys) {
      const std::string* v = get(key);
      if (v == nullptr) continue;
      const std::vector<std::string> words = splitWords(*v);
      if (words.size() != n) {
        fail(path, "header field '" + key + "' has " + std::to_string(words.size()) +
                       " values, expected " + std::to_string(n) + " (NDims: " + std::to_string(ndims) + ")");
      }
      out.resize(n);
      for (std::size_t i = 0; i < n; ++i) {
        if (!parseDouble(words[i], out[i]) || !std::isfinite(out[i])) {
          fail(path, "header field '" + key + "' value " + quoted(words[i]) +
                         " is not a finite number");
        }
      }
      return true;
    }
    return false;
  };

  ImageFileShape shape;
  std::string not_a_volume;
  if (const std::string* ch = get("ElementNumberOfChannels")) {
    if (!parseLong(*ch, shape.components) || shape.components < 1 || shape.components > INT_MAX) {
      fail(path, "header field 'ElementNumberOfChannels' is " + quoted(*ch) +
                     "; expected an integer from 1 to " + std::to_string(INT_MAX));
    }
    if (shape.components != 1) not_a_volume = "header field 'ElementNumberOfChannels' is " + std::to_string(shape.components);
  }
  ScalarType type = ScalarType::kUint8;
  if (!metaType(trim(require("ElementType")), type)) {
    fail(path, "header field 'ElementType' is " + quoted(require("ElementType")) +
                   "; supported: MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_UINT, MET_INT, "
                   "MET_ULONG, MET_LONG, MET_ULONG_LONG, MET_LONG_LONG, MET_FLOAT, MET_DOUBLE");
  }

  std::vector<double> v;
  if (!numbers({"DimSize"}, static_cast<std::size_t>(ndims), v)) fail(path, "header field 'DimSize' is missing");
  for (const double d : v) {
    if (!(d >= 1 && d <= INT_MAX) || d != std::floor(d)) {
      fail(path, "header field 'DimSize' value " + formatNumber(d) + " is not an integer from 1 to " +
                     std::to_string(INT_MAX));
    }
    shape.sizes.push_back(static_cast<long>(d));
  }
  if (not_a_volume.empty() && ndims != 3) not_a_volume = "header field 'NDims' is " + std::to_string(ndims);
  if (sink.shape) sink.shape(shape, not_a_volume);
  if (!not_a_volume.empty()) {
    fail(path, not_a_volume + "; only 3-D images of one value per voxel are supported");
  }
  for (int a = 0; a < 3; ++a) image.size(a) = static_cast<int>(shape.sizes[a]);
  // Each size may fit while their product wraps (4194304·2097152·2097152 = 2^64 → 0 voxels).
  const std::int64_t num_voxels = requireVoxelCount(image.size, path, "DimSize", require("DimSize"));
  Eigen::Vector3d spacing_mm(1, 1, 1);
  if (numbers({"ElementSpacing", "ElementSize"}, 3, v)) spacing_mm << v[0], v[1], v[2];
  Eigen::Vector3d origin_mm(0, 0, 0);
  if (numbers({"Offset", "Position", "Origin"}, 3, v)) origin_mm << v[0], v[1], v[2];
  Eigen::Matrix3d direction = Eigen::Matrix3d::Identity();
  if (numbers({"TransformMatrix", "Rotation", "Orientation"}, 9, v)) {
    // As ITK's MetaImageIO: the 9 numbers list axis 0's direction, then axis 1's, then axis 2's,
    // so file entry [3·a + r] is row r of direction column a.
    for (int a = 0; a < 3; ++a) {
      for (int r = 0; r < 3; ++r) direction(r, a) = v[3 * a + r];
    }
  }
  // Negative spacing (seen from some writers) means the axis points the other way.
  const Eigen::Matrix3d axes = direction * spacing_mm.asDiagonal();
  Eigen::Vector3d lengths;
  if (!splitAxes(axes, path, "header fields 'TransformMatrix' and 'ElementSpacing'", lengths,
                 image.direction)) {
    int a = 0;
    int b = 0;
    const double c = largestAxisCosine(axes, a, b);
    fail(path, "header field 'TransformMatrix' has axes " + std::to_string(a) + " and " +
                   std::to_string(b) + " that are not orthogonal (cosine " + formatNumber(c) +
                   "); sheared grids are not supported");
  }
  image.spacing_m = lengths * 1e-3;
  image.origin_m = origin_mm * 1e-3;

  // ---- voxel data ----
  const bool binary = boolean("BinaryData", true);
  bool big_endian = boolean("BinaryDataByteOrderMSB", false);
  if (get("BinaryDataByteOrderMSB") == nullptr) big_endian = boolean("ElementByteOrderMSB", false);
  const bool compressed = boolean("CompressedData", false);
  long header_size = 0;
  if (const std::string* hs = get("HeaderSize")) {
    if (!parseLong(*hs, header_size) || header_size < -1) {
      fail(path, "header field 'HeaderSize' is " + quoted(*hs) + "; expected -1 or an integer ≥ 0");
    }
  }
  const std::string data_file = require("ElementDataFile");
  std::string detached;
  const std::string* source = &file;
  std::size_t begin = data_begin;
  if (data_file != "LOCAL" && toLower(data_file) != "local") {
    if (toLower(data_file).rfind("list", 0) == 0 || data_file.find('%') != std::string::npos) {
      fail(path, "header field 'ElementDataFile' is " + quoted(data_file) +
                     "; multiple data files (LIST or a %d pattern) are not supported");
    }
    const std::string data_path = siblingPath(path, data_file);
    try {
      detached = readFileBytes(data_path);
    } catch (const std::runtime_error& e) {
      fail(path, std::string("data file: ") + e.what());
    }
    source = &detached;
    begin = 0;
    if (header_size > 0) {
      if (static_cast<std::size_t>(header_size) > detached.size()) {
        fail(path, "header field 'HeaderSize' (" + std::to_string(header_size) +
                       ") is larger than the data file (" + std::to_string(detached.size()) +
                       " bytes)");
      }
      begin = static_cast<std::size_t>(header_size);
    }
  }
  const std::size_t expected = static_cast<std::size_t>(num_voxels) * scalarSize(type);
  const std::string what = std::to_string(image.size.x()) + "×" + std::to_string(image.size.y()) +
                           "×" + std::to_string(image.size.z()) + " " + scalarName(type) + " values";
  if (!binary) {
    sink.ascii(source->data() + begin, source->data() + source->size(), type, image.size);
  } else if (compressed) {
    std::size_t n = source->size() - begin;
    if (const std::string* cs = get("CompressedDataSize")) {
      long c = 0;
      if (!parseLong(*cs, c) || c < 0) {
        fail(path, "header field 'CompressedDataSize' is " + quoted(*cs) + "; expected an integer ≥ 0");
      }
      if (static_cast<std::size_t>(c) > n) {
        fail(path, "compressed voxel data is truncated: expected " + std::to_string(c) +
                       " bytes (CompressedDataSize), found " + std::to_string(n));
      }
      if (c > 0) n = static_cast<std::size_t>(c);  // 0 is what some writers put for "unknown"
    }
    const std::string raw = inflateBytes(source->data() + begin, n, expected, path);
    if (raw.size() < expected) {
      fail(path, "voxel data is truncated: expected " + std::to_string(expected) +
                     " bytes after decompression (" + what + "), found " +
                     std::to_string(raw.size()));
    }
    sink.binary(raw.data(), type, big_endian, image.size);
  } else {
    const std::size_t available = source->size() - begin;
    if (available < expected) {
      fail(path, "voxel data is truncated: expected " + std::to_string(expected) + " bytes (" +
                     what + "), found " + std::to_string(available));
    }
    // HeaderSize = -1: the data are the last bytes of the data file.
    if (header_size == -1) begin = source->size() - expected;
    sink.binary(source->data() + begin, type, big_endian, image.size);
  }
}

LabelImage readMetaImage(const std::string& path) {
  LabelImage image;
  readMetaImage(path, image, labelSink(path, image));
  return image;
}

void writeMetaImage(const std::string& path, const LabelImage& image) {
  const ScalarType type = narrowestLabelType(image);
  const bool detached = endsWith(path, ".mhd");
  const std::string data = deflateBytes(encodeLabels(image, type), Wrapper::kZlib);
  const auto triple = [](const Eigen::Vector3d& v) {
    return formatNumber(v.x()) + " " + formatNumber(v.y()) + " " + formatNumber(v.z());
  };
  std::ostringstream h;
  h << "ObjectType = Image\n"
    << "NDims = 3\n"
    << "BinaryData = True\n"
    << "BinaryDataByteOrderMSB = False\n"
    << "CompressedData = True\n"
    << "CompressedDataSize = " << data.size() << "\n"
    // Axis 0's direction first, as ITK writes it (see readMetaImage).
    << "TransformMatrix = " << triple(image.direction.col(0)) << " "
    << triple(image.direction.col(1)) << " " << triple(image.direction.col(2)) << "\n"
    << "Offset = " << triple(image.origin_m * 1e3) << "\n"
    << "CenterOfRotation = 0 0 0\n"
    << "AnatomicalOrientation = " << anatomicalOrientation(image.direction) << "\n"
    << "ElementSpacing = " << triple(image.spacing_m * 1e3) << "\n"
    << "DimSize = " << image.size.x() << " " << image.size.y() << " " << image.size.z() << "\n"
    << "ElementType = " << metaTypeName(type) << "\n";
  if (detached) {
    const std::string data_name = stemOf(path, ".mhd") + ".zraw";
    h << "ElementDataFile = " << data_name << "\n";
    writeFileBytes(siblingPath(path, data_name), data);
    writeFileBytes(path, h.str());
  } else {
    h << "ElementDataFile = LOCAL\n";
    writeFileBytes(path, h.str() + data);
  }
}

}  // namespace breast_sim::core::image_io
