// TetGen .node / .ele reader and writer.
// Format reference: TetGen user's manual (H. Si), section 5.2 "File formats".

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "breast_sim/core/mesh/mesh_io_detail.h"

namespace breast_sim::core {
namespace {

using mesh_io_detail::appendInteger;
using mesh_io_detail::appendReal;
using mesh_io_detail::FileCursor;

/// `path` without a .node / .ele extension (case-insensitive).
std::string tetgenBase(const std::string& path) {
  for (const char* ext : {".node", ".ele"}) {
    const std::size_t n = std::char_traits<char>::length(ext);
    if (path.size() > n) {
      std::string tail = path.substr(path.size() - n);
      std::transform(tail.begin(), tail.end(), tail.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
      if (tail == ext) return path.substr(0, path.size() - n);
    }
  }
  throw std::runtime_error(path + ": a TetGen path must end in .node or .ele");
}

/// Reads the whitespace-separated values of the next line that holds any, after removing '#' comments.
/// Returns false at the end of the file.
bool nextDataLine(FileCursor& f, std::vector<std::string_view>& tokens, std::size_t& pos) {
  while (true) {
    f.skipWhitespace();
    if (f.atEnd()) return false;
    pos = f.pos();
    std::string_view line = f.line();
    const std::size_t hash = line.find('#');
    if (hash != std::string_view::npos) line = line.substr(0, hash);
    mesh_io_detail::splitTokens(line, false, tokens);
    if (!tokens.empty()) return true;
  }
}

long long integerAt(const FileCursor& f, std::string_view t, std::size_t pos, const char* what) {
  long long v = 0;
  if (!mesh_io_detail::parseInteger(t, v)) f.failAtLine(pos, std::string("expected ") + what + ", got '" + std::string(t) + "'");
  return v;
}

double realAt(const FileCursor& f, std::string_view t, std::size_t pos, const char* what) {
  double v = 0;
  if (!mesh_io_detail::parseReal(t, v)) f.failAtLine(pos, std::string("expected ") + what + ", got '" + std::string(t) + "'");
  return v;
}

}  // namespace

TetMesh readTetGen(const std::string& path, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "readTetGen");
  const std::string base = tetgenBase(path);
  std::vector<std::string_view> tokens;
  std::size_t pos = 0;

  // .node: "<#points> <dimension=3> <#attributes> <boundary markers 0|1>", then
  // "<number> <x> <y> <z> [attributes] [marker]".
  FileCursor nf(base + ".node");
  if (!nextDataLine(nf, tokens, pos)) nf.fail("empty file: expected the header '<#points> 3 <#attributes> <0|1>'");
  const long long n = integerAt(nf, tokens[0], pos, "the number of points");
  if (n < 0 || n > std::numeric_limits<int>::max()) nf.failAtLine(pos, "implausible number of points " + std::to_string(n));
  if (tokens.size() >= 2 && integerAt(nf, tokens[1], pos, "the dimension") != 3) {
    nf.failAtLine(pos, "only 3-dimensional .node files are supported, got dimension " + std::string(tokens[1]));
  }
  // Checked before Points(n, 3) allocates: "1 0 0 0\n" is the shortest point line.
  mesh_io_detail::checkCountFits(nf, n, pos, nf.pos(), 8, "points", false);
  Points nodes(n, 3);
  mesh_io_detail::NumberMap node_index;
  for (long long i = 0; i < n; ++i) {
    if (!nextDataLine(nf, tokens, pos)) {
      nf.fail("reached the end of the file after " + std::to_string(i) + " of " + std::to_string(n) + " points");
    }
    if (tokens.size() < 4) {
      nf.failAtLine(pos, "expected a point number and 3 coordinates, got " + std::to_string(tokens.size()) + " values");
    }
    const long long number = integerAt(nf, tokens[0], pos, "a point number");
    if (!node_index.insert(number, static_cast<int>(i))) {
      nf.failAtLine(pos, "point number " + std::to_string(number) + " appears twice");
    }
    for (int k = 0; k < 3; ++k) nodes(i, k) = realAt(nf, tokens[1 + k], pos, "a coordinate") * length_unit_m;
  }

