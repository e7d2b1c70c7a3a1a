// Gmsh MSH 2.2 and 4.1 reader, ASCII and binary; the writer is gmsh_write.cpp.
// Format reference: Gmsh reference manual, section "MSH file format" (4.1) and "Legacy formats" (2.2).

#include <algorithm>
#include <array>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/mesh/mesh_io_detail.h"
#include "gmsh_element_types.h"

namespace breast_sim::core {
namespace {

using gmsh_detail::gmshElementDimension;
using gmsh_detail::gmshNodesPerElement;
using gmsh_detail::kTet4;
using mesh_io_detail::checkCountFits;
using mesh_io_detail::FileCursor;
using mesh_io_detail::NumberMap;

class GmshReader {
 public:
  GmshReader(const std::string& path, double length_unit_m) : f_(path), unit_(length_unit_m) {}

  TetMesh read() {
    while (true) {
      f_.skipWhitespace();
      if (f_.atEnd()) break;
      const std::size_t section_pos = f_.pos();
      const std::string_view t = f_.token();
      if (t.size() < 2 || t[0] != '$') {
        f_.failAtLine(section_pos, "expected a section such as $MeshFormat, $Nodes or $Elements, got '" +
                                       std::string(t.substr(0, 40)) + "'");
      }
      const std::string name(t.substr(1));
      // MSH 4.1 binary sections start right after the line break that ends their name.
      if (binary_ && version_ == Version::k41 && (name == "Entities" || name == "Nodes" || name == "Elements")) {
        f_.line();
      }
      if (name != "MeshFormat" && version_ == Version::kUnknown) {
        f_.failAtLine(section_pos, "expected $MeshFormat first, got $" + name);
      }
      if (name == "MeshFormat") {
        readFormat();
        expectEnd(name, false);
      } else if (name == "PhysicalNames") {
        readPhysicalNames();
        expectEnd(name, false);
      } else if (name == "Entities" && version_ == Version::k41) {
        readEntities();
        expectEnd(name, binary_);
      } else if (name == "Nodes") {
        if (have_nodes_) f_.failAtLine(section_pos, "a second $Nodes section");
        version_ == Version::k41 ? readNodes41() : readNodes2();
        have_nodes_ = true;
        expectEnd(name, binary_);
      } else if (name == "Elements") {
        if (!have_nodes_) f_.failAtLine(section_pos, "$Elements before $Nodes");
        if (have_elements_) f_.failAtLine(section_pos, "a second $Elements section");
        version_ == Version::k41 ? readElements41() : readElements2();
        have_elements_ = true;
        expectEnd(name, binary_);
      } else {
        // Sections we do not use ($Comments, $Periodic, $NodeData, $PartitionedEntities, …).
        const std::string end = "$End" + name;
        const std::size_t found = f_.data().find(end, f_.pos());
        if (found == std::string::npos) f_.failAtLine(section_pos, "section $" + name + " has no " + end);
        f_.setPos(found + end.size());
      }
    }
    const std::size_t eof = f_.data().size();
    if (version_ == Version::kUnknown) f_.failAtLine(eof, "no $MeshFormat section: not a Gmsh .msh file");
    if (!have_nodes_) f_.failAtLine(eof, "reached the end of the file without a $Nodes section");
    if (!have_elements_) f_.failAtLine(eof, "reached the end of the file without an $Elements section");
    if (labels_.empty()) {
      throw std::runtime_error(f_.path() + ": no 4-node tetrahedra (element type 4) in the file; " +
                               std::to_string(skipped_) + " other elements were skipped");
    }
    return build();
  }

 private:
  enum class Version { kUnknown, k2, k41 };

  [[noreturn]] void failAt(std::size_t pos, bool binary, const std::string& what) const {
    if (binary) f_.failAtByte(pos, what);
    f_.failAtLine(pos, what);
  }

  void expectEnd(const std::string& name, bool binary) {
    f_.skipWhitespace();
    const std::size_t pos = f_.pos();
    const std::string_view t = f_.token();
    if (t != "$End" + name) {
      failAt(pos, binary, "expected $End" + name + ", got " +
                              (t.empty() ? std::string("the end of the file") : "'" + std::string(t.substr(0, 40)) + "'") +
                              " (wrong element or node count?)");
    }
  }

