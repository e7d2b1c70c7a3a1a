// A user's mesh as the simulation model: checks, node sets, tissue classes and its label image
// (see user_mesh.h).
#include "breast_sim/core/model/user_mesh.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <map>
#include <numeric>
#include <set>
#include <sstream>
#include <stdexcept>

#include <Eigen/Dense>

#include "breast_sim/core/image/distance_transform.h"
#include "breast_sim/core/mesh/mesh_io.h"

namespace breast_sim::core {
namespace {

std::string mm(double m) {
  std::ostringstream s;
  s.precision(4);
  s << m * 1e3 << " mm";
  return s.str();
}

std::string where(const Eigen::Vector3d& p) {
  std::ostringstream s;
  s.precision(4);
  s << "(" << p.x() * 1e3 << ", " << p.y() * 1e3 << ", " << p.z() * 1e3 << ") mm";
  return s.str();
}

/// Circumradius of a tetrahedron [m].
double circumradius(const Eigen::Vector3d& p0, const Eigen::Vector3d& p1, const Eigen::Vector3d& p2,
                    const Eigen::Vector3d& p3) {
  const Eigen::Vector3d a = p1 - p0, b = p2 - p0, c = p3 - p0;
  const Eigen::Vector3d num = a.squaredNorm() * b.cross(c) + b.squaredNorm() * c.cross(a) + c.squaredNorm() * a.cross(b);
  return num.norm() / (2.0 * std::abs(a.dot(b.cross(c))));
}

double percentile90(std::vector<double> v) {
  if (v.empty()) return 0.0;
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(0.9 * static_cast<double>(v.size())));
  std::nth_element(v.begin(), v.begin() + static_cast<long>(k), v.end());
  return v[k];
}

int findRoot(std::vector<int>& parent, int i) {
  while (parent[i] != i) i = parent[i] = parent[parent[i]];
  return i;
}

/// The mesh without nodes no tetrahedron uses; node sets renumbered (unused members dropped).
TetMesh withoutUnusedNodes(const TetMesh& mesh, int* dropped) {
  const std::vector<bool> used = mesh.usedNodes();
  std::vector<int> new_index(used.size(), -1);
  int n = 0;
  for (size_t i = 0; i < used.size(); ++i)
    if (used[i]) new_index[i] = n++;
  *dropped = mesh.numNodes() - n;
  if (*dropped == 0) return mesh;
  Points nodes(n, 3);
  for (size_t i = 0; i < used.size(); ++i)
    if (used[i]) nodes.row(new_index[i]) = mesh.nodes().row(static_cast<Eigen::Index>(i));
  Tets tets = mesh.tets();
  for (Eigen::Index t = 0; t < tets.rows(); ++t)
    for (int k = 0; k < 4; ++k) tets(t, k) = new_index[tets(t, k)];
  TetMesh out(std::move(nodes), std::move(tets), mesh.regionLabels());
  for (const auto& [name, set] : mesh.nodeSets()) {
    std::vector<int> kept;
    for (int v : set)
      if (new_index[v] >= 0) kept.push_back(new_index[v]);
    out.setNodeSet(name, std::move(kept));
  }
  return out;
}

}  // namespace

