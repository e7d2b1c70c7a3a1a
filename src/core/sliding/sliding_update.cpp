// ChestWallSliding's constraint update (chest_wall_sliding.h, steps 1–5 and the robustness steps):
// wall loads → traction averaged over the wall ring → friction law and mobility (stability cap,
// inertia) → rim nodes follow their neighbours → move smoothing → step cap, permissible shift and
// projection onto the wall → volume guard → new targets.
#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>

#include "sliding_internal.h"

namespace breast_sim::core {

using sliding_internal::bad;
using sliding_internal::since;
using sliding_internal::tetVolume;

SlidingStepStats ChestWallSliding::update(DynamicSimulator& sim, const Eigen::VectorXd* external_forces) {
  const auto t0 = std::chrono::steady_clock::now();
  const Eigen::VectorXd& f = sim.elasticForces();
  const double tf = since(t0);
  SlidingStepStats st = update(sim.state().displacement_m, f, sim.lumpedMass(), sim.params().gravity_mps2,
                               sim.params().time_step_s, external_forces);
  st.force_seconds = tf;
  sim.setNodeTargets(nodes_, targets_);
  return st;
}

SlidingStepStats ChestWallSliding::update(const Eigen::VectorXd& u, const Eigen::VectorXd& f_el,
                                          const Eigen::VectorXd& mass, const Eigen::Vector3d& g, double dt,
                                          const Eigen::VectorXd* f_ext) {
  const long n3 = 3L * num_mesh_nodes_;
  if (u.size() != n3 || f_el.size() != n3 || mass.size() != num_mesh_nodes_ || (f_ext && f_ext->size() != n3))
    throw std::invalid_argument("ChestWallSliding::update: vectors do not match the mesh's " +
                                std::to_string(num_mesh_nodes_) + " nodes");
  // Applied load on each sliding node (the reaction is its negative), quasi-static.
  Eigen::VectorXd load = Eigen::VectorXd::Zero(n3);
  for (int v : nodes_) {
    Eigen::Vector3d l = f_el.segment<3>(3 * v) + mass[v] * g;
    if (f_ext) l += f_ext->segment<3>(3 * v);
    load.segment<3>(3 * v) = l;
  }
  return updateFromLoads(u, load, dt, 1.0);
}

SlidingStepStats ChestWallSliding::updateFromLoads(const Eigen::VectorXd& u, const Eigen::VectorXd& load, double dt,
                                                   double scale) {
  const auto t0 = std::chrono::steady_clock::now();
  const long n3 = 3L * num_mesh_nodes_;
  if (u.size() != n3 || load.size() != n3)
    throw std::invalid_argument("ChestWallSliding::updateFromLoads: vectors do not match the mesh's " +
                                std::to_string(num_mesh_nodes_) + " nodes");
  if (!(dt > 0) || !std::isfinite(dt)) bad("update dt_s", dt, "a finite time step > 0 [s]");
  if (!(scale > 0 && scale <= 1)) bad("updateFromLoads move_scale", scale, "(0, 1]");
  const SlidingSettings& s = settings_;
  const int n = static_cast<int>(nodes_.size());
  const Eigen::Index k_slots = stiffness_.size() / 9;  // slots with a measured stiffness block
  auto movable = [&](int i) { return !held_flag_[i] && weight_[i] > 0; };

  // 1. Traction per node [Pa]: the load of the node and its ring(s) of wall neighbours over their area.
  Points F(n, 3);
  Eigen::VectorXd A = area_;
  for (int i = 0; i < n; ++i) F.row(i) = load.segment<3>(3 * nodes_[i]).transpose();
  for (int ring = 0; ring < s.traction_smoothing_rings; ++ring) {
    Points F2 = F;
    Eigen::VectorXd A2 = A;
    for (int i = 0; i < n; ++i)
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) {
        F2.row(i) += F.row(nbr_[k]);
        A2[i] += A[nbr_[k]];
      }
    F.swap(F2);
    A.swap(A2);
  }