  // Next non-blank line, with the position of its start.
  std::string_view nextLine(std::size_t& pos, const char* while_reading) {
    f_.skipWhitespace();
    pos = f_.pos();
    if (f_.atEnd()) f_.fail(std::string("reached the end of the file while reading ") + while_reading);
    return f_.line();
  }

  long long tokenInteger(std::string_view t, std::size_t line_pos, const char* what) const {
    long long v = 0;
    if (!mesh_io_detail::parseInteger(t, v)) {
      f_.failAtLine(line_pos, std::string("expected ") + what + ", got '" + std::string(t) + "'");
    }
    return v;
  }

  double tokenReal(std::string_view t, std::size_t line_pos, const char* what) const {
    double v = 0;
    if (!mesh_io_detail::parseReal(t, v)) {
      f_.failAtLine(line_pos, std::string("expected ") + what + ", got '" + std::string(t) + "'");
    }
    return v;
  }

  /// A tag or dimension stored in an int (region labels, physical and entity tags): a value the file
  /// gives beyond an int is an error, not a silently different label.
  int intValue(long long v, std::size_t pos, bool binary, const char* what) const {
    if (v < std::numeric_limits<int>::min() || v > std::numeric_limits<int>::max()) {
      failAt(pos, binary, std::string(what) + " is " + std::to_string(v) + ", which does not fit a 32-bit integer");
    }
    return static_cast<int>(v);
  }

  long long countToken(const char* what) {
    const std::size_t pos = (f_.skipWhitespace(), f_.pos());
    const long long n = f_.integerToken(what);
    if (n < 0 || n > std::numeric_limits<int>::max()) {
      f_.failAtLine(pos, std::string("expected ") + what + ", got " + std::to_string(n));
    }
    return n;
  }

  std::size_t countPos() {
    f_.skipWhitespace();
    return f_.pos();
  }

  std::size_t binaryCount(const char* what) {
    const std::size_t pos = f_.pos();
    const auto n = f_.binary<std::uint64_t>(what);
    if (n > static_cast<std::uint64_t>(std::numeric_limits<int>::max())) {
      f_.failAtByte(pos, std::string("implausible ") + what + " " + std::to_string(n));
    }
    return static_cast<std::size_t>(n);
  }

  void readFormat() {
    const std::size_t pos = (f_.skipWhitespace(), f_.pos());
    const std::string version(f_.token());
    const long long file_type = f_.integerToken("the file type (0 ASCII, 1 binary)");
    const long long data_size = f_.integerToken("the data size");
    if (version == "4.1") {
      version_ = Version::k41;
    } else if (version == "2" || version == "2.0" || version == "2.1" || version == "2.2") {
      version_ = Version::k2;
    } else if (version == "4" || version == "4.0") {
      f_.failAtLine(pos, "MSH 4.0 is not supported; save the mesh as MSH 4.1 or 2.2");
    } else {
      f_.failAtLine(pos, "unsupported MSH version '" + version + "'; MSH 2.2 and 4.1 are supported");
    }
    if (file_type != 0 && file_type != 1) {
      f_.failAtLine(pos, "file type must be 0 (ASCII) or 1 (binary), got " + std::to_string(file_type));
    }
    binary_ = file_type == 1;
    if (!binary_) return;
    if (data_size != 8) {
      f_.failAtLine(pos, "binary data size " + std::to_string(data_size) + " is not supported (only 8)");
    }
    f_.line();
    const std::size_t one_pos = f_.pos();
    const int one = f_.binary<int>("the integer 1 that tells the byte order");
    if (one != 1) {
      f_.failAtByte(one_pos, one == 0x01000000 ? "big-endian binary files are not supported"
                                              : "expected the integer 1 that tells the byte order, got " +
                                                    std::to_string(one));
    }
  }

  void readPhysicalNames() {
    const long long n = countToken("the number of physical names");
    for (long long i = 0; i < n; ++i) {
      std::size_t pos = 0;
      const std::string_view line = nextLine(pos, "$PhysicalNames");
      mesh_io_detail::splitTokens(line, false, tokens_);
      if (tokens_.size() < 3) f_.failAtLine(pos, "expected: dimension tag \"name\"");
      const int dim = intValue(tokenInteger(tokens_[0], pos, "a physical group dimension"), pos, false,
                               "physical group dimension");
      const int tag = intValue(tokenInteger(tokens_[1], pos, "a physical tag"), pos, false, "physical tag");
      const std::size_t q0 = line.find('"');
      const std::size_t q1 = line.rfind('"');
      std::string name = (q0 != std::string_view::npos && q1 > q0) ? std::string(line.substr(q0 + 1, q1 - q0 - 1))
                                                                 : std::string(tokens_[2]);
      physical_names_[{dim, tag}] = std::move(name);
    }
  }

