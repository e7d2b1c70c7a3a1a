// Stage 1 of the pipeline: the gravity precomputation with the chest wall fixed (then the sliding
// stage, sliding_stage.cpp), or with coarse_start the whole stage on the coarse model.
#include <atomic>
#include <chrono>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_internal.h"
#include "breast_sim/core/thread_budget.h"

namespace breast_sim::core {

using pipeline_detail::kMaxStuckCalls;
using pipeline_detail::logFraction;
using pipeline_detail::since;

namespace {

/// What runGravity returns: the fixed-wall settle's report, cancelled when the settle or the sliding
/// stage after it was (the caller must not go on to morphing).
StageReport gravityResult(StageReport settle, const StageReport& sliding) {
  settle.cancelled = settle.cancelled || sliding.cancelled;
  return settle;
}

}  // namespace

StageReport ProneToSupinePipeline::runGravity(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
  const ThreadCountScope threads(ThreadCountScope::Sample::reuse);  // as many threads as the steps
  const auto t0 = std::chrono::steady_clock::now();
  setTrackingMode(false);
  if (coarse_ && field_) {
    // Nested iteration: the whole stage on the coarse model, its state carried to this one (the
    // fine model settles in the morphing stage).
    coarse_running_ = true;
    const bool cancelled = coarse_->runGravity(progress, cancel).cancelled;
    coarse_running_ = false;
    gravity_ = coarse_->gravityReport();
    sliding_report_ = coarse_->slidingReport();
    // A cancelled coarse stage is not carried over (this model keeps its state).
    if (!cancelled) {
      const auto tt = std::chrono::steady_clock::now();
      startFrom(*coarse_, settings_.coarse_start.snap_tolerance_m);
      coarse_ahead_ = true;
      (sliding_report_.ran ? sliding_report_ : gravity_).seconds += since(tt);
    }
    stage_ = PipelineStage::kIdle;
    return gravityResult(gravity_, sliding_report_);
  }
  if (hasSliding() && sliding_attached_ && gravity_.converged) {
    // Once the wall slides, the fixed-wall settle does not come again: a run stopped in its sliding
    // or morphing stage and started again goes on in the sliding stage. Settling with the wall on its
    // sliding springs is not the fixed-wall stage (it could stall, or let the wall slide off by far
    // more than the run's own slide).
    Eigen::VectorXd previous = simulator().state().displacement_m;
    runSlidingStage(previous, progress, cancel);
    stage_ = PipelineStage::kIdle;
    return gravityResult(gravity_, sliding_report_);
  }
  const SettleOptions& so = settings_.simulation.settle;
  const double tol = so.increment_tolerance_m;
  StageReport rep;
  rep.ran = true;
  // The sliding report is of this call: a settle that stops early leaves it "not run" (the largest
  // slide, a state of the wall, is kept).
  const double max_slide_m = sliding_report_.max_slide_m;
  sliding_report_ = StageReport{};
  sliding_report_.max_slide_m = max_slide_m;
  stage_ = PipelineStage::kGravity;
  setTimeStep(so.time_step_s > 0 ? so.time_step_s : settings_.simulation.dynamics.time_step_s);
  Eigen::VectorXd previous = simulator().state().displacement_m;
  const RunStats before = stiff_->stats();
  double first = -1;
  long calls = 0;
  int quiet = 0, stuck = 0;
  // Stage 1: the wall fixed. Without stiffening the step is the plain co-rotated one, settled by the
  // increment; with it, by the stiffening driver's residual-and-speed criterion.
  while (rep.steps < so.max_steps && calls < 2L * so.max_steps) {
    if (cancel && cancel->load()) {
      rep.cancelled = true;
      break;
    }
    ++calls;
    const StiffeningStepResult r = stiff_->step();
    if (r.advanced) ++rep.steps;
    stuck = r.advanced ? 0 : stuck + 1;
    if (stuck >= kMaxStuckCalls) {
      rep.stuck = true;
      break;
    }
    rep.last_increment_m = increment(previous);
    if (first < 0) first = rep.last_increment_m;
    quiet = rep.last_increment_m <= tol ? quiet + 1 : 0;
    if (progress)
      progress({stage_, rep.steps, so.max_steps, rep.last_increment_m, -1, -1, r.alpha_per_pa,
                logFraction(first, rep.last_increment_m, tol)});
    const bool settled = settings_.simulation.stiffening ? stiff_->settled() : quiet >= so.consecutive_steps;
    if (r.advanced && settled) {
      rep.converged = true;
      break;
    }
  }
  closeReport(rep, before, since(t0));
  rep.volume_change_percent = volumeChangePercent();
  gravity_ = rep;

  // Sliding on the chest wall after the fixed-wall settling (sliding_stage.cpp).
  if (hasSliding() && rep.converged) runSlidingStage(previous, progress, cancel);
  stage_ = PipelineStage::kIdle;
  return gravityResult(gravity_, sliding_report_);
}

}  // namespace breast_sim::core