TetMesh readUserMesh(const UserMeshSource& source, UserMeshReport* report) {
  const std::string& file = source.path;
  auto fail = [&](const std::string& what) { throw std::runtime_error(file + ": " + what); };
  if (!(source.length_unit_m > 0.0)) fail("the length unit is not given: set mesh.units to m or mm");
  TetMesh raw;
  try {
    raw = readTetMesh(file, source.length_unit_m);
  } catch (const std::invalid_argument& e) {  // TetMesh's checks (overlap, zero volume) do not name the file
    fail(e.what());
  }
  UserMeshReport r;
  r.file_nodes = raw.numNodes();
  const TetMesh mesh = withoutUnusedNodes(raw, &r.unused_nodes);

  const double span_m = (mesh.boundsMax() - mesh.boundsMin()).norm();
  if (!(span_m >= 0.02 && span_m <= 1.0)) {
    std::ostringstream s;
    s << "the mesh spans " << span_m << " m (bounding-box diagonal) read in "
      << (source.length_unit_m == 1.0 ? "metres" : source.length_unit_m == 1e-3 ? "millimetres" : "the given unit")
      << "; a breast spans 0.02 to 1 m: is mesh.units right?";
    fail(s.str());
  }

  // Tissue classes of the region labels.
  std::vector<int> classes(mesh.numTets());
  {
    std::set<int> present(mesh.regionLabels().begin(), mesh.regionLabels().end());
    if (source.regions.empty()) {
      if (present.size() > 1) {
        std::ostringstream s;
        s << "the elements have " << present.size() << " region labels (";
        int shown = 0;
        for (int l : present) s << (shown++ ? ", " : "") << l;
        s << "): say which tissue each is in mesh.regions {fat: [...], fibroglandular: [...], skin: [...], lesion: [...]}";
        fail(s.str());
      }
      std::fill(classes.begin(), classes.end(), static_cast<int>(TissueClass::kFat));
    } else {
      for (int t = 0; t < mesh.numTets(); ++t) {
        const int label = mesh.regionLabels()[t];
        const auto it = source.regions.find(label);
        if (it == source.regions.end()) {
          const long count = std::count(mesh.regionLabels().begin(), mesh.regionLabels().end(), label);
          fail("region label " + std::to_string(label) + " (" + std::to_string(count) +
               " elements) is in none of mesh.regions' lists: add it to fat, fibroglandular, skin or lesion");
        }
        classes[t] = static_cast<int>(it->second);
      }
    }
  }

  const BoundarySurface& boundary = mesh.boundary();
  std::vector<bool> on_boundary(mesh.numNodes(), false);
  for (int v : boundary.nodes) on_boundary[v] = true;
  auto boundarySet = [&](const std::string& name, const char* key) -> const std::vector<int>& {
    if (!mesh.hasNodeSet(name))
      fail("no node set '" + name + "' (mesh." + key + "); the file has " + mesh.nodeSetNames() + mesh.nodeSetHint(name));
    const std::vector<int>& set = mesh.nodeSet(name);
    if (set.empty()) fail("node set '" + name + "' (mesh." + key + ") holds no node of a tetrahedron");
    const long off = std::count_if(set.begin(), set.end(), [&](int v) { return !on_boundary[v]; });
    if (off > 0)
      fail("node set '" + name + "' (mesh." + key + "): " + std::to_string(off) + " of its " + std::to_string(set.size()) +
           " nodes are not on the mesh's boundary; it must hold surface nodes only");
    return set;
  };
  const std::vector<int>& wall = boundarySet(source.chest_wall_set, "chest_wall");
  std::vector<bool> is_wall(mesh.numNodes(), false);
  for (int v : wall) is_wall[v] = true;

  // A boundary face is on the wall when all three of its nodes are; the others are skin.
  std::vector<bool> wall_face(boundary.triangles.rows());
  for (Eigen::Index f = 0; f < boundary.triangles.rows(); ++f) {
    wall_face[f] = is_wall[boundary.triangles(f, 0)] && is_wall[boundary.triangles(f, 1)] && is_wall[boundary.triangles(f, 2)];
    (wall_face[f] ? r.chest_wall_faces : r.skin_faces) += 1;
  }
  std::vector<int> skin;
  if (!source.skin_set.empty()) {
    skin = boundarySet(source.skin_set, "skin");
  } else {
    std::vector<bool> in_skin(mesh.numNodes(), false);
    for (Eigen::Index f = 0; f < boundary.triangles.rows(); ++f)
      if (!wall_face[f])
        for (int k = 0; k < 3; ++k) in_skin[boundary.triangles(f, k)] = true;
    for (int v = 0; v < mesh.numNodes(); ++v)
      if (in_skin[v]) skin.push_back(v);
  }
  if (r.chest_wall_faces == 0)
    fail("node set '" + source.chest_wall_set + "' covers no boundary face (no face has all three nodes in it): "
         "the chest wall must be a surface of the mesh");
  if (r.skin_faces == 0) fail("every boundary face is on the chest wall: the mesh has no skin");
  std::vector<int> nipple;
  if (!source.nipple_set.empty()) nipple = boundarySet(source.nipple_set, "nipple");

  // Connected pieces; each must rest on the chest wall.
  {
    std::vector<int> parent(mesh.numNodes());
    std::iota(parent.begin(), parent.end(), 0);
    for (int t = 0; t < mesh.numTets(); ++t)
      for (int k = 1; k < 4; ++k) {
        const int a = findRoot(parent, mesh.tets()(t, 0)), b = findRoot(parent, mesh.tets()(t, k));
        if (a != b) parent[std::max(a, b)] = std::min(a, b);
      }
    std::map<int, bool> rests;  // root → has a wall node
    for (int v = 0; v < mesh.numNodes(); ++v) rests[findRoot(parent, v)] |= is_wall[v];
    r.components = static_cast<int>(rests.size());
    for (const auto& [root, ok] : rests) {
      if (ok) continue;
      int tets = 0;
      Eigen::Vector3d c = Eigen::Vector3d::Zero();
      for (int t = 0; t < mesh.numTets(); ++t)
        if (findRoot(parent, mesh.tets()(t, 0)) == root) ++tets, c += mesh.nodes().row(mesh.tets()(t, 0)).transpose();
      fail("a piece of " + std::to_string(tets) + " tetrahedra around " + where(c / std::max(tets, 1)) +
           " is not connected to any chest-wall node and would float free: remove it, or add its wall nodes to '" +
           source.chest_wall_set + "'");
    }
  }

  // Element sizes.
  {
    std::vector<bool> skin_tet(mesh.numTets(), false), boundary_tet(mesh.numTets(), false);
    for (size_t f = 0; f < boundary.owner_tet.size(); ++f) boundary_tet[boundary.owner_tet[f]] = true;
    for (Eigen::Index f = 0; f < boundary.triangles.rows(); ++f)
      if (!wall_face[f]) skin_tet[boundary.owner_tet[f]] = true;
    std::vector<double> inner, outer;
    for (int t = 0; t < mesh.numTets(); ++t) {
      const auto p = [&](int k) { return Eigen::Vector3d(mesh.nodes().row(mesh.tets()(t, k)).transpose()); };
      const double rad = circumradius(p(0), p(1), p(2), p(3));
      if (!boundary_tet[t]) inner.push_back(rad);
      if (skin_tet[t]) outer.push_back(rad);
    }
    r.skin_size_m = percentile90(outer);
    r.interior_size_m = inner.empty() ? r.skin_size_m : percentile90(inner);
  }

  TetMesh out(mesh.nodes(), mesh.tets(), classes);
  out.setNodeSet(node_sets::kChestWall, wall);
  out.setNodeSet(node_sets::kSkin, skin);
  if (!nipple.empty()) out.setNodeSet(node_sets::kNipple, nipple);
  if (report) *report = r;
  return mortonOrdered(out);
}

