#include "breast_sim/core/model/point_embedding.h"

#include "../util/closest_point.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include <Eigen/Dense>

namespace breast_sim::core {

Eigen::Vector4d barycentricCoordinates(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                       const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                       const Eigen::Vector3d& d) {
  Eigen::Matrix3d m;
  m << b - a, c - a, d - a;
  const Eigen::Vector3d l = m.partialPivLu().solve(p - a);
  return Eigen::Vector4d(1.0 - l.sum(), l.x(), l.y(), l.z());
}

PointEmbedding::PointEmbedding(const TetMesh& mesh, const Points& points_m,
                               const std::vector<std::string>& names, double snap_tolerance_m)
    : tets_(mesh.tets()) {
  const Points& x = mesh.nodes();
  const int nt = mesh.numTets();
  if (nt == 0 && points_m.rows() > 0) throw std::invalid_argument("PointEmbedding: the mesh is empty");
  const Eigen::Vector3d lo = mesh.boundsMin(), hi = mesh.boundsMax();
  // Uniform grid with about one element per cell.
  const double vol = std::max((hi - lo).prod(), 1e-30);
  const double cell = std::cbrt(vol / std::max(nt, 1)) * 1.5;
  Eigen::Vector3i dims;
  for (int a = 0; a < 3; ++a) dims[a] = std::max(1, static_cast<int>(std::ceil((hi[a] - lo[a]) / cell)));
  auto cellOf = [&](const Eigen::Vector3d& p) {
    Eigen::Vector3i c;
    for (int a = 0; a < 3; ++a) c[a] = std::clamp(static_cast<int>((p[a] - lo[a]) / cell), 0, dims[a] - 1);
    return c;
  };
  const long ncells = static_cast<long>(dims.x()) * dims.y() * dims.z();
  std::vector<std::vector<int>> grid(ncells);
  for (int t = 0; t < nt; ++t) {
    Eigen::Vector3d tlo = x.row(tets_(t, 0)), thi = tlo;
    for (int k = 1; k < 4; ++k) {
      tlo = tlo.cwiseMin(Eigen::Vector3d(x.row(tets_(t, k))));
      thi = thi.cwiseMax(Eigen::Vector3d(x.row(tets_(t, k))));
    }
    const Eigen::Vector3i c0 = cellOf(tlo), c1 = cellOf(thi);
    for (int k = c0.z(); k <= c1.z(); ++k)
      for (int j = c0.y(); j <= c1.y(); ++j)
        for (int i = c0.x(); i <= c1.x(); ++i) grid[i + dims.x() * (j + static_cast<long>(dims.y()) * k)].push_back(t);
  }

  auto vertex = [&](int t, int k) { return Eigen::Vector3d(x.row(tets_(t, k))); };
  points_.resize(points_m.rows());
  for (Eigen::Index p = 0; p < points_m.rows(); ++p) {
    const Eigen::Vector3d q = points_m.row(p).transpose();
    const std::string name = p < static_cast<Eigen::Index>(names.size()) ? names[p] : "#" + std::to_string(p);
    if (!q.allFinite()) throw std::invalid_argument("PointEmbedding: point '" + name + "' has a non-finite coordinate");
    EmbeddedPoint best;
    double best_outside = std::numeric_limits<double>::infinity();
    const bool in_box = (q.array() >= lo.array()).all() && (q.array() <= hi.array()).all();
    if (in_box) {
      const Eigen::Vector3i c = cellOf(q);
      for (int t : grid[c.x() + dims.x() * (c.y() + static_cast<long>(dims.y()) * c.z())]) {
        const Eigen::Vector4d w = barycentricCoordinates(q, vertex(t, 0), vertex(t, 1), vertex(t, 2), vertex(t, 3));
        if (w.minCoeff() >= -1e-10) {
          best = {t, w, 0.0};
          best_outside = 0.0;
          break;
        }
      }
    }
    if (best_outside > 0.0) {
      // Outside: the nearest element, searched over boundary-face owners (the nearest point of the
      // mesh lies on its boundary).
      const BoundarySurface& b = mesh.boundary();
      Eigen::Vector3d closest = q;
      for (Eigen::Index f = 0; f < b.triangles.rows(); ++f) {
        const Eigen::Vector3d cp = closestPointOnTriangle(q, x.row(b.triangles(f, 0)), x.row(b.triangles(f, 1)),
                                                          x.row(b.triangles(f, 2)));
        const double d = (cp - q).norm();
        if (d < best_outside) {
          best_outside = d;
          best.tet = b.owner_tet[f];
          closest = cp;
        }
      }
      if (!(best_outside <= snap_tolerance_m)) {
        std::ostringstream s;
        s.precision(4);
        s << "point '" << name << "' at (" << q.x() * 1e3 << ", " << q.y() * 1e3 << ", " << q.z() * 1e3
          << ") mm lies " << best_outside * 1e3 << " mm outside the mesh (tolerance "
          << snap_tolerance_m * 1e3
          << " mm); check that it is given in the prone image's patient space (LPS, mm) and inside the tissue";
        throw std::invalid_argument(s.str());
      }
      // Embed the closest point of the mesh surface (on a face of the owner element).
      Eigen::Vector4d w = barycentricCoordinates(closest, vertex(best.tet, 0), vertex(best.tet, 1),
                                                 vertex(best.tet, 2), vertex(best.tet, 3));
      w = w.cwiseMax(0.0);  // round-off only: the point is on the element's face
      best.weights = w / w.sum();
      best.outside_distance_m = best_outside;
    }
    points_[p] = best;
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
