// Legacy VTK (.vtk) unstructured-grid reader: file versions 2.0 to 5.1, ASCII and BINARY (big-endian).
// Format reference: "VTK File Formats" (VTK User's Guide), and vtkDataReader / vtkDataWriter for what
// the sections hold in binary (vtkIdType as 4-byte int, `long` as 8 bytes, length-prefixed strings).
// Why not vtkUnstructuredGridReader: vtk_read_detail.h.

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>
#include <vector>

#include "vtk_read_detail.h"

namespace breast_sim::core::vtk_read {
namespace {

using mesh_io_detail::checkCountFits;
using mesh_io_detail::FileCursor;

std::string lower(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

/// A data type name of the format: a binary scalar, packed bits, or strings (skipped).
struct DataType {
  enum class Kind { kScalar, kBit, kString } kind = Kind::kScalar;
  Scalar scalar = Scalar::kFloat32;
};

bool dataType(std::string_view name, DataType& t) {
  const std::string n = lower(name);
  struct Entry {
    const char* name;
    Scalar scalar;
  };
  // vtkIdType is written as a 4-byte int; long and unsigned_long as 8 bytes (LP64, as VTK on Linux).
  static const Entry kTypes[] = {
      {"unsigned_char", Scalar::kUInt8},   {"char", Scalar::kInt8},           {"signed_char", Scalar::kInt8},
      {"short", Scalar::kInt16},           {"unsigned_short", Scalar::kUInt16}, {"int", Scalar::kInt32},
      {"unsigned_int", Scalar::kUInt32},   {"long", Scalar::kInt64},          {"unsigned_long", Scalar::kUInt64},
      {"long_long", Scalar::kInt64},       {"unsigned_long_long", Scalar::kUInt64},
      {"vtkidtype", Scalar::kInt32},       {"vtktypeint8", Scalar::kInt8},    {"vtktypeuint8", Scalar::kUInt8},
      {"vtktypeint16", Scalar::kInt16},    {"vtktypeuint16", Scalar::kUInt16}, {"vtktypeint32", Scalar::kInt32},
      {"vtktypeuint32", Scalar::kUInt32},  {"vtktypeint64", Scalar::kInt64},  {"vtktypeuint64", Scalar::kUInt64},
      {"float", Scalar::kFloat32},         {"double", Scalar::kFloat64},      {"vtktypefloat32", Scalar::kFloat32},
      {"vtktypefloat64", Scalar::kFloat64},
  };
  for (const Entry& e : kTypes) {
    if (n == e.name) {
      t.kind = DataType::Kind::kScalar;
      t.scalar = e.scalar;
      return true;
    }
  }
  if (n == "bit") {
    t.kind = DataType::Kind::kBit;
    return true;
  }
  if (n == "string" || n == "utf8_string") {
    t.kind = DataType::Kind::kString;
    return true;
  }
  return false;
}

class LegacyReader {
 public:
  explicit LegacyReader(FileCursor& f) : f_(f) {}

  Grid read() {
    readHeader();
    while (true) {
      f_.skipWhitespace();
      if (f_.atEnd()) break;
      const std::size_t pos = f_.pos();
      const std::string key = lower(f_.token());
      if (key == "points") {
        readPoints(pos);
      } else if (key == "cells") {
        readCells(pos);
      } else if (key == "cell_types") {
        readCellTypes(pos);
      } else if (key == "point_data" || key == "cell_data") {
        const bool points = key == "point_data";
        const long long n = count(points ? "the POINT_DATA count" : "the CELL_DATA count");
        const long long expected = points ? grid_.numPoints() : cellCount();
        if ((points && !have_points_) || (!points && !have_cells_)) {
          f_.failAtLine(pos, std::string(points ? "POINT_DATA before POINTS" : "CELL_DATA before CELLS"));
        }
        if (n != expected) {
          f_.failAtLine(pos, key == "point_data" ? "POINT_DATA " + std::to_string(n) + " for " + std::to_string(expected) + " points"
                                                 : "CELL_DATA " + std::to_string(n) + " for " + std::to_string(expected) + " cells");
        }
        target_ = points ? &grid_.point_arrays : &grid_.cell_arrays;
        tuples_ = n;
      } else if (key == "field") {
        readField(pos);
      } else if (key == "metadata") {
        skipMetadata();
      } else if (target_ != nullptr && readAttribute(key, pos)) {
        // an attribute of POINT_DATA / CELL_DATA
      } else {
        f_.failAtLine(pos, "unknown or misplaced keyword '" + std::string(key.substr(0, 40)) + "'");
      }
    }
    if (have_cells_ && !have_types_) f_.failAtLine(cells_pos_, "CELLS without CELL_TYPES");
    return std::move(grid_);
  }

 private:
  void readHeader() {
    const std::string first = lower(f_.line());
    if (first.rfind("# vtk datafile version", 0) != 0) {
      f_.failAtLine(0, "not a legacy VTK file: it does not start with '# vtk DataFile Version'");
    }
    const std::string version = first.substr(std::strlen("# vtk datafile version"));
    major_ = std::atoi(version.c_str());
    f_.line();  // title
    const std::size_t format_pos = f_.pos();
    std::string format = lower(f_.line());
    format.erase(std::remove_if(format.begin(), format.end(), [](unsigned char c) { return std::isspace(c); }), format.end());
    if (format != "ascii" && format != "binary") {
      f_.failAtLine(format_pos, "expected ASCII or BINARY on line 3, got '" + format.substr(0, 40) + "'");
    }
    binary_ = format == "binary";
    // FIELD data of the dataset may come before DATASET.
    while (true) {
      f_.skipWhitespace();
      const std::size_t pos = f_.pos();
      const std::string key = lower(f_.token());
      if (key == "field") {
        readField(pos);
        continue;
      }
      const std::string type = lower(f_.token());
      if (key != "dataset" || type != "unstructured_grid") {
        f_.failAtLine(pos, "not a legacy VTK unstructured grid (expected 'DATASET UNSTRUCTURED_GRID', got '" +
                               std::string(key.substr(0, 30)) + " " + std::string(type.substr(0, 30)) + "')");
      }
      return;
    }
  }

  long long count(const char* what) {
    f_.skipWhitespace();
    const std::size_t pos = f_.pos();
    const long long n = f_.integerToken(what);
    if (n < 0 || n > kMaxCount) {
      f_.failAtLine(pos, std::string(what) + " is " + std::to_string(n) + "; expected 0 to " + std::to_string(kMaxCount));
    }
    return n;
  }

  DataType type(const char* what) {
    f_.skipWhitespace();
    const std::size_t pos = f_.pos();
    const std::string_view name = f_.token();
    DataType t;
    if (!dataType(name, t)) {
      f_.failAtLine(pos, std::string("unknown data type '") + std::string(name.substr(0, 40)) + "' of " + what);
    }
    return t;
  }

  long long cellCount() const { return static_cast<long long>(grid_.offsets.size()) - 1; }

  /// `n` values of type `t` (after the keyword line in binary); `count_pos` is where the count
  /// stands, for the message when the file cannot hold them.
  std::vector<double> values(const DataType& t, long long n, std::size_t count_pos, const char* what) {
    std::vector<double> out;
    if (t.kind == DataType::Kind::kString) {
      skipStrings(n, count_pos, what);
      return out;
    }
    if (binary_) {
      f_.line();  // the data start after the keyword line's line break
      if (t.kind == DataType::Kind::kBit) {
        const std::size_t bytes = (static_cast<std::size_t>(n) + 7) / 8;
        checkCountFits(f_, static_cast<long long>(bytes), count_pos, f_.pos(), 1, what, true);
        f_.requireBytes(bytes, what);
        out.resize(static_cast<std::size_t>(n));
        const auto* b = reinterpret_cast<const unsigned char*>(f_.data().data() + f_.pos());
        for (std::size_t i = 0; i < out.size(); ++i) out[i] = (b[i / 8] >> (7 - i % 8)) & 1;
        f_.setPos(f_.pos() + bytes);
        return out;
      }
      const std::size_t size = scalarBytes(t.scalar);
      checkCountFits(f_, n, count_pos, f_.pos(), size, what, true);
      f_.requireBytes(static_cast<std::size_t>(n) * size, what);
      out.resize(static_cast<std::size_t>(n));
      const char* p = f_.data().data() + f_.pos();
      for (std::size_t i = 0; i < out.size(); ++i) out[i] = scalarValue(p + i * size, t.scalar, true);
      f_.setPos(f_.pos() + static_cast<std::size_t>(n) * size);
      return out;
    }
    checkCountFits(f_, n, count_pos, f_.pos(), 2, what, false);  // a digit and a separator each
    out.resize(static_cast<std::size_t>(n));
    for (double& v : out) v = f_.realToken(what);
    return out;
  }

  /// Integer values (cell sizes, ids, offsets, types): a float type is refused.
  std::vector<std::int64_t> integers(const DataType& t, long long n, std::size_t count_pos, const char* what) {
    if (t.kind != DataType::Kind::kScalar || t.scalar == Scalar::kFloat32 || t.scalar == Scalar::kFloat64) {
      f_.failAtLine(count_pos, std::string(what) + " need an integer type");
    }
    std::vector<std::int64_t> out(0);
    if (binary_) {
      f_.line();
      const std::size_t size = scalarBytes(t.scalar);
      checkCountFits(f_, n, count_pos, f_.pos(), size, what, true);
      f_.requireBytes(static_cast<std::size_t>(n) * size, what);
      out.resize(static_cast<std::size_t>(n));
      const char* p = f_.data().data() + f_.pos();
      for (std::size_t i = 0; i < out.size(); ++i) {
        if (!scalarInteger(p + i * size, t.scalar, true, out[i])) {
          f_.failAtByte(f_.pos() + i * size, std::string("a value of ") + what + " does not fit a 64-bit integer");
        }
      }
      f_.setPos(f_.pos() + static_cast<std::size_t>(n) * size);
      return out;
    }
    checkCountFits(f_, n, count_pos, f_.pos(), 2, what, false);
    out.resize(static_cast<std::size_t>(n));
    for (std::int64_t& v : out) v = f_.integerToken(what);
    return out;
  }

  /// String arrays hold no numbers for a mesh: skipped (ASCII: one per line; binary: each after a
  /// 1-, 2-, 4- or 8-byte big-endian length whose top two bits say which).
  void skipStrings(long long n, std::size_t count_pos, const char* what) {
    f_.line();
    checkCountFits(f_, n, count_pos, f_.pos(), 1, what, binary_);
    for (long long i = 0; i < n; ++i) {
      if (!binary_) {
        if (f_.atEnd()) f_.fail(std::string("reached the end of the file while reading ") + what);
        f_.line();
        continue;
      }
      f_.requireBytes(1, what);
      const auto* b = reinterpret_cast<const unsigned char*>(f_.data().data() + f_.pos());
      const int tag = b[0] >> 6;
      const std::size_t header = tag == 3 ? 1 : tag == 2 ? 2 : tag == 1 ? 4 : 8;
      f_.requireBytes(header, what);
      std::uint64_t length = b[0] & (tag == 0 ? 0xff : 0x3f);
      for (std::size_t k = 1; k < header; ++k) length = (length << 8) | b[k];
      f_.setPos(f_.pos() + header);
      if (length > f_.data().size() - f_.pos()) {
        f_.failAtByte(f_.pos(), "a string of " + std::to_string(length) + " bytes in " + what + ", past the end of the file");
      }
      f_.setPos(f_.pos() + static_cast<std::size_t>(length));
    }
  }

  void readPoints(std::size_t pos) {
    if (have_points_) f_.failAtLine(pos, "a second POINTS section");
    const long long n = count("the number of points");
    const DataType t = type("POINTS");
    if (t.kind != DataType::Kind::kScalar) f_.failAtLine(pos, "POINTS need a numeric type");
    grid_.points = values(t, 3 * n, pos, "point coordinates");
    have_points_ = true;
  }

  void readCells(std::size_t pos) {
    if (have_cells_) f_.failAtLine(pos, "a second CELLS section");
    cells_pos_ = pos;
    const long long a = count("the first CELLS count");
    const long long b = count("the second CELLS count");
    if (major_ >= 5) {
      // CELLS <offsets> <connectivity size>, then OFFSETS and CONNECTIVITY arrays.
      std::vector<std::int64_t> offsets, connectivity;
      for (const char* name : {"offsets", "connectivity"}) {
        f_.skipWhitespace();
        const std::size_t at = f_.pos();
        const std::string key = lower(f_.token());
        if (key != name) f_.failAtLine(at, std::string("expected ") + (name[0] == 'o' ? "OFFSETS" : "CONNECTIVITY") + " after CELLS, got '" + key.substr(0, 40) + "'");
        const DataType t = type(name);
        (name[0] == 'o' ? offsets : connectivity) = integers(t, name[0] == 'o' ? a : b, at, name[0] == 'o' ? "cell offsets" : "cell connectivity");
        skipMetadataIfAny();
      }
      if (offsets.empty()) offsets.push_back(0);
      if (offsets.front() != 0) f_.failAtLine(pos, "the first cell offset is " + std::to_string(offsets.front()) + ", expected 0");
      for (std::size_t c = 1; c < offsets.size(); ++c) {
        if (offsets[c] < offsets[c - 1]) {
          f_.failAtLine(pos, "cell offsets decrease at cell " + std::to_string(c - 1) + " (" + std::to_string(offsets[c - 1]) +
                                 ", then " + std::to_string(offsets[c]) + ")");
        }
      }
      if (offsets.back() != static_cast<std::int64_t>(connectivity.size())) {
        f_.failAtLine(pos, "the last cell offset is " + std::to_string(offsets.back()) + " but the connectivity holds " +
                               std::to_string(connectivity.size()) + " ids");
      }
      grid_.offsets = std::move(offsets);
      grid_.connectivity = std::move(connectivity);
    } else {
      // CELLS <cells> <size>, then per cell its point count and ids (size values in all).
      DataType t;
      t.scalar = Scalar::kInt32;
      const std::vector<std::int64_t> data = integers(t, b, pos, "cell data");
      grid_.offsets.assign(1, 0);
      grid_.offsets.reserve(static_cast<std::size_t>(a) + 1);
      grid_.connectivity.reserve(data.size());
      std::size_t at = 0;
      for (long long c = 0; c < a; ++c) {
        if (at >= data.size()) {
          f_.failAtLine(pos, "CELLS " + std::to_string(a) + " " + std::to_string(b) + ": the data end after " +
                                 std::to_string(c) + " cells");
        }
        const std::int64_t npts = data[at++];
        if (npts < 0 || static_cast<std::uint64_t>(npts) > data.size() - at) {
          f_.failAtLine(pos, "cell " + std::to_string(c) + " has " + std::to_string(npts) + " points, more than the " +
                                 std::to_string(data.size() - at) + " values left in CELLS");
        }
        grid_.connectivity.insert(grid_.connectivity.end(), data.begin() + static_cast<std::ptrdiff_t>(at),
                                  data.begin() + static_cast<std::ptrdiff_t>(at + static_cast<std::size_t>(npts)));
        at += static_cast<std::size_t>(npts);
        grid_.offsets.push_back(static_cast<std::int64_t>(grid_.connectivity.size()));
      }
      if (at != data.size()) {
        f_.failAtLine(pos, "CELLS " + std::to_string(a) + " " + std::to_string(b) + ": the cells use " +
                               std::to_string(at) + " of the " + std::to_string(b) + " values");
      }
      skipMetadataIfAny();
    }
    have_cells_ = true;
  }

  void readCellTypes(std::size_t pos) {
    if (have_types_) f_.failAtLine(pos, "a second CELL_TYPES section");
    if (!have_cells_) f_.failAtLine(pos, "CELL_TYPES before CELLS");
    const long long n = count("the number of cell types");
    if (n != cellCount()) {
      f_.failAtLine(pos, "CELL_TYPES " + std::to_string(n) + " for " + std::to_string(cellCount()) + " cells");
    }
    DataType t;
    t.scalar = Scalar::kInt32;
    const std::vector<std::int64_t> types = integers(t, n, pos, "cell types");
    grid_.types.assign(types.begin(), types.end());
    have_types_ = true;
  }

  /// Reads an array of `components` per tuple of the current POINT_DATA / CELL_DATA.
  void attributeArray(const std::string& name, const DataType& t, long long components, std::size_t pos) {
    if (components < 1 || components > 1024) {
      f_.failAtLine(pos, "array '" + name.substr(0, 40) + "' has " + std::to_string(components) + " components; expected 1 to 1024");
    }
    Array a;
    a.name = name;
    a.components = static_cast<int>(components);
    a.values = values(t, tuples_ * components, pos, "array values");
    skipMetadataIfAny();
    if (t.kind != DataType::Kind::kString) addArray(*target_, std::move(a));
  }

  bool readAttribute(const std::string& key, std::size_t pos) {
    if (key == "scalars") {
      const std::string name(f_.token());
      const DataType t = type("SCALARS");
      // An optional component count ends the line.
      long long components = 1;
      const std::string_view rest = f_.line();
      std::vector<std::string_view> words;
      mesh_io_detail::splitTokens(rest, false, words);
      if (!words.empty() && !mesh_io_detail::parseInteger(words[0], components)) {
        f_.failAtLine(pos, "expected the component count of SCALARS '" + name.substr(0, 40) + "', got '" + std::string(words[0].substr(0, 40)) + "'");
      }
      f_.skipWhitespace();
      const std::size_t table_pos = f_.pos();
      if (lower(f_.token()) != "lookup_table") f_.failAtLine(table_pos, "expected LOOKUP_TABLE after SCALARS '" + name.substr(0, 40) + "'");
      f_.token();  // the table's name
      attributeArray(name, t, components, pos);
    } else if (key == "color_scalars") {
      const std::string name(f_.token());
      const long long components = count("the COLOR_SCALARS component count");
      DataType t;
      t.scalar = binary_ ? Scalar::kUInt8 : Scalar::kFloat32;
      Array a;
      a.name = name;
      if (components < 1 || components > 1024) f_.failAtLine(pos, "COLOR_SCALARS '" + name.substr(0, 40) + "' has " + std::to_string(components) + " components");
      a.components = static_cast<int>(components);
      a.values = values(t, tuples_ * components, pos, "color values");
      // ASCII colours are 0…1 and VTK stores them as bytes 0…255.
      if (!binary_) {
        for (double& v : a.values) v = std::floor(255.0 * std::clamp(v, 0.0, 1.0) + 0.5);
      }
      skipMetadataIfAny();
      addArray(*target_, std::move(a));
    } else if (key == "lookup_table") {
      f_.token();  // name
      const long long n = count("the LOOKUP_TABLE size");
      DataType t;
      t.scalar = binary_ ? Scalar::kUInt8 : Scalar::kFloat32;
      values(t, 4 * n, pos, "lookup table colours");  // RGBA per entry, not a mesh array
    } else if (key == "vectors" || key == "normals") {
      const std::string name(f_.token());
      attributeArray(name, type(key == "vectors" ? "VECTORS" : "NORMALS"), 3, pos);
    } else if (key == "texture_coordinates") {
      const std::string name(f_.token());
      const long long dim = count("the texture coordinate dimension");
      attributeArray(name, type("TEXTURE_COORDINATES"), dim, pos);
    } else if (key == "tensors" || key == "tensors6") {
      const std::string name(f_.token());
      attributeArray(name, type("TENSORS"), key == "tensors" ? 9 : 6, pos);
    } else if (key == "global_ids" || key == "pedigree_ids" || key == "edge_flags") {
      const std::string name(f_.token());
      attributeArray(name, type("the ids"), 1, pos);
    } else {
      return false;
    }
    return true;
  }

  /// FIELD <name> <arrays>, then per array "<name> <components> <tuples> <type>" and its values (or
  /// NULL_ARRAY). Arrays of POINT_DATA / CELL_DATA need one tuple per point / cell; the dataset's
  /// own FIELD data are skipped.
  void readField(std::size_t pos) {
    f_.token();  // the field's name
    const long long arrays = count("the number of FIELD arrays");
    for (long long i = 0; i < arrays; ++i) {
      f_.skipWhitespace();
      const std::size_t at = f_.pos();
      if (f_.atEnd()) f_.fail("reached the end of the file while reading FIELD arrays");
      const std::string name(f_.token());
      if (name == "NULL_ARRAY") continue;
      const long long components = count("the component count of a FIELD array");
      const long long tuples = count("the tuple count of a FIELD array");
      const DataType t = type("a FIELD array");
      if (components < 1 || components > 1024) {
        f_.failAtLine(at, "FIELD array '" + name.substr(0, 40) + "' has " + std::to_string(components) + " components; expected 1 to 1024");
      }
      const bool attribute = target_ != nullptr;
      if (attribute && tuples != tuples_) {
        f_.failAtLine(at, "FIELD array '" + name.substr(0, 40) + "' has " + std::to_string(tuples) + " tuples, expected " +
                              std::to_string(tuples_));
      }
      Array a;
      a.name = name;
      a.components = static_cast<int>(components);
      a.values = values(t, tuples * components, at, "FIELD array values");
      skipMetadataIfAny();
      if (attribute && t.kind != DataType::Kind::kString) addArray(*target_, std::move(a));
    }
    (void)pos;
  }

  /// METADATA blocks (component names, information keys) end with a blank line.
  void skipMetadata() {
    f_.line();
    while (!f_.atEnd()) {
      const std::string_view l = f_.line();
      if (l.find_first_not_of(" \t\r") == std::string_view::npos) return;
    }
  }

  void skipMetadataIfAny() {
    const std::size_t keep = f_.pos();
    f_.skipWhitespace();
    if (lower(f_.token()) == "metadata") {
      skipMetadata();
    } else {
      f_.setPos(keep);
    }
  }

  FileCursor& f_;
  Grid grid_;
  int major_ = 0;
  bool binary_ = false;
  bool have_points_ = false;
  bool have_cells_ = false;
  bool have_types_ = false;
  std::size_t cells_pos_ = 0;
  std::vector<Array>* target_ = nullptr;
  long long tuples_ = 0;
};

}  // namespace

Grid readLegacy(FileCursor& f) { return LegacyReader(f).read(); }

}  // namespace breast_sim::core::vtk_read
