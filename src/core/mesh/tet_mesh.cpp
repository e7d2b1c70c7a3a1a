#include "breast_sim/core/mesh/tet_mesh.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <string>
#include <stdexcept>
#include <unordered_map>
#include <vector>

#include <Eigen/Geometry>

namespace breast_sim::core {

double signedTetVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                       const Eigen::Vector3d& d) {
  return (b - a).dot((c - a).cross(d - a)) / 6.0;
}

TetMesh::TetMesh(Points nodes_m, Tets tets, std::vector<int> region_labels)
    : nodes_(std::move(nodes_m)), tets_(std::move(tets)), region_labels_(std::move(region_labels)) {
  const int n = numNodes();
  for (int i = 0; i < n; ++i) {
    if (!nodes_.row(i).allFinite()) {
      std::ostringstream msg;
      msg << "TetMesh: node " << i << " has a non-finite coordinate (" << nodes_.row(i) << ")";
      throw std::invalid_argument(msg.str());
    }
  }
  if (region_labels_.empty()) region_labels_.assign(tets_.rows(), 0);
  if (static_cast<Eigen::Index>(region_labels_.size()) != tets_.rows()) {
    throw std::invalid_argument("TetMesh: " + std::to_string(region_labels_.size()) +
                                " region labels given for " + std::to_string(tets_.rows()) +
                                " tetrahedra; give one per tetrahedron or none");
  }
  for (int t = 0; t < numTets(); ++t) {
    for (int k = 0; k < 4; ++k) {
      const int v = tets_(t, k);
      if (v < 0 || v >= n) {
        throw std::invalid_argument("TetMesh: tetrahedron " + std::to_string(t) + " refers to node " +
                                    std::to_string(v) + ", but the mesh has " + std::to_string(n) +
                                    " nodes (indices are 0-based)");
      }
    }
    std::array<int, 4> s{tets_(t, 0), tets_(t, 1), tets_(t, 2), tets_(t, 3)};
    std::sort(s.begin(), s.end());
    if (std::adjacent_find(s.begin(), s.end()) != s.end()) {
      throw std::invalid_argument("TetMesh: tetrahedron " + std::to_string(t) +
                                  " repeats a node; it has zero volume");
    }
    const double vol = signedTetVolume(nodes_.row(tets_(t, 0)), nodes_.row(tets_(t, 1)),
                                       nodes_.row(tets_(t, 2)), nodes_.row(tets_(t, 3)));
    if (vol == 0.0 || !std::isfinite(vol)) {
      throw std::invalid_argument("TetMesh: tetrahedron " + std::to_string(t) +
                                  " has zero volume (its four nodes are coplanar)");
    }
    if (vol < 0.0) std::swap(tets_(t, 2), tets_(t, 3));
  }
  boundary_ = extractBoundary(tets_, nodes_);
  volume_m3_ = tetVolumes().sum();
}

void TetMesh::setNodeSet(const std::string& name, std::vector<int> node_indices) {
  if (name.empty()) throw std::invalid_argument("TetMesh::setNodeSet: the node-set name is empty");
  for (int v : node_indices) {
    if (v < 0 || v >= numNodes()) {
      throw std::invalid_argument("TetMesh::setNodeSet: node set '" + name + "' holds node " +
                                  std::to_string(v) + ", but the mesh has " +
                                  std::to_string(numNodes()) + " nodes");
    }
  }
  std::sort(node_indices.begin(), node_indices.end());
  node_indices.erase(std::unique(node_indices.begin(), node_indices.end()), node_indices.end());
  node_sets_[name] = std::move(node_indices);
}

const std::vector<int>& TetMesh::nodeSet(const std::string& name) const {
  auto it = node_sets_.find(name);
  if (it == node_sets_.end()) throw std::out_of_range("TetMesh: no node set named '" + name + "'" + nodeSetHint(name));
  return it->second;
}

std::string TetMesh::nodeSetHint(const std::string& name) const {
  const std::string have = nodeSetNames();
  if (have.empty()) return " (it has none)";
  const std::string near = nearestNodeSetName(name);
  return " (it has: " + have + ")" + (near.empty() ? "" : "; did you mean '" + near + "'?");
}

std::string TetMesh::nodeSetNames() const {
  std::string have;
  for (const auto& kv : node_sets_) have += (have.empty() ? "" : ", ") + kv.first;
  return have;
}

namespace {
std::string lowerCase(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

// Optimal string alignment distance (Levenshtein with transpositions of adjacent characters).
int editDistance(const std::string& a, const std::string& b) {
  const size_t m = a.size(), n = b.size();
  std::vector<std::vector<int>> d(m + 1, std::vector<int>(n + 1));
  for (size_t i = 0; i <= m; ++i) d[i][0] = static_cast<int>(i);
  for (size_t j = 0; j <= n; ++j) d[0][j] = static_cast<int>(j);
  for (size_t i = 1; i <= m; ++i)
    for (size_t j = 1; j <= n; ++j) {
      const int cost = a[i - 1] == b[j - 1] ? 0 : 1;
      d[i][j] = std::min({d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + cost});
      if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1]) d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
    }
  return d[m][n];
}
}  // namespace