  void readEntities() {
    if (binary_) {
      std::array<std::size_t, 4> count{};
      for (auto& c : count) c = binaryCount("an entity count");
      for (int dim = 0; dim < 4; ++dim) {
        for (std::size_t e = 0; e < count[dim]; ++e) {
          const int tag = f_.binary<int>("an entity tag");
          f_.requireBytes((dim == 0 ? 3 : 6) * sizeof(double), "an entity's coordinates");
          f_.setPos(f_.pos() + (dim == 0 ? 3 : 6) * sizeof(double));
          const std::size_t nphys = binaryCount("a physical tag count");
          f_.requireBytes(nphys * sizeof(int), "physical tags");
          std::vector<int> phys(nphys);
          for (auto& p : phys) p = f_.binary<int>("a physical tag");
          entity_physicals_[{dim, tag}] = std::move(phys);
          if (dim > 0) {
            const std::size_t nbound = binaryCount("a bounding entity count");
            f_.requireBytes(nbound * sizeof(int), "bounding entity tags");
            f_.setPos(f_.pos() + nbound * sizeof(int));
          }
        }
      }
      return;
    }
    std::array<long long, 4> count{};
    for (auto& c : count) c = countToken("an entity count");
    for (int dim = 0; dim < 4; ++dim) {
      for (long long e = 0; e < count[dim]; ++e) {
        const std::size_t tag_pos = countPos();
        const int tag = intValue(f_.integerToken("an entity tag"), tag_pos, false, "entity tag");
        for (int k = 0; k < (dim == 0 ? 3 : 6); ++k) f_.realToken("an entity coordinate");
        const std::size_t nphys_pos = countPos();
        const long long nphys = countToken("a physical tag count");
        checkCountFits(f_, nphys, nphys_pos, f_.pos(), 2, "physical tags", false);  // " 7"
        std::vector<int> phys(static_cast<std::size_t>(nphys));
        for (auto& p : phys) p = intValue(f_.integerToken("a physical tag"), countPos(), false, "physical tag");
        entity_physicals_[{dim, tag}] = std::move(phys);
        if (dim > 0) {
          const long long nbound = countToken("a bounding entity count");
          for (long long b = 0; b < nbound; ++b) f_.integerToken("a bounding entity tag");
        }
      }
    }
  }

  void addNode(long long tag, double x, double y, double z, std::size_t pos, bool binary) {
    if (!node_index_.insert(tag, static_cast<int>(xyz_.size() / 3))) {
      failAt(pos, binary, "node tag " + std::to_string(tag) + " appears twice");
    }
    xyz_.push_back(x * unit_);
    xyz_.push_back(y * unit_);
    xyz_.push_back(z * unit_);
  }

  void readNodes2() {
    const std::size_t count_pos = countPos();
    const long long n = countToken("the number of nodes");
    if (binary_) {
      f_.line();
      checkCountFits(f_, n, count_pos, f_.pos(), sizeof(int) + 3 * sizeof(double), "nodes", false);
      f_.requireBytes(static_cast<std::size_t>(n) * (sizeof(int) + 3 * sizeof(double)), "the binary node data");
      xyz_.reserve(static_cast<std::size_t>(3 * n));
      for (long long i = 0; i < n; ++i) {
        const std::size_t pos = f_.pos();
        const int tag = f_.binary<int>("a node tag");
        const double x = f_.binary<double>("x"), y = f_.binary<double>("y"), z = f_.binary<double>("z");
        addNode(tag, x, y, z, pos, true);
      }
      return;
    }
    checkCountFits(f_, n, count_pos, f_.pos(), 8, "nodes", false);  // "1 0 0 0\n"
    xyz_.reserve(static_cast<std::size_t>(3 * n));
    for (long long i = 0; i < n; ++i) {
      std::size_t pos = 0;
      mesh_io_detail::splitTokens(nextLine(pos, "$Nodes"), false, tokens_);
      if (tokens_.size() != 4) {
        f_.failAtLine(pos, "expected a node tag and 3 coordinates, got " + std::to_string(tokens_.size()) + " values");
      }
      addNode(tokenInteger(tokens_[0], pos, "a node tag"), tokenReal(tokens_[1], pos, "a coordinate"),
              tokenReal(tokens_[2], pos, "a coordinate"), tokenReal(tokens_[3], pos, "a coordinate"), pos, false);
    }
  }

