// Abaqus / CalculiX .inp reader and writer for linear tetrahedra (C3D4).
// Format reference: Abaqus Keywords Reference (*NODE, *ELEMENT, *NSET, *ELSET); CalculiX CrunchiX
// User's Manual, section 7 "Input deck format".

#include <algorithm>
#include <cctype>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/mesh/mesh_io_detail.h"

namespace breast_sim::core {
namespace {

using mesh_io_detail::appendInteger;
using mesh_io_detail::appendReal;
using mesh_io_detail::FileCursor;

std::string upper(std::string_view s) {
  std::string u(s);
  std::transform(u.begin(), u.end(), u.begin(), [](unsigned char c) { return static_cast<char>(std::toupper(c)); });
  return u;
}

std::string_view trim(std::string_view s) {
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.front()))) s.remove_prefix(1);
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.remove_suffix(1);
  return s;
}

struct Keyword {
  std::string name;                           // upper case, without '*'
  std::map<std::string, std::string> params;  // upper-case key → value as written (flags map to "")
};

Keyword parseKeyword(std::string_view line) {
  std::vector<std::string_view> fields;
  mesh_io_detail::splitTokens(line.substr(1), true, fields);
  Keyword kw;
  if (fields.empty()) return kw;
  kw.name = upper(fields[0]);
  for (std::size_t i = 1; i < fields.size(); ++i) {
    const std::size_t eq = fields[i].find('=');
    std::string key = upper(trim(fields[i].substr(0, eq)));
    std::string value = eq == std::string_view::npos ? "" : std::string(trim(fields[i].substr(eq + 1)));
    if (value.size() >= 2 && value.front() == '"' && value.back() == '"') value = value.substr(1, value.size() - 2);
    if (!key.empty()) kw.params[key] = value;
  }
  return kw;
}

/// "REGION_29" → 29, "EB-3" → 3, "R_-2" → −2 (a '-' counts as a sign only after '_' or at the start).
bool integerSuffix(const std::string& name, int& value) {
  std::size_t start = name.size();
  while (start > 0 && std::isdigit(static_cast<unsigned char>(name[start - 1]))) --start;
  const std::size_t digits = name.size() - start;
  if (digits == 0 || digits > 9) return false;
  long long v = std::stoll(name.substr(start));
  if (start > 0 && name[start - 1] == '-' && (start == 1 || name[start - 2] == '_')) v = -v;
  value = static_cast<int>(v);
  return true;
}

/// Most numbers all node and element sets of a file may hold together (duplicates merged): 2^27,
/// 2 GiB of set entries. Each set alone holds at most as many distinct numbers as the file has lines
/// (a node or an element needs a line of its own), so this bounds only files with very many sets.
constexpr std::size_t kMaxSetNumbers = std::size_t{1} << 27;

/// The numbers of one set as the file lists them. Duplicates are merged whenever the list has
/// doubled since the last merge, so a set that copies sets ("A = A, A" again and again) grows to
/// its distinct numbers, not exponentially.
template <typename Entry>
struct SetList {
  std::vector<Entry> items;
  std::size_t merged_size = 0;
};

long long entryNumber(long long v) { return v; }

std::size_t lineCount(const std::string& data) {
  const auto breaks = static_cast<std::size_t>(std::count(data.begin(), data.end(), '\n'));
  return breaks + (!data.empty() && data.back() != '\n' ? 1 : 0);
}
long long entryNumber(const std::pair<long long, std::size_t>& v) { return v.first; }

class InpReader {
 public:
  InpReader(const std::string& path, double unit)
      : f_(path), unit_(unit), lines_(lineCount(f_.data())) {}

  TetMesh read() {
    while (!f_.atEnd()) {
      const std::size_t pos = f_.pos();
      const std::string_view line = trim(f_.line());
      if (line.empty() || line.substr(0, 2) == "**") continue;
      if (line.front() == '*') {
        if (!pending_.empty()) failPendingElement();
        keyword(parseKeyword(line), pos);
      } else {
        data(line, pos);
      }
    }
    if (!pending_.empty()) failPendingElement();
    return build();
  }

 private:
  enum class Mode { kNone, kSkip, kNode, kTet, kNset, kElset };