std::vector<Lesion> lesionsOfRegions(const TetMesh& mesh) {
  const int lesion = static_cast<int>(TissueClass::kLesion);
  const auto& labels = mesh.regionLabels();
  std::vector<int> parent(mesh.numTets());
  std::iota(parent.begin(), parent.end(), 0);
  // Lesion tetrahedra joined across shared faces (a face is keyed by its sorted nodes).
  std::map<std::array<int, 3>, int> face_owner;
  for (int t = 0; t < mesh.numTets(); ++t) {
    if (labels[t] != lesion) continue;
    for (int skip = 0; skip < 4; ++skip) {
      std::array<int, 3> key;
      for (int k = 0, n = 0; k < 4; ++k)
        if (k != skip) key[n++] = mesh.tets()(t, k);
      std::sort(key.begin(), key.end());
      const auto [it, inserted] = face_owner.emplace(key, t);
      if (inserted) continue;
      const int a = findRoot(parent, it->second), b = findRoot(parent, t);
      if (a != b) parent[std::max(a, b)] = std::min(a, b);
    }
  }
  std::map<int, std::pair<double, Eigen::Vector3d>> pieces;  // root → volume [m³], volume × centroid
  const Eigen::VectorXd volume = mesh.tetVolumes();
  for (int t = 0; t < mesh.numTets(); ++t) {
    if (labels[t] != lesion) continue;
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) c += 0.25 * mesh.nodes().row(mesh.tets()(t, k)).transpose();
    auto& piece = pieces.try_emplace(findRoot(parent, t), 0.0, Eigen::Vector3d::Zero()).first->second;
    piece.first += volume[t];
    piece.second += volume[t] * c;
  }
  std::vector<Lesion> out;
  for (const auto& [root, piece] : pieces)  // roots are each piece's smallest tetrahedron
    out.push_back({"L" + std::to_string(out.size() + 1), piece.second / piece.first,
                   std::cbrt(3.0 * piece.first / (4.0 * M_PI))});
  return out;
}