  void readNodes41() {
    if (binary_) {
      const std::size_t blocks = binaryCount("the number of node blocks");
      const std::size_t total_pos = f_.pos();
      const std::size_t total = binaryCount("the number of nodes");
      f_.binary<std::uint64_t>("the smallest node tag");
      f_.binary<std::uint64_t>("the largest node tag");
      // A uint64 tag and 3 double coordinates per node.
      checkCountFits(f_, static_cast<long long>(total), total_pos, f_.pos(), 32, "nodes", true);
      xyz_.reserve(3 * total);
      std::vector<long long> tags;
      for (std::size_t b = 0; b < blocks; ++b) {
        const int dim = f_.binary<int>("an entity dimension");
        f_.binary<int>("an entity tag");
        const int parametric = f_.binary<int>("the parametric flag");
        const std::size_t block_pos = f_.pos();
        const std::size_t n = binaryCount("the number of nodes in a block");
        if (xyz_.size() / 3 + n > total) {
          f_.failAtByte(block_pos, "node blocks hold more than the " + std::to_string(total) + " nodes announced");
        }
        const std::size_t per_node = 3 + (parametric ? static_cast<std::size_t>(std::max(dim, 0)) : 0);
        f_.requireBytes(n * sizeof(std::uint64_t), "node tags");
        tags.resize(n);
        for (auto& t : tags) t = static_cast<long long>(f_.binary<std::uint64_t>("a node tag"));
        f_.requireBytes(n * per_node * sizeof(double), "node coordinates");
        for (std::size_t i = 0; i < n; ++i) {
          const std::size_t pos = f_.pos();
          const double x = f_.binary<double>("x"), y = f_.binary<double>("y"), z = f_.binary<double>("z");
          f_.setPos(f_.pos() + (per_node - 3) * sizeof(double));
          addNode(tags[i], x, y, z, pos, true);
        }
      }
      if (xyz_.size() / 3 != total) {
        f_.failAtByte(f_.pos(), "node blocks hold " + std::to_string(xyz_.size() / 3) + " nodes, " +
                                    std::to_string(total) + " announced");
      }
      return;
    }
    const long long blocks = countToken("the number of node blocks");
    const std::size_t total_pos = countPos();
    const long long total = countToken("the number of nodes");
    f_.integerToken("the smallest node tag");
    f_.integerToken("the largest node tag");
    checkCountFits(f_, total, total_pos, f_.pos(), 8, "nodes", false);  // "1\n" and "0 0 0\n"
    xyz_.reserve(static_cast<std::size_t>(3 * total));
    std::vector<long long> tags;
    for (long long b = 0; b < blocks; ++b) {
      const std::size_t block_header = countPos();
      const int dim = intValue(f_.integerToken("an entity dimension"), block_header, false, "entity dimension");
      f_.integerToken("an entity tag");
      const long long parametric = f_.integerToken("the parametric flag");
      const std::size_t block_pos = (f_.skipWhitespace(), f_.pos());
      const long long n = countToken("the number of nodes in a block");
      if (static_cast<long long>(xyz_.size() / 3) + n > total) {
        f_.failAtLine(block_pos, "node blocks hold more than the " + std::to_string(total) + " nodes announced");
      }
      const std::size_t per_node = 3 + (parametric ? static_cast<std::size_t>(std::max(dim, 0)) : 0);
      tags.resize(static_cast<std::size_t>(n));
      for (auto& t : tags) t = f_.integerToken("a node tag");
      for (long long i = 0; i < n; ++i) {
        std::size_t pos = 0;
        mesh_io_detail::splitTokens(nextLine(pos, "$Nodes"), false, tokens_);
        if (tokens_.size() != per_node) {
          f_.failAtLine(pos, "expected " + std::to_string(per_node) + " coordinates for node " +
                                 std::to_string(tags[i]) + ", got " + std::to_string(tokens_.size()));
        }
        addNode(tags[i], tokenReal(tokens_[0], pos, "a coordinate"), tokenReal(tokens_[1], pos, "a coordinate"),
                tokenReal(tokens_[2], pos, "a coordinate"), pos, false);
      }
    }
    if (static_cast<long long>(xyz_.size() / 3) != total) {
      f_.fail("node blocks hold " + std::to_string(xyz_.size() / 3) + " nodes, " + std::to_string(total) +
              " announced");
    }
  }

