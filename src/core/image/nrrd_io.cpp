// NRRD reader and writer (http://teem.sourceforge.net/nrrd/format.html, NRRD0001–NRRD0005).

#include <algorithm>
#include <climits>
#include <iterator>
#include <cmath>
#include <map>
#include <sstream>
#include <string>

#include "breast_sim/core/image/image_io_detail.h"

namespace breast_sim::core::image_io {
namespace {

/// A header line for an error message: short and printable.
bool nrrdType(const std::string& name, ScalarType& type) {
  static const std::map<std::string, ScalarType> kTypes = {
      {"uchar", ScalarType::kUint8},          {"unsigned char", ScalarType::kUint8},
      {"uint8", ScalarType::kUint8},          {"uint8_t", ScalarType::kUint8},
      {"signed char", ScalarType::kInt8},     {"int8", ScalarType::kInt8},
      {"int8_t", ScalarType::kInt8},          {"short", ScalarType::kInt16},
      {"short int", ScalarType::kInt16},      {"signed short", ScalarType::kInt16},
      {"signed short int", ScalarType::kInt16}, {"int16", ScalarType::kInt16},
      {"int16_t", ScalarType::kInt16},        {"ushort", ScalarType::kUint16},
      {"unsigned short", ScalarType::kUint16}, {"unsigned short int", ScalarType::kUint16},
      {"uint16", ScalarType::kUint16},        {"uint16_t", ScalarType::kUint16},
      {"int", ScalarType::kInt32},            {"signed int", ScalarType::kInt32},
      {"int32", ScalarType::kInt32},          {"int32_t", ScalarType::kInt32},
      {"uint", ScalarType::kUint32},          {"unsigned int", ScalarType::kUint32},
      {"uint32", ScalarType::kUint32},        {"uint32_t", ScalarType::kUint32},
      {"longlong", ScalarType::kInt64},       {"long long", ScalarType::kInt64},
      {"long long int", ScalarType::kInt64},  {"signed long long", ScalarType::kInt64},
      {"signed long long int", ScalarType::kInt64}, {"int64", ScalarType::kInt64},
      {"int64_t", ScalarType::kInt64},        {"ulonglong", ScalarType::kUint64},
      {"unsigned long long", ScalarType::kUint64}, {"unsigned long long int", ScalarType::kUint64},
      {"uint64", ScalarType::kUint64},        {"uint64_t", ScalarType::kUint64},
      {"float", ScalarType::kFloat32},        {"double", ScalarType::kFloat64},
  };
  const auto it = kTypes.find(name);
  if (it == kTypes.end()) return false;
  type = it->second;
  return true;
}

/// "(a,b,c) none (d,e,f)" → vectors; "none" gives an empty vector.
std::vector<std::vector<double>> parseVectors(const std::string& path, const std::string& field,
                                              const std::string& value) {
  std::vector<std::vector<double>> vectors;
  std::size_t p = 0;
  const auto malformed = [&]() {
    fail(path, "header field '" + field + "' is malformed: expected vectors like (1,0,0), got " +
                   quoted(value));
  };
  while (p < value.size()) {
    if (std::isspace(static_cast<unsigned char>(value[p]))) {
      ++p;
      continue;
    }
    if (value.compare(p, 4, "none") == 0) {
      vectors.emplace_back();
      p += 4;
      continue;
    }
    if (value[p] != '(') malformed();
    const std::size_t close = value.find(')', p);
    if (close == std::string::npos) malformed();
    std::vector<double> v;
    std::istringstream parts(value.substr(p + 1, close - p - 1));
    std::string part;
    while (std::getline(parts, part, ',')) {
      double d = 0.0;
      if (!parseDouble(part, d)) malformed();
      v.push_back(d);
    }
    vectors.push_back(v);
    p = close + 1;
  }
  return vectors;
}

/// Metres per unit of a NRRD "space units" entry.
bool unitScale(std::string unit, double& scale) {
  if (unit.size() >= 2 && unit.front() == '"' && unit.back() == '"') unit = unit.substr(1, unit.size() - 2);
  unit = toLower(unit);
  if (unit == "mm" || unit == "millimeter" || unit == "millimeters" || unit.empty()) {
    scale = 1e-3;
  } else if (unit == "m" || unit == "meter" || unit == "meters") {
    scale = 1.0;
  } else if (unit == "cm") {
    scale = 1e-2;
  } else if (unit == "um" || unit == "µm" || unit == "micron" || unit == "microns") {
    scale = 1e-6;
  } else {
    return false;
  }
  return true;
}

/// Teem's NRRD_DIM_MAX.
constexpr long kMaxNrrdDimension = 16;

/// Whether a NRRD axis kind is a range kind (the axis holds the values of one voxel) rather than a
/// domain kind (domain, space, time) or unknown (???, none).
bool isRangeKind(const std::string& kind) {
  static const char* const kRange[] = {
      "list", "point", "vector", "covariant-vector", "normal", "stub", "scalar", "complex", "2-vector",
      "3-color", "rgb-color", "hsv-color", "xyz-color", "4-color", "rgba-color", "3-vector",
      "3-gradient", "3-normal", "4-vector", "quaternion", "2d-symmetric-matrix",
      "2d-masked-symmetric-matrix", "2d-matrix", "2d-masked-matrix", "3d-symmetric-matrix",
      "3d-masked-symmetric-matrix", "3d-matrix", "3d-masked-matrix"};
  const std::string k = toLower(kind);
  return std::any_of(std::begin(kRange), std::end(kRange), [&](const char* r) { return k == r; });
}

std::string sizeText(const Eigen::Vector3i& size, ScalarType type) {
  return std::to_string(size.x()) + "×" + std::to_string(size.y()) + "×" + std::to_string(size.z()) +
         " " + scalarName(type) + " values";
}

}  // namespace

void readNrrd(const std::string& path, LabelImage& image, const VoxelSink& sink) {
  const std::string file = readFileBytes(path);
  if (file.compare(0, 7, "NRRD000") != 0) {
    fail(path, "not a NRRD file: it does not start with the magic 'NRRD000x'");
  }

  // ---- header lines ----
  std::map<std::string, std::string> fields;
  std::size_t pos = file.find('\n');
  pos = pos == std::string::npos ? file.size() : pos + 1;
  bool blank_line = false;
  std::size_t data_begin = file.size();
  int line_no = 1;
  while (pos < file.size()) {
    const std::size_t eol = file.find('\n', pos);
    const std::size_t line_end = eol == std::string::npos ? file.size() : eol;
    std::string line = file.substr(pos, line_end - pos);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    pos = eol == std::string::npos ? file.size() : eol + 1;
    ++line_no;
    if (line.empty()) {
      blank_line = true;
      data_begin = pos;
      break;
    }
    if (line[0] == '#') continue;
    if (line.find(":=") != std::string::npos) continue;  // key/value pairs carry no geometry
    std::size_t colon = line.find(": ");
    if (colon == std::string::npos && line.back() == ':') colon = line.size() - 1;
    if (colon == std::string::npos) {
      fail(path, "header line " + std::to_string(line_no) + " " + quoted(line) +
                     " is not 'field: value' (is the blank line before the data missing?)");
    }
    std::string key = toLower(trim(line.substr(0, colon)));
    if (key == "datafile") key = "data file";
    if (key == "byteskip") key = "byte skip";
    if (key == "lineskip") key = "line skip";
    if (!fields.emplace(key, trim(line.substr(colon + 1))).second) {
      fail(path, "header field '" + key + "' appears twice");
    }
  }
  const auto get = [&](const std::string& key) -> const std::string* {
    const auto it = fields.find(key);
    return it == fields.end() ? nullptr : &it->second;
  };
  const auto require = [&](const std::string& key) -> const std::string& {
    const std::string* v = get(key);
    if (v == nullptr) fail(path, "header field '" + key + "' is missing");
    return *v;
  };

  // ---- dimension, type, sizes, kinds: the shape, before anything else ----
  long dimension = 0;
  if (!parseLong(require("dimension"), dimension)) {
    fail(path, "header field 'dimension' is " + quoted(require("dimension")) + ", not an integer");
  }
  if (dimension < 1 || dimension > kMaxNrrdDimension) {
    fail(path, "header field 'dimension' is " + std::to_string(dimension) + "; NRRD allows 1 to " +
                   std::to_string(kMaxNrrdDimension));
  }
  ScalarType type = ScalarType::kUint8;
  if (!nrrdType(toLower(require("type")), type)) {
    fail(path, "header field 'type' is " + quoted(require("type")) +
                   "; supported: int8, uint8, int16, uint16, int32, uint32, int64, uint64, float, "
                   "double");
  }
  const std::string dim_text = " (dimension: " + std::to_string(dimension) + ")";
  const std::vector<std::string> size_words = splitWords(require("sizes"));
  if (static_cast<long>(size_words.size()) != dimension) {
    fail(path, "header field 'sizes' has " + std::to_string(size_words.size()) + " values, expected " +
                   std::to_string(dimension) + dim_text);
  }
  std::vector<long> sizes(size_words.size());
  for (std::size_t a = 0; a < sizes.size(); ++a) {
    if (!parseLong(size_words[a], sizes[a]) || sizes[a] < 1 || sizes[a] > INT_MAX) {
      fail(path, "header field 'sizes' value " + quoted(size_words[a]) +
                     " is not an integer from 1 to " + std::to_string(INT_MAX));
    }
  }
  // Axes of a range kind hold the values of one voxel (an RGB colour, a vector); the others are the
  // image's axes.
  ImageFileShape shape;
  std::string not_a_volume;
  const std::string* kinds = get("kinds");
  const std::vector<std::string> kind_words = kinds != nullptr ? splitWords(*kinds) : std::vector<std::string>{};
  if (kinds != nullptr && static_cast<long>(kind_words.size()) != dimension) {
    fail(path, "header field 'kinds' has " + std::to_string(kind_words.size()) + " values, expected " +
                   std::to_string(dimension) + dim_text);
  }
  for (std::size_t a = 0; a < sizes.size(); ++a) {
    if (kinds != nullptr && isRangeKind(kind_words[a])) {
      shape.components = std::min(shape.components * sizes[a], 1L << 40);  // only ever reported
      not_a_volume = "header field 'kinds' is " + quoted(*kinds) + ": axis " + std::to_string(a) +
                     " holds the values of a voxel (" + kind_words[a] + ")";
    } else {
      shape.sizes.push_back(sizes[a]);
    }
  }
  if (not_a_volume.empty() && dimension != 3) {
    not_a_volume = "header field 'dimension' is " + std::to_string(dimension);
  }
  if (sink.shape) sink.shape(shape, not_a_volume);
  if (!not_a_volume.empty()) {
    fail(path, not_a_volume + "; only 3-D images of one value per voxel are supported");
  }
  for (int a = 0; a < 3; ++a) image.size(a) = static_cast<int>(sizes[a]);
  // Each size may fit while their product wraps (4194304·2097152·2097152 = 2^64 → 0 voxels).
  const std::int64_t num_voxels = requireVoxelCount(image.size, path, "sizes", require("sizes"));
  const std::string encoding = toLower(require("encoding"));
  const bool ascii = encoding == "ascii" || encoding == "text" || encoding == "txt";
  const bool gzip = encoding == "gzip" || encoding == "gz";
  if (!ascii && !gzip && encoding != "raw") {
    fail(path, "header field 'encoding' is " + quoted(encoding) +
                   ", which is not supported; supported: raw, gzip, ascii (convert with unu or "
                   "3D Slicer)");
  }
  bool big_endian = false;
  if (const std::string* endian = get("endian")) {
    const std::string e = toLower(*endian);
    if (e != "little" && e != "big") {
      fail(path, "header field 'endian' is " + quoted(*endian) + "; expected little or big");
    }
    big_endian = e == "big";
  } else if (scalarSize(type) > 1 && !ascii) {
    fail(path, std::string("header field 'endian' is missing (required for type ") +
                   scalarName(type) + " with " + encoding + " encoding)");
  }

  // ---- geometry ----
  // Which patient space the vectors are in; RAS and LAS are converted to LPS by flipping rows.
  // Teem requires a space with 'space directions'; without one the vectors are taken as they are.
  Eigen::Vector3d flip(1, 1, 1);
  if (const std::string* space = get("space")) {
    const std::string s = toLower(*space);
    if (s == "right-anterior-superior" || s == "ras") {
      flip << -1, -1, 1;
    } else if (s == "left-anterior-superior" || s == "las") {
      flip << 1, -1, 1;
    } else if (s == "left-posterior-superior" || s == "lps" || s == "3d-right-handed" ||
               s == "3d-left-handed" || s == "scanner-xyz") {
      // LPS already, or not anatomical: taken as it is.
    } else {
      fail(path, "header field 'space' is " + quoted(*space) +
                     "; supported: left-posterior-superior, right-anterior-superior, "
                     "left-anterior-superior, scanner-xyz, 3D-right-handed, 3D-left-handed");
    }
    if (get("space dimension") != nullptr) {
      fail(path, "header has both 'space' and 'space dimension'; give only one");
    }
  } else if (const std::string* sd = get("space dimension")) {
    long d = 0;
    if (!parseLong(*sd, d) || d != 3) {
      fail(path, "header field 'space dimension' is " + quoted(*sd) + "; expected 3");
    }
  }

  Eigen::Matrix3d axes = Eigen::Matrix3d::Identity();
  std::string axes_field = "default spacing 1 mm";
  if (const std::string* sd = get("space directions")) {
    axes_field = "space directions";
    const auto vectors = parseVectors(path, "space directions", *sd);
    if (vectors.size() != 3) {
      fail(path, "header field 'space directions' has " + std::to_string(vectors.size()) +
                     " vectors, expected 3 (dimension: 3)");
    }
    for (int a = 0; a < 3; ++a) {
      if (vectors[a].empty()) {
        fail(path, "header field 'space directions' gives 'none' for axis " + std::to_string(a) +
                       "; a 3-D image needs three spatial axes");
      }
      if (vectors[a].size() != 3) {
        fail(path, "header field 'space directions' vector " + std::to_string(a) + " has " +
                       std::to_string(vectors[a].size()) + " components, expected 3 (space dimension: 3)");
      }
      axes.col(a) << vectors[a][0], vectors[a][1], vectors[a][2];
    }
    if (get("spacings") != nullptr) {
      fail(path, "header has both 'space directions' and 'spacings'; give only one");
    }
  } else if (const std::string* sp = get("spacings")) {
    axes_field = "spacings";
    const std::vector<std::string> words = splitWords(*sp);
    if (words.size() != 3) {
      fail(path, "header field 'spacings' has " + std::to_string(words.size()) +
                     " values, expected 3 (dimension: 3)");
    }
    for (int a = 0; a < 3; ++a) {
      double d = 0.0;
      if (!parseDouble(words[a], d) || !std::isfinite(d) || d == 0.0) {
        fail(path, "header field 'spacings' value " + quoted(words[a]) +
                       " is not a finite, non-zero number");
      }
      axes(a, a) = d;
    }
  }
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  if (const std::string* so = get("space origin")) {
    const auto vectors = parseVectors(path, "space origin", *so);
    if (vectors.size() != 1 || vectors[0].size() != 3) {
      fail(path, "header field 'space origin' is " + quoted(*so) +
                     ", expected one vector of 3 components like (0,0,0) (space dimension: 3)");
    }
    origin << vectors[0][0], vectors[0][1], vectors[0][2];
    if (!origin.allFinite()) fail(path, "header field 'space origin' is not finite");
  }
  double scale = 1e-3;
  if (const std::string* su = get("space units")) {
    const std::vector<std::string> units = splitWords(*su);
    if (units.size() != 3) {
      fail(path, "header field 'space units' has " + std::to_string(units.size()) +
                     " values, expected 3 (space dimension: 3)");
    }
    for (int a = 0; a < 3; ++a) {
      double s = 0.0;
      if (!unitScale(units[a], s)) {
        fail(path, "header field 'space units' value " + quoted(units[a]) +
                       " is not a length unit (mm, cm, m, um)");
      }
      if (a > 0 && s != scale) fail(path, "header field 'space units' mixes units; use one unit");
      scale = s;
    }
  }
  axes = flip.asDiagonal() * axes;
  origin = flip.asDiagonal() * origin;
  Eigen::Vector3d lengths;
  if (!splitAxes(axes, path, "header field '" + axes_field + "'", lengths, image.direction)) {
    int a = 0;
    int b = 0;
    const double c = largestAxisCosine(axes, a, b);
    fail(path, "header field 'space directions' has axes " + std::to_string(a) + " and " +
                   std::to_string(b) + " that are not orthogonal (cosine " + formatNumber(c) +
                   "); sheared grids are not supported");
  }
  image.spacing_m = lengths * scale;
  image.origin_m = origin * scale;

  // ---- voxel data ----
  std::string detached;
  const std::string* source = &file;
  std::size_t begin = data_begin;
  if (const std::string* df = get("data file")) {
    if (*df == "LIST" || df->find('%') != std::string::npos) {
      fail(path, "header field 'data file' is " + quoted(*df) +
                     "; multiple data files (LIST or a %d pattern) are not supported");
    }
    const std::string data_path = siblingPath(path, *df);
    try {
      detached = readFileBytes(data_path);
    } catch (const std::runtime_error& e) {
      fail(path, std::string("data file: ") + e.what());
    }
    source = &detached;
    begin = 0;
  } else if (!blank_line) {
    fail(path, "the header has no 'data file' field and no blank line after it, so there is no "
               "voxel data");
  }
  long line_skip = 0;
  if (const std::string* ls = get("line skip")) {
    if (!parseLong(*ls, line_skip) || line_skip < 0) {
      fail(path, "header field 'line skip' is " + quoted(*ls) + "; expected an integer ≥ 0");
    }
  }
  for (long l = 0; l < line_skip; ++l) {
    const std::size_t eol = source->find('\n', begin);
    if (eol == std::string::npos) {
      fail(path, "header field 'line skip' (" + std::to_string(line_skip) +
                     ") passes the end of the data");
    }
    begin = eol + 1;
  }
  long byte_skip = 0;
  if (const std::string* bs = get("byte skip")) {
    if (!parseLong(*bs, byte_skip) || byte_skip < -1) {
      fail(path, "header field 'byte skip' is " + quoted(*bs) + "; expected -1 or an integer ≥ 0");
    }
  }
  const std::size_t expected = static_cast<std::size_t>(num_voxels) * scalarSize(type);
  if (ascii) {
    if (byte_skip != 0) fail(path, "header field 'byte skip' is not valid with ascii encoding");
    sink.ascii(source->data() + begin, source->data() + source->size(), type, image.size);
  } else if (gzip) {
    if (byte_skip < 0) fail(path, "header field 'byte skip' is -1, which only raw encoding allows");
    const std::size_t skip = static_cast<std::size_t>(byte_skip);
    const std::string raw = inflateBytes(source->data() + begin, source->size() - begin,
                                         expected + skip, path);
    if (raw.size() < expected + skip) {
      fail(path, "voxel data is truncated: expected " + std::to_string(expected + skip) +
                     " bytes after decompression (" + sizeText(image.size, type) +
                     (skip > 0 ? " after a byte skip of " + std::to_string(skip) : std::string()) +
                     "), found " + std::to_string(raw.size()));
    }
    sink.binary(raw.data() + skip, type, big_endian, image.size);
  } else {
    const std::size_t available = source->size() - begin;
    if (byte_skip == -1) {
      if (available < expected) {
        fail(path, "voxel data is truncated: expected " + std::to_string(expected) + " bytes (" +
                       sizeText(image.size, type) + "), found " + std::to_string(available));
      }
      begin = source->size() - expected;
    } else {
      const std::size_t skip = static_cast<std::size_t>(byte_skip);
      if (available < skip + expected) {
        fail(path, "voxel data is truncated: expected " + std::to_string(expected) + " bytes (" +
                       sizeText(image.size, type) + "), found " +
                       std::to_string(available > skip ? available - skip : 0));
      }
      begin += skip;
    }
    sink.binary(source->data() + begin, type, big_endian, image.size);
  }
}

LabelImage readNrrd(const std::string& path) {
  LabelImage image;
  readNrrd(path, image, labelSink(path, image));
  return image;
}

void writeNrrd(const std::string& path, const LabelImage& image) {
  const ScalarType type = narrowestLabelType(image);
  const bool detached = endsWith(path, ".nhdr");
  const Eigen::Matrix3d axes_mm = image.direction * (image.spacing_m * 1e3).asDiagonal();
  const Eigen::Vector3d origin_mm = image.origin_m * 1e3;
  const auto vec = [](const Eigen::Vector3d& v) {
    return "(" + formatNumber(v.x()) + "," + formatNumber(v.y()) + "," + formatNumber(v.z()) + ")";
  };
  std::ostringstream h;
  h << "NRRD0004\n"
    << "# breast_sim label image; lengths in mm, LPS patient space\n"
    << "type: " << (type == ScalarType::kUint8 ? "uint8" : "uint16") << "\n"
    << "dimension: 3\n"
    << "space: left-posterior-superior\n"
    << "sizes: " << image.size.x() << " " << image.size.y() << " " << image.size.z() << "\n"
    << "space directions: " << vec(axes_mm.col(0)) << " " << vec(axes_mm.col(1)) << " "
    << vec(axes_mm.col(2)) << "\n"
    << "kinds: domain domain domain\n"
    << "endian: little\n"
    << "encoding: gzip\n"
    << "space origin: " << vec(origin_mm) << "\n";
  const std::string data = deflateBytes(encodeLabels(image, type), Wrapper::kGzip);
  if (detached) {
    const std::string data_name = stemOf(path, ".nhdr") + ".raw.gz";
    h << "data file: " << data_name << "\n";
    writeFileBytes(siblingPath(path, data_name), data);
    writeFileBytes(path, h.str());
  } else {
    h << "\n";
    writeFileBytes(path, h.str() + data);
  }
}

}  // namespace breast_sim::core::image_io
