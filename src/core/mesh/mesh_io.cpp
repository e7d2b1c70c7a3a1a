#include "breast_sim/core/mesh/mesh_io_detail.h"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <numeric>
#include <stdexcept>

namespace breast_sim::core {
namespace mesh_io_detail {

namespace {

bool isSpace(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n' || c == '\v' || c == '\f'; }

std::string_view trimView(std::string_view s) {
  while (!s.empty() && isSpace(s.front())) s.remove_prefix(1);
  while (!s.empty() && isSpace(s.back())) s.remove_suffix(1);
  return s;
}

}  // namespace

// ---- FileCursor ----------------------------------------------------------------------------------

FileCursor::FileCursor(std::string path) : path_(std::move(path)) {
  // A folder opens like a file on Linux, and its "size" can be 2^63: name it instead.
  std::error_code ec;
  const auto status = std::filesystem::status(path_, ec);
  if (!ec && std::filesystem::is_directory(status)) throw std::runtime_error(path_ + ": is a folder, not a mesh file");
  if (!ec && std::filesystem::exists(status) && !std::filesystem::is_regular_file(status)) {
    throw std::runtime_error(path_ + ": is not a regular file (a device, a pipe or a socket)");
  }
  std::FILE* file = std::fopen(path_.c_str(), "rb");
  if (!file) throw std::runtime_error(path_ + ": cannot open for reading (" + std::strerror(errno) + ")");
  // Reading the whole file at once keeps parsing a single pass over memory; a 300k-tet mesh is tens of MB.
  std::fseek(file, 0, SEEK_END);
  const long size = std::ftell(file);
  std::fseek(file, 0, SEEK_SET);
  if (size < 0) {
    std::fclose(file);
    throw std::runtime_error(path_ + ": cannot read (not a regular file?)");
  }
  data_.resize(static_cast<std::size_t>(size));
  const std::size_t got = size > 0 ? std::fread(data_.data(), 1, data_.size(), file) : 0;
  const bool failed = std::ferror(file) != 0;
  std::fclose(file);
  if (failed || got != data_.size()) {
    throw std::runtime_error(path_ + ": read error after " + std::to_string(got) + " of " +
                             std::to_string(data_.size()) + " bytes");
  }
}

int FileCursor::lineAt(std::size_t pos) const {
  // Only called on the way to an error, so counting from the start keeps the happy path free of
  // line bookkeeping.
  std::size_t end = std::min(pos, data_.size());
  // At the end of a file that ends with a line break, name the last line rather than the empty one after it.
  if (end == data_.size() && end > 0 && data_[end - 1] == '\n') --end;
  return 1 + static_cast<int>(std::count(data_.begin(), data_.begin() + static_cast<std::ptrdiff_t>(end), '\n'));
}

void FileCursor::failAtLine(std::size_t pos, const std::string& what) const {
  throw std::runtime_error(path_ + ":" + std::to_string(lineAt(pos)) + ": " + what);
}

void FileCursor::failAtByte(std::size_t offset, const std::string& what) const {
  throw std::runtime_error(path_ + ": byte " + std::to_string(offset) + ": " + what);
}

void FileCursor::skipWhitespace() {
  while (pos_ < data_.size() && isSpace(data_[pos_])) ++pos_;
}

std::string_view FileCursor::token() {
  skipWhitespace();
  const std::size_t start = pos_;
  while (pos_ < data_.size() && !isSpace(data_[pos_])) ++pos_;
  return std::string_view(data_.data() + start, pos_ - start);
}

std::string_view FileCursor::line() {
  const std::size_t start = std::min(pos_, data_.size());
  const void* nl = std::memchr(data_.data() + start, '\n', data_.size() - start);
  const std::size_t end = nl ? static_cast<std::size_t>(static_cast<const char*>(nl) - data_.data())
                             : data_.size();
  pos_ = nl ? end + 1 : end;
  std::string_view s(data_.data() + start, end - start);
  if (!s.empty() && s.back() == '\r') s.remove_suffix(1);
  return s;
}

long long FileCursor::integerToken(const char* what) {
  const std::string_view t = token();
  if (t.empty()) fail(std::string("expected ") + what + ", reached the end of the file");
  long long v = 0;
  if (!parseInteger(t, v)) failAtLine(pos_ - t.size(), std::string("expected ") + what + ", got '" + std::string(t) + "'");
  return v;
}

double FileCursor::realToken(const char* what) {
  const std::string_view t = token();
  if (t.empty()) fail(std::string("expected ") + what + ", reached the end of the file");
  double v = 0;
  if (!parseReal(t, v)) failAtLine(pos_ - t.size(), std::string("expected ") + what + ", got '" + std::string(t) + "'");
  return v;
}

void FileCursor::requireBytes(std::size_t n, const char* what) const {
  if (pos_ > data_.size() || n > data_.size() - pos_) {
    failAtByte(pos_, std::string("truncated: expected ") + what + " (" + std::to_string(n) +
                         " bytes), but the file ends at byte " + std::to_string(data_.size()));
  }
}

// ---- numbers and tokens --------------------------------------------------------------------------

bool parseInteger(std::string_view s, long long& value) {
  if (!s.empty() && s.front() == '+') s.remove_prefix(1);
  if (s.empty()) return false;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  return ec == std::errc() && ptr == s.data() + s.size();
}

bool parseReal(std::string_view s, double& value) {
  if (!s.empty() && s.front() == '+') s.remove_prefix(1);
  if (s.empty()) return false;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  return ec == std::errc() && ptr == s.data() + s.size();
}

void splitTokens(std::string_view line, bool commas, std::vector<std::string_view>& out) {
  out.clear();
  if (commas) {
    line = trimView(line);
    if (line.empty()) return;
    std::size_t start = 0;
    while (true) {
      const std::size_t comma = line.find(',', start);
      if (comma == std::string_view::npos) {
        const std::string_view last = trimView(line.substr(start));
        if (!last.empty() || out.empty()) out.push_back(last);
        return;
      }
      out.push_back(trimView(line.substr(start, comma - start)));
      start = comma + 1;
    }
  }
  std::size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && isSpace(line[i])) ++i;
    const std::size_t start = i;
    while (i < line.size() && !isSpace(line[i])) ++i;
    if (i > start) out.push_back(line.substr(start, i - start));
  }
}

// ---- NumberMap -----------------------------------------------------------------------------------

bool NumberMap::insert(long long number, int index) {
  if (find(number) >= 0) return false;
  ++count_;
  // A dense table while numbers stay within a few times the count (the usual 0/1-based or gappy
  // numbering); a hash map for the rest, so a single huge number cannot allocate gigabytes.
  const long long dense_limit = std::max<long long>(1 << 16, 4 * static_cast<long long>(count_));
  if (number >= 0 && number < dense_limit) {
    if (number >= static_cast<long long>(dense_.size())) {
      dense_.resize(std::max<std::size_t>(static_cast<std::size_t>(number) + 1, 2 * dense_.size()), -1);
    }
    dense_[static_cast<std::size_t>(number)] = index;
  } else {
    sparse_.emplace(number, index);
  }
  return true;
}

// ---- writing -------------------------------------------------------------------------------------

void appendReal(std::string& out, double v) {
  char buf[32];
  const auto [ptr, ec] = std::to_chars(buf, buf + sizeof(buf), v);
  out.append(buf, ptr);
}

void appendInteger(std::string& out, long long v) {
  char buf[24];
  const auto [ptr, ec] = std::to_chars(buf, buf + sizeof(buf), v);
  out.append(buf, ptr);
}

void writeFile(const std::string& path, const std::string& bytes) {
  std::FILE* file = std::fopen(path.c_str(), "wb");
  if (!file) throw std::runtime_error(path + ": cannot open for writing (" + std::strerror(errno) + ")");
  const std::size_t put = std::fwrite(bytes.data(), 1, bytes.size(), file);
  const bool closed = std::fclose(file) == 0;
  if (put != bytes.size() || !closed) {
    throw std::runtime_error(path + ": write error after " + std::to_string(put) + " of " +
                             std::to_string(bytes.size()) + " bytes (disk full?)");
  }
}

// ---- mesh building -------------------------------------------------------------------------------

void checkLengthUnit(double length_unit_m, const char* function) {
  if (!(std::isfinite(length_unit_m) && length_unit_m > 0.0)) {
    throw std::invalid_argument(std::string(function) + ": length_unit_m must be a finite length > 0 "
                                "(1.0 for metres, 1e-3 for millimetres), got " + std::to_string(length_unit_m));
  }
}

TetMesh makeMesh(const std::string& path, Points nodes_m, Tets tets, std::vector<int> labels) {
  try {
    return TetMesh(std::move(nodes_m), std::move(tets), std::move(labels));
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
}

void addNodeSet(const std::string& path, TetMesh& mesh, const std::string& name, std::vector<int> nodes) {
  try {
    mesh.setNodeSet(name, std::move(nodes));
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
}

void sortByElementNumber(const std::string& path, std::vector<long long>& numbers, Tets& tets,
                         std::vector<int>& labels) {
  const std::size_t n = numbers.size();
  bool sorted = true;
  for (std::size_t i = 1; i < n && sorted; ++i) {
    if (numbers[i] == numbers[i - 1]) {
      throw std::runtime_error(path + ": element number " + std::to_string(numbers[i]) + " appears twice");
    }
    sorted = numbers[i] > numbers[i - 1];
  }
  if (sorted) return;
  std::vector<int> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return numbers[a] < numbers[b]; });
  Tets sorted_tets(tets.rows(), 4);
  std::vector<int> sorted_labels(n);
  std::vector<long long> sorted_numbers(n);
  for (std::size_t i = 0; i < n; ++i) {
    if (i > 0 && numbers[order[i]] == numbers[order[i - 1]]) {
      throw std::runtime_error(path + ": element number " + std::to_string(numbers[order[i]]) +
                               " appears twice");
    }
    sorted_tets.row(static_cast<Eigen::Index>(i)) = tets.row(order[i]);
    sorted_labels[i] = labels[order[i]];
    sorted_numbers[i] = numbers[order[i]];
  }
  tets = std::move(sorted_tets);
  labels = std::move(sorted_labels);
  numbers = std::move(sorted_numbers);
}

}  // namespace mesh_io_detail

