// Error metrics against a reference displacement field (reference/error_metrics.h).

#include "breast_sim/core/reference/error_metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "breast_sim/core/material/stiffening.h"  // deformationMeasures
#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/morphing/target_surface.h"

namespace breast_sim::core {

Points transferDisplacement(const TetMesh& reference_mesh, const Points& reference_u_m, const Points& points_m,
                           double snap_tolerance_m) {
  if (reference_u_m.rows() != reference_mesh.numNodes())
    throw std::invalid_argument("transferDisplacement: the reference field has " + std::to_string(reference_u_m.rows()) +
                                " rows; the reference mesh has " + std::to_string(reference_mesh.numNodes()) + " nodes");
  const PointEmbedding e(reference_mesh, points_m, {}, snap_tolerance_m);
  return e.interpolate(reference_u_m);
}

Eigen::VectorXd pointSurfaceDistance(const Points& points_m, const Points& vertices_m, const Triangles& triangles) {
  if (triangles.rows() == 0) return Eigen::VectorXd::Constant(points_m.rows(), std::numeric_limits<double>::infinity());
  TargetSurface surface;
  surface.vertices_m = vertices_m;
  surface.triangles = triangles;
  return SurfaceDistance(surface).distances(points_m);
}

DisplacementErrors compareDisplacements(const TetMesh& mesh, const Points& u_m, const TetMesh& reference_mesh,
                                        const Points& reference_u_m, const Points& lesions_m,
                                        const std::string& fixed_node_set, const std::string& skin_node_set) {
  if (u_m.rows() != mesh.numNodes())
    throw std::invalid_argument("compareDisplacements: the field has " + std::to_string(u_m.rows()) + " rows; the mesh has " +
                                std::to_string(mesh.numNodes()) + " nodes");
  if (reference_u_m.rows() != reference_mesh.numNodes())
    throw std::invalid_argument("compareDisplacements: the reference field has " + std::to_string(reference_u_m.rows()) +
                                " rows; the reference mesh has " + std::to_string(reference_mesh.numNodes()) + " nodes");
  const bool same = &mesh == &reference_mesh ||
                    (mesh.numNodes() == reference_mesh.numNodes() && mesh.numTets() == reference_mesh.numTets() &&
                     mesh.nodes() == reference_mesh.nodes() && mesh.tets() == reference_mesh.tets());
  const Points ref_at_ours = same ? reference_u_m : transferDisplacement(reference_mesh, reference_u_m, mesh.nodes());

  DisplacementErrors e;
  std::vector<char> skip(mesh.numNodes(), 0);
  if (!fixed_node_set.empty() && mesh.hasNodeSet(fixed_node_set))
    for (int n : mesh.nodeSet(fixed_node_set)) skip[n] = 1;
  const std::vector<bool> used = mesh.usedNodes();
  std::vector<double> err;
  err.reserve(mesh.numNodes());
  double ref_max = 0;
  for (int n = 0; n < mesh.numNodes(); ++n) {
    if (skip[n] || !used[n]) continue;
    err.push_back((u_m.row(n) - ref_at_ours.row(n)).norm());
    e.max_displacement_mm = std::max(e.max_displacement_mm, 1e3 * u_m.row(n).norm());
    ref_max = std::max(ref_max, ref_at_ours.row(n).norm());
  }
  e.reference_max_displacement_mm = 1e3 * ref_max;
  e.nodes_compared = static_cast<int>(err.size());
  if (!err.empty()) {
    double s = 0, s2 = 0;
    for (double x : err) {
      s += x;
      s2 += x * x;
    }
    e.mean_mm = 1e3 * s / err.size();
    e.rms_mm = 1e3 * std::sqrt(s2 / err.size());
    std::vector<double> sorted = err;
    std::sort(sorted.begin(), sorted.end());
    e.max_mm = 1e3 * sorted.back();
    e.p95_mm = 1e3 * sorted[std::min(sorted.size() - 1, static_cast<std::size_t>(std::ceil(0.95 * sorted.size())) - 1)];
  }

  if (lesions_m.rows() > 0) {
    const PointEmbedding ours(mesh, lesions_m, {}, 5e-3);
    const Points lu = ours.interpolate(u_m);
    const Points lr = same ? ours.interpolate(reference_u_m) : transferDisplacement(reference_mesh, reference_u_m, lesions_m);
    for (Eigen::Index l = 0; l < lesions_m.rows(); ++l) {
      e.lesion_error_mm.push_back(1e3 * (lu.row(l) - lr.row(l)).norm());
      e.lesion_max_mm = std::max(e.lesion_max_mm, e.lesion_error_mm.back());
    }
  }

  // Surface distance: our deformed skin nodes to the reference's deformed boundary.
  std::vector<int> skin;
  if (!skin_node_set.empty() && mesh.hasNodeSet(skin_node_set)) {
    for (int n : mesh.nodeSet(skin_node_set))
      if (!skip[n]) skin.push_back(n);
  } else {
    for (int n : mesh.boundary().nodes)
      if (!skip[n]) skin.push_back(n);
  }
  if (!skin.empty()) {
    Points ours(static_cast<Eigen::Index>(skin.size()), 3), rest(static_cast<Eigen::Index>(skin.size()), 3);
    for (std::size_t i = 0; i < skin.size(); ++i) {
      rest.row(i) = mesh.nodes().row(skin[i]);
      ours.row(i) = mesh.nodes().row(skin[i]) + u_m.row(skin[i]);
    }
    const Points ref_deformed = reference_mesh.nodes() + reference_u_m;
    const Eigen::VectorXd d = pointSurfaceDistance(ours, ref_deformed, reference_mesh.boundary().triangles);
    e.surface_distance_mean_mm = 1e3 * d.mean();
    e.surface_distance_max_mm = 1e3 * d.maxCoeff();
    if (!same) {
      const Eigen::VectorXd d0 = pointSurfaceDistance(rest, reference_mesh.nodes(), reference_mesh.boundary().triangles);
      e.rest_surface_distance_mean_mm = 1e3 * d0.mean();
    }
  }

  double maxd = 0;
  Eigen::VectorXd flat_u = Eigen::Map<const Eigen::VectorXd>(u_m.data(), u_m.size());
  deformationMeasures(mesh, flat_u, e.volume_change_percent, maxd);
  Eigen::VectorXd flat_r = Eigen::Map<const Eigen::VectorXd>(reference_u_m.data(), reference_u_m.size());
  deformationMeasures(reference_mesh, flat_r, e.reference_volume_change_percent, maxd);
  return e;
}

}  // namespace breast_sim::core
