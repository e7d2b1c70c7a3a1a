#include "breast_sim/core/model/point_embedding.h"

#include "../util/closest_point.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <sstream>
#include <stdexcept>

#include <Eigen/Dense>

namespace breast_sim::core {

Eigen::Vector4d barycentricCoordinates(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                       const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                       const Eigen::Vector3d& d) {
  // Cramer's rule with scalar triple products: l = M⁻¹ (p − a) for M = [b − a, c − a, d − a].
  const Eigen::Vector3d e1 = b - a, e2 = c - a, e3 = d - a, q = p - a;
  const Eigen::Vector3d c23 = e2.cross(e3), c31 = e3.cross(e1), c12 = e1.cross(e2);
  const double det = e1.dot(c23);
  if (!(std::abs(det) > 0.0)) {  // a flat element: the pivoting solve gives its least-bad answer
    Eigen::Matrix3d m;
    m << e1, e2, e3;
    const Eigen::Vector3d l = m.partialPivLu().solve(q);
    return Eigen::Vector4d(1.0 - l.sum(), l.x(), l.y(), l.z());
  }
  const Eigen::Vector3d l = Eigen::Vector3d(q.dot(c23), q.dot(c31), q.dot(c12)) / det;
  return Eigen::Vector4d(1.0 - l.sum(), l.x(), l.y(), l.z());
}

namespace {

/// A uniform grid of axis-aligned boxes (elements or triangles) over a bounding box: each cell lists
/// the items whose bounds overlap it.
struct BoxGrid {
  Eigen::Vector3d lo;
  double cell = 1.0;
  Eigen::Vector3i dims = Eigen::Vector3i::Ones();
  std::vector<int> start;  // CSR: items of cell i are items[start[i] .. start[i + 1])
  std::vector<int> items;

  Eigen::Vector3i cellOf(const Eigen::Vector3d& p) const {
    Eigen::Vector3i c;
    for (int a = 0; a < 3; ++a) c[a] = std::clamp(static_cast<int>(std::floor((p[a] - lo[a]) / cell)), 0, dims[a] - 1);
    return c;
  }
  long index(int i, int j, int k) const { return i + dims.x() * (j + static_cast<long>(dims.y()) * k); }

  /// @param bounds(i, lo_i, hi_i) gives item i's bounds.
  template <class Bounds>
  BoxGrid(const Eigen::Vector3d& box_lo, const Eigen::Vector3d& box_hi, int count, double cell_size, Bounds bounds)
      : lo(box_lo), cell(cell_size) {
    for (int a = 0; a < 3; ++a) dims[a] = std::max(1, static_cast<int>(std::ceil((box_hi[a] - box_lo[a]) / cell)));
    const long ncells = static_cast<long>(dims.x()) * dims.y() * dims.z();
    start.assign(static_cast<size_t>(ncells) + 1, 0);
    std::vector<Eigen::Vector3i> c0(static_cast<size_t>(count)), c1(static_cast<size_t>(count));
    for (int t = 0; t < count; ++t) {
      Eigen::Vector3d tlo, thi;
      bounds(t, tlo, thi);
      c0[t] = cellOf(tlo), c1[t] = cellOf(thi);
      forCells(c0[t], c1[t], [&](long i) { ++start[static_cast<size_t>(i) + 1]; });
    }
    for (long i = 0; i < ncells; ++i) start[static_cast<size_t>(i) + 1] += start[static_cast<size_t>(i)];
    items.resize(static_cast<size_t>(start.back()));
    std::vector<int> fill(start.begin(), start.end() - 1);
    for (int t = 0; t < count; ++t) forCells(c0[t], c1[t], [&](long i) { items[static_cast<size_t>(fill[static_cast<size_t>(i)]++)] = t; });
  }

