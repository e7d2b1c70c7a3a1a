// ChestWallSliding::afterStep() (the sliding step of the combined loop with stiffening, with the
// take-back of a move after a call that could not advance) and the settle loops.
#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <chrono>
#include <limits>
#include <stdexcept>

#include "breast_sim/core/fem/equilibrium.h"
#include "sliding_internal.h"

namespace breast_sim::core {

using sliding_internal::bad;
using sliding_internal::since;

SlidingStepStats ChestWallSliding::afterStep(StiffeningSimulation& stiff, const StiffeningStepResult& r) {
  const auto t0 = std::chrono::steady_clock::now();
  DynamicSimulator& sim = stiff.simulator();
  if (sim.numNodes() != num_mesh_nodes_)
    throw std::invalid_argument("ChestWallSliding::afterStep: the simulator has " + std::to_string(sim.numNodes()) +
                                " nodes, the mesh " + std::to_string(num_mesh_nodes_));
  const Eigen::VectorXd& u = sim.state().displacement_m;
  SlidingStepStats st;
  if (!r.advanced) {
    // The call could not advance: the state is where it started.
    const int n = static_cast<int>(nodes_.size());
    st.taken_back = true;
    if (last_moved_) {
      // The pending move is the suspect: no α saves an inversion that the targets force. Undo the
      // α escalation of the failed call (state, moduli, controller of the last accepted step) and
      // take half the move back; hold the wall once the scale is exhausted. Contact nodes are part
      // of it: their constraints were made at that same state.
      if (stiff.historySize() > 0) stiff.revertTo(0);
      move_scale_ *= 0.25;
      const bool hold = move_scale_ < settings_.min_move_scale;
      for (int i = 0; i < n; ++i) {
        const Eigen::RowVector3d now = u.segment<3>(3 * nodes_[i]).transpose();
        targets_.row(i) = hold ? now : Eigen::RowVector3d(now + 0.5 * (targets_.row(i) - now));
        st.max_move_m = std::max(st.max_move_m, (targets_.row(i) - now).norm());
      }
      velocity_.setZero();
      if (hold) {
        move_scale_ = settings_.min_move_scale;
        last_moved_ = false;
        st.held_wall = true;
      }
      base_targets_ = targets_.topRows(num_base_);
      sim.setNodeTargets(nodes_, targets_);
    }
    for (int i = 0; i < n; ++i)
      st.max_slide_m = std::max(st.max_slide_m, (rest_.row(i) + targets_.row(i) - origin_.row(i)).norm());
    st.move_scale = move_scale_;
    st.contacts = n - num_base_;
    st.min_free_skin_distance_m = std::numeric_limits<double>::quiet_NaN();
    st.seconds = since(t0);
    return st;
  }
  move_scale_ = r.reversals > 0 && last_moved_ ? std::max(settings_.min_move_scale, 0.5 * move_scale_)
                                               : std::min(1.0, 1.25 * move_scale_);
  Eigen::VectorXd load = -sim.constraintForces();
  SlidingStepStats cs;
  updateContacts(sim, load, cs);
  st = updateFromLoads(u, load, sim.params().time_step_s, move_scale_);
  st.contacts = cs.contacts;
  st.contacts_added = cs.contacts_added;
  st.contacts_released = cs.contacts_released;
  st.min_free_skin_distance_m = cs.min_free_skin_distance_m;
  last_moved_ = st.max_move_m > 0 || cs.contacts_added > 0 || cs.contacts_released > 0;
  sim.setNodeTargets(nodes_, targets_);
  st.seconds = since(t0);
  return st;
}

StiffSlidingSettleResult settleWithSlidingAndStiffening(
    StiffeningSimulation& stiff, ChestWallSliding& sliding, int max_calls, double increment_tolerance_m,
    int consecutive_steps, const std::function<void(int, const StiffeningStepResult&, const SlidingStepStats&)>& progress) {
  if (max_calls < 1) bad("settleWithSlidingAndStiffening max_calls", max_calls, "≥ 1");
  if (!(increment_tolerance_m > 0))
    bad("settleWithSlidingAndStiffening increment_tolerance_m", increment_tolerance_m, "> 0 [m]");
  if (consecutive_steps < 1) bad("settleWithSlidingAndStiffening consecutive_steps", consecutive_steps, "≥ 1");
  StiffSlidingSettleResult out;
  const auto t0 = std::chrono::steady_clock::now();
  int quiet = 0;
  while (out.calls < max_calls) {
    const StiffeningStepResult r = stiff.step();
    ++out.calls;
    const SlidingStepStats st = sliding.afterStep(stiff, r);
    out.sliding_seconds += st.seconds;
    out.take_backs += st.taken_back ? 1 : 0;
    out.max_slide_m = st.max_slide_m;
    if (progress) progress(out.calls, r, st);
    quiet = r.advanced && stiff.settled() && st.max_move_m <= increment_tolerance_m ? quiet + 1 : 0;
    if (quiet >= consecutive_steps) {
      out.settled = true;
      break;
    }
  }
  out.seconds = since(t0);
  return out;
}

SlidingSettleResult settleWithSliding(DynamicSimulator& sim, ChestWallSliding& sliding, int max_steps,
                                      double increment_tolerance_m, int consecutive_steps,
                                      const std::function<void(int, double, const SlidingStepStats&)>& progress) {
  if (max_steps < 1) bad("settleWithSliding max_steps", max_steps, "≥ 1");
  if (!(increment_tolerance_m > 0)) bad("settleWithSliding increment_tolerance_m", increment_tolerance_m, "> 0 [m]");
  if (consecutive_steps < 1) bad("settleWithSliding consecutive_steps", consecutive_steps, "≥ 1");
  SlidingSettleResult r;
  const auto t0 = std::chrono::steady_clock::now();
  int quiet = 0;
  Eigen::VectorXd before;
  while (r.steps < max_steps) {
    before = sim.state().displacement_m;
    sim.step();
    ++r.steps;
    const SlidingStepStats st = sliding.update(sim);
    r.sliding_seconds += st.seconds;
    r.force_seconds += st.force_seconds;
    r.last_increment_m = std::max(maxNodalNorm(sim.state().displacement_m - before), st.max_move_m);
    r.max_slide_m = st.max_slide_m;
    if (progress) progress(r.steps, r.last_increment_m, st);
    quiet = r.last_increment_m <= increment_tolerance_m ? quiet + 1 : 0;
    if (quiet >= consecutive_steps) {
      r.settled = true;
      break;
    }
  }
  r.seconds = since(t0);
  return r;
}

}  // namespace breast_sim::core