  // .ele: "<#tetrahedra> <nodes per tetrahedron> <#attributes>", then
  // "<number> <n1> <n2> <n3> <n4> [attributes]"; node numbers refer to .node's numbers.
  FileCursor ef(base + ".ele");
  if (!nextDataLine(ef, tokens, pos)) ef.fail("empty file: expected the header '<#tetrahedra> 4 <#attributes>'");
  const long long t = integerAt(ef, tokens[0], pos, "the number of tetrahedra");
  if (t < 0 || t > std::numeric_limits<int>::max()) ef.failAtLine(pos, "implausible number of tetrahedra " + std::to_string(t));
  const long long per = tokens.size() >= 2 ? integerAt(ef, tokens[1], pos, "the nodes per tetrahedron") : 4;
  if (per != 4) ef.failAtLine(pos, std::to_string(per) + "-node tetrahedra are not supported, only 4-node");
  const long long nattr = tokens.size() >= 3 ? integerAt(ef, tokens[2], pos, "the number of attributes") : 0;
  // Checked before the arrays below allocate: "1 1 2 3 4\n" is the shortest tetrahedron line.
  mesh_io_detail::checkCountFits(ef, t, pos, ef.pos(), 10, "tetrahedra", false);
  Tets tets(t, 4);
  std::vector<int> labels(static_cast<std::size_t>(t), 0);
  std::vector<long long> numbers(static_cast<std::size_t>(t));
  for (long long e = 0; e < t; ++e) {
    if (!nextDataLine(ef, tokens, pos)) {
      ef.fail("reached the end of the file after " + std::to_string(e) + " of " + std::to_string(t) + " tetrahedra");
    }
    const long long number = integerAt(ef, tokens[0], pos, "a tetrahedron number");
    if (static_cast<long long>(tokens.size()) < 5 + std::min<long long>(nattr, 1)) {
      ef.failAtLine(pos, "expected 4 node indices" + std::string(nattr > 0 ? " and a region attribute" : "") +
                             " for tetrahedron " + std::to_string(number) + ", got " + std::to_string(tokens.size() - 1) +
                             " values");
    }
    numbers[e] = number;
    for (int k = 0; k < 4; ++k) {
      const long long v = integerAt(ef, tokens[1 + k], pos, "a node index");
      const int index = node_index.find(v);
      if (index < 0) {
        ef.failAtLine(pos, "tetrahedron " + std::to_string(number) + " refers to node " + std::to_string(v) +
                               ", which is not in " + base + ".node");
      }
      tets(e, k) = index;
    }
    if (nattr > 0) {
      // TetGen writes region attributes as reals ("1" or "1.0e+00"); labels are integers.
      const double a = realAt(ef, tokens[5], pos, "a region attribute");
      if (a != std::round(a) || std::abs(a) > std::numeric_limits<int>::max()) {
        ef.failAtLine(pos, "region attribute of tetrahedron " + std::to_string(number) + " is not an integer: " +
                               std::string(tokens[5]));
      }
      labels[e] = static_cast<int>(a);
    }
  }
  if (t == 0) throw std::runtime_error(ef.path() + ": no tetrahedra in the file");
  mesh_io_detail::sortByElementNumber(ef.path(), numbers, tets, labels);
  return mesh_io_detail::makeMesh(ef.path(), std::move(nodes), std::move(tets), std::move(labels));
}

void writeTetGen(const std::string& path, const TetMesh& mesh, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeTetGen");
  const std::string base = tetgenBase(path);
  std::string out;
  out.reserve(64 * static_cast<std::size_t>(mesh.numNodes()) + 64);
  out += "# breast_sim tetrahedral mesh: <#points> <dimension> <#attributes> <boundary markers>\n";
  appendInteger(out, mesh.numNodes());
  out += " 3 0 0\n";
  for (int i = 0; i < mesh.numNodes(); ++i) {
    appendInteger(out, i + 1);
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      appendReal(out, mesh.nodes()(i, k) / length_unit_m);
    }
    out += '\n';
  }
  mesh_io_detail::writeFile(base + ".node", out);

  out.clear();
  out += "# <#tetrahedra> <nodes per tetrahedron> <#attributes: 1, the region label>\n";
  appendInteger(out, mesh.numTets());
  out += " 4 1\n";
  for (int e = 0; e < mesh.numTets(); ++e) {
    appendInteger(out, e + 1);
    for (int k = 0; k < 4; ++k) {
      out += ' ';
      appendInteger(out, mesh.tets()(e, k) + 1);
    }
    out += ' ';
    appendInteger(out, mesh.regionLabels()[e]);
    out += '\n';
  }
  mesh_io_detail::writeFile(base + ".ele", out);
}

}  // namespace breast_sim::core
