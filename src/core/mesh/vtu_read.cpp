// VTK XML (.vtu) unstructured-grid reader. Format reference: "VTK File Formats", XML section:
// <VTKFile type="UnstructuredGrid" byte_order header_type compressor> / <UnstructuredGrid> /
// <Piece NumberOfPoints NumberOfCells> with <Points>, <Cells> (connectivity, offsets, types),
// <PointData> and <CellData>, each <DataArray type Name NumberOfComponents format [offset]>.
// Binary data: a header of header_type integers — the byte count, or for compressed data the block
// count, block size, last block size and each block's compressed size — then the data; inline as
// base64, or in <AppendedData> (raw bytes after '_', or base64) at the DataArray's offset.
// Why not vtkXMLUnstructuredGridReader: vtk_read_detail.h (it also sizes the connectivity from the
// last offset, and reads polyhedron faces without bounds).

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <cstring>
#include <tuple>
#include <string>
#include <string_view>
#include <vector>

#include <vtkCommand.h>
#include <vtkDataCompressor.h>
#include <vtkLZ4DataCompressor.h>
#include <vtkLZMADataCompressor.h>
#include <vtkNew.h>
#include <vtkSmartPointer.h>
#include <vtkZLibDataCompressor.h>

#include "vtk_read_detail.h"

namespace breast_sim::core::vtk_read {
namespace {

using mesh_io_detail::FileCursor;

/// A compressed block may expand at most this many times: deflate's limit (LZ4's is 255). LZMA can
/// expand further, but VTK's 32 KiB blocks stay within it; a block that claims more is refused
/// before its buffer is allocated.
constexpr double kMaxBlockExpansion = 1032.0;
constexpr int kMaxDepth = 32;
/// Largest LZMA2 dictionary an LZMA block may declare. liblzma allocates the dictionary a stream's
/// header declares (up to 1.5 GiB) whatever the data, and VTK calls it without a memory limit;
/// VTK writes 8 MiB (its default preset), xz's strongest preset uses 64 MiB.
constexpr std::uint64_t kMaxLzmaDictionary = std::uint64_t{64} << 20;

/// Checks that `p` is an xz stream as VTK's LZMA compressor writes one: a single block with the
/// LZMA2 filter alone, its compressed size in its header, and a dictionary of at most
/// kMaxLzmaDictionary; returns what is wrong, or "" (xz file format 1.0.4, sections 2 and 3).
std::string xzProblem(const unsigned char* p, std::size_t n) {
  static const unsigned char kMagic[6] = {0xFD, '7', 'z', 'X', 'Z', 0x00};
  if (n < 12 + 8 || std::memcmp(p, kMagic, 6) != 0) return "not an xz stream";
  if (p[6] != 0 || (p[7] & 0xF0) != 0) return "unknown xz stream flags";
  static const int kCheckSizes[16] = {0, 4, 4, 4, 8, 8, 8, 16, 16, 16, 32, 32, 32, 64, 64, 64};
  const std::size_t check_size = static_cast<std::size_t>(kCheckSizes[p[7] & 0x0F]);
  std::size_t at = 12;
  if (p[at] == 0) return "";  // no block: the index follows at once
  const std::size_t header = (static_cast<std::size_t>(p[at]) + 1) * 4;
  if (header > n - at) return "its block header passes the end";
  const unsigned char flags = p[at + 1];
  if ((flags & 0x3C) != 0 || (flags & 0x03) != 0) return "its block has reserved flags or more than one filter";
  if ((flags & 0x40) == 0) return "its block header does not give the compressed size";
  std::size_t q = at + 2;
  const std::size_t header_end = at + header;
  const auto varint = [&](std::uint64_t& v) {
    v = 0;
    for (int i = 0; i < 9 && q < header_end; ++i) {
      const unsigned char b = p[q++];
      v |= static_cast<std::uint64_t>(b & 0x7F) << (7 * i);
      if ((b & 0x80) == 0) return true;
    }
    return false;
  };
  std::uint64_t compressed = 0, ignored = 0, filter = 0, props = 0;
  if (!varint(compressed)) return "its compressed size is malformed";
  if ((flags & 0x80) != 0 && !varint(ignored)) return "its uncompressed size is malformed";
  if (!varint(filter) || filter != 0x21 || !varint(props) || props != 1 || q >= header_end) {
    return "its filter is not LZMA2";
  }
  const unsigned code = p[q] & 0x3F;
  if (code > 40) return "its LZMA2 dictionary size is malformed";
  const std::uint64_t dictionary = code == 40 ? 0xFFFFFFFFull : (std::uint64_t{2} | (code & 1)) << (code / 2 + 11);
  if (dictionary > kMaxLzmaDictionary) {
    return "it declares an LZMA2 dictionary of " + std::to_string(dictionary >> 20) + " MiB, more than the " +
           std::to_string(kMaxLzmaDictionary >> 20) + " MiB allowed";
  }
  // One block only: the index (its indicator byte 0) follows the block's padded data and check.
  if (compressed > n) return "its compressed size passes the end";
  std::size_t end = header + static_cast<std::size_t>(compressed);
  end = (end + 3) / 4 * 4 + at + check_size;
  if (end >= n || p[end] != 0) return "it holds more than one block";
  return "";
}

struct Element {
  std::string name;
  std::vector<std::pair<std::string, std::string>> attributes;
  std::vector<int> children;
  std::size_t pos = 0;            // of its '<'
  std::size_t content_begin = 0;  // its text: after the start tag ...
  std::size_t content_end = 0;    // ... to its end tag
  std::size_t end = 0;            // after its end tag