  template <class F>
  void forCells(const Eigen::Vector3i& c0, const Eigen::Vector3i& c1, F f) const {
    for (int k = c0.z(); k <= c1.z(); ++k)
      for (int j = c0.y(); j <= c1.y(); ++j)
        for (int i = c0.x(); i <= c1.x(); ++i) f(index(i, j, k));
  }
};

}  // namespace

PointEmbedding::PointEmbedding(const TetMesh& mesh, const Points& points_m,
                               const std::vector<std::string>& names, double snap_tolerance_m)
    : tets_(mesh.tets()) {
  const Points& x = mesh.nodes();
  const int nt = mesh.numTets();
  if (nt == 0 && points_m.rows() > 0) throw std::invalid_argument("PointEmbedding: the mesh is empty");
  if (points_m.rows() == 0) return;
  const Eigen::Vector3d lo = mesh.boundsMin(), hi = mesh.boundsMax();
  auto vertex = [&](int t, int k) { return Eigen::Vector3d(x.row(tets_(t, k))); };
  // Uniform grid with about one element per cell.
  const double vol = std::max((hi - lo).prod(), 1e-30);
  const double cell = std::cbrt(vol / std::max(nt, 1)) * 1.5;
  const BoxGrid elements(lo, hi, nt, cell, [&](int t, Eigen::Vector3d& tlo, Eigen::Vector3d& thi) {
    tlo = thi = vertex(t, 0);
    for (int k = 1; k < 4; ++k) tlo = tlo.cwiseMin(vertex(t, k)), thi = thi.cwiseMax(vertex(t, k));
  });
  // Points outside: the nearest boundary face, searched in a grid of the faces within the snap
  // tolerance (any face nearer than the tolerance overlaps a cell of the ball's box), else all faces
  // (for the error message, or a point farther than the grid reaches).
  const BoundarySurface& b = mesh.boundary();
  const int nf = static_cast<int>(b.triangles.rows());
  auto corner = [&](int f, int k) { return Eigen::Vector3d(x.row(b.triangles(f, k))); };
  std::unique_ptr<BoxGrid> faces;  // built on the first point outside
  auto nearestFace = [&](const Eigen::Vector3d& q, int f, double& best, int& best_face, Eigen::Vector3d& closest) {
    const Eigen::Vector3d cp = closestPointOnTriangle(q, corner(f, 0), corner(f, 1), corner(f, 2));
    const double d = (cp - q).norm();
    if (d < best) best = d, best_face = f, closest = cp;
  };

  const Eigen::Index np = points_m.rows();
  points_.resize(static_cast<size_t>(np));
  std::vector<double> outside(static_cast<size_t>(np), 0.0);  // > tolerance: an error for that point
  std::vector<char> needs_faces(static_cast<size_t>(np), 0);
  bool any_outside = false;
#pragma omp parallel for schedule(dynamic, 256) reduction(|| : any_outside)
  for (Eigen::Index p = 0; p < np; ++p) {
    const Eigen::Vector3d q = points_m.row(p).transpose();
    if (!q.allFinite()) {
      outside[static_cast<size_t>(p)] = std::numeric_limits<double>::quiet_NaN();
      continue;
    }
    const bool in_box = (q.array() >= lo.array()).all() && (q.array() <= hi.array()).all();
    bool found = false;
    if (in_box) {
      const Eigen::Vector3i c = elements.cellOf(q);
      const long i = elements.index(c.x(), c.y(), c.z());
      for (int k = elements.start[static_cast<size_t>(i)]; k < elements.start[static_cast<size_t>(i) + 1]; ++k) {
        const int t = elements.items[static_cast<size_t>(k)];
        const Eigen::Vector4d w = barycentricCoordinates(q, vertex(t, 0), vertex(t, 1), vertex(t, 2), vertex(t, 3));
        if (w.minCoeff() >= -1e-10) {
          points_[static_cast<size_t>(p)] = {t, w, 0.0};
          found = true;
          break;
        }
      }
    }
    if (!found) needs_faces[static_cast<size_t>(p)] = 1, any_outside = true;
  }
  if (any_outside && nf > 0) {
    const double face_cell = std::max(cell, 1e-9);
    faces = std::make_unique<BoxGrid>(lo, hi, nf, face_cell, [&](int f, Eigen::Vector3d& tlo, Eigen::Vector3d& thi) {
      tlo = thi = corner(f, 0);
      for (int k = 1; k < 3; ++k) tlo = tlo.cwiseMin(corner(f, k)), thi = thi.cwiseMax(corner(f, k));
    });
  }
#pragma omp parallel for schedule(dynamic, 16)
  for (Eigen::Index p = 0; p < np; ++p) {
    if (!needs_faces[static_cast<size_t>(p)]) continue;
    const Eigen::Vector3d q = points_m.row(p).transpose();
    double best = std::numeric_limits<double>::infinity();
    int best_face = -1;
    Eigen::Vector3d closest = q;
    // The grid reaches a ball of the tolerance (at least one cell) around the point, clamped to the mesh box.
    const double reach = std::max(snap_tolerance_m, cell);
    if (faces && reach < 8.0 * (hi - lo).maxCoeff()) {
      const Eigen::Vector3d r = Eigen::Vector3d::Constant(reach);
      if (((q + r).array() >= lo.array()).all() && ((q - r).array() <= hi.array()).all())
        faces->forCells(faces->cellOf(q - r), faces->cellOf(q + r), [&](long i) {
          for (int k = faces->start[static_cast<size_t>(i)]; k < faces->start[static_cast<size_t>(i) + 1]; ++k)
            nearestFace(q, faces->items[static_cast<size_t>(k)], best, best_face, closest);
        });
    }
    if (!(best <= reach))  // not within the grid's reach: every face
      for (int f = 0; f < nf; ++f) nearestFace(q, f, best, best_face, closest);
    outside[static_cast<size_t>(p)] = best;
    if (!(best <= snap_tolerance_m)) continue;  // reported below
    // Embed the closest point of the mesh surface (on a face of the owner element).
    EmbeddedPoint e;
    e.tet = b.owner_tet[static_cast<size_t>(best_face)];
    Eigen::Vector4d w = barycentricCoordinates(closest, vertex(e.tet, 0), vertex(e.tet, 1), vertex(e.tet, 2), vertex(e.tet, 3));
    w = w.cwiseMax(0.0);  // round-off only: the point is on the element's face
    e.weights = w / w.sum();
    e.outside_distance_m = best;
    points_[static_cast<size_t>(p)] = e;
  }
  // The first point that failed, named (in input order, whatever the threads did).
  for (Eigen::Index p = 0; p < np; ++p) {
    const double d = outside[static_cast<size_t>(p)];
    if (d <= snap_tolerance_m) continue;
    const std::string name = p < static_cast<Eigen::Index>(names.size()) ? names[static_cast<size_t>(p)] : "#" + std::to_string(p);
    if (std::isnan(d)) throw std::invalid_argument("PointEmbedding: point '" + name + "' has a non-finite coordinate");
    const Eigen::Vector3d q = points_m.row(p).transpose();
    std::ostringstream s;
    s.precision(4);
    s << "point '" << name << "' at (" << q.x() * 1e3 << ", " << q.y() * 1e3 << ", " << q.z() * 1e3 << ") mm lies "
      << d * 1e3 << " mm outside the mesh (tolerance " << snap_tolerance_m * 1e3
      << " mm); check that it is given in the prone image's patient space (LPS, mm) and inside the tissue";
    throw std::invalid_argument(s.str());
  }
}

Points PointEmbedding::interpolate(const Points& u) const {
  const int needed = tets_.rows() ? tets_.maxCoeff() + 1 : 0;
  if (u.rows() < needed)
    throw std::invalid_argument("PointEmbedding::interpolate: the field has " + std::to_string(u.rows()) +
                                " rows; the mesh has " + std::to_string(needed) + " nodes");
  Points out(size(), 3);
  for (int p = 0; p < size(); ++p) {
    const auto& e = points_[p];
    Eigen::RowVector3d v = Eigen::RowVector3d::Zero();
    for (int k = 0; k < 4; ++k) v += e.weights[k] * u.row(tets_(e.tet, k));
    out.row(p) = v;
  }
  return out;
}

Points PointEmbedding::positions(const Points& nodal_positions_m) const {
  return interpolate(nodal_positions_m);
}

}  // namespace breast_sim::core
