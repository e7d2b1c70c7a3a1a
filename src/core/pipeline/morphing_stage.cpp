// Stage 2 of the pipeline: surface morphing, one Figure-2 iteration per step (iterate), the stage's
// loop and stop rules (runMorphing), and the tracking mode.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <stdexcept>
#include <vector>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_internal.h"
#include "breast_sim/core/thread_budget.h"

namespace breast_sim::core {

using pipeline_detail::kMaxStuckCalls;
using pipeline_detail::logFraction;
using pipeline_detail::since;

std::unique_ptr<SurfaceMorphing> ProneToSupinePipeline::makeMorphing(const std::vector<char>& fixed) const {
  std::vector<int> constrained;
  for (int n = 0; n < model_.mesh.numNodes(); ++n)
    if (fixed[static_cast<size_t>(n)]) constrained.push_back(n);
  auto morph = std::make_unique<SurfaceMorphing>(model_.mesh, field_, model_.mesh.nodeSet(node_sets::kSkin), constrained,
                                                 settings_.morphing.forces);
  morph->setAlongNormal(tracking_);
  return morph;
}

SurfaceMorphing& ProneToSupinePipeline::ensureMorphing() {
  if (!morphing_forces_) {
    std::vector<char> fixed;
    simulator().constrainedNodes(fixed);
    morphing_forces_ = makeMorphing(fixed);
  }
  return *morphing_forces_;
}

void ProneToSupinePipeline::setTrackingMode(bool on) {
  tracking_ = on;
  simulator().setMatrixReuse(on ? pipeline_detail::kTrackingMatrixReuse : 1);
  stiff_->setTracking(on);
  if (slip_ && sliding_attached_) slip_->setHeld(on, simulator());
  if (morphing_forces_) morphing_forces_->setAlongNormal(on);
}

IterationReport ProneToSupinePipeline::iterate() {
  const ThreadCountScope threads(ThreadCountScope::Sample::reuse);  // as many threads as the steps
  if (!field_) throw std::logic_error("ProneToSupinePipeline::iterate: no target surface (setTarget first)");
  const auto t0 = std::chrono::steady_clock::now();
  ensureMorphing();
  IterationReport it;
  iterate_previous_ = simulator().state().displacement_m;  // reuses the buffer
  // Seed 2.6: after a step that could not advance, no new forces (the positions are back where
  // they received the last ones).
  DistanceStats d;
  if (last_advanced_) {
    morphing_forces_->addForces(simulator());
    d = morphing_forces_->lastStats();
    it.forces_added = true;
  } else {
    d = morphing_forces_->lastStats();
  }
  it.surface_mean_m = d.mean_m;
  it.surface_p95_m = d.p95_m;
  // With the surface within tolerance the material is soft enough: hold α (seed 2.6).
  const bool met = d.mean_m <= settings_.morphing.tolerance_mean_m && d.p95_m <= settings_.morphing.tolerance_p95_m;
  stiff_->holdAlpha(met);
  it.alpha_held = met;
  int stalls = 0;
  // The implicit pull (augmented Lagrangian), anchored at the target points of the current positions
  // (after a call that could not advance these are the positions the last forces were read at).
  const bool pull = settings_.morphing.forces.spring_pa_per_m > 0;
  if (pull)
    morphing_forces_->springs(morph_springs_.nodes, morph_springs_.stiffness_n_per_m, morph_springs_.anchors_m);
  // Divergence guard: the state before the step (with the forces just added, the α controller, the
  // stick points) to come back to when the step runs away.
  const MorphingStageSettings& ms = settings_.morphing;
  const bool guard = ms.max_step_move_m > 0 || ms.max_step_volume_change_percent > 0;
  PipelineState& before = guard_before_;  // a kept buffer: no allocation per step
  double volume_before = 0.0;
  if (guard) {
    fillState(before);
    if (ms.max_step_volume_change_percent > 0) volume_before = volumeChangePercent();
  }
  // `before` is also the step's start for the friction repeat (no second copy).
  StiffeningStepResult r = stepWithSliding(&stalls, nullptr, pull ? &morph_springs_ : nullptr, guard ? &before : nullptr);
  // The step's moves (zero after a call that could not advance: the state is back at its start).
  if (!morphing_forces_->vertices().empty()) {  // no pulled vertex (e.g. nothing within reach): no p95
    const Eigen::VectorXd& u = simulator().state().displacement_m;
    const std::vector<int>& vs = morphing_forces_->vertices();
    pulled_moves_.resize(vs.size());
    for (size_t i = 0; i < vs.size(); ++i)
      pulled_moves_[i] = (u.segment<3>(3 * vs[i]) - iterate_previous_.segment<3>(3 * vs[i])).squaredNorm();
    // The ⌈0.95 n⌉-th smallest, as distanceStats' p95.
    const size_t k = std::min(vs.size() - 1, static_cast<size_t>(std::ceil(0.95 * static_cast<double>(vs.size()))) - 1);
    std::nth_element(pulled_moves_.begin(), pulled_moves_.begin() + static_cast<std::ptrdiff_t>(k), pulled_moves_.end());
    it.pulled_increment_p95_m = std::sqrt(pulled_moves_[k]);
  }
  StepMoves mv = stepMoves(iterate_previous_);
  if (guard && r.advanced) {
    const bool too_far = ms.max_step_move_m > 0 && !(mv.all_max <= ms.max_step_move_m);
    const bool volume_jump = ms.max_step_volume_change_percent > 0 &&
                             !(std::abs(volumeChangePercent() - volume_before) <= ms.max_step_volume_change_percent);
    if (too_far || volume_jump) {
      // A failed step like an inversion (seed 2.6): back to the state before it, α up, and the next
      // call repeats it without new forces. The last good state is never overwritten.
      restore(before);  // state, moduli, α, stick points, slip directions and morphing forces
      // Repeated run-aways grow α as repeated reversals of one step do (reversal_growth).
      stiff_->controller().onReversed(++diverged_run_);
      ++diverged_steps_;
      it.diverged = true;
      r.advanced = false;
      r.reversals += 1;
      r.alpha_per_pa = stiff_->alpha();
      mv = StepMoves{};  // back at the start: nothing moved
      it.pulled_increment_p95_m = 0.0;
    }
  }
  if (r.advanced) diverged_run_ = 0;
  last_advanced_ = r.advanced;
  it.advanced = r.advanced;
  it.reversals = r.reversals;
  it.step_fraction = r.advanced ? r.step_fraction : 1.0;
  it.alpha_per_pa = r.alpha_per_pa;
  it.increment_m = mv.all_max;
  it.off_wall_increment_m = mv.off_wall_max;
  it.wall_increment_p95_m = mv.wall_p95;
  it.seconds = since(t0);
  return it;
}

StageReport ProneToSupinePipeline::runMorphing(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
  const ThreadCountScope threads(ThreadCountScope::Sample::reuse);  // as many threads as the steps
  setTrackingMode(false);
  if (!field_) throw std::logic_error("ProneToSupinePipeline::runMorphing: no target surface (setTarget first)");
  const auto t0 = std::chrono::steady_clock::now();
  const MorphingStageSettings& ms = settings_.morphing;
  StageReport rep;
  rep.ran = true;
  if (coarse_ && coarse_ahead_) {
    // Nested iteration: the coarse model morphs first; this one starts from its state.
    coarse_running_ = true;
    const StageReport c = coarse_->runMorphing(progress, cancel);
    coarse_running_ = false;
    rep.coarse_steps = c.steps;
    rep.coarse_reversed_steps = c.reversed_steps;
    rep.coarse_friction_repeats = c.friction_repeats;
    rep.coarse_elements = coarse_model_->mesh.numTets();
    if (c.cancelled) {  // not carried over: this model keeps its state
      rep.cancelled = true;
      rep.seconds = since(t0);
      morphing_ = rep;
      return rep;
    }
    startFrom(*coarse_, settings_.coarse_start.snap_tolerance_m);  // clears coarse_ahead_
  }
  stage_ = PipelineStage::kMorphing;
  setTimeStep(ms.time_step_s);
  if (hasSliding() && !sliding_attached_) attachSliding();  // e.g. the gravity stage was skipped
  // The stage's reversal growth, given back on every way out (iterate() may throw).
  struct AlphaParamsScope {
    AlphaController& controller;
    const AlphaControllerParams saved;
    AlphaParamsScope(AlphaController& c, double reversal_growth) : controller(c), saved(c.params()) {
      AlphaControllerParams a = saved;
      a.reversal_growth = reversal_growth;
      controller.setParams(a);
    }
    ~AlphaParamsScope() { controller.setParams(saved); }
  } alpha_scope(stiff_->controller(), ms.alpha_reversal_growth);
  const RunStats before = stiff_->stats();
  const long diverged_before = diverged_steps_, repeats_before = friction_repeats_;
  long calls = 0;
  int quiet = 0, stuck = 0;
  double first = -1;
  while (rep.steps < ms.max_steps && calls < 2L * ms.max_steps) {
    if (cancel && cancel->load()) {
      rep.cancelled = true;
      break;
    }
    ++calls;
    const IterationReport it = iterate();
    stuck = it.advanced ? 0 : stuck + 1;
    if (stuck >= kMaxStuckCalls) {
      rep.stuck = true;
      break;
    }
    if (!it.advanced) continue;
    ++rep.steps;
    rep.last_increment_m = it.increment_m;
    rep.surface_mean_m = it.surface_mean_m;
    rep.surface_p95_m = it.surface_p95_m;
    if (first < 0) first = it.surface_mean_m;
    bool still = false;
    switch (ms.increment_measure) {
      case MorphingStageSettings::IncrementMeasure::kAllMax: still = it.increment_m <= ms.increment_tolerance_m; break;
      case MorphingStageSettings::IncrementMeasure::kPulledP95: still = it.pulled_increment_p95_m <= ms.increment_tolerance_m; break;
      case MorphingStageSettings::IncrementMeasure::kOffWall:
        still = it.off_wall_increment_m <= ms.increment_tolerance_m && it.wall_increment_p95_m <= ms.increment_tolerance_m;
        break;
    }
    // The volume (an O(elements) sum) only when everything else holds.
    if (still && it.alpha_held && ms.volume_tolerance_percent > 0)
      still = std::abs(volumeChangePercent()) <= ms.volume_tolerance_percent;
    quiet = it.alpha_held && still && it.step_fraction == 1.0 ? quiet + 1 : 0;
    if (progress)
      progress({stage_, rep.steps, ms.max_steps, it.increment_m, it.surface_mean_m, it.surface_p95_m, it.alpha_per_pa,
                logFraction(first, it.surface_mean_m, ms.tolerance_mean_m)});
    if (quiet >= 3) {
      rep.converged = true;
      break;
    }
  }
  // The distances at the final state (the force generator too when no iteration ran: cancelled before the first).
  const DistanceStats d = ensureMorphing().measure(simulator());
  rep.surface_mean_m = d.mean_m;
  rep.surface_p95_m = d.p95_m;
  rep.converged = rep.converged && d.mean_m <= ms.tolerance_mean_m && d.p95_m <= ms.tolerance_p95_m;
  stiff_->holdAlpha(false);
  closeReport(rep, before, since(t0));
  rep.diverged_steps = diverged_steps_ - diverged_before;
  rep.reversed_steps += rep.diverged_steps;
  rep.friction_repeats = friction_repeats_ - repeats_before;
  rep.max_slide_m = sliding_report_.max_slide_m;
  rep.volume_change_percent = volumeChangePercent();
  morphing_ = rep;
  stage_ = PipelineStage::kIdle;
  return rep;
}

}  // namespace breast_sim::core