  int nodeIndex(long long tag, long long element, std::size_t pos, bool binary) const {
    const int index = node_index_.find(tag);
    if (index < 0) {
      failAt(pos, binary, "element " + std::to_string(element) + " refers to node " + std::to_string(tag) +
                              ", which is not in $Nodes");
    }
    return index;
  }

  void addTet(long long number, const long long* node_tags, int label, std::size_t pos, bool binary) {
    for (int k = 0; k < 4; ++k) tet_nodes_.push_back(nodeIndex(node_tags[k], number, pos, binary));
    labels_.push_back(label);
    numbers_.push_back(number);
  }

  // Node sets from named physical groups of dimension 0–2: the names of the groups an element is in.
  void namedGroups(int dim, const int* phys, std::size_t nphys, std::vector<const std::string*>& out) const {
    out.clear();
    if (dim > 2 || physical_names_.empty()) return;
    for (std::size_t i = 0; i < nphys; ++i) {
      auto it = physical_names_.find({dim, phys[i]});
      if (it != physical_names_.end()) out.push_back(&it->second);
    }
  }

  void addToGroups(const std::vector<const std::string*>& groups, long long number, const long long* node_tags,
                   int nn, std::size_t pos, bool binary) {
    for (const std::string* name : groups) {
      std::vector<int>& set = node_sets_[*name];
      for (int k = 0; k < nn; ++k) set.push_back(nodeIndex(node_tags[k], number, pos, binary));
    }
  }

  void readElements2() {
    const std::size_t count_pos = countPos();
    const long long n = countToken("the number of elements");
    if (binary_) f_.line();
    // Text: 4 tokens and their separators at least ("1 15 0 1\n": number, type, tag count, one
    // node); binary: an int number and one int node at least.
    checkCountFits(f_, n, count_pos, f_.pos(), 8, "elements", false);
    labels_.reserve(static_cast<std::size_t>(n));
    std::vector<long long> values;
    std::vector<const std::string*> groups;
    if (binary_) {
      long long done = 0;
      while (done < n) {
        const std::size_t header_pos = f_.pos();
        const int type = f_.binary<int>("an element type");
        const int follow = f_.binary<int>("an element count");
        const int ntags = f_.binary<int>("a tag count");
        const int nn = gmshNodesPerElement(type);
        if (nn < 0) f_.failAtByte(header_pos, "unknown element type " + std::to_string(type) + "; cannot skip it");
        if (follow < 0 || follow > n - done || ntags < 0 || ntags > 1000) {
          f_.failAtByte(header_pos, "implausible element block header (type " + std::to_string(type) + ", " +
                                        std::to_string(follow) + " elements, " + std::to_string(ntags) + " tags)");
        }
        const std::size_t per = static_cast<std::size_t>(1 + ntags + nn);
        f_.requireBytes(static_cast<std::size_t>(follow) * per * sizeof(int), "the binary element data");
        values.resize(per);
        for (int e = 0; e < follow; ++e) {
          const std::size_t pos = f_.pos();
          for (auto& v : values) v = f_.binary<int>("element data");
          handleElement2(type, ntags, values.data(), nn, pos, true, groups);
        }
        done += follow;
      }
      return;
    }
    for (long long i = 0; i < n; ++i) {
      std::size_t pos = 0;
      mesh_io_detail::splitTokens(nextLine(pos, "$Elements"), false, tokens_);
      if (tokens_.size() < 3) {
        f_.failAtLine(pos, "expected an element number, type and tag count, got " + std::to_string(tokens_.size()) +
                               " values");
      }
      const long long number = tokenInteger(tokens_[0], pos, "an element number");
      const long long type = tokenInteger(tokens_[1], pos, "an element type");
      const long long ntags = tokenInteger(tokens_[2], pos, "a tag count");
      // Compared without adding to ntags, which the file may set to 2^63 − 1.
      if (ntags < 0 || ntags > static_cast<long long>(tokens_.size()) - 3) {
        f_.failAtLine(pos, "element " + std::to_string(number) + " announces " + std::to_string(ntags) +
                               " tags but the line has " + std::to_string(tokens_.size() - 3) + " values after them");
      }
      const long long nn = static_cast<long long>(tokens_.size()) - 3 - ntags;
      if (type == kTet4 && nn != 4) {
        f_.failAtLine(pos, "expected 4 node indices for element " + std::to_string(number) + ", got " +
                               std::to_string(nn));
      }
      values.resize(static_cast<std::size_t>(1 + ntags + nn));
      values[0] = number;
      for (std::size_t k = 1; k < values.size(); ++k) {
        values[k] = tokenInteger(tokens_[k + 2], pos, k <= static_cast<std::size_t>(ntags) ? "an element tag" : "a node tag");
      }
      handleElement2(type, static_cast<int>(ntags), values.data(), static_cast<int>(nn), pos, false, groups);
    }
  }