  void keyword(const Keyword& kw, std::size_t pos) {
    auto param = [&](const char* key) -> const std::string* {
      auto it = kw.params.find(key);
      return it == kw.params.end() ? nullptr : &it->second;
    };
    generate_ = param("GENERATE") != nullptr;
    if (kw.name == "NODE") {
      mode_ = Mode::kNode;
      const std::string* nset = param("NSET");
      current_nset_ = nset && !nset->empty() ? &nsets_[*nset] : nullptr;
      if (current_nset_) current_nset_name_ = *nset;
    } else if (kw.name == "ELEMENT") {
      const std::string* type = param("TYPE");
      if (!type || type->empty()) f_.failAtLine(pos, "*ELEMENT without TYPE=");
      if (upper(*type) != "C3D4") {
        mode_ = Mode::kSkip;
        skipped_types_.push_back(*type);
        return;
      }
      mode_ = Mode::kTet;
      const std::string* elset = param("ELSET");
      const bool labelled = elset && !elset->empty();
      current_set_ = labelled ? setId(*elset) : -1;
      current_elset_ = labelled ? &elset_members_[*elset] : nullptr;
      if (current_elset_) current_elset_name_ = *elset;
    } else if (kw.name == "NSET") {
      const std::string* name = param("NSET");
      if (!name || name->empty()) f_.failAtLine(pos, "*NSET without NSET=");
      mode_ = Mode::kNset;
      current_nset_ = &nsets_[*name];
      current_nset_name_ = *name;
    } else if (kw.name == "ELSET") {
      const std::string* name = param("ELSET");
      if (!name || name->empty()) f_.failAtLine(pos, "*ELSET without ELSET=");
      mode_ = Mode::kElset;
      elset_assignments_.push_back({setId(*name), {}});
      current_elset_ = &elset_members_[*name];
      current_elset_name_ = *name;
    } else if (kw.name == "INCLUDE") {
      f_.failAtLine(pos, "*INCLUDE is not supported; merge the included file into this one");
    } else {
      mode_ = Mode::kSkip;  // *HEADING, *MATERIAL, *STEP, … and their data lines
    }
  }

  /// Index of a set name among the names that can label elements, in order of appearance. Labels
  /// are given in build(), when every name is known (see setLabels()).
  int setId(const std::string& name) {
    const auto [it, inserted] = set_id_.emplace(name, static_cast<int>(set_names_.size()));
    if (inserted) set_names_.push_back(name);
    return it->second;
  }

  /// The label of each set name: the integer a name ends with, else its rank among the names
  /// without one, counted on from the largest such integer (0 if none is positive). Ranking from 1
  /// instead would let "FAT" (rank 1) and "REGION_1" share label 1 without a word.
  std::vector<int> setLabels() const {
    std::vector<int> labels(set_names_.size(), 0);
    std::vector<bool> numbered(set_names_.size(), false);
    long long largest = 0;
    for (std::size_t i = 0; i < set_names_.size(); ++i) {
      int value = 0;
      if (integerSuffix(set_names_[i], value)) {
        labels[i] = value;
        numbered[i] = true;
        largest = std::max<long long>(largest, value);
      }
    }
    long long next = largest;  // below 10^9 (at most 9 digits), so the ranks fit in an int
    for (std::size_t i = 0; i < set_names_.size(); ++i) {
      if (!numbered[i]) labels[i] = static_cast<int>(++next);
    }
    return labels;
  }

  long long integer(std::string_view t, std::size_t pos, const char* what) const {
    long long v = 0;
    if (!mesh_io_detail::parseInteger(t, v)) f_.failAtLine(pos, std::string("expected ") + what + ", got '" + std::string(t) + "'");
    return v;
  }

  void data(std::string_view line, std::size_t pos) {
    switch (mode_) {
      case Mode::kNone: f_.failAtLine(pos, "data line before any keyword");
      case Mode::kSkip: return;
      case Mode::kNode: return nodeLine(line, pos);
      case Mode::kTet: return elementLine(line, pos);
      case Mode::kNset:
      case Mode::kElset: return setLine(line, pos);
    }
  }

  void nodeLine(std::string_view line, std::size_t pos) {
    mesh_io_detail::splitTokens(line, true, tokens_);
    const long long number = integer(tokens_[0], pos, "a node number");
    double x[3] = {0, 0, 0};  // omitted coordinates are 0 in Abaqus
    for (std::size_t k = 0; k < 3 && k + 1 < tokens_.size(); ++k) {
      if (tokens_[k + 1].empty()) continue;
      if (!mesh_io_detail::parseReal(tokens_[k + 1], x[k])) {
        f_.failAtLine(pos, "expected a coordinate of node " + std::to_string(number) + ", got '" +
                               std::string(tokens_[k + 1]) + "'");
      }
    }
    const int index = static_cast<int>(xyz_.size() / 3);
    if (!node_index_.insert(number, index)) f_.failAtLine(pos, "node " + std::to_string(number) + " is defined twice");
    for (double v : x) xyz_.push_back(v * unit_);
    if (current_nset_) addToSet(*current_nset_, std::pair<long long, std::size_t>{number, pos}, "node", current_nset_name_, pos);
  }