std::string TetMesh::nearestNodeSetName(const std::string& name) const {
  if (node_sets_.count(name)) return name;
  const std::string key = lowerCase(name);
  for (const auto& kv : node_sets_)
    if (lowerCase(kv.first) == key) return kv.first;
  const int limit = name.size() <= 3 ? 1 : 2;
  std::string best;
  int best_distance = limit + 1;
  for (const auto& kv : node_sets_) {
    const int d = editDistance(key, lowerCase(kv.first));
    if (d < best_distance) best_distance = d, best = kv.first;
  }
  return best;
}

Eigen::VectorXd TetMesh::tetVolumes() const {
  Eigen::VectorXd v(numTets());
  for (int t = 0; t < numTets(); ++t) {
    v[t] = signedTetVolume(nodes_.row(tets_(t, 0)), nodes_.row(tets_(t, 1)), nodes_.row(tets_(t, 2)),
                           nodes_.row(tets_(t, 3)));
  }
  return v;
}

Eigen::Vector3d TetMesh::boundsMin() const {
  return numNodes() ? Eigen::Vector3d(nodes_.colwise().minCoeff().transpose()) : Eigen::Vector3d::Zero();
}
Eigen::Vector3d TetMesh::boundsMax() const {
  return numNodes() ? Eigen::Vector3d(nodes_.colwise().maxCoeff().transpose()) : Eigen::Vector3d::Zero();
}

std::vector<bool> TetMesh::usedNodes() const {
  std::vector<bool> used(numNodes(), false);
  for (int t = 0; t < numTets(); ++t)
    for (int k = 0; k < 4; ++k) used[tets_(t, k)] = true;
  return used;
}

namespace {
// Faces of a positively oriented tet (a,b,c,d), each ordered so its normal points out of the tet.
constexpr int kFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

struct FaceEntry {
  std::array<int, 3> key;  // sorted node indices
  int id;                  // 4 × tet + local face
  bool operator<(const FaceEntry& o) const { return key < o.key; }
};
}  // namespace

BoundarySurface extractBoundary(const Tets& tets, const Points& positions) {
  // Sort all 4·T faces by their sorted node triple; a face that appears once is on the boundary.
  // (Sorting is several times faster than hashing here and keeps the output order deterministic.)
  const Eigen::Index nt = tets.rows();
  std::vector<FaceEntry> faces(static_cast<size_t>(nt) * 4);
#pragma omp parallel for schedule(static)
  for (Eigen::Index t = 0; t < nt; ++t) {
    for (int f = 0; f < 4; ++f) {
      FaceEntry& e = faces[static_cast<size_t>(4 * t + f)];
      e.key = {tets(t, kFaces[f][0]), tets(t, kFaces[f][1]), tets(t, kFaces[f][2])};
      std::sort(e.key.begin(), e.key.end());
      e.id = static_cast<int>(4 * t + f);
    }
  }
  std::sort(faces.begin(), faces.end());
  std::vector<int> boundary_ids;
  // Orientation of a face occurrence relative to its sorted key: even or odd permutation.
  auto parity = [&](int id) {
    const int t = id / 4, f = id % 4;
    const int a = tets(t, kFaces[f][0]), b = tets(t, kFaces[f][1]), c = tets(t, kFaces[f][2]);
    return (a < b) + (b < c) + (a < c);  // 3 or 1: even; 2 or 0: odd
  };
  for (size_t i = 0; i < faces.size();) {
    size_t j = i + 1;
    while (j < faces.size() && faces[j].key == faces[i].key) ++j;
    if (j - i == 1) {
      boundary_ids.push_back(faces[i].id);
    } else if (j - i > 2 || (parity(faces[i].id) % 2) == (parity(faces[i + 1].id) % 2)) {
      // A face in three or more tets, or two tets on the same side of it: overlapping elements.
      std::string which;
      for (size_t k = i; k < j; ++k) which += (k > i ? ", " : "") + std::to_string(faces[k].id / 4);
      throw std::invalid_argument("tetrahedra " + which + " share the face (" + std::to_string(faces[i].key[0]) + ", " +
                                  std::to_string(faces[i].key[1]) + ", " + std::to_string(faces[i].key[2]) +
                                  ") " + (j - i > 2 ? "three or more times" : "from the same side") +
                                  ": the mesh has overlapping or duplicate elements");
    }
    i = j;
  }
  std::sort(boundary_ids.begin(), boundary_ids.end());  // in tet order

  BoundarySurface b;
  const Eigen::Index nf = static_cast<Eigen::Index>(boundary_ids.size());
  b.triangles.resize(nf, 3);
  b.normals.resize(nf, 3);
  b.owner_tet.resize(static_cast<size_t>(nf));
  b.nodes.reserve(static_cast<size_t>(nf) * 3);
  for (Eigen::Index i = 0; i < nf; ++i) {
    const int t = boundary_ids[static_cast<size_t>(i)] / 4, f = boundary_ids[static_cast<size_t>(i)] % 4;
    b.owner_tet[static_cast<size_t>(i)] = t;
    for (int k = 0; k < 3; ++k) {
      b.triangles(i, k) = tets(t, kFaces[f][k]);
      b.nodes.push_back(b.triangles(i, k));
    }
    const Eigen::Vector3d a = positions.row(b.triangles(i, 0));
    const Eigen::Vector3d n = (Eigen::Vector3d(positions.row(b.triangles(i, 1))) - a)
                                  .cross(Eigen::Vector3d(positions.row(b.triangles(i, 2))) - a);
    const double len = n.norm();
    b.normals.row(i) = len > 0 ? Eigen::Vector3d(n / len) : Eigen::Vector3d::Zero();
  }
  std::sort(b.nodes.begin(), b.nodes.end());
  b.nodes.erase(std::unique(b.nodes.begin(), b.nodes.end()), b.nodes.end());
  return b;
}