// ---- dispatch by extension -----------------------------------------------------------------------

namespace {

std::string lowerExtension(const std::string& path) {
  const std::size_t slash = path.find_last_of("/\\");
  const std::size_t dot = path.find_last_of('.');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return "";
  std::string ext = path.substr(dot);
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

const char* formatName(MeshFileFormat format) {
  switch (format) {
    case MeshFileFormat::kGmsh: return "Gmsh .msh";
    case MeshFileFormat::kVtu: return "VTK .vtu";
    case MeshFileFormat::kVtkLegacy: return "legacy VTK .vtk";
    case MeshFileFormat::kTetGen: return "TetGen .node/.ele";
    case MeshFileFormat::kAbaqusInp: return "Abaqus .inp";
  }
  return "?";
}

}  // namespace

MeshFileFormat meshFileFormat(const std::string& path) {
  const std::string ext = lowerExtension(path);
  if (ext == ".msh") return MeshFileFormat::kGmsh;
  if (ext == ".vtu") return MeshFileFormat::kVtu;
  if (ext == ".vtk") return MeshFileFormat::kVtkLegacy;
  if (ext == ".node" || ext == ".ele") return MeshFileFormat::kTetGen;
  if (ext == ".inp") return MeshFileFormat::kAbaqusInp;
  throw std::runtime_error(path + ": unknown mesh file extension '" + ext +
                           "'; supported: .msh (Gmsh), .vtu and .vtk (VTK), .node/.ele (TetGen), .inp (Abaqus)");
}

TetMesh readTetMesh(const std::string& path, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "readTetMesh");
  switch (meshFileFormat(path)) {
    case MeshFileFormat::kGmsh: return readGmsh(path, length_unit_m);
    case MeshFileFormat::kVtu:
    case MeshFileFormat::kVtkLegacy: return readVtkUnstructured(path, length_unit_m);
    case MeshFileFormat::kTetGen: return readTetGen(path, length_unit_m);
    case MeshFileFormat::kAbaqusInp: return readAbaqusInp(path, length_unit_m);
  }
  throw std::logic_error("readTetMesh: unhandled format");
}

void writeTetMesh(const std::string& path, const TetMesh& mesh, const MeshFields& fields,
                  double length_unit_m, const MeshWriteOptions& options) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeTetMesh");
  const MeshFileFormat format = meshFileFormat(path);
  const bool has_fields = !fields.point_data.empty() || !fields.cell_data.empty();
  if (has_fields && format != MeshFileFormat::kVtu && format != MeshFileFormat::kVtkLegacy) {
    throw std::invalid_argument("writeTetMesh: " + path + ": the " + formatName(format) +
                                " format cannot hold point or cell fields; write a .vtu or .vtk file");
  }
  switch (format) {
    case MeshFileFormat::kGmsh: return writeGmsh(path, mesh, options.gmsh, length_unit_m);
    case MeshFileFormat::kVtu: return writeVtu(path, mesh, fields, length_unit_m, options.vtk);
    case MeshFileFormat::kVtkLegacy: return writeVtkLegacy(path, mesh, fields, length_unit_m, options.vtk);
    case MeshFileFormat::kTetGen: return writeTetGen(path, mesh, length_unit_m);
    case MeshFileFormat::kAbaqusInp: return writeAbaqusInp(path, mesh, length_unit_m);
  }
}

}  // namespace breast_sim::core