LabelImage voxelizeModel(const TetMesh& mesh, const TissueLabels& labels, double voxel_size_m, double margin_m) {
  if (!(voxel_size_m > 0.0) || !(margin_m > 0.0))
    throw std::invalid_argument("voxelizeModel: voxel size " + mm(voxel_size_m) + " and margin " + mm(margin_m) + " must be > 0");
  if (!mesh.hasNodeSet(node_sets::kChestWall) || !mesh.hasNodeSet(node_sets::kSkin))
    throw std::invalid_argument("voxelizeModel: the mesh needs the node sets chest_wall and skin");
  // The label value of each tissue class the mesh uses and of the chest wall (the first value of
  // the class in `labels`).
  std::uint16_t value[6] = {0, 0, 0, 0, 0, 0};
  {
    const std::set<std::uint16_t>* sets[6] = {nullptr, &labels.fat, &labels.fibroglandular, &labels.skin, &labels.lesion,
                                              &labels.chest_wall};
    std::set<int> used;
    for (int t = 0; t < mesh.numTets(); ++t) {
      const int cls = mesh.regionLabels()[t];
      if (cls < static_cast<int>(TissueClass::kFat) || cls > static_cast<int>(TissueClass::kLesion))
        throw std::invalid_argument("voxelizeModel: tetrahedron " + std::to_string(t) + " has region label " +
                                    std::to_string(cls) + ", not a tissue class (1 fat, 2 fibroglandular, 3 skin, 4 lesion)");
      used.insert(cls);
    }
    used.insert(static_cast<int>(TissueClass::kChestWall));
    for (int cls : used) {
      if (sets[cls]->empty())
        throw std::invalid_argument("voxelizeModel: no label value for " + tissueClassName(static_cast<TissueClass>(cls)));
      value[cls] = *sets[cls]->begin();
    }
  }
  const Eigen::Vector3d lo = mesh.boundsMin().array() - margin_m;
  const Eigen::Vector3d extent = (mesh.boundsMax() - mesh.boundsMin()).array() + 2.0 * margin_m;
  Eigen::Vector3i size;
  double voxels = 1.0;
  for (int a = 0; a < 3; ++a) {
    const double n = std::ceil(extent[a] / voxel_size_m) + 1.0;
    voxels *= n;
    size[a] = static_cast<int>(std::min(n, 1e9));
  }
  if (voxels > static_cast<double>(1 << 26)) {
    std::ostringstream s;
    s << "voxelizeModel: a grid of " << voxel_size_m * 1e3 << " mm over the mesh would hold " << voxels
      << " voxels (at most 2^26): choose mesh.voxel_size_mm ≥ " << std::cbrt(extent.prod() / (1 << 26)) * 1e3 * 1.01;
    throw std::invalid_argument(s.str());
  }
  LabelImage image(size, Eigen::Vector3d::Constant(voxel_size_m), lo, 0);
  const Points& X = mesh.nodes();
  auto centre = [&](long idx) {
    const long i = idx % size.x(), j = (idx / size.x()) % size.y(), k = idx / (static_cast<long>(size.x()) * size.y());
    return Eigen::Vector3d(lo + voxel_size_m * Eigen::Vector3d(double(i), double(j), double(k)));
  };
  auto voxelOf = [&](const Eigen::Vector3d& p) {
    Eigen::Vector3i v;
    for (int a = 0; a < 3; ++a)
      v[a] = std::clamp(static_cast<int>(std::lround((p[a] - lo[a]) / voxel_size_m)), 0, size[a] - 1);
    return v;
  };

  // Tissue: voxel centres inside a tetrahedron.
  for (int t = 0; t < mesh.numTets(); ++t) {
    const Eigen::Vector3d a = X.row(mesh.tets()(t, 0)).transpose();
    Eigen::Matrix3d E;
    Eigen::Vector3d bmin = a, bmax = a;
    for (int k = 1; k < 4; ++k) {
      const Eigen::Vector3d p = X.row(mesh.tets()(t, k)).transpose();
      E.col(k - 1) = p - a;
      bmin = bmin.cwiseMin(p), bmax = bmax.cwiseMax(p);
    }
    const Eigen::Matrix3d inv = E.inverse();
    const std::uint16_t label = value[mesh.regionLabels()[t]];
    Eigen::Vector3i i0, i1;
    for (int ax = 0; ax < 3; ++ax) {
      i0[ax] = std::max(0, static_cast<int>(std::ceil((bmin[ax] - lo[ax]) / voxel_size_m)));
      i1[ax] = std::min(size[ax] - 1, static_cast<int>(std::floor((bmax[ax] - lo[ax]) / voxel_size_m)));
    }
    for (int k = i0.z(); k <= i1.z(); ++k)
      for (int j = i0.y(); j <= i1.y(); ++j)
        for (int i = i0.x(); i <= i1.x(); ++i) {
          const Eigen::Vector3d l = inv * (lo + voxel_size_m * Eigen::Vector3d(i, j, k) - a);
          if (l.minCoeff() >= -1e-9 && l.sum() <= 1.0 + 1e-9) image.at(i, j, k) = label;
        }
  }

  // Sites of the wall and skin faces: the voxels their sample points (≤ half a voxel apart) fall in,
  // each with the face whose sample lies nearest its centre.
  const BoundarySurface& boundary = mesh.boundary();
  std::vector<bool> is_wall(mesh.numNodes(), false);
  for (int v : mesh.nodeSet(node_sets::kChestWall)) is_wall[v] = true;
  struct Site {
    std::int32_t voxel;
    float distance;   // from the sample to the voxel centre
    int face;
    Eigen::Vector3d sample;
  };
  std::vector<Site> wall_sites, skin_sites, face_sites;
  std::vector<int> wall_faces;
  auto unique_sites = [](std::vector<Site>& s) {
    std::sort(s.begin(), s.end(), [](const Site& x, const Site& y) {
      return x.voxel != y.voxel ? x.voxel < y.voxel : x.distance != y.distance ? x.distance < y.distance : x.face < y.face;
    });
    s.erase(std::unique(s.begin(), s.end(), [](const Site& x, const Site& y) { return x.voxel == y.voxel; }), s.end());
    std::vector<std::int32_t> voxels(s.size());
    for (size_t i = 0; i < s.size(); ++i) voxels[i] = s[i].voxel;
    return voxels;
  };

  for (Eigen::Index f = 0; f < boundary.triangles.rows(); ++f) {
    const int n0 = boundary.triangles(f, 0), n1 = boundary.triangles(f, 1), n2 = boundary.triangles(f, 2);
    const bool wall = is_wall[n0] && is_wall[n1] && is_wall[n2];
    if (wall) wall_faces.push_back(static_cast<int>(f));
    const Eigen::Vector3d a = X.row(n0).transpose(), b = X.row(n1).transpose(), c = X.row(n2).transpose();
    const double longest = std::max({(b - a).norm(), (c - b).norm(), (a - c).norm()});
    const int n = std::max(1, static_cast<int>(std::ceil(longest / (0.5 * voxel_size_m))));
    // One site per voxel the face crosses (its sample nearest the voxel centre), whatever the
    // (n+1)(n+2)/2 samples of a long, thin face.
    face_sites.clear();
    for (int i = 0; i <= n; ++i)
      for (int j = 0; i + j <= n; ++j) {
        const Eigen::Vector3d p = a + (double(i) / n) * (b - a) + (double(j) / n) * (c - a);
        const Eigen::Vector3i v = voxelOf(p);
        const std::int32_t idx = static_cast<std::int32_t>(image.index(v.x(), v.y(), v.z()));
        face_sites.push_back({idx, static_cast<float>((p - centre(idx)).norm()), static_cast<int>(f), p});
      }
    unique_sites(face_sites);
    std::vector<Site>& sites = wall ? wall_sites : skin_sites;
    sites.insert(sites.end(), face_sites.begin(), face_sites.end());
  }
  const std::vector<std::int32_t> wall_voxels = unique_sites(wall_sites), skin_voxels = unique_sites(skin_sites);

  // The wall's normal at each site: the area-weighted mean of the normals of the wall faces off the
  // rim (no node on the skin) within kNormalRadiusM; the faces of the rim, which a mesher tilts
  // towards the skin, would tilt the wall continued past it. Sites with no such face near take the
  // normal of their own face.
  constexpr double kNormalRadiusM = 10e-3;
  std::vector<bool> is_skin(mesh.numNodes(), false);
  for (int v : mesh.nodeSet(node_sets::kSkin)) is_skin[v] = true;
  std::vector<Eigen::Vector3d> site_normal(wall_sites.size(), Eigen::Vector3d::Zero());
  {
    std::vector<Eigen::Vector3d> centroid(wall_faces.size()), weighted(wall_faces.size());
    for (size_t w = 0; w < wall_faces.size(); ++w) {
      const int f = wall_faces[w];
      const Eigen::Vector3d a = X.row(boundary.triangles(f, 0)).transpose(), b = X.row(boundary.triangles(f, 1)).transpose(),
                            c = X.row(boundary.triangles(f, 2)).transpose();
      centroid[w] = (a + b + c) / 3.0;
      weighted[w] = 0.5 * (b - a).cross(c - a);  // area × outward normal
    }
    // Faces binned in cells of the radius: a site looks at its cell and the 26 around it.
    std::map<std::array<long, 3>, std::vector<int>> cells;
    auto cellOf = [&](const Eigen::Vector3d& p) {
      return std::array<long, 3>{std::lround(std::floor(p.x() / kNormalRadiusM)), std::lround(std::floor(p.y() / kNormalRadiusM)),
                                 std::lround(std::floor(p.z() / kNormalRadiusM))};
    };
    for (size_t w = 0; w < wall_faces.size(); ++w) {
      const int f = wall_faces[w];
      if (is_skin[boundary.triangles(f, 0)] || is_skin[boundary.triangles(f, 1)] || is_skin[boundary.triangles(f, 2)]) continue;
      cells[cellOf(centroid[w])].push_back(static_cast<int>(w));
    }
#pragma omp parallel for schedule(static)
    for (long i = 0; i < static_cast<long>(wall_sites.size()); ++i) {
      const Eigen::Vector3d& q = wall_sites[i].sample;
      const auto c = cellOf(q);
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (long dx = -1; dx <= 1; ++dx)
        for (long dy = -1; dy <= 1; ++dy)
          for (long dz = -1; dz <= 1; ++dz) {
            const auto it = cells.find({c[0] + dx, c[1] + dy, c[2] + dz});
            if (it == cells.end()) continue;
            for (int w : it->second)
              if ((centroid[w] - q).squaredNorm() <= kNormalRadiusM * kNormalRadiusM) sum += weighted[w];
          }
      const Eigen::Vector3d own = boundary.normals.row(wall_sites[i].face).transpose();
      site_normal[i] = sum.norm() > 0 ? Eigen::Vector3d(sum.normalized()) : own;
    }
  }

  const long total = image.numVoxels();
  std::vector<std::int32_t> near_wall(total), near_skin(total);
  euclideanFeatureTransformOfSites(wall_voxels, size, image.spacing_m, near_wall.data());
  euclideanFeatureTransformOfSites(skin_voxels, size, image.spacing_m, near_skin.data());

  const std::uint16_t wall_label = value[5];
#pragma omp parallel for schedule(static)
  for (long v = 0; v < total; ++v) {
    if (image.labels[v] != 0 || near_wall[v] < 0) continue;
    const Eigen::Vector3d x = centre(v);
    const auto site = std::lower_bound(wall_voxels.begin(), wall_voxels.end(), near_wall[v]) - wall_voxels.begin();
    if ((x - wall_sites[site].sample).dot(site_normal[site]) <= 0.0) continue;  // in front of the wall
    const double d_wall = (x - centre(near_wall[v])).norm();
    const double d_skin = near_skin[v] < 0 ? 1e300 : (x - centre(near_skin[v])).norm();
    if (d_wall <= d_skin + voxel_size_m) image.labels[v] = wall_label;
  }
  return image;
}

}  // namespace breast_sim::core