  // values = number, tags…, node tags…
  void handleElement2(long long type, int ntags, const long long* values, int nn, std::size_t pos, bool binary,
                      std::vector<const std::string*>& groups) {
    const long long number = values[0];
    const long long* tags = values + 1;
    const long long* nodes = values + 1 + ntags;
    if (type == kTet4) {
      // Physical tag; files saved without physical groups carry 0 there, then the elementary tag.
      const long long tag = ntags == 0 ? 0 : (tags[0] != 0 || ntags == 1) ? tags[0] : tags[1];
      const int label = intValue(tag, pos, binary, ("region tag of element " + std::to_string(number)).c_str());
      addTet(number, nodes, label, pos, binary);
      return;
    }
    ++skipped_;
    if (ntags >= 1) {
      const int phys = intValue(tags[0], pos, binary, ("physical tag of element " + std::to_string(number)).c_str());
      namedGroups(gmshElementDimension(type), &phys, 1, groups);
      addToGroups(groups, number, nodes, nn, pos, binary);
    }
  }

  int volumeLabel(int entity_tag) const {
    auto it = entity_physicals_.find({3, entity_tag});
    return (it != entity_physicals_.end() && !it->second.empty()) ? it->second.front() : entity_tag;
  }

  void blockGroups(int dim, int entity_tag, std::vector<const std::string*>& groups) const {
    groups.clear();
    auto it = entity_physicals_.find({dim, entity_tag});
    if (it != entity_physicals_.end()) namedGroups(dim, it->second.data(), it->second.size(), groups);
  }