  void elementLine(std::string_view line, std::size_t pos) {
    // A line ending in a comma continues on the next one.
    const bool continues = line.back() == ',';
    if (pending_.empty()) pending_pos_ = pos;
    mesh_io_detail::splitTokens(line, true, tokens_);
    for (std::string_view t : tokens_) {
      if (!t.empty()) pending_.push_back(integer(t, pos, pending_.empty() ? "an element number" : "a node number"));
    }
    if (continues && pending_.size() < 5) return;
    if (pending_.size() != 5) failPendingElement();
    element_numbers_.push_back(pending_[0]);
    element_nodes_.insert(element_nodes_.end(), pending_.begin() + 1, pending_.end());
    element_pos_.push_back(pending_pos_);
    element_sets_.push_back(current_set_);
    if (current_elset_) addToSet(*current_elset_, pending_[0], "element", current_elset_name_, pending_pos_);
    pending_.clear();
  }

  [[noreturn]] void failPendingElement() const {
    f_.failAtLine(pending_pos_, "expected 4 node indices for C3D4 element " +
                                    (pending_.empty() ? std::string("?") : std::to_string(pending_[0])) + ", got " +
                                    std::to_string(pending_.empty() ? 0 : pending_.size() - 1));
  }

  /// Merges the duplicates of a set whose list has doubled since the last merge; then checks the
  /// limits (a set's distinct numbers against the file's lines, all sets against kMaxSetNumbers).
  template <typename Entry>
  void grew(SetList<Entry>& set, const char* kind, const std::string& name, std::size_t pos, bool force = false) {
    if (!force && set.items.size() <= 2 * set.merged_size + 1024) return;
    const std::size_t before = set.items.size();
    std::sort(set.items.begin(), set.items.end());  // by number, then by line: the first line is kept
    set.items.erase(std::unique(set.items.begin(), set.items.end(),
                                [](const Entry& a, const Entry& b) { return entryNumber(a) == entryNumber(b); }),
                    set.items.end());
    set.merged_size = set.items.size();
    set_numbers_ -= before - set.items.size();
    if (set.items.size() > lines_) {
      f_.failAtLine(pos, std::string(kind) + " set '" + name + "' holds " + std::to_string(set.items.size()) +
                             " distinct numbers, more " + kind + "s than the file's " + std::to_string(lines_) +
                             " lines can define");
    }
  }

  template <typename Entry>
  void addToSet(SetList<Entry>& set, const Entry& entry, const char* kind, const std::string& name, std::size_t pos) {
    set.items.push_back(entry);
    ++set_numbers_;
    grew(set, kind, name, pos);
    checkSetTotal(pos);
  }

  void checkSetTotal(std::size_t pos) const {
    if (set_numbers_ > kMaxSetNumbers) {
      f_.failAtLine(pos, "the node and element sets hold more than " + std::to_string(kMaxSetNumbers) +
                             " numbers together (duplicates merged); split the file's sets");
    }
  }