  const std::string* attribute(const char* key) const {
    for (const auto& [k, v] : attributes)
      if (k == key) return &v;
    return nullptr;
  }
};

bool isSpace(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n'; }
bool isNameChar(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == ':' || c == '-' || c == '.';
}

class XmlReader {
 public:
  explicit XmlReader(FileCursor& f) : f_(f), d_(f.data()) {}

  Grid read() {
    parse();
    const Element& root = elements_[0];
    const std::string* type = root.attribute("type");
    if (root.name != "VTKFile" || !type || *type != "UnstructuredGrid") {
      f_.failAtLine(root.pos, "not a VTK XML unstructured grid (expected <VTKFile type=\"UnstructuredGrid\">)");
    }
    if (const std::string* order = root.attribute("byte_order")) {
      if (*order != "LittleEndian" && *order != "BigEndian") f_.failAtLine(root.pos, "byte_order is '" + order->substr(0, 40) + "'");
      big_endian_ = *order == "BigEndian";
    }
    if (const std::string* header = root.attribute("header_type")) {
      if (*header != "UInt32" && *header != "UInt64") f_.failAtLine(root.pos, "header_type is '" + header->substr(0, 40) + "'; expected UInt32 or UInt64");
      header_bytes_ = *header == "UInt64" ? 8 : 4;
    }
    if (const std::string* c = root.attribute("compressor"); c && !c->empty()) {
      if (*c == "vtkZLibDataCompressor") {
        compressor_ = vtkSmartPointer<vtkZLibDataCompressor>::New();
      } else if (*c == "vtkLZ4DataCompressor") {
        compressor_ = vtkSmartPointer<vtkLZ4DataCompressor>::New();
      } else if (*c == "vtkLZMADataCompressor") {
        compressor_ = vtkSmartPointer<vtkLZMADataCompressor>::New();
        lzma_ = true;
      } else {
        f_.failAtLine(root.pos, "compressor '" + c->substr(0, 60) + "' is not supported (zlib, LZ4, LZMA are)");
      }
      compressor_->AddObserver(vtkCommand::ErrorEvent, errors_);  // keeps VTK's messages off stderr
      compressor_->AddObserver(vtkCommand::WarningEvent, errors_);
    }
    const Element* grid = child(root, "UnstructuredGrid");
    if (!grid) f_.failAtLine(root.pos, "<VTKFile> has no <UnstructuredGrid>");
    for (int c : grid->children) {
      if (elements_[c].name == "Piece") readPiece(elements_[c]);
    }
    return std::move(grid_);
  }

 private:
  // ---- XML ----------------------------------------------------------------------------------------

  void parse() {
    std::size_t p = 0;
    if (d_.compare(0, 3, "\xEF\xBB\xBF") == 0) p = 3;  // UTF-8 byte-order mark
    std::vector<int> open;
    bool root_done = false;
    while (true) {
      const std::size_t lt = d_.find('<', p);
      if (elements_.empty() || open.empty()) {
        // Outside the root only whitespace may stand.
        for (std::size_t i = p; i < std::min(lt, d_.size()); ++i) {
          if (!isSpace(d_[i])) f_.failAtLine(i, "not a VTK XML unstructured grid (expected <VTKFile type=\"UnstructuredGrid\">)");
        }
      }
      if (lt == std::string::npos) break;
      p = lt;
      if (d_.compare(p, 4, "<!--") == 0) {
        p = skipPast(p, "-->", "a comment");
      } else if (d_.compare(p, 2, "<?") == 0) {
        p = skipPast(p, "?>", "a processing instruction");
      } else if (d_.compare(p, 9, "<![CDATA[") == 0) {
        f_.failAtLine(p, "CDATA sections are not supported");
      } else if (d_.compare(p, 2, "<!") == 0) {
        p = skipPast(p, ">", "a declaration");
      } else if (d_.compare(p, 2, "</") == 0) {
        std::size_t q = p + 2;
        while (q < d_.size() && isNameChar(d_[q])) ++q;
        const std::string name = d_.substr(p + 2, q - p - 2);
        if (open.empty() || elements_[open.back()].name != name) {
          f_.failAtLine(p, "end tag </" + name.substr(0, 40) + "> does not close " +
                               (open.empty() ? std::string("any element") : "<" + elements_[open.back()].name + ">"));
        }
        elements_[open.back()].content_end = p;
        p = skipPast(q, ">", "an end tag");
        elements_[open.back()].end = p;
        open.pop_back();
        if (open.empty()) root_done = true;
      } else {
        if (root_done) f_.failAtLine(p, "a second root element");
        const int e = startTag(p);
        p = elements_[e].content_begin;
        if (!open.empty()) elements_[open.back()].children.push_back(e);
        if (elements_[e].name == "AppendedData") {
          // Raw appended bytes may hold anything, '<' included: the data start after '_' and the
          // document ends there (as VTK reads it).
          const std::size_t underscore = d_.find('_', elements_[e].content_begin);
          if (underscore == std::string::npos) f_.failAtLine(p, "<AppendedData> without the '_' that starts its data");
          for (std::size_t i = elements_[e].content_begin; i < underscore; ++i) {
            if (!isSpace(d_[i])) f_.failAtLine(i, "<AppendedData> data must start with '_'");
          }
          appended_ = underscore + 1;
          const std::string* encoding = elements_[e].attribute("encoding");
          appended_base64_ = encoding && *encoding == "base64";
          if (encoding && *encoding != "base64" && *encoding != "raw") {
            f_.failAtLine(p, "<AppendedData> encoding '" + encoding->substr(0, 40) + "'; expected raw or base64");
          }
          break;
        }
        if (self_closing_) {
          elements_[e].content_end = elements_[e].end = elements_[e].content_begin;
          if (open.empty()) root_done = true;
        } else {
          open.push_back(e);
          if (open.size() > kMaxDepth) f_.failAtLine(p, "elements nested more than " + std::to_string(kMaxDepth) + " deep");
        }
      }
    }
    if (elements_.empty()) f_.failAtLine(0, "not a VTK XML unstructured grid (expected <VTKFile type=\"UnstructuredGrid\">)");
    if (appended_ == 0 && !open.empty()) {
      f_.failAtLine(d_.size(), "the file ends inside <" + elements_[open.back()].name + ">");
    }
  }

  std::size_t skipPast(std::size_t from, const char* end, const char* what) {
    const std::size_t at = d_.find(end, from);
    if (at == std::string::npos) f_.failAtLine(from, std::string(what) + " is not closed");
    return at + std::strlen(end);
  }

  /// Parses "<Name a="v" ...>" or "/>" at p; returns the element's index.
  int startTag(std::size_t p) {
    Element e;
    e.pos = p;
    std::size_t q = p + 1;
    while (q < d_.size() && isNameChar(d_[q])) ++q;
    e.name = d_.substr(p + 1, q - p - 1);
    if (e.name.empty()) f_.failAtLine(p, "expected an element name after '<'");
    self_closing_ = false;
    while (true) {
      while (q < d_.size() && isSpace(d_[q])) ++q;
      if (q >= d_.size()) f_.failAtLine(p, "the tag <" + e.name.substr(0, 40) + " is not closed");
      if (d_[q] == '>') {
        ++q;
        break;
      }
      if (d_.compare(q, 2, "/>") == 0) {
        q += 2;
        self_closing_ = true;
        break;
      }
      const std::size_t k = q;
      while (q < d_.size() && isNameChar(d_[q])) ++q;
      if (q == k) f_.failAtLine(q, "unexpected character in the tag <" + e.name.substr(0, 40));
      std::string key = d_.substr(k, q - k);
      while (q < d_.size() && isSpace(d_[q])) ++q;
      if (q >= d_.size() || d_[q] != '=') f_.failAtLine(q, "attribute " + key.substr(0, 40) + " has no value");
      ++q;
      while (q < d_.size() && isSpace(d_[q])) ++q;
      if (q >= d_.size() || (d_[q] != '"' && d_[q] != '\'')) f_.failAtLine(q, "attribute " + key.substr(0, 40) + " is not quoted");
      const char quote = d_[q];
      const std::size_t close = d_.find(quote, q + 1);
      if (close == std::string::npos) f_.failAtLine(q, "attribute " + key.substr(0, 40) + " is not closed");
      e.attributes.emplace_back(std::move(key), unescape(d_.substr(q + 1, close - q - 1), q));
      q = close + 1;
    }
    e.content_begin = q;
    elements_.push_back(std::move(e));
    return static_cast<int>(elements_.size()) - 1;
  }

  std::string unescape(const std::string& s, std::size_t pos) const {
    std::string out;
    for (std::size_t i = 0; i < s.size(); ++i) {
      if (s[i] != '&') {
        out += s[i];
        continue;
      }
      const std::size_t semi = s.find(';', i);
      if (semi == std::string::npos) f_.failAtLine(pos, "an '&' without ';' in an attribute");
      const std::string ref = s.substr(i + 1, semi - i - 1);
      if (ref == "amp") out += '&';
      else if (ref == "lt") out += '<';
      else if (ref == "gt") out += '>';
      else if (ref == "quot") out += '"';
      else if (ref == "apos") out += '\'';
      else if (ref.size() > 1 && ref[0] == '#') {
        long long code = 0;
        const bool hex = ref[1] == 'x';
        const std::string digits = ref.substr(hex ? 2 : 1);
        if (digits.empty() || digits.size() > 6 ||
            digits.find_first_not_of(hex ? "0123456789abcdefABCDEF" : "0123456789") != std::string::npos)
          f_.failAtLine(pos, "bad character reference '&" + ref.substr(0, 12) + ";'");
        code = std::stoll(digits, nullptr, hex ? 16 : 10);
        if (code < 1 || code > 127) f_.failAtLine(pos, "character reference '&" + ref.substr(0, 12) + ";' beyond ASCII");
        out += static_cast<char>(code);
      } else {
        f_.failAtLine(pos, "unknown entity '&" + ref.substr(0, 12) + ";'");
      }
      i = semi;
    }
    return out;
  }

  const Element* child(const Element& e, const char* name) const {
    for (int c : e.children)
      if (elements_[c].name == name) return &elements_[c];
    return nullptr;
  }

  // ---- the grid -----------------------------------------------------------------------------------

  long long countAttribute(const Element& e, const char* key) const {
    const std::string* v = e.attribute(key);
    long long n = 0;
    if (!v || !mesh_io_detail::parseInteger(*v, n) || n < 0 || n > kMaxCount) {
      f_.failAtLine(e.pos, "<" + e.name + "> " + key + " is " + (v ? "'" + v->substr(0, 40) + "'" : std::string("missing")) +
                               "; expected 0 to " + std::to_string(kMaxCount));
    }
    return n;
  }

  void readPiece(const Element& piece) {
    const long long np = countAttribute(piece, "NumberOfPoints");
    const long long nc = countAttribute(piece, "NumberOfCells");
    const long long first_point = grid_.numPoints();
    if (first_point + np > kMaxCount || grid_.numCells() + nc > kMaxCount) {
      f_.failAtLine(piece.pos, "the pieces hold more than " + std::to_string(kMaxCount) + " points or cells");
    }
    if (np > 0) {
      const Element* points = child(piece, "Points");
      const Element* array = points ? child(*points, "DataArray") : nullptr;
      if (!array) f_.failAtLine(piece.pos, "<Piece> with " + std::to_string(np) + " points has no <Points><DataArray>");
      if (components(*array) != 3) f_.failAtLine(array->pos, "<Points> DataArray has " + std::to_string(components(*array)) + " components, expected 3");
      const std::vector<double> x = values(*array, 3 * np);
      grid_.points.insert(grid_.points.end(), x.begin(), x.end());
    }
    if (nc > 0) {
      const Element* cells = child(piece, "Cells");
      if (!cells) f_.failAtLine(piece.pos, "<Piece> with " + std::to_string(nc) + " cells has no <Cells>");
      const Element* conn = namedArray(*cells, "connectivity");
      const Element* offsets = namedArray(*cells, "offsets");
      const Element* types = namedArray(*cells, "types");
      const std::vector<std::int64_t> o = integers(*offsets, nc);
      const std::vector<std::int64_t> t = integers(*types, nc);
      const std::vector<std::int64_t> c = integers(*conn, -1);
      // Offsets are the ends of the cells: non-decreasing, the last one the connectivity's size.
      std::int64_t previous = 0;
      for (long long k = 0; k < nc; ++k) {
        if (o[k] < previous) {
          f_.failAtLine(offsets->pos, "cell offsets decrease at cell " + std::to_string(k) + " (" + std::to_string(previous) +
                                          ", then " + std::to_string(o[k]) + ")");
        }
        previous = o[k];
      }
      if (previous != static_cast<std::int64_t>(c.size())) {
        f_.failAtLine(offsets->pos, "the last cell offset is " + std::to_string(previous) + " but the connectivity holds " +
                                        std::to_string(c.size()) + " ids");
      }
      const std::int64_t base = static_cast<std::int64_t>(grid_.connectivity.size());
      for (long long k = 0; k < nc; ++k) grid_.offsets.push_back(base + o[k]);
      // A piece's ids count from its own first point.
      for (std::size_t k = 0; k < c.size(); ++k) {
        if (c[k] < 0 || c[k] >= np) {
          f_.failAtLine(conn->pos, "connectivity entry " + std::to_string(k) + " is point " + std::to_string(c[k]) +
                                       ", but the piece has " + std::to_string(np) + " points");
        }
        grid_.connectivity.push_back(c[k] + first_point);
      }
      for (const std::int64_t type : t) {
        if (type < 0 || type > 255) f_.failAtLine(types->pos, "cell type " + std::to_string(type) + " is not a VTK cell type");
        grid_.types.push_back(static_cast<int>(type));
      }
    }
    for (const auto& [section, tuples, arrays] :
         {std::tuple<const char*, long long, std::vector<Array>*>{"PointData", np, &grid_.point_arrays},
          std::tuple<const char*, long long, std::vector<Array>*>{"CellData", nc, &grid_.cell_arrays}}) {
      const Element* data = child(piece, section);
      if (!data) continue;
      for (int k : data->children) {
        const Element& a = elements_[k];
        if (a.name != "DataArray") continue;
        const std::string* type = a.attribute("type");
        if (type && *type == "String") continue;  // no numbers for a mesh
        Array array;
        if (const std::string* name = a.attribute("Name")) array.name = *name;
        array.components = components(a);
        array.values = values(a, tuples * array.components);
        if (pieces_ == 0) {
          addArray(*arrays, std::move(array));
          continue;
        }
        // A later piece's values continue the first piece's array of the same name.
        const auto same = std::find_if(arrays->begin(), arrays->end(), [&](const Array& x) { return x.name == array.name; });
        if (same == arrays->end() || same->components != array.components) {
          f_.failAtLine(a.pos, "piece " + std::to_string(pieces_ + 1) + " has the array '" + array.name.substr(0, 40) +
                                   "' that the first piece lacks (or with other components)");
        }
        same->values.insert(same->values.end(), array.values.begin(), array.values.end());
      }
    }
    ++pieces_;
    // Every array has one tuple per point / cell of the pieces so far.
    for (const auto& [arrays, n, what] :
         {std::tuple<const std::vector<Array>*, long long, const char*>{&grid_.point_arrays, grid_.numPoints(), "point"},
          std::tuple<const std::vector<Array>*, long long, const char*>{&grid_.cell_arrays, grid_.numCells(), "cell"}}) {
      for (const Array& x : *arrays) {
        if (static_cast<long long>(x.values.size()) != n * x.components) {
          f_.failAtLine(piece.pos, std::string(what) + " array '" + x.name.substr(0, 40) + "' is missing from piece " +
                                       std::to_string(pieces_));
        }
      }
    }
  }

  const Element* namedArray(const Element& cells, const char* name) const {
    for (int c : cells.children) {
      const std::string* n = elements_[c].attribute("Name");
      if (elements_[c].name == "DataArray" && n && *n == name) return &elements_[c];
    }
    f_.failAtLine(cells.pos, std::string("<Cells> has no DataArray named '") + name + "'");
  }

  int components(const Element& a) const {
    const std::string* v = a.attribute("NumberOfComponents");
    if (!v) return 1;
    long long n = 0;
    if (!mesh_io_detail::parseInteger(*v, n) || n < 1 || n > 1024) {
      f_.failAtLine(a.pos, "NumberOfComponents is '" + v->substr(0, 40) + "'; expected 1 to 1024");
    }
    return static_cast<int>(n);
  }

  Scalar scalarType(const Element& a) const {
    const std::string* t = a.attribute("type");
    static const std::pair<const char*, Scalar> kTypes[] = {
        {"Int8", Scalar::kInt8},     {"UInt8", Scalar::kUInt8},   {"Int16", Scalar::kInt16},
        {"UInt16", Scalar::kUInt16}, {"Int32", Scalar::kInt32},   {"UInt32", Scalar::kUInt32},
        {"Int64", Scalar::kInt64},   {"UInt64", Scalar::kUInt64}, {"Float32", Scalar::kFloat32},
        {"Float64", Scalar::kFloat64}, {"Char", Scalar::kInt8}, {"UChar", Scalar::kUInt8}};
    if (t) {
      for (const auto& [name, s] : kTypes)
        if (*t == name) return s;
    }
    f_.failAtLine(a.pos, "DataArray type " + (t ? "'" + t->substr(0, 40) + "'" : std::string("missing")) +
                             " is not a numeric type (Int8 … UInt64, Float32, Float64, Bit)");
  }

  // ---- data ---------------------------------------------------------------------------------------

  /// `count` values of a DataArray (−1: as many as it holds).
  std::vector<double> values(const Element& a, long long count) {
    std::vector<double> out;
    const std::string* type_name = a.attribute("type");
    if (type_name && *type_name == "Bit" && format(a) != "ascii") {
      // Packed, most significant bit first (vtkBitArray's memory).
      const std::string bytes = binary(a, Scalar::kUInt8, count < 0 ? -1 : (count + 7) / 8);
      const long long n = count < 0 ? static_cast<long long>(bytes.size()) * 8 : count;
      out.resize(static_cast<std::size_t>(n));
      for (std::size_t i = 0; i < out.size(); ++i) out[i] = (static_cast<unsigned char>(bytes[i / 8]) >> (7 - i % 8)) & 1;
      return out;
    }
    const Scalar type = type_name && *type_name == "Bit" ? Scalar::kUInt8 : scalarType(a);
    if (format(a) == "ascii") {
      ascii(a, count, [&](std::string_view t, std::size_t at) {
        double v = 0;
        if (!mesh_io_detail::parseReal(t, v)) f_.failAtLine(at, "expected a number in <DataArray>, got '" + std::string(t.substr(0, 40)) + "'");
        out.push_back(v);
      });
      return out;
    }
    const std::string bytes = binary(a, type, count);
    const std::size_t size = scalarBytes(type);
    out.resize(bytes.size() / size);
    for (std::size_t i = 0; i < out.size(); ++i) out[i] = scalarValue(bytes.data() + i * size, type, big_endian_);
    return out;
  }

  std::vector<std::int64_t> integers(const Element& a, long long count) {
    const Scalar type = scalarType(a);
    std::vector<std::int64_t> out;
    if (type == Scalar::kFloat32 || type == Scalar::kFloat64) f_.failAtLine(a.pos, "cell arrays need an integer type");
    if (format(a) == "ascii") {
      ascii(a, count, [&](std::string_view t, std::size_t at) {
        long long v = 0;
        if (!mesh_io_detail::parseInteger(t, v)) f_.failAtLine(at, "expected an integer in <DataArray>, got '" + std::string(t.substr(0, 40)) + "'");
        out.push_back(v);
      });
      return out;
    }
    const std::string bytes = binary(a, type, count);
    const std::size_t size = scalarBytes(type);
    out.resize(bytes.size() / size);
    for (std::size_t i = 0; i < out.size(); ++i) {
      if (!scalarInteger(bytes.data() + i * size, type, big_endian_, out[i])) {
        f_.failAtLine(a.pos, "a value of the DataArray does not fit a 64-bit integer");
      }
    }
    return out;
  }

  std::string format(const Element& a) const {
    const std::string* f = a.attribute("format");
    if (!f || (*f != "ascii" && *f != "binary" && *f != "appended")) {
      f_.failAtLine(a.pos, "DataArray format is " + (f ? "'" + f->substr(0, 40) + "'" : std::string("missing")) +
                               "; expected ascii, binary or appended");
    }
    return *f;
  }

  /// The text of an element. Child elements (VTK writes an <InformationKey> into a DataArray that
  /// carries information) are left out; `direct` says whether the text is d_'s own range
  /// [content_begin, content_end), so that positions in it name lines.
  std::string_view text(const Element& a, std::string& storage, bool& direct) const {
    direct = a.children.empty();
    if (direct) return std::string_view(d_.data() + a.content_begin, a.content_end - a.content_begin);
    storage.clear();
    std::size_t p = a.content_begin;
    for (int c : a.children) {
      storage.append(d_, p, elements_[c].pos - p);
      p = elements_[c].end;
    }
    storage.append(d_, p, a.content_end - p);
    return storage;
  }

  template <typename Add>
  void ascii(const Element& a, long long count, Add add) {
    std::string storage;
    bool direct = true;
    const std::string_view t = text(a, storage, direct);
    const char* base = t.data();
    const std::size_t begin = 0, end = t.size();
    if (count >= 0) {
      // A digit and a separator per value, checked before the values are kept.
      const std::size_t most = (end - begin + 1) / 2;
      if (static_cast<unsigned long long>(count) > most) {
        f_.failAtLine(a.pos, "the DataArray should hold " + std::to_string(count) + " values, but its " +
                                 std::to_string(end - begin) + " characters hold at most " + std::to_string(most));
      }
    }
    std::size_t p = begin;
    long long got = 0;
    while (count < 0 || got < count) {
      while (p < end && isSpace(base[p])) ++p;
      if (p >= end) break;
      std::size_t q = p;
      while (q < end && !isSpace(base[q])) ++q;
      add(std::string_view(base + p, q - p), direct ? a.content_begin + p : a.pos);
      ++got;
      p = q;
    }
    if (count >= 0 && got < count) {
      f_.failAtLine(a.pos, "the DataArray holds " + std::to_string(got) + " values, expected " + std::to_string(count));
    }
  }

  /// A byte stream: raw bytes, or base64 decoded on the way (4 characters → 3 bytes, '=' padding
  /// ending a group early so that separately encoded parts join).
  class Bytes {
   public:
    Bytes(const std::string& d, std::size_t begin, std::size_t end, bool base64)
        : d_(d), p_(begin), end_(end), base64_(base64) {}
    /// At most this many bytes can follow.
    std::size_t bound() const { return base64_ ? (end_ - p_) / 4 * 3 + 3 : end_ - p_; }
    bool read(std::size_t n, char* out) {
      if (!base64_) {
        if (n > end_ - p_) return false;
        std::memcpy(out, d_.data() + p_, n);
        p_ += n;
        return true;
      }
      while (n > 0) {
        if (have_ == used_ && !group()) return false;
        const std::size_t take = std::min(n, have_ - used_);
        std::memcpy(out, buffer_ + used_, take);
        used_ += take;
        out += take;
        n -= take;
      }
      return true;
    }

   private:
    bool group() {
      int values[4];
      int got = 0;
      while (got < 4 && p_ < end_) {
        const char c = d_[p_++];
        if (isSpace(c)) continue;
        const char* kAlphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        const char* at = c == '=' ? nullptr : std::strchr(kAlphabet, c);
        if (c != '=' && (at == nullptr || c == '\0')) return false;
        values[got++] = c == '=' ? -1 : static_cast<int>(at - kAlphabet);
      }
      if (got < 4 || values[0] < 0 || values[1] < 0) return false;
      const unsigned v = (static_cast<unsigned>(values[0]) << 18) | (static_cast<unsigned>(values[1]) << 12) |
                         (static_cast<unsigned>(std::max(values[2], 0)) << 6) | static_cast<unsigned>(std::max(values[3], 0));
      buffer_[0] = static_cast<char>(v >> 16);
      buffer_[1] = static_cast<char>((v >> 8) & 0xff);
      buffer_[2] = static_cast<char>(v & 0xff);
      have_ = values[2] < 0 ? 1 : values[3] < 0 ? 2 : 3;
      used_ = 0;
      return true;
    }
    const std::string& d_;
    std::size_t p_, end_;
    bool base64_;
    char buffer_[3] = {0, 0, 0};
    std::size_t have_ = 0, used_ = 0;
  };

  std::uint64_t headerInt(Bytes& b, const Element& a, const char* what) {
    char raw[8];
    if (!b.read(header_bytes_, raw)) f_.failAtLine(a.pos, std::string("the DataArray's data end in its header (") + what + ")");
    std::int64_t v = 0;
    if (!scalarInteger(raw, header_bytes_ == 8 ? Scalar::kUInt64 : Scalar::kUInt32, big_endian_, v)) {
      f_.failAtLine(a.pos, std::string("the DataArray's header gives ") + what + " beyond 2^63");
    }
    return static_cast<std::uint64_t>(v);
  }

  /// The bytes of a binary or appended DataArray, after its header: `count` values, or what the
  /// header says when count is −1.
  std::string binary(const Element& a, Scalar type, long long count) {
    const std::size_t size = scalarBytes(type);
    std::string storage;
    bool direct = true;
    const std::string_view inline_text = text(a, storage, direct);
    const std::string* source = direct ? &d_ : &storage;
    std::size_t begin = direct ? a.content_begin : 0;
    std::size_t end = begin + inline_text.size();
    bool base64 = true;
    if (format(a) == "appended") {
      if (appended_ == 0) f_.failAtLine(a.pos, "an appended DataArray but no <AppendedData>");
      const std::string* offset = a.attribute("offset");
      long long o = 0;
      if (!offset || !mesh_io_detail::parseInteger(*offset, o) || o < 0 || static_cast<unsigned long long>(o) > d_.size() - appended_) {
        f_.failAtLine(a.pos, "the DataArray's offset is " + (offset ? "'" + offset->substr(0, 40) + "'" : std::string("missing")) +
                                 "; expected 0 to " + std::to_string(d_.size() - appended_) + " (the appended data's size)");
      }
      source = &d_;
      begin = appended_ + static_cast<std::size_t>(o);
      end = d_.size();
      base64 = appended_base64_;
    }
    Bytes b(*source, begin, end, base64);
    const std::string want = count < 0 ? std::string("as many as its header says")
                                       : std::to_string(count) + " values of " + std::to_string(size) + " bytes";
    std::string out;
    if (!compressor_) {
      const std::uint64_t n = headerInt(b, a, "the byte count");
      if ((count >= 0 && n != static_cast<std::uint64_t>(count) * size) || n % size != 0) {
        f_.failAtLine(a.pos, "the DataArray's header gives " + std::to_string(n) + " bytes; expected " + want);
      }
      if (n > b.bound()) {
        f_.failAtLine(a.pos, "the DataArray's header gives " + std::to_string(n) + " bytes, but at most " +
                                 std::to_string(b.bound()) + " follow");
      }
      out.resize(static_cast<std::size_t>(n));
      if (!b.read(out.size(), out.data())) f_.failAtLine(a.pos, "the DataArray's data are truncated or not base64");
      return out;
    }
    // Compressed: block count, block size, last block size, then each block's compressed size.
    const std::uint64_t blocks = headerInt(b, a, "the block count");
    const std::uint64_t block = headerInt(b, a, "the block size");
    const std::uint64_t last = headerInt(b, a, "the last block size");
    if (blocks > b.bound() / header_bytes_) {
      f_.failAtLine(a.pos, "the DataArray's header gives " + std::to_string(blocks) + " compressed blocks, more than the file holds");
    }
    if (block > (std::uint64_t{1} << 32) || last > block) {
      f_.failAtLine(a.pos, "the DataArray's blocks are " + std::to_string(block) + " bytes, the last " + std::to_string(last) +
                               "; expected at most 2^32 and the last no larger");
    }
    std::vector<std::uint64_t> sizes(static_cast<std::size_t>(blocks));
    std::uint64_t compressed = 0;
    std::uint64_t total = 0;
    for (std::uint64_t k = 0; k < blocks; ++k) {
      sizes[k] = headerInt(b, a, "a compressed block size");
      compressed += sizes[k];
      const std::uint64_t u = k + 1 == blocks && last != 0 ? last : block;
      total += u;
      if (static_cast<double>(u) > kMaxBlockExpansion * static_cast<double>(sizes[k]) + 1024.0) {
        f_.failAtLine(a.pos, "compressed block " + std::to_string(k) + " of the DataArray claims " + std::to_string(u) +
                                 " bytes from " + std::to_string(sizes[k]) + "; a block expands at most " +
                                 std::to_string(static_cast<int>(kMaxBlockExpansion)) + " times");
      }
      if (compressed > b.bound()) {
        f_.failAtLine(a.pos, "the DataArray's compressed blocks need " + std::to_string(compressed) + " bytes, but at most " +
                                 std::to_string(b.bound()) + " follow");
      }
    }
    if ((count >= 0 && total != static_cast<std::uint64_t>(count) * size) || total % size != 0) {
      f_.failAtLine(a.pos, "the DataArray's blocks hold " + std::to_string(total) + " bytes; expected " + want);
    }
    out.resize(static_cast<std::size_t>(total));
    std::string packed;
    std::size_t at = 0;
    for (std::uint64_t k = 0; k < blocks; ++k) {
      const std::size_t u = static_cast<std::size_t>(k + 1 == blocks && last != 0 ? last : block);
      packed.resize(static_cast<std::size_t>(sizes[k]));
      if (!b.read(packed.size(), packed.data())) f_.failAtLine(a.pos, "the DataArray's compressed data are truncated or not base64");
      if (lzma_) {
        const std::string problem = xzProblem(reinterpret_cast<const unsigned char*>(packed.data()), packed.size());
        if (!problem.empty()) f_.failAtLine(a.pos, "LZMA block " + std::to_string(k) + " of the DataArray is refused: " + problem);
      }
      const std::size_t got = compressor_->Uncompress(reinterpret_cast<const unsigned char*>(packed.data()), packed.size(),
                                                      reinterpret_cast<unsigned char*>(out.data() + at), u);
      if (got != u) {
        f_.failAtLine(a.pos, "compressed block " + std::to_string(k) + " of the DataArray does not decompress to its " +
                                 std::to_string(u) + " bytes (corrupt data)");
      }
      at += u;
    }
    return out;
  }

  FileCursor& f_;
  const std::string& d_;
  std::vector<Element> elements_;
  bool self_closing_ = false;
  std::size_t appended_ = 0;  // first byte after '_', 0 without appended data
  bool appended_base64_ = false;
  bool big_endian_ = false;
  std::size_t header_bytes_ = 4;
  vtkSmartPointer<vtkDataCompressor> compressor_;
  bool lzma_ = false;
  class Silence : public vtkCommand {
   public:
    static Silence* New() { return new Silence; }
    void Execute(vtkObject*, unsigned long, void*) override {}
  };
  vtkNew<Silence> errors_;
  int pieces_ = 0;
  Grid grid_;
};

}  // namespace

Grid readXml(FileCursor& f) { return XmlReader(f).read(); }

}  // namespace breast_sim::core::vtk_read