  void readElements41() {
    std::vector<long long> values;
    std::vector<const std::string*> groups;
    if (binary_) {
      const std::size_t blocks = binaryCount("the number of element blocks");
      const std::size_t total_pos = f_.pos();
      const std::size_t total = binaryCount("the number of elements");
      f_.binary<std::uint64_t>("the smallest element tag");
      f_.binary<std::uint64_t>("the largest element tag");
      // A uint64 tag and at least one uint64 node per element.
      checkCountFits(f_, static_cast<long long>(total), total_pos, f_.pos(), 16, "elements", true);
      labels_.reserve(total);
      std::size_t done = 0;
      for (std::size_t b = 0; b < blocks; ++b) {
        const std::size_t header_pos = f_.pos();
        const int dim = f_.binary<int>("an entity dimension");
        const int entity = f_.binary<int>("an entity tag");
        const int type = f_.binary<int>("an element type");
        const std::size_t n = binaryCount("the number of elements in a block");
        const int nn = gmshNodesPerElement(type);
        if (nn < 0) f_.failAtByte(header_pos, "unknown element type " + std::to_string(type) + "; cannot skip it");
        if (done + n > total) {
          f_.failAtByte(header_pos, "element blocks hold more than the " + std::to_string(total) +
                                        " elements announced");
        }
        const std::size_t per = static_cast<std::size_t>(1 + nn);
        f_.requireBytes(n * per * sizeof(std::uint64_t), "the binary element data");
        const int label = volumeLabel(entity);
        blockGroups(dim, entity, groups);
        values.resize(per);
        for (std::size_t e = 0; e < n; ++e) {
          const std::size_t pos = f_.pos();
          for (auto& v : values) v = static_cast<long long>(f_.binary<std::uint64_t>("element data"));
          if (type == kTet4) {
            addTet(values[0], values.data() + 1, label, pos, true);
          } else {
            ++skipped_;
            addToGroups(groups, values[0], values.data() + 1, nn, pos, true);
          }
        }
        done += n;
      }
      if (done != total) {
        f_.failAtByte(f_.pos(), "element blocks hold " + std::to_string(done) + " elements, " +
                                    std::to_string(total) + " announced");
      }
      return;
    }
    const long long blocks = countToken("the number of element blocks");
    const std::size_t total_pos = countPos();
    const long long total = countToken("the number of elements");
    f_.integerToken("the smallest element tag");
    f_.integerToken("the largest element tag");
    checkCountFits(f_, total, total_pos, f_.pos(), 4, "elements", false);  // "1 1\n"
    labels_.reserve(static_cast<std::size_t>(total));
    long long done = 0;
    for (long long b = 0; b < blocks; ++b) {
      const std::size_t header_pos = (f_.skipWhitespace(), f_.pos());
      const int dim = intValue(f_.integerToken("an entity dimension"), header_pos, false, "entity dimension");
      const int entity = intValue(f_.integerToken("an entity tag"), header_pos, false, "entity tag");
      const long long type = f_.integerToken("an element type");
      const long long n = countToken("the number of elements in a block");
      if (done + n > total) {
        f_.failAtLine(header_pos, "element blocks hold more than the " + std::to_string(total) + " elements announced");
      }
      const int label = volumeLabel(entity);
      blockGroups(dim, entity, groups);
      for (long long e = 0; e < n; ++e) {
        std::size_t pos = 0;
        mesh_io_detail::splitTokens(nextLine(pos, "$Elements"), false, tokens_);
        if (tokens_.empty()) f_.failAtLine(pos, "expected an element");
        const long long number = tokenInteger(tokens_[0], pos, "an element number");
        const long long nn = static_cast<long long>(tokens_.size()) - 1;
        if (type == kTet4 && nn != 4) {
          f_.failAtLine(pos, "expected 4 node indices for element " + std::to_string(number) + ", got " +
                                 std::to_string(nn));
        }
        if (type != kTet4 && groups.empty()) {
          ++skipped_;
          continue;
        }
        values.resize(static_cast<std::size_t>(nn));
        for (long long k = 0; k < nn; ++k) values[k] = tokenInteger(tokens_[k + 1], pos, "a node tag");
        if (type == kTet4) {
          addTet(number, values.data(), label, pos, false);
        } else {
          ++skipped_;
          addToGroups(groups, number, values.data(), static_cast<int>(nn), pos, false);
        }
      }
      done += n;
    }
    if (done != total) {
      f_.fail("element blocks hold " + std::to_string(done) + " elements, " + std::to_string(total) + " announced");
    }
  }

  TetMesh build() {
    const Eigen::Index n = static_cast<Eigen::Index>(xyz_.size() / 3);
    Points nodes = Eigen::Map<const Points>(xyz_.data(), n, 3);
    const Eigen::Index t = static_cast<Eigen::Index>(labels_.size());
    Tets tets = Eigen::Map<const Tets>(tet_nodes_.data(), t, 4);
    mesh_io_detail::sortByElementNumber(f_.path(), numbers_, tets, labels_);
    TetMesh mesh = mesh_io_detail::makeMesh(f_.path(), std::move(nodes), std::move(tets), std::move(labels_));
    for (auto& [name, set] : node_sets_) mesh_io_detail::addNodeSet(f_.path(), mesh, name, std::move(set));
    return mesh;
  }

  FileCursor f_;
  double unit_;
  Version version_ = Version::kUnknown;
  bool binary_ = false;
  bool have_nodes_ = false;
  bool have_elements_ = false;

  std::vector<double> xyz_;
  NumberMap node_index_;
  std::vector<int> tet_nodes_;
  std::vector<int> labels_;
  std::vector<long long> numbers_;
  std::size_t skipped_ = 0;
  std::vector<std::string_view> tokens_;

  std::map<std::pair<int, int>, std::string> physical_names_;         // (dim, physical tag) → name
  std::map<std::pair<int, int>, std::vector<int>> entity_physicals_;  // (dim, entity tag) → physical tags
  std::map<std::string, std::vector<int>> node_sets_;
};

}  // namespace

TetMesh readGmsh(const std::string& path, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "readGmsh");
  return GmshReader(path, length_unit_m).read();
}

}  // namespace breast_sim::core