  void setLine(std::string_view line, std::size_t pos) {
    mesh_io_detail::splitTokens(line, true, tokens_);
    const bool nset = mode_ == Mode::kNset;
    const char* kind = nset ? "node" : "element";
    const std::string& name = nset ? current_nset_name_ : current_elset_name_;
    SetList<long long>* elset_assignment = nset ? nullptr : &elset_assignments_.back().second;
    const auto add = [&](long long v) {
      if (nset) {
        addToSet(*current_nset_, std::pair<long long, std::size_t>{v, pos}, kind, name, pos);
      } else {
        addToSet(*current_elset_, v, kind, name, pos);
        addToSet(*elset_assignment, v, kind, name, pos);
      }
    };
    if (generate_) {
      if (tokens_.size() < 2 || tokens_.size() > 3) f_.failAtLine(pos, "expected 'first, last[, increment]' after GENERATE");
      const long long first = integer(tokens_[0], pos, "the first number");
      const long long last = integer(tokens_[1], pos, "the last number");
      const long long step = tokens_.size() == 3 ? integer(tokens_[2], pos, "the increment") : 1;
      const std::string range = std::to_string(first) + ", " + std::to_string(last) + ", " + std::to_string(step);
      if (step <= 0 || last < first) {
        f_.failAtLine(pos, "bad GENERATE range " + range + ": expected first <= last and an increment >= 1");
      }
      // How many numbers, in unsigned arithmetic: last − first can exceed a long long, and the count
      // 2^64 (first = −2^63, last = 2^63 − 1) an unsigned one.
      const unsigned long long span = static_cast<unsigned long long>(last) - static_cast<unsigned long long>(first);
      const unsigned long long steps = span / static_cast<unsigned long long>(step);
      if (steps >= lines_) {
        f_.failAtLine(pos, "GENERATE range " + range + " names " + (steps == ~0ULL ? std::string("2^64") : std::to_string(steps + 1)) +
                               " " + kind + "s, more than the file's " + std::to_string(lines_) + " lines can define");
      }
      const unsigned long long count = steps + 1;
      for (unsigned long long k = 0; k < count; ++k) {
        add(static_cast<long long>(static_cast<unsigned long long>(first) + k * static_cast<unsigned long long>(step)));
      }
      return;
    }
    for (std::string_view t : tokens_) {
      if (t.empty()) continue;
      long long v = 0;
      if (mesh_io_detail::parseInteger(t, v)) {
        add(v);
        continue;
      }
      // The name of an earlier set of the same kind: its distinct numbers are copied.
      const std::string other(t);
      if (nset) {
        auto it = nsets_.find(other);
        if (it == nsets_.end() || &it->second == current_nset_) {
          f_.failAtLine(pos, "expected a node number or the name of an earlier node set, got '" + other + "'");
        }
        grew(it->second, kind, other, pos, true);
        const auto copy = it->second.items;
        for (const auto& entry : copy) add(entry.first);
      } else {
        auto it = elset_members_.find(other);
        if (it == elset_members_.end() || &it->second == current_elset_) {
          f_.failAtLine(pos, "expected an element number or the name of an earlier element set, got '" + other + "'");
        }
        grew(it->second, kind, other, pos, true);
        const auto copy = it->second.items;
        for (long long v2 : copy) add(v2);
      }
    }
  }

  TetMesh build() {
    const std::size_t t = element_numbers_.size();
    if (t == 0) {
      std::string skipped;
      for (const auto& s : skipped_types_) skipped += (skipped.empty() ? "" : ", ") + s;
      throw std::runtime_error(f_.path() + ": no C3D4 elements in the file" +
                               (skipped.empty() ? std::string() : " (skipped element types: " + skipped + ")"));
    }
    const Eigen::Index n = static_cast<Eigen::Index>(xyz_.size() / 3);
    Points nodes = Eigen::Map<const Points>(xyz_.data(), n, 3);
    Tets tets(static_cast<Eigen::Index>(t), 4);
    for (std::size_t e = 0; e < t; ++e) {
      for (int k = 0; k < 4; ++k) {
        const long long v = element_nodes_[4 * e + k];
        const int index = node_index_.find(v);
        if (index < 0) {
          f_.failAtLine(element_pos_[e], "element " + std::to_string(element_numbers_[e]) + " refers to node " +
                                             std::to_string(v) + ", which no *NODE line defines");
        }
        tets(static_cast<Eigen::Index>(e), k) = index;
      }
    }
    // *ELSET blocks label the elements that no ELSET= of their *ELEMENT (nor an earlier *ELSET) labelled.
    if (!elset_assignments_.empty()) {
      mesh_io_detail::NumberMap element_index;
      for (std::size_t e = 0; e < t; ++e) {
        if (!element_index.insert(element_numbers_[e], static_cast<int>(e))) {
          f_.failAtLine(element_pos_[e], "element " + std::to_string(element_numbers_[e]) + " is defined twice");
        }
      }
      for (const auto& [set, members] : elset_assignments_) {
        for (long long number : members.items) {
          const int e = element_index.find(number);
          if (e >= 0 && element_sets_[e] < 0) {  // other numbers belong to skipped element types
            element_sets_[e] = set;
          }
        }
      }
    }
    const std::vector<int> set_labels = setLabels();
    std::vector<int> labels(t, 0);
    for (std::size_t e = 0; e < t; ++e) {
      if (element_sets_[e] >= 0) labels[e] = set_labels[static_cast<std::size_t>(element_sets_[e])];
    }
    mesh_io_detail::sortByElementNumber(f_.path(), element_numbers_, tets, labels);
    TetMesh mesh = mesh_io_detail::makeMesh(f_.path(), std::move(nodes), std::move(tets), std::move(labels));
    for (const auto& [name, entries] : nsets_) {
      std::vector<int> set;
      set.reserve(entries.items.size());
      for (const auto& [number, pos] : entries.items) {
        const int index = node_index_.find(number);
        if (index < 0) {
          f_.failAtLine(pos, "node set '" + name + "' refers to node " + std::to_string(number) +
                                 ", which no *NODE line defines");
        }
        set.push_back(index);
      }
      mesh_io_detail::addNodeSet(f_.path(), mesh, name, std::move(set));
    }
    return mesh;
  }

