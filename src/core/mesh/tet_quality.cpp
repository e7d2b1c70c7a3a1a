#include "breast_sim/core/mesh/tet_quality.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Geometry>

namespace breast_sim::core {

TetQuality tetQuality(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                      const Eigen::Vector3d& d) {
  TetQuality q;
  q.volume_m3 = signedTetVolume(a, b, c, d);
  const Eigen::Vector3d p[4] = {a, b, c, d};
  // Face areas and outward (for positive orientation) area vectors.
  constexpr int kFaces[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};
  Eigen::Vector3d n[4];
  double area_sum = 0.0;
  for (int f = 0; f < 4; ++f) {
    n[f] = 0.5 * (p[kFaces[f][1]] - p[kFaces[f][0]]).cross(p[kFaces[f][2]] - p[kFaces[f][0]]);
    area_sum += n[f].norm();
  }
  const double vol = std::abs(q.volume_m3);
  if (vol <= 0.0 || area_sum <= 0.0) {
    q.aspect_ratio = std::numeric_limits<double>::infinity();
    q.min_dihedral_deg = 0.0;
    return q;
  }
  // Inradius r = 3V / A. Circumradius from the standard formula with edge products:
  // R = sqrt((aA+bB+cC)(aA+bB−cC)(aA−bB+cC)(−aA+bB+cC)) / (24 V), a,A opposite edge lengths.
  const double inradius = 3.0 * vol / area_sum;
  const double e01 = (b - a).norm(), e23 = (d - c).norm();
  const double e02 = (c - a).norm(), e13 = (d - b).norm();
  const double e03 = (d - a).norm(), e12 = (c - b).norm();
  const double x = e01 * e23, y = e02 * e13, z = e03 * e12;
  const double prod = (x + y + z) * (x + y - z) * (x - y + z) * (-x + y + z);
  const double circumradius = std::sqrt(std::max(prod, 0.0)) / (24.0 * vol);
  q.aspect_ratio = circumradius / (3.0 * inradius);
  // Dihedral angle at the edge shared by faces f and g: π − angle between their outward normals.
  double min_angle = M_PI;
  for (int f = 0; f < 4; ++f) {
    for (int g = f + 1; g < 4; ++g) {
      const double nf = n[f].norm(), ng = n[g].norm();
      if (nf <= 0 || ng <= 0) { min_angle = 0; continue; }
      const double cosang = std::clamp(n[f].dot(n[g]) / (nf * ng), -1.0, 1.0);
      min_angle = std::min(min_angle, M_PI - std::acos(cosang));
    }
  }
  q.min_dihedral_deg = min_angle * 180.0 / M_PI;
  if (q.volume_m3 < 0) q.min_dihedral_deg = 0.0;
  return q;
}

QualityStats qualityStats(const Tets& tets, const Points& positions) {
  QualityStats s;
  s.num_tets = static_cast<int>(tets.rows());
  if (s.num_tets == 0) return s;
  s.min_volume_m3 = std::numeric_limits<double>::infinity();
  s.max_volume_m3 = -std::numeric_limits<double>::infinity();
  s.min_dihedral_deg = 180.0;
  double sum_ar = 0, sum_dih = 0;
  for (int t = 0; t < s.num_tets; ++t) {
    const TetQuality q = tetQuality(positions.row(tets(t, 0)), positions.row(tets(t, 1)),
                                    positions.row(tets(t, 2)), positions.row(tets(t, 3)));
    s.total_volume_m3 += q.volume_m3;
    s.min_volume_m3 = std::min(s.min_volume_m3, q.volume_m3);
    s.max_volume_m3 = std::max(s.max_volume_m3, q.volume_m3);
    if (!(q.volume_m3 > 0)) ++s.num_inverted;  // NaN counts as inverted
    s.max_aspect_ratio = std::max(s.max_aspect_ratio, q.aspect_ratio);
    sum_ar += std::isfinite(q.aspect_ratio) ? q.aspect_ratio : 0.0;
    s.min_dihedral_deg = std::min(s.min_dihedral_deg, q.min_dihedral_deg);
    sum_dih += q.min_dihedral_deg;
    if (q.min_dihedral_deg < 10.0) ++s.num_dihedral_below_10deg;
  }
  s.mean_aspect_ratio = sum_ar / s.num_tets;
  s.mean_min_dihedral_deg = sum_dih / s.num_tets;
  return s;
}

std::vector<int> invertedTets(const Tets& tets, const Points& positions, double min_volume_m3) {
  const int n = static_cast<int>(tets.rows());
  std::vector<char> bad(n, 0);
#pragma omp parallel for schedule(static)
  for (int t = 0; t < n; ++t) {
    // Written as !(v > min) so that a NaN volume (a diverged solve) counts as inverted.
    bad[t] = signedTetVolume(positions.row(tets(t, 0)), positions.row(tets(t, 1)),
                             positions.row(tets(t, 2)), positions.row(tets(t, 3))) > min_volume_m3 ? 0 : 1;
  }
  std::vector<int> out;
  for (int t = 0; t < n; ++t)
    if (bad[t]) out.push_back(t);
  return out;
}

}  // namespace breast_sim::core
