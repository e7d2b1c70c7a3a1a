// Implicit sliding on the chest wall: node springs the implicit step solves with the tissue (see
// wall_slip.h for the model).
#include "breast_sim/core/sliding/wall_slip.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>


namespace breast_sim::core {

namespace {

/// A point, its signed distance h from the wall [m] and the unit wall normal there.
struct WallPoint {
  Eigen::Vector3d x, n;
  double h;
};

WallPoint wallPoint(const ChestWallSurface& wall, const Eigen::Vector3d& x) {
  Eigen::Vector3d grad;
  const double h = wall.signedDistance(x, grad);
  const double gn = grad.norm();
  return {x, gn > 0 ? Eigen::Vector3d(grad / gn) : Eigen::Vector3d::UnitZ(), h};
}

void require(bool ok, const std::string& field, double value, const std::string& range) {
  if (!ok) throw std::invalid_argument("WallSlipSettings::" + field + " = " + std::to_string(value) + ": must be " + range);
}

}  // namespace

void WallSlipSettings::validate() const {
  require(normal_stiffness_pa_per_m > 0 && std::isfinite(normal_stiffness_pa_per_m), "normal_stiffness_pa_per_m",
          normal_stiffness_pa_per_m, "> 0 Pa/m");
  require(friction_stiffness_pa_per_m > 0 && std::isfinite(friction_stiffness_pa_per_m), "friction_stiffness_pa_per_m",
          friction_stiffness_pa_per_m, "> 0 Pa/m");
  require(static_friction >= 0 && std::isfinite(static_friction), "static_friction", static_friction, ">= 0");
  require(kinetic_friction >= 0 && kinetic_friction <= static_friction, "kinetic_friction", kinetic_friction,
          "in [0, static_friction]");
  require(static_threshold_pa >= 0 && std::isfinite(static_threshold_pa), "static_threshold_pa", static_threshold_pa, ">= 0 Pa");
  require(stick_speed_mps >= 0 && std::isfinite(stick_speed_mps), "stick_speed_mps", stick_speed_mps, ">= 0 m/s");
  require(tether_stiffness_pa_per_m >= 0 && std::isfinite(tether_stiffness_pa_per_m), "tether_stiffness_pa_per_m",
          tether_stiffness_pa_per_m, ">= 0 Pa/m");
  require(reversal_tolerance_m >= 0 && std::isfinite(reversal_tolerance_m), "reversal_tolerance_m", reversal_tolerance_m, ">= 0 m");
  require(min_weight > 0 && min_weight <= 1, "min_weight", min_weight, "in (0, 1]");
  require(contact_gap_m >= 0 && std::isfinite(contact_gap_m), "contact_gap_m", contact_gap_m, ">= 0 m");
  require(contact_range_m > contact_gap_m && std::isfinite(contact_range_m), "contact_range_m", contact_range_m,
          "> contact_gap_m");
}

WallSlip::WallSlip(std::shared_ptr<const ChestWallSliding> geometry, const TetMesh& mesh, const WallSlipSettings& settings)
    : geometry_(std::move(geometry)), mesh_(mesh), settings_(settings) {
  settings_.validate();
  if (!geometry_) throw std::invalid_argument("WallSlip: no chest-wall geometry given");
  nodes_ = geometry_->nodes();
  const Eigen::Index n = static_cast<Eigen::Index>(nodes_.size());
  area_ = geometry_->nodeAreas().head(n);
  const Eigen::VectorXd w = geometry_->weights().head(n);
  h0_.resize(n);
  tether_.resize(n);
  stick_.resize(n, 3);
  slipping_.assign(static_cast<size_t>(n), 0);
  slip_dir_ = Points::Zero(n, 3);
  on_wall_.assign(static_cast<size_t>(mesh.numNodes()), 0);
  const ChestWallSurface& wall = geometry_->surface();
  for (Eigen::Index i = 0; i < n; ++i) {
    const int v = nodes_[static_cast<size_t>(i)];
    on_wall_[static_cast<size_t>(v)] = 1;
    h0_[i] = wall.signedDistance(mesh.nodes().row(v).transpose());
    stick_.row(i) = mesh.nodes().row(v);
    const double wi = std::clamp(w[i], settings_.min_weight, 1.0);
    tether_[i] = settings_.tether_stiffness_pa_per_m / wi;
  }
  contact_area_m2_ = n > 0 ? area_.mean() : 0.0;
  if (settings_.contact) {
    for (int v : mesh.nodeSet(node_sets::kSkin)) {
      if (on_wall_[static_cast<size_t>(v)]) continue;
      if (std::abs(wall.signedDistance(mesh.nodes().row(v).transpose())) <= settings_.contact_range_m)
        contact_candidates_.push_back(v);
    }
  }
}

WallSlip WallSlip::fromCase(const ModelCase& model_case, const TetMesh& mesh, const SlidingSettings& sliding,
                            const WallSlipSettings& settings) {
  SlidingSettings s = sliding;
  s.rim_band = false;  // the rim band is a device of the explicit update; here the skin is free
  return WallSlip(std::make_shared<ChestWallSliding>(ChestWallSliding::fromCase(model_case, mesh, s)), mesh, settings);
}

void WallSlip::attach(DynamicSimulator& sim) {
  sim.clearConstraints();
  beforeStep(sim);
}

Points WallSlip::slipDirections() const {
  Points d = Points::Zero(slip_dir_.rows(), 3);
  for (Eigen::Index i = 0; i < d.rows(); ++i)
    if (slipping_[static_cast<size_t>(i)]) d.row(i) = slip_dir_.row(i);
  return d;
}

void WallSlip::setStickPoints(const Points& stick_m, const Points& slip_directions) {
  if (stick_m.rows() != stick_.rows() || stick_m.cols() != 3 ||
      (slip_directions.size() > 0 && (slip_directions.rows() != stick_.rows() || slip_directions.cols() != 3)))
    throw std::invalid_argument("WallSlip::setStickPoints: " + std::to_string(stick_m.rows()) + " stick points and " +
                                std::to_string(slip_directions.rows()) + " slip directions for " +
                                std::to_string(stick_.rows()) + " wall nodes");
  stick_ = stick_m;
  slip_dir_.setZero();
  for (Eigen::Index i = 0; i < stick_.rows(); ++i) {
    const bool slipping = slip_directions.size() > 0 && slip_directions.row(i).squaredNorm() > 0;
    slipping_[static_cast<size_t>(i)] = slipping ? 1 : 0;
    if (slipping) slip_dir_.row(i) = slip_directions.row(i);
  }
}

void WallSlip::setHeld(bool held, const DynamicSimulator& sim) {
  held_ = held;
  if (!held) return;
  const ChestWallSurface& wall = geometry_->surface();
  const Eigen::VectorXd& u = sim.state().displacement_m;
  for (size_t i = 0; i < nodes_.size(); ++i) {
    if (!slipping_[i]) continue;
    const int v = nodes_[i];
    const Eigen::Index r = static_cast<Eigen::Index>(i);
    const Eigen::Vector3d x = mesh_.nodes().row(v).transpose() + u.segment<3>(3 * v);
    const WallProjection pr = wall.project(x, h0_[r]);
    stick_.row(r) = (pr.converged ? pr.point_m : x).transpose();
    slipping_[i] = 0;
  }
}

void WallSlip::beforeStep(DynamicSimulator& sim, const NodeSprings* extra) {
  const ChestWallSurface& wall = geometry_->surface();
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const Eigen::VectorXd& vel = sim.state().velocity_mps;
  const double dt = sim.params().time_step_s;
  const double kn = settings_.normal_stiffness_pa_per_m, kf = settings_.friction_stiffness_pa_per_m;
  const std::vector<char>& held_nodes = geometry_->heldFlags();
  std::vector<int> nodes = nodes_;
  std::vector<Eigen::Matrix3d> k(nodes_.size());
  Points anchors(static_cast<Eigen::Index>(nodes_.size()), 3);
  Points forces = Points::Zero(static_cast<Eigen::Index>(nodes_.size()), 3);
#pragma omp parallel for schedule(static)
  for (size_t i = 0; i < nodes_.size(); ++i) {
    const int v = nodes_[i];
    const Eigen::Index r = static_cast<Eigen::Index>(i);
    if (held_nodes[i]) {  // kept at its rest point
      k[i] = area_[r] * kn * Eigen::Matrix3d::Identity();
      anchors.row(r) = mesh_.nodes().row(v);
      continue;
    }
    const WallPoint w = wallPoint(wall, mesh_.nodes().row(v).transpose() + u.segment<3>(3 * v));
    const Eigen::Vector3d &x = w.x, &n = w.n;
    const double h = w.h;
    const Eigen::Matrix3d nn = n * n.transpose();
    const Eigen::Matrix3d p = Eigen::Matrix3d::Identity() - nn;
    const Eigen::Vector3d rest = mesh_.nodes().row(v).transpose();
    Eigen::Vector3d m = rest;  // tangential anchor
    double kt = tether_[r];
    if (slipping_[i]) {
      // Kinetic friction against the slip direction (in today's tangent plane), F_n from now.
      Eigen::Vector3d dir = p * slip_dir_.row(r).transpose();
      const double dn = dir.norm();
      if (dn > 0) {
        const double fn = area_[r] * kn * std::abs(h - h0_[r]);
        const double limit = settings_.kinetic_friction * fn + settings_.static_threshold_pa * area_[r];
        forces.row(r) = (-limit / dn * dir).transpose();
      }
    } else {
      kt += kf;
      m = (kf * stick_.row(r).transpose() + tether_[r] * rest) / kt;
    }
    k[i] = area_[r] * (kn * nn + kt * p);
    anchors.row(r) = (nn * x - (h - h0_[r]) * n + p * m).transpose();
  }
  // Contact: skin nodes at (or, by their velocity, within a step of) the gap level.
  last_contacts_ = 0;
  const int num_candidates = static_cast<int>(contact_candidates_.size());
  std::vector<double> contact_h(contact_candidates_.size());
  Points contact_grad(num_candidates, 3);
#pragma omp parallel for schedule(static)
  for (int q = 0; q < num_candidates; ++q) {
    const int v = contact_candidates_[static_cast<size_t>(q)];
    const Eigen::Vector3d x = mesh_.nodes().row(v).transpose() + u.segment<3>(3 * v);
    Eigen::Vector3d grad;
    const double h = wall.signedDistance(x, grad);
    const double h_ahead = wall.signedDistance(Eigen::Vector3d(x + dt * vel.segment<3>(3 * v)));
    contact_h[static_cast<size_t>(q)] = std::min(h, h_ahead) < settings_.contact_gap_m ? h : std::numeric_limits<double>::quiet_NaN();
    contact_grad.row(q) = grad.transpose();
  }
  for (int q = 0; q < num_candidates; ++q) {
    const double h = contact_h[static_cast<size_t>(q)];
    if (std::isnan(h)) continue;
    const int v = contact_candidates_[static_cast<size_t>(q)];
    const Eigen::Vector3d x = mesh_.nodes().row(v).transpose() + u.segment<3>(3 * v);
    const Eigen::Vector3d grad = contact_grad.row(q).transpose();
    const double gn = grad.norm();
    if (gn <= 0) continue;
    const Eigen::Vector3d n = grad / gn;
    nodes.push_back(v);
    k.push_back(contact_area_m2_ * kn * n * n.transpose());
    anchors.conservativeResize(anchors.rows() + 1, 3);
    anchors.row(anchors.rows() - 1) = (x - (h - settings_.contact_gap_m) * n).transpose();
    forces.conservativeResize(forces.rows() + 1, 3);
    forces.row(forces.rows() - 1).setZero();
    ++last_contacts_;
  }
  if (extra && !extra->nodes.empty()) {
    if (extra->stiffness_n_per_m.size() != extra->nodes.size() ||
        extra->anchors_m.rows() != static_cast<Eigen::Index>(extra->nodes.size()))
      throw std::invalid_argument("WallSlip::beforeStep: " + std::to_string(extra->nodes.size()) + " extra spring nodes, " +
                                  std::to_string(extra->stiffness_n_per_m.size()) + " blocks and " +
                                  std::to_string(extra->anchors_m.rows()) + " anchors; give one of each per node");
    // Node → spring row, in a buffer kept across steps (all −1 on entry and again on exit).
    std::vector<int>& slot = spring_slot_;
    if (slot.size() != static_cast<size_t>(mesh_.numNodes())) slot.assign(static_cast<size_t>(mesh_.numNodes()), -1);
    for (size_t i = 0; i < nodes.size(); ++i) slot[static_cast<size_t>(nodes[i])] = static_cast<int>(i);
    const Eigen::Index own = anchors.rows();
    Eigen::Index added = 0;
    for (size_t j = 0; j < extra->nodes.size(); ++j)
      if (slot[static_cast<size_t>(extra->nodes[j])] < 0) ++added;
    anchors.conservativeResize(own + added, 3);
    forces.conservativeResize(own + added, 3);
    for (size_t j = 0; j < extra->nodes.size(); ++j) {
      const int v = extra->nodes[j];
      const Eigen::Matrix3d& k2 = extra->stiffness_n_per_m[j];
      const Eigen::Vector3d a2 = extra->anchors_m.row(static_cast<Eigen::Index>(j)).transpose();
      const int s = slot[static_cast<size_t>(v)];
      if (s >= 0) {
        // −K1 (x − a1) − K2 (x − a2) = −(K1 + K2)(x − a1) + K2 (a2 − a1)
        const Eigen::Vector3d a1 = anchors.row(s).transpose();
        k[static_cast<size_t>(s)] += k2;
        forces.row(s) += (k2 * (a2 - a1)).transpose();
      } else {
        slot[static_cast<size_t>(v)] = static_cast<int>(nodes.size());
        nodes.push_back(v);
        k.push_back(k2);
        anchors.row(static_cast<Eigen::Index>(nodes.size()) - 1) = a2.transpose();
        forces.row(static_cast<Eigen::Index>(nodes.size()) - 1).setZero();
      }
    }
    for (const int v : nodes) slot[static_cast<size_t>(v)] = -1;
  }
  sim.setNodeSprings(nodes, k, anchors, forces);
}

WallSlipStats WallSlip::afterStep(const DynamicSimulator& sim) {
  WallSlipStats st;
  st.contacts = last_contacts_;
  const ChestWallSurface& wall = geometry_->surface();
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const double kn = settings_.normal_stiffness_pa_per_m, kf = settings_.friction_stiffness_pa_per_m;
  const std::vector<char>& held_nodes = geometry_->heldFlags();
  double max_normal_error = 0, max_slide = 0;
  int slipping = 0;
#pragma omp parallel for schedule(static) reduction(max : max_normal_error, max_slide) reduction(+ : slipping)
  for (size_t i = 0; i < nodes_.size(); ++i) {
    const int v = nodes_[i];
    const Eigen::Index r = static_cast<Eigen::Index>(i);
    if (held_nodes[i]) continue;
    const WallPoint w = wallPoint(wall, mesh_.nodes().row(v).transpose() + u.segment<3>(3 * v));
    const Eigen::Vector3d &x = w.x, &n = w.n;
    const double h = w.h;
    max_normal_error = std::max(max_normal_error, std::abs(h - h0_[r]));
    const Eigen::Vector3d rest = mesh_.nodes().row(v).transpose();
    max_slide = std::max(max_slide, ((x - rest) - n * n.dot(x - rest)).norm());
    const Eigen::Matrix3d p = Eigen::Matrix3d::Identity() - n * n.transpose();
    if (slipping_[i]) {
      // Slipping: on while it keeps moving the same way, else it sticks where it is.
      const Eigen::Vector3d vt = p * sim.state().velocity_mps.segment<3>(3 * v);
      const double speed = vt.norm();
      if (speed > settings_.stick_speed_mps && vt.dot(slip_dir_.row(r).transpose()) > 0) {
        slip_dir_.row(r) = (vt / speed).transpose();
        ++slipping;
        continue;
      }
      slipping_[i] = 0;
      const WallProjection pr = wall.project(x, h0_[r]);
      stick_.row(r) = (pr.converged ? pr.point_m : x).transpose();
      continue;
    }
    if (held_) continue;
    // Sticking: the stick spring's force against the static limit.
    const Eigen::Vector3d t = p * (x - stick_.row(r).transpose());
    const double ft = area_[r] * kf * t.norm();
    const double fn = area_[r] * kn * std::abs(h - h0_[r]);
    const double limit_static = settings_.static_friction * fn + settings_.static_threshold_pa * area_[r];
    if (ft <= limit_static || ft <= 0) continue;
    slipping_[i] = 1;
    slip_dir_.row(r) = (t / t.norm()).transpose();
    ++slipping;
  }
  st.max_normal_error_m = max_normal_error;
  st.max_slide_m = max_slide;
  st.slipping = slipping;
  return st;
}

int WallSlip::stickReversed(const DynamicSimulator& sim, const Eigen::VectorXd& u_start_m) {
  if (u_start_m.size() != 3 * static_cast<Eigen::Index>(mesh_.numNodes()))
    throw std::invalid_argument("WallSlip::stickReversed: the start displacement has " + std::to_string(u_start_m.size()) +
                                " entries, the mesh needs 3 x " + std::to_string(mesh_.numNodes()));
  const ChestWallSurface& wall = geometry_->surface();
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const double kn = settings_.normal_stiffness_pa_per_m, kf = settings_.friction_stiffness_pa_per_m;
  int stuck = 0;
  for (size_t i = 0; i < nodes_.size(); ++i) {
    if (!slipping_[i]) continue;
    const int v = nodes_[i];
    const Eigen::Index r = static_cast<Eigen::Index>(i);
    const Eigen::Vector3d d = slip_dir_.row(r).transpose();
    const double back = -d.dot(u.segment<3>(3 * v) - u_start_m.segment<3>(3 * v));  // move against the slip [m]
    if (!(back > 0)) continue;
    // The kinetic limit at the start of the step, as beforeStep applied it, and its pre-slip length.
    const Eigen::Vector3d x0 = mesh_.nodes().row(v).transpose() + u_start_m.segment<3>(3 * v);
    const double h = wall.signedDistance(x0);
    const double limit = settings_.kinetic_friction * area_[r] * kn * std::abs(h - h0_[r]) + settings_.static_threshold_pa * area_[r];
    if (back <= std::max(limit / (area_[r] * kf), settings_.reversal_tolerance_m)) continue;
    slipping_[i] = 0;
    const WallProjection pr = wall.project(x0, h0_[r]);
    stick_.row(r) = (pr.converged ? pr.point_m : x0).transpose();
    ++stuck;
  }
  return stuck;
}

Points WallSlip::slidingVectors(const DynamicSimulator& sim) const {
  Points out = Points::Zero(mesh_.numNodes(), 3);
  const ChestWallSurface& wall = geometry_->surface();
  const Eigen::VectorXd& u = sim.state().displacement_m;
  for (int v : nodes_) {
    const Eigen::Vector3d rest = mesh_.nodes().row(v).transpose();
    const Eigen::Vector3d n = wall.normal(rest);
    const Eigen::Vector3d d = u.segment<3>(3 * v);
    out.row(v) = (d - n * n.dot(d)).transpose();
  }
  return out;
}

}  // namespace breast_sim::core