  FileCursor f_;
  double unit_;
  Mode mode_ = Mode::kNone;
  bool generate_ = false;
  std::vector<std::string_view> tokens_;

  std::vector<double> xyz_;
  mesh_io_detail::NumberMap node_index_;

  std::vector<long long> element_numbers_;
  std::vector<long long> element_nodes_;  // 4 node numbers per element, resolved at the end
  std::vector<std::size_t> element_pos_;
  std::vector<int> element_sets_;  // index into set_names_, -1 for an element in no set
  std::vector<long long> pending_;  // element being read, possibly over several lines
  std::size_t pending_pos_ = 0;
  int current_set_ = -1;
  std::vector<std::string> skipped_types_;

  std::vector<std::string> set_names_;  // names that can label elements, in order of appearance
  std::map<std::string, int> set_id_;   // name → index into set_names_
  std::map<std::string, SetList<long long>> elset_members_;
  SetList<long long>* current_elset_ = nullptr;
  std::string current_elset_name_;
  std::vector<std::pair<int, SetList<long long>>> elset_assignments_;  // (set index, members)

  // name → (node number, position of the line that named it)
  std::map<std::string, SetList<std::pair<long long, std::size_t>>> nsets_;
  SetList<std::pair<long long, std::size_t>>* current_nset_ = nullptr;
  std::string current_nset_name_;

  std::size_t lines_;           // a set holds at most this many distinct numbers
  std::size_t set_numbers_ = 0;  // held by all sets together
};

void checkSetName(const std::string& name) {
  const bool bad = name.empty() || name.front() == '*' ||
                   std::any_of(name.begin(), name.end(), [](unsigned char c) { return c == ',' || c == '=' || std::isspace(c); });
  if (bad) {
    throw std::invalid_argument("writeAbaqusInp: node set name '" + name +
                                "' cannot be written to .inp (empty, starts with '*', or holds ',', '=' or a space)");
  }
}

}  // namespace

TetMesh readAbaqusInp(const std::string& path, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "readAbaqusInp");
  return InpReader(path, length_unit_m).read();
}

void writeAbaqusInp(const std::string& path, const TetMesh& mesh, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeAbaqusInp");
  for (const auto& kv : mesh.nodeSets()) checkSetName(kv.first);
  std::string out;
  out.reserve(64 * static_cast<std::size_t>(mesh.numNodes() + mesh.numTets()) + 1024);
  out += "** breast_sim tetrahedral mesh; one length unit = ";
  appendReal(out, length_unit_m);
  out += " m\n*HEADING\nbreast_sim tetrahedral mesh\n*NODE\n";
  for (int i = 0; i < mesh.numNodes(); ++i) {
    appendInteger(out, i + 1);
    for (int k = 0; k < 3; ++k) {
      out += ", ";
      appendReal(out, mesh.nodes()(i, k) / length_unit_m);
    }
    out += '\n';
  }
  std::map<int, std::vector<int>> by_label;
  for (int e = 0; e < mesh.numTets(); ++e) by_label[mesh.regionLabels()[e]].push_back(e);
  for (const auto& [label, tets] : by_label) {
    out += "*ELEMENT, TYPE=C3D4, ELSET=REGION_" + std::to_string(label) + "\n";
    for (int e : tets) {
      appendInteger(out, e + 1);
      for (int k = 0; k < 4; ++k) {
        out += ", ";
        appendInteger(out, mesh.tets()(e, k) + 1);
      }
      out += '\n';
    }
  }
  for (const auto& [name, nodes] : mesh.nodeSets()) {
    out += "*NSET, NSET=" + name + "\n";
    for (std::size_t i = 0; i < nodes.size(); ++i) {
      appendInteger(out, nodes[i] + 1);
      out += (i % 16 == 15 || i + 1 == nodes.size()) ? "\n" : ", ";  // at most 16 entries per data line
    }
  }
  mesh_io_detail::writeFile(path, out);
}

}  // namespace breast_sim::core
