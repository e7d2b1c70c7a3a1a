#include "breast_sim/core/morphing/surface_morphing.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <sstream>
#include <stdexcept>

#include "../util/ordered_sum.h"

namespace breast_sim::core {

void MorphingOptions::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "morphing '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(gain_pa_per_m >= 0) || !std::isfinite(gain_pa_per_m)) bad("gain_pa_per_m", gain_pa_per_m, "≥ 0 Pa/m");
  if (!(max_distance_m >= 0) || !std::isfinite(max_distance_m)) bad("max_distance_m", max_distance_m, "≥ 0 m (0 = no limit)");
  if (!(max_traction_pa >= 0) || !std::isfinite(max_traction_pa)) bad("max_traction_pa", max_traction_pa, "≥ 0 Pa (0 = no cap)");
  if (!(spring_pa_per_m >= 0) || !std::isfinite(spring_pa_per_m)) bad("spring_pa_per_m", spring_pa_per_m, "≥ 0 Pa/m (0 = no implicit pull)");
}

SurfaceMorphing::SurfaceMorphing(const TetMesh& mesh, std::shared_ptr<const SurfaceVectorField> field,
                                 const std::vector<int>& skin_nodes, const std::vector<int>& constrained_nodes,
                                 const MorphingOptions& options)
    : rest_(mesh.nodes()), field_(std::move(field)), options_(options) {
  options_.validate();
  if (!field_) throw std::invalid_argument("SurfaceMorphing: no target field");
  const int nn = mesh.numNodes();
  std::vector<char> excluded(static_cast<size_t>(nn), 0), is_skin(static_cast<size_t>(nn), 0);
  for (int n : constrained_nodes) {
    if (n < 0 || n >= nn) throw std::invalid_argument("SurfaceMorphing: constrained node " + std::to_string(n) + " out of range");
    if (options_.skip_constrained) excluded[static_cast<size_t>(n)] = 1;
  }
  for (int n : skin_nodes) {
    if (n < 0 || n >= nn) throw std::invalid_argument("SurfaceMorphing: skin node " + std::to_string(n) + " out of range");
    is_skin[static_cast<size_t>(n)] = 1;
  }
  // Area share: a third of each boundary face with all three nodes on the skin, to each node.
  Eigen::VectorXd node_area = Eigen::VectorXd::Zero(nn);
  const Triangles& b = mesh.boundary().triangles;
  std::vector<Eigen::Index> skin_faces;
  for (Eigen::Index f = 0; f < b.rows(); ++f) {
    if (!is_skin[b(f, 0)] || !is_skin[b(f, 1)] || !is_skin[b(f, 2)]) continue;
    skin_faces.push_back(f);
    const Eigen::Vector3d p0 = rest_.row(b(f, 0)), p1 = rest_.row(b(f, 1)), p2 = rest_.row(b(f, 2));
    const double a = 0.5 * (p1 - p0).cross(p2 - p0).norm() / 3.0;
    for (int k = 0; k < 3; ++k) node_area[b(f, k)] += a;
  }
  for (int n = 0; n < nn; ++n)
    if (is_skin[static_cast<size_t>(n)] && !excluded[static_cast<size_t>(n)] && node_area[n] > 0) vertices_.push_back(n);
  if (vertices_.empty()) throw std::invalid_argument("SurfaceMorphing: no skin vertex is left to pull");
  area_.resize(static_cast<Eigen::Index>(vertices_.size()));
  for (size_t i = 0; i < vertices_.size(); ++i) area_[static_cast<Eigen::Index>(i)] = node_area[vertices_[i]];
  total_ = Points::Zero(static_cast<Eigen::Index>(vertices_.size()), 3);
  step_forces_ = total_;
  distance_ = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(vertices_.size()));
  anchor_ = total_;
  normal_ = total_;
  vertex_normals_ = total_;
  slot_.assign(static_cast<size_t>(nn), -1);
  for (size_t i = 0; i < vertices_.size(); ++i) slot_[static_cast<size_t>(vertices_[i])] = static_cast<int>(i);
  skin_faces_.resize(static_cast<Eigen::Index>(skin_faces.size()), 3);
  for (size_t i = 0; i < skin_faces.size(); ++i) skin_faces_.row(static_cast<Eigen::Index>(i)) = b.row(skin_faces[i]);
}