bool isClosedManifold(const Triangles& triangles) {
  // Each directed edge must appear exactly once, and its reverse exactly once.
  std::unordered_map<long long, int> directed;
  directed.reserve(static_cast<size_t>(triangles.rows()) * 3);
  auto key = [](long long a, long long b) { return (a << 32) | b; };
  for (Eigen::Index f = 0; f < triangles.rows(); ++f) {
    for (int e = 0; e < 3; ++e) {
      const long long a = triangles(f, e), b = triangles(f, (e + 1) % 3);
      if (++directed[key(a, b)] > 1) return false;
    }
  }
  for (const auto& kv : directed) {
    const long long a = kv.first >> 32, b = kv.first & 0xffffffffLL;
    if (directed.find(key(b, a)) == directed.end()) return false;
  }
  return !directed.empty();
}

namespace {

// Interleaves the low 21 bits of x, y, z.
uint64_t mortonCode(uint64_t x, uint64_t y, uint64_t z) {
  auto spread = [](uint64_t v) {
    v &= 0x1fffff;
    v = (v | v << 32) & 0x1f00000000ffffULL;
    v = (v | v << 16) & 0x1f0000ff0000ffULL;
    v = (v | v << 8) & 0x100f00f00f00f00fULL;
    v = (v | v << 4) & 0x10c30c30c30c30c3ULL;
    v = (v | v << 2) & 0x1249249249249249ULL;
    return v;
  };
  return spread(x) | spread(y) << 1 | spread(z) << 2;
}

// Permutation sorting points along the Morton curve of their bounding box.
std::vector<int> mortonOrder(const Points& p) {
  const Eigen::RowVector3d lo = p.colwise().minCoeff(), hi = p.colwise().maxCoeff();
  const double extent = std::max((hi - lo).maxCoeff(), 1e-30);
  std::vector<std::pair<uint64_t, int>> keys(static_cast<size_t>(p.rows()));
  for (Eigen::Index i = 0; i < p.rows(); ++i) {
    const Eigen::RowVector3d q = (p.row(i) - lo) / extent * 2097151.0;
    keys[i] = {mortonCode(static_cast<uint64_t>(q.x()), static_cast<uint64_t>(q.y()), static_cast<uint64_t>(q.z())),
               static_cast<int>(i)};
  }
  std::sort(keys.begin(), keys.end());
  std::vector<int> order(keys.size());
  for (size_t k = 0; k < keys.size(); ++k) order[k] = keys[k].second;
  return order;
}

}  // namespace

TetMesh mortonOrdered(const TetMesh& mesh, std::vector<int>* old_to_new) {
  const int n = mesh.numNodes(), nt = mesh.numTets();
  const std::vector<int> node_order = mortonOrder(mesh.nodes());
  std::vector<int> new_index(static_cast<size_t>(n));
  Points nodes(n, 3);
  for (int k = 0; k < n; ++k) {
    new_index[node_order[k]] = k;
    nodes.row(k) = mesh.nodes().row(node_order[k]);
  }
  Points centroids(nt, 3);
  for (int t = 0; t < nt; ++t) {
    Eigen::RowVector3d c = Eigen::RowVector3d::Zero();
    for (int v = 0; v < 4; ++v) c += mesh.nodes().row(mesh.tets()(t, v));
    centroids.row(t) = c / 4.0;
  }
  const std::vector<int> tet_order = nt > 0 ? mortonOrder(centroids) : std::vector<int>();
  Tets tets(nt, 4);
  std::vector<int> labels(static_cast<size_t>(nt));
  for (int k = 0; k < nt; ++k) {
    for (int v = 0; v < 4; ++v) tets(k, v) = new_index[mesh.tets()(tet_order[k], v)];
    labels[k] = mesh.regionLabels()[tet_order[k]];
  }
  TetMesh out(std::move(nodes), std::move(tets), std::move(labels));
  for (const auto& [name, set] : mesh.nodeSets()) {
    std::vector<int> renumbered;
    renumbered.reserve(set.size());
    for (int v : set) renumbered.push_back(new_index[v]);
    std::sort(renumbered.begin(), renumbered.end());
    out.setNodeSet(name, std::move(renumbered));
  }
  if (old_to_new) *old_to_new = std::move(new_index);
  return out;
}

}  // namespace breast_sim::core
