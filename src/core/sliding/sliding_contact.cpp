// ChestWallSliding's skin–wall contact (chest_wall_sliding.h, "Skin–wall contact"): contact nodes
// released when their load pulls them off the wall, free skin nodes that reach the wall added as
// sliding constraints.
#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <limits>

namespace breast_sim::core {

namespace {

// Accepted calls in a row a contact node must pull off the wall before it is freed: one call's
// reaction carries inertia (a node caught while falling, a bounce), which is no lift-off.
constexpr int kReleaseCalls = 3;

}  // namespace

bool ChestWallSliding::updateContacts(DynamicSimulator& sim, const Eigen::VectorXd& load, SlidingStepStats& st) {
  const SlidingSettings& s = settings_;
  st.min_free_skin_distance_m = std::numeric_limits<double>::infinity();
  if (!s.contact || skin_candidates_.empty()) return false;
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const Eigen::VectorXd& vel = sim.state().velocity_mps;
  const double dt = sim.params().time_step_s;
  auto position = [&](int v) { return Eigen::Vector3d(mesh_rest_.row(v).transpose() + u.segment<3>(3 * v)); };

  // 1. Contact nodes: freed when their load pulls them off the wall (unilateral), else their level
  //    descends half way to the gap while they press on it.
  int n = static_cast<int>(nodes_.size());
  std::vector<char> keep(n, 1);
  int released = 0;
  for (int i = num_base_; i < n; ++i) {
    const int v = nodes_[i];
    const Eigen::Vector3d nrm = surface_->normal(position(v));
    if (nrm.isZero()) continue;
    const double fn = load.segment<3>(3 * v).dot(nrm);  // > 0: the node pulls away from the wall
    const bool pulled = fn > s.contact_release_pa * area_[i];
    tension_calls_[v] = pulled ? tension_calls_[v] + 1 : 0;
    if (s.contact_release && tension_calls_[v] >= kReleaseCalls) {
      keep[i] = 0;
      released_[v] = 1;
      tension_calls_[v] = 0;
      ++released;
    } else if (fn < 0) {
      h0_[i] = std::max(s.contact_gap_m, h0_[i] - 0.5 * (h0_[i] - s.contact_gap_m));
    }
  }
  if (released > 0) {
    compactSlots(keep);
    // No call frees single nodes: clear, then re-impose the others' constraints (file comment);
    // the caller re-imposes the slots' targets.
    sim.clearConstraints();
    sim.fixNodes(foreign_fixed_);
    contacts_released_ += released;
    n = static_cast<int>(nodes_.size());
  }

  // 2. Free skin nodes that touch the wall, now or one step ahead along their velocity.
  const int m = static_cast<int>(skin_candidates_.size());
  std::vector<double> level(m, -1.0);
  double min_h = std::numeric_limits<double>::infinity();
#pragma omp parallel for schedule(static) reduction(min : min_h)
  for (int q = 0; q < m; ++q) {
    const int v = skin_candidates_[q];
    if (slot_of_[v] >= 0) continue;
    Eigen::Vector3d grad;
    const Eigen::Vector3d x = position(v);
    const double h = surface_->signedDistance(x, grad);
    // Look two steps ahead along the approach: a node falling onto the wall still accelerates.
    const double h_pred = h + 2.0 * dt * std::min(0.0, grad.dot(vel.segment<3>(3 * v)));
    // A freed node was let go at the gap or above: it is caught again only below half of it.
    const double threshold = released_[v] ? 0.5 * s.contact_gap_m : s.contact_tolerance_m;
    if (std::min(h, h_pred) <= threshold) level[q] = std::max(s.contact_gap_m, h);
    else min_h = std::min(min_h, h);
  }
  std::vector<int> add_v;
  std::vector<Eigen::Vector3d> add_y;
  std::vector<double> add_l;
  for (int q = 0; q < m; ++q) {
    if (level[q] < 0) continue;
    const int v = skin_candidates_[q];
    const WallProjection p = surface_->project(position(v), level[q], s.projection_iterations, s.projection_tolerance_m);
    if (!p.converged && p.residual_m > 1e-5) {  // no usable wall point: stays free this call
      min_h = std::min(min_h, surface_->signedDistance(position(v)));
      continue;
    }
    add_v.push_back(v);
    add_y.push_back(p.point_m);
    add_l.push_back(level[q]);
  }
  st.min_free_skin_distance_m = min_h;
  st.contacts_released = released;
  st.contacts_added = static_cast<int>(add_v.size());
  if (!add_v.empty()) {
    const int k = static_cast<int>(add_v.size());
    const int n2 = n + k;
    rest_.conservativeResize(n2, 3);
    origin_.conservativeResize(n2, 3);
    targets_.conservativeResize(n2, 3);
    velocity_.conservativeResize(n2, 3);
    for (Eigen::VectorXd* vec : {&h0_, &area_, &weight_, &thickness_factor_, &gaussian_factor_, &thickness_m_})
      vec->conservativeResize(n2);
    held_flag_.resize(n2, 0);
    rim_level_.resize(n2, 0);
    // The median wall area of the sliding set: a contact node's share of the contact surface.
    std::vector<double> areas(area_.data(), area_.data() + num_base_);
    std::nth_element(areas.begin(), areas.begin() + areas.size() / 2, areas.end());
    const double median_area = areas.empty() ? 1e-6 : areas[areas.size() / 2];
    for (int j = 0; j < k; ++j) {
      const int i = n + j, v = add_v[j];
      nodes_.push_back(v);
      rest_.row(i) = mesh_rest_.row(v);
      origin_.row(i) = add_y[j].transpose();
      targets_.row(i) = (add_y[j] - mesh_rest_.row(v).transpose()).transpose();
      velocity_.row(i).setZero();
      h0_[i] = add_l[j];
      area_[i] = median_area;
      // Limiting weight of the touch-down point's foot on the wall.
      const WallProjection foot = surface_->project(add_y[j], 0.0, s.projection_iterations, s.projection_tolerance_m);
      gaussian_factor_[i] = s.gaussian_limit ? gaussianWeight(foot.point_m) : 1.0;
      thickness_factor_[i] = 1.0;
      thickness_m_[i] = 0.0;
      held_flag_[i] = 0;
    }
    contacts_made_ += k;
    buildGraph();
    // Thickness factor and stiffness block (when attach() measured them): the means of the node's
    // constrained neighbours.
    const bool have_k = stiffness_.size() == 9L * n;
    if (have_k) stiffness_.conservativeResize(9L * n2);
    for (int i = n; i < n2; ++i) {
      double tf = 0;
      Eigen::Matrix<double, 9, 1> kb = Eigen::Matrix<double, 9, 1>::Zero();
      int cnt = 0, kcnt = 0;
      for (int q = nbr_start_[i]; q < nbr_start_[i + 1]; ++q) {
        const int j = nbr_[q];
        if (j >= n) continue;
        tf += thickness_factor_[j];
        ++cnt;
        if (have_k) {
          kb += stiffness_.segment<9>(9L * j);
          ++kcnt;
        }
      }
      if (s.thickness_limit && cnt > 0) thickness_factor_[i] = tf / cnt;
      if (have_k) stiffness_.segment<9>(9L * i) = kcnt > 0 ? Eigen::Matrix<double, 9, 1>(kb / kcnt) : kb;
      weight_[i] = thickness_factor_[i] * gaussian_factor_[i];
    }
  }
  st.contacts = static_cast<int>(nodes_.size()) - num_base_;
  return released > 0;
}

}  // namespace breast_sim::core