  // 2. Per-node move from friction and mobility (stability-capped), plus inertia.
  Points move = Points::Zero(n, 3), normal = Points::Zero(n, 3);
  int limited = 0;
  for (int i = 0; i < n; ++i) {
    if (!movable(i)) continue;
    const Eigen::Vector3d x = rest_.row(i).transpose() + u.segment<3>(3 * nodes_[i]);
    const Eigen::Vector3d nrm = surface_->normal(x);
    if (nrm.isZero()) continue;
    normal.row(i) = nrm.transpose();
    const Eigen::Vector3d tau = F.row(i).transpose() / A[i];
    const double tn = tau.dot(nrm);
    const Eigen::Vector3d tt = tau - tn * nrm;
    const double tau_n = std::abs(tn), tau_t = tt.norm();
    const Eigen::Vector3d v_prev = velocity_.row(i).transpose();
    const Eigen::Vector3d v_prev_t = v_prev - v_prev.dot(nrm) * nrm;
    const bool was_moving = v_prev_t.squaredNorm() > 0;
    if (!(was_moving || tau_t > s.static_friction * tau_n + s.static_threshold_pa)) continue;
    Eigen::Vector3d m = Eigen::Vector3d::Zero();
    const double drive = std::max(0.0, tau_t - s.kinetic_friction * tau_n - s.static_threshold_pa);
    if (tau_t > 0 && drive > 0) {
      const Eigen::Vector3d t = tt / tau_t;
      double len = dt * (1.0 - s.inertia) * weight_[i] * s.mobility_m_per_pa_s * drive;
      // Stiffness of the node along its driving direction: tᵀ K_ii t [N/m].
      const double kt = i < k_slots ? t.dot(Eigen::Map<const Eigen::Matrix3d>(&stiffness_[9 * i]).transpose() * t) : 0.0;
      if (kt > 0 && s.stiffness_safety > 0) {
        const double stable = drive * area_[i] / (s.stiffness_safety * kt);
        if (len > stable) {
          len = stable;
          ++limited;
        }
      }
      m = len * t;
    }
    m += dt * s.inertia * v_prev_t;
    move.row(i) = m.transpose();
  }

  // 3. Rim and rim-band nodes follow their neighbours of a lower level (the rim follows the wall
  //    nodes next to it, the band the rim), level by level.
  int rim = 0;
  if (s.rim_follows_neighbours) {
    const int max_level = n > 0 ? *std::max_element(rim_level_.begin(), rim_level_.end()) : 0;
    for (int lv = 1; lv <= max_level; ++lv)
      for (int i = 0; i < n; ++i) {
        if (rim_level_[i] != lv || !movable(i) || normal.row(i).isZero()) continue;
        Eigen::Vector3d sum = Eigen::Vector3d::Zero();
        double wsum = 0.0;
        int cnt = 0;
        for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k)
          if (rim_level_[nbr_[k]] < lv) {
            sum += move.row(nbr_[k]).transpose();
            wsum += weight_[nbr_[k]];
            ++cnt;
          }
        if (cnt == 0) continue;
        const Eigen::Vector3d nrm = normal.row(i).transpose();
        sum /= cnt;
        // The node's own limiting weight still applies: scaled by it relative to its neighbours'
        // (a rim node near the sternum does not take the full move of livelier neighbours).
        if (wsum > 0) sum *= std::min(1.0, weight_[i] * cnt / wsum);
        move.row(i) = (sum - sum.dot(nrm) * nrm).transpose();
        ++rim;
      }
  }

  // 4. Smoothing of the move field (held nodes take part with 0), back into each tangent plane.
  for (int it = 0; it < s.move_smoothing_iterations; ++it) {
    Points next = move;
    for (int i = 0; i < n; ++i) {
      if (!movable(i) || normal.row(i).isZero()) continue;
      const int deg = nbr_start_[i + 1] - nbr_start_[i];
      if (deg == 0) continue;
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) mean += move.row(nbr_[k]).transpose();
      mean /= deg;
      double wmean = 0.0;
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) wmean += weight_[nbr_[k]];
      wmean /= deg;
      // Smoothing blends the neighbours' moves in, but not beyond the node's own limiting weight.
      if (wmean > 0) mean *= std::min(1.0, weight_[i] / wmean);
      const Eigen::Vector3d nrm = normal.row(i).transpose();
      Eigen::Vector3d m = 0.5 * (move.row(i).transpose() + mean);
      m -= m.dot(nrm) * nrm;
      next.row(i) = m.transpose();
    }
    move.swap(next);
  }

  // 5. Scale, step cap, permissible shift, projection onto the node's rest level of the wall.
  Points proposed(n, 3), current(n, 3);
  std::vector<char> ok(n, 0), cap(n, 0);
  int failures = 0;