void SurfaceMorphing::springs(std::vector<int>& nodes, std::vector<Eigen::Matrix3d>& k, Points& anchors) const {
  nodes.clear();
  k.clear();
  anchors.resize(0, 3);
  if (!(options_.spring_pa_per_m > 0)) return;
  const Eigen::Index nv = static_cast<Eigen::Index>(vertices_.size());
  anchors.resize(nv, 3);
  for (Eigen::Index i = 0; i < nv; ++i) {
    const Eigen::Vector3d n = normal_.row(i).transpose();
    if (n.squaredNorm() == 0.0) continue;  // never off the target yet: no direction
    // A vertex beyond max_distance_m gets no pull, as it gets no force.
    if (options_.max_distance_m > 0 && distance_[i] > options_.max_distance_m) continue;
    anchors.row(static_cast<Eigen::Index>(nodes.size())) = anchor_.row(i);
    nodes.push_back(vertices_[static_cast<size_t>(i)]);
    k.push_back(options_.spring_pa_per_m * area_[i] * n * n.transpose());
  }
  anchors.conservativeResize(static_cast<Eigen::Index>(nodes.size()), 3);
}

void SurfaceMorphing::setField(std::shared_ptr<const SurfaceVectorField> field) {
  if (!field) throw std::invalid_argument("SurfaceMorphing::setField: no target field");
  field_ = std::move(field);
}

void SurfaceMorphing::restoreForces(DynamicSimulator& sim, const Points& accumulated_n) {
  if (accumulated_n.rows() != total_.rows() || accumulated_n.cols() != 3)
    throw std::invalid_argument("SurfaceMorphing::restoreForces: expected " + std::to_string(total_.rows()) +
                                " x 3 forces, got " + std::to_string(accumulated_n.rows()) + " x " +
                                std::to_string(accumulated_n.cols()));
  total_ = accumulated_n;
  sim.clearExternalForces();
  sim.addNodalForces(vertices_, total_);
}

DistanceStats SurfaceMorphing::measure(const DynamicSimulator& sim) {
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const int nv = static_cast<int>(vertices_.size());
#pragma omp parallel for schedule(static) if (nv > 2000)
  for (int i = 0; i < nv; ++i) {
    const int n = vertices_[i];
    distance_[i] = field_->vectorToSurface(rest_.row(n).transpose() + u.segment<3>(3 * n)).norm();
  }
  return lastStats();
}

DistanceStats SurfaceMorphing::lastStats() const {
  return distanceStats(std::vector<double>(distance_.data(), distance_.data() + distance_.size()));
}

double SurfaceMorphing::addForces(DynamicSimulator& sim) {
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const int nv = static_cast<int>(vertices_.size());
  if (along_normal_) {
    // Area-weighted vertex normals at the current positions: each face adds its (b−a)×(c−a).
    vertex_normals_.setZero();
    for (Eigen::Index f = 0; f < skin_faces_.rows(); ++f) {
      Eigen::Vector3d p[3];
      for (int k = 0; k < 3; ++k) p[k] = rest_.row(skin_faces_(f, k)).transpose() + u.segment<3>(3 * skin_faces_(f, k));
      const Eigen::RowVector3d n = (p[1] - p[0]).cross(p[2] - p[0]).transpose();
      for (int k = 0; k < 3; ++k) {
        const int slot = slot_[static_cast<size_t>(skin_faces_(f, k))];
        if (slot >= 0) vertex_normals_.row(slot) += n;
      }
    }
  }
  // The mean distance in a fixed order (util/ordered_sum.h): the same on any thread count.
  const double sum = util::orderedSum(nv, nv > 2000, [&](long i) {
    const int n = vertices_[i];
    const Eigen::Vector3d x = rest_.row(n).transpose() + u.segment<3>(3 * n);
    Eigen::Vector3d v = field_->vectorToSurface(x);
    if (along_normal_) {
      const double len = vertex_normals_.row(i).norm();
      if (len > 0) {
        const Eigen::Vector3d nrm = vertex_normals_.row(i).transpose() / len;
        v = nrm * nrm.dot(v);
      }
    }
    const double d = v.norm();
    distance_[i] = d;
    anchor_.row(i) = (x + v).transpose();
    // The direction of the implicit pull; on the target (d ≈ 0) the last one is kept.
    if (d > 1e-9) normal_.row(i) = (v / d).transpose();
    const bool pull = options_.max_distance_m == 0.0 || d <= options_.max_distance_m;
    Eigen::RowVector3d f = pull ? Eigen::RowVector3d(options_.gain_pa_per_m * area_[i] * v.transpose()) : Eigen::RowVector3d::Zero();
    if (options_.max_traction_pa > 0) {
      // Cap the accumulated force (anti-windup): only the part of this step's force that keeps it
      // within the cap is added.
      const double cap = options_.max_traction_pa * area_[i];
      const Eigen::RowVector3d total = total_.row(i) + f;
      if (total.norm() > cap) f = total * (cap / total.norm()) - total_.row(i);
    }
    step_forces_.row(i) = f;
    return d;
  });
  total_ += step_forces_;
  sim.addNodalForces(vertices_, step_forces_);
  return sum / nv;
}

}  // namespace breast_sim::core
