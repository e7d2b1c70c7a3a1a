// The sliding stage (after the fixed-wall settle) and the step with sliding around it, which the
// morphing stage uses too: the implicit springs with the friction repeat, or the explicit constraint
// update.
#include <algorithm>
#include <atomic>
#include <chrono>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_internal.h"

namespace breast_sim::core {

using pipeline_detail::kMaxFrictionPasses;
using pipeline_detail::kMaxStuckCalls;
using pipeline_detail::logFraction;
using pipeline_detail::since;

WallSlipSettings ProneToSupinePipeline::wallSlipSettings() const {
  WallSlipSettings w = settings_.wall_slip;
  w.static_friction = settings_.sliding.static_friction;
  w.kinetic_friction = settings_.sliding.kinetic_friction;
  w.static_threshold_pa = settings_.sliding.static_threshold_pa;
  return w;
}

StiffeningStepResult ProneToSupinePipeline::stepWithSliding(int* stalls, bool* moving, const NodeSprings* extra,
                                                            const PipelineState* now) {
  if (slip_ && sliding_attached_) {
    // Coulomb friction holds a slipping node that comes to rest: a step in which slipping wall nodes
    // were driven back by their (constant) kinetic friction is repeated from its start with those
    // nodes sticking (wall_slip.h, stickReversed).
    // The step's start: the caller's snapshot of it, or a copy into kept buffers (no allocation per step).
    if (!now) stiff_->snapshot(step_start_);
    const SimulationState& start = now ? now->simulation : step_start_.state;
    const Eigen::VectorXd& start_factors = now ? now->modulus_factors : step_start_.modulus_factors;
    const Eigen::VectorXd& start_local_alpha = now ? now->element_alpha_per_pa : step_start_.element_alpha;
    const AlphaController::State start_alpha = now ? now->alpha : step_start_.controller;
    StiffeningStepResult r;
    for (int pass = 0;; ++pass) {
      slip_->beforeStep(simulator(), extra);
      r = stiff_->step();
      if (!r.advanced || pass >= kMaxFrictionPasses || slip_->stickReversed(simulator(), start.displacement_m) == 0) break;
      ++friction_repeats_;
      // Back to the step's start, its local α's included; the resync inside gives the stiffening
      // driver its stress at that state (the next moduli come from it) and drops the taken-back step
      // from its history.
      stiff_->restoreSnapshot(start, start_factors, start_alpha, start_local_alpha);
    }
    if (r.advanced) {
      const WallSlipStats ws = slip_->afterStep(simulator());
      sliding_report_.max_slide_m = std::max(sliding_report_.max_slide_m, ws.max_slide_m);
    }
    if (moving) *moving = false;  // the wall moves with the tissue: the tissue's increment says it
    return r;
  }
  if (extra) simulator().setNodeSprings(extra->nodes, extra->stiffness_n_per_m, extra->anchors_m);
  const StiffeningStepResult r = stiff_->step();
  const bool m = slideAfter(r, stalls);
  if (moving) *moving = m;
  return r;
}

void ProneToSupinePipeline::attachSliding() {
  if (slip_) slip_->attach(simulator());
  else if (sliding_) sliding_->attach(simulator());
  else return;
  sliding_attached_ = true;
  // A new α search (the boundary conditions changed), from the α the fixed-wall settle ended at:
  // the initial α is knowingly too high, and coming down from it would soften the tissue again.
  stiff_->restartAlphaSearch(stiff_->alpha());
}

bool ProneToSupinePipeline::slideAfter(const StiffeningStepResult& r, int* stalls) {
  if (!sliding_ || !sliding_attached_ || tracking_) return false;  // tracking: the constraints stay
  // Moves the constraints after an accepted step; after a call that could not advance it takes the
  // last move back (the move may be what inverts), holding the wall once that does not help.
  const SlidingStepStats ss = sliding_->afterStep(*stiff_, r);
  sliding_report_.max_slide_m = std::max(sliding_report_.max_slide_m, ss.max_slide_m);
  if (stalls) *stalls = ss.held_wall ? *stalls + 1 : 0;
  return ss.max_move_m > settings_.simulation.settle.increment_tolerance_m;
}

void ProneToSupinePipeline::runSlidingStage(Eigen::VectorXd& previous, const PipelineProgressFn& progress,
                                            const std::atomic<bool>* cancel) {
  // The wall nodes become moving constraints (implicit: sliding springs), updated with every
  // accepted step at the sliding stage's time step, until the wall stops moving and the tissue has
  // settled.
  const SettleOptions& so = settings_.simulation.settle;
  const double tol = so.increment_tolerance_m;
  const auto ts = std::chrono::steady_clock::now();
  StageReport sr;
  sr.ran = true;
  stage_ = PipelineStage::kSliding;
  setTimeStep(settings_.sliding_stage.time_step_s > 0 ? settings_.sliding_stage.time_step_s
                                                       : settings_.simulation.dynamics.time_step_s);
  attachSliding();
  const double sliding_tol = settings_.sliding_stage.increment_tolerance_m > 0 ? settings_.sliding_stage.increment_tolerance_m : tol;
  const RunStats b2 = stiff_->stats();
  const long repeats_before = friction_repeats_;
  int stalls = 0, quiet_steps = 0, stuck_calls = 0;
  long sl_calls = 0;
  double first = -1;
  while (sr.steps < so.max_steps && sl_calls < 2L * so.max_steps) {
    if (cancel && cancel->load()) {
      sr.cancelled = true;
      break;
    }
    ++sl_calls;
    bool moving = false;
    const StiffeningStepResult r = stepWithSliding(&stalls, &moving);
    if (!r.advanced) {
      if (stalls >= 3 || ++stuck_calls >= kMaxStuckCalls) {  // no α and no take-back lets it advance
        sr.stuck = true;
        break;
      }
      continue;
    }
    stuck_calls = 0;
    ++sr.steps;
    const StepMoves mv = stepMoves(previous);
    sr.last_increment_m = mv.all_max;
    if (first < 0) first = sr.last_increment_m;
    const bool still = settings_.sliding_stage.increment_measure == SlidingStageSettings::IncrementMeasure::kOffWall
                           ? mv.off_wall_max <= sliding_tol && mv.wall_p95 <= sliding_tol
                           : mv.all_max <= sliding_tol;
    quiet_steps = !moving && still && stiff_->settled() ? quiet_steps + 1 : 0;
    if (progress)
      progress({stage_, sr.steps, so.max_steps, sr.last_increment_m, -1, -1, r.alpha_per_pa,
                logFraction(first, sr.last_increment_m, sliding_tol)});
    if (quiet_steps >= 3) {
      sr.converged = true;
      break;
    }
  }
  closeReport(sr, b2, since(ts));
  sr.friction_repeats = friction_repeats_ - repeats_before;
  sr.max_slide_m = sliding_report_.max_slide_m;
  sr.volume_change_percent = volumeChangePercent();
  sliding_report_ = sr;
}

}  // namespace breast_sim::core