#pragma omp parallel for schedule(static) reduction(+ : failures)
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d X = rest_.row(i).transpose();
    const Eigen::Vector3d x = X + u.segment<3>(3 * nodes_[i]);
    current.row(i) = x.transpose();
    proposed.row(i) = x.transpose();
    Eigen::Vector3d m = scale * move.row(i).transpose();
    const double len = m.norm();
    if (len > s.max_step_m) m *= s.max_step_m / len;
    // Contact nodes are projected even without a move: their level may have changed.
    const bool relevel = i >= num_base_;
    if (!movable(i) || !(m.squaredNorm() > 0 || relevel)) continue;
    Eigen::Vector3d y = x + m;
    if (s.max_slide_m > 0) {
      const Eigen::Vector3d O = origin_.row(i).transpose();
      const double limit = weight_[i] * s.max_slide_m;
      const Eigen::Vector3d d = y - O;
      if (d.norm() > limit) {
        y = O + d * (limit / d.norm());
        cap[i] = 1;
      }
    }
    const WallProjection p = surface_->project(y, h0_[i], s.projection_iterations, s.projection_tolerance_m);
    if (!p.converged && p.residual_m > 1e-5) {  // keep the old constraint rather than a bad point
      ++failures;
      continue;
    }
    proposed.row(i) = p.point_m.transpose();
    ok[i] = 1;
  }

  // 6. Volume guard on the wall elements: halve the moves of an element's sliding nodes while it
  //    would shrink below min_volume_fraction of its rest volume (or invert); six halvings, then hold.
  std::vector<double> factor(n, 1.0);
  std::vector<char> guarded(n, 0);
  int guard_held = 0;
  const int m_tets = static_cast<int>(wall_tets_.size());
  for (int round = 0; round <= 6; ++round) {
    std::vector<char> shrink(n, 0);
    bool any = false;
    for (int e = 0; e < m_tets; ++e) {
      const Eigen::Vector4i& tv = wall_tets_[e];
      const Eigen::Vector4i& sl = wall_slots_[e];
      bool moves = false;
      for (int c = 0; c < 4; ++c) moves = moves || (sl[c] >= 0 && ok[sl[c]] && factor[sl[c]] > 0);
      if (!moves) continue;
      Eigen::Vector3d pc[4], pt[4];
      for (int c = 0; c < 4; ++c) {
        const int i = sl[c];
        if (i < 0) {
          pc[c] = pt[c] = mesh_rest_.row(tv[c]).transpose() + u.segment<3>(3 * tv[c]);
        } else {
          pc[c] = current.row(i).transpose();
          pt[c] = ok[i] ? Eigen::Vector3d(pc[c] + factor[i] * (proposed.row(i) - current.row(i)).transpose()) : pc[c];
        }
      }
      const double v_new = tetVolume(pt[0], pt[1], pt[2], pt[3]);
      const double v_now = tetVolume(pc[0], pc[1], pc[2], pc[3]);
      if (v_new >= s.min_volume_fraction * wall_rest_volume_[e] && v_new > 0) continue;
      if (v_new >= v_now && v_new > 0) continue;  // the move does not shrink it
      any = true;
      for (int c = 0; c < 4; ++c)
        if (sl[c] >= 0 && ok[sl[c]]) shrink[sl[c]] = 1;
    }
    if (!any) break;
    for (int i = 0; i < n; ++i)
      if (shrink[i]) {
        guarded[i] = 1;
        factor[i] = round < 6 ? 0.5 * factor[i] : 0.0;
      }
  }

  // 7. The new targets.
  int moving = 0, stuck = 0, capped = 0, guard_limited = 0;
  double max_move = 0, max_slide = 0, max_pen = 0;
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d X = rest_.row(i).transpose();
    const Eigen::Vector3d x = current.row(i).transpose();
    if (guarded[i]) {
      ++guard_limited;
      if (factor[i] == 0) ++guard_held;
    }
    if (!ok[i] || factor[i] == 0) {
      targets_.row(i) = (x - X).transpose();
      velocity_.row(i).setZero();
      ++stuck;
      continue;
    }
    const Eigen::Vector3d y = x + factor[i] * (proposed.row(i).transpose() - x);
    const Eigen::Vector3d moved = y - x;
    targets_.row(i) = (y - X).transpose();
    velocity_.row(i) = cap[i] || guarded[i] ? Eigen::RowVector3d::Zero() : Eigen::RowVector3d((moved / dt).transpose());
    ++moving;
    capped += cap[i];
    max_move = std::max(max_move, moved.norm());
    max_pen = std::max(max_pen, -surface_->signedDistance(y));
  }
  for (int i = 0; i < n; ++i)
    max_slide = std::max(max_slide, (rest_.row(i) + targets_.row(i) - origin_.row(i)).norm());
  base_targets_ = targets_.topRows(num_base_);
  SlidingStepStats st;
  st.moving = moving;
  st.stuck = stuck;
  st.capped = capped;
  st.stiffness_limited = limited;
  st.projection_failures = failures;
  st.guard_limited = guard_limited;
  st.guard_held = guard_held;
  st.rim_nodes = rim;
  st.move_scale = scale;
  st.max_move_m = max_move;
  st.max_slide_m = max_slide;
  st.max_penetration_m = std::max(0.0, max_pen);
  st.seconds = since(t0);
  return st;
}

}  // namespace breast_sim::core
