// The combined prone-to-supine pipeline (seed Figure 2); see prone_to_supine.h.
#include "breast_sim/core/pipeline/prone_to_supine.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>
#include <stdexcept>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/phantom.h"

namespace breast_sim::core {

namespace {

/// A stage stops after this many stiffening calls in a row that could not advance (each already
/// tried max_reversals_per_step α increases): the state cannot go on without inverting elements.
constexpr int kMaxStuckCalls = 5;

/// Implicit sliding: a step is repeated at most this many times with the wall nodes that reversed
/// against their kinetic friction set sticking (WallSlip::stickReversed); a node set sticking cannot
/// reverse again, so the passes only catch nodes that reverse because others stopped.
constexpr int kMaxFrictionPasses = 3;

/// FNV-1a hash of the rest mesh (node coordinates and connectivity), cut to 52 bits so that a double
/// holds it exactly (never 0): which mesh a saved state (its nodes must be numbered the same way) or
/// a kept embedding belongs to.
double meshFingerprint(const TetMesh& mesh) {
  std::uint64_t h = 1469598103934665603ULL;
  auto mix = [&](const void* data, size_t bytes) {
    const auto* c = static_cast<const unsigned char*>(data);
    for (size_t k = 0; k < bytes; ++k) h = (h ^ c[k]) * 1099511628211ULL;
  };
  mix(mesh.nodes().data(), sizeof(double) * static_cast<size_t>(mesh.nodes().size()));
  mix(mesh.tets().data(), sizeof(int) * static_cast<size_t>(mesh.tets().size()));
  return static_cast<double>(h & ((std::uint64_t{1} << 52) - 1)) + 1.0;  // never 0 (0: older files)
}

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// Completion estimate: how far the increment came down from the first one towards the tolerance,
/// on a log scale.
double logFraction(double first, double now, double tolerance) {
  if (!(first > tolerance) || !(now > 0)) return now <= tolerance ? 1.0 : 0.0;
  return std::clamp(std::log(first / now) / std::log(first / tolerance), 0.0, 1.0);
}

/// What runGravity returns: the fixed-wall settle's report, cancelled when the settle or the sliding
/// stage after it was (the caller must not go on to morphing).
StageReport gravityResult(StageReport settle, const StageReport& sliding) {
  settle.cancelled = settle.cancelled || sliding.cancelled;
  return settle;
}

}  // namespace

void ProneToSupinePipeline::closeReport(StageReport& r, const RunStats& before, double seconds) const {
  const RunStats after = stiff_->stats();
  r.reversed_steps = after.reversed_steps - before.reversed_steps;
  r.reversal_limit_hits = after.reversal_limit_hits - before.reversal_limit_hits;
  r.final_alpha_per_pa = stiff_->controller().alpha();
  r.seconds = seconds;
  r.elements = model_.mesh.numTets();
}

const char* stageName(PipelineStage stage) {
  switch (stage) {
    case PipelineStage::kIdle: return "idle";
    case PipelineStage::kGravity: return "gravity";
    case PipelineStage::kSliding: return "sliding";
    case PipelineStage::kMorphing: return "morphing";
    case PipelineStage::kDone: return "done";
  }
  return "unknown";
}

ProneToSupinePipeline::ProneToSupinePipeline(const ModelCase& model_case, const SimulationModel& model,
                                             const PipelineSettings& settings)
    : case_(model_case), model_(model), settings_(settings) {
  settings_.validate();
  mesh_volume_m3_ = model_.mesh.volume();
  settings_.simulation.dynamics.gravity_mps2 = supineGravityLoad();
  build_ = buildSimulator(case_, model_, settings_.simulation);  // fixes the fixed node set
  StiffeningParams sp = settings_.stiffening;
  if (!settings_.simulation.stiffening) sp.update_moduli = false;  // co-rotated with E0 throughout
  stiff_ = std::make_unique<StiffeningSimulation>(*build_.simulator, model_.mesh, sp);
  stiff_->setGravity(settings_.simulation.dynamics.gravity_mps2);
  if (settings_.simulation.sliding) {
    if (settings_.sliding_method == PipelineSettings::SlidingMethod::kImplicit)
      slip_ = std::make_unique<WallSlip>(WallSlip::fromCase(case_, model_.mesh, settings_.sliding, wallSlipSettings()));
    else
      sliding_ = std::make_unique<ChestWallSliding>(ChestWallSliding::fromCase(case_, model_.mesh, settings_.sliding));
    // The wall band: the sliding nodes and every node of an element that touches one. The wall's
    // stick–slip drags that first layer of tissue along (its largest move was the largest move
    // off the wall in every late morphing step at 48.8k elements, nodes 1–3 mm from the wall).
    std::vector<char> wall(static_cast<size_t>(model_.mesh.numNodes()), 0);
    for (int n : slip_ ? slip_->nodes() : sliding_->nodes()) wall[static_cast<size_t>(n)] = 1;
    wall_band_ = wall;
    const Tets& T = model_.mesh.tets();
    for (int t = 0; t < model_.mesh.numTets(); ++t)
      if (wall[T(t, 0)] || wall[T(t, 1)] || wall[T(t, 2)] || wall[T(t, 3)])
        for (int k = 0; k < 4; ++k) wall_band_[static_cast<size_t>(T(t, k))] = 1;
    for (int n = 0; n < model_.mesh.numNodes(); ++n)
      if (wall_band_[static_cast<size_t>(n)]) wall_band_nodes_.push_back(n);
  }
  const MorphingStageSettings& ms = settings_.morphing;
  if (ms.enabled && !ms.target.empty() && !(ms.target == "auto" && !case_.phantom)) {
    if (ms.target == "phantom" || ms.target == "auto") {
      if (!case_.phantom)
        throw std::invalid_argument("morphing target 'phantom' needs the software phantom; case '" + case_.name +
                                    "' is an image: give a surface file as morphing.target, or set morphing.enabled: false");
      setTarget(skinTarget(case_.phantom->supine_surface));
    } else {
      setTarget(readTargetSurface(ms.target, ms.target_length_unit_m));
    }
  }
  // A case file serves models of any size (target_elements is overridden by tools and the node): the
  // coarse start is used only where it is at most half the model, and only with a morphing target
  // (the model settles in the morphing stage); else the model runs alone (the reports' elements say
  // which model each stage ran on).
  if (settings_.coarse_start.elements > 0 && 2 * settings_.coarse_start.elements <= model_.mesh.numTets() &&
      settings_.morphing.enabled && field_) {
    coarse_case_ = std::make_unique<ModelCase>(case_);
    coarse_case_->meshing.target_elements = settings_.coarse_start.elements;
    coarse_model_ = std::make_unique<SimulationModel>(buildSimulationModel(*coarse_case_));
    PipelineSettings cs = settings_;
    cs.coarse_start.elements = 0;
    coarse_ = std::make_unique<ProneToSupinePipeline>(*coarse_case_, *coarse_model_, cs);
  }
}

ProneToSupinePipeline::~ProneToSupinePipeline() = default;

Eigen::Vector3d ProneToSupinePipeline::supineGravityLoad() const {
  const Eigen::Vector3d prone = settings_.simulation.gravity_mps2 * case_.prone_gravity_direction.normalized();
  // The phantom brings its supine direction (tilted, seed 3.3); the magnitude is the settings' for both.
  const Eigen::Vector3d supine = case_.phantom && case_.phantom->gravity_supine_mps2.norm() > 0
                                     ? Eigen::Vector3d(settings_.simulation.gravity_mps2 * case_.phantom->gravity_supine_mps2.normalized())
                                     : Eigen::Vector3d(-prone);
  return supine - prone;
}

void ProneToSupinePipeline::setGravityLoad(const Eigen::Vector3d& g_mps2) { stiff_->setGravity(g_mps2); }

Eigen::Vector3d ProneToSupinePipeline::gravityLoad() const { return simulator().params().gravity_mps2; }

void ProneToSupinePipeline::setTimeStep(double dt_s) {
  DynamicsParams p = simulator().params();
  if (p.time_step_s == dt_s) return;
  p.time_step_s = dt_s;
  simulator().setParams(p);
}

double ProneToSupinePipeline::increment(Eigen::VectorXd& previous) const {
  // Largest nodal change, without a temporary (iterate() runs per tracker frame).
  const Eigen::VectorXd& u = simulator().state().displacement_m;
  double worst = 0.0;
  for (Eigen::Index i = 0; i + 2 < u.size(); i += 3) worst = std::max(worst, (u.segment<3>(i) - previous.segment<3>(i)).squaredNorm());
  previous = u;  // same size: no allocation
  return std::sqrt(worst);
}

ProneToSupinePipeline::StepMoves ProneToSupinePipeline::stepMoves(Eigen::VectorXd& previous) {
  const Eigen::VectorXd& u = simulator().state().displacement_m;
  StepMoves m;
  double all2 = 0.0, off2 = 0.0;
  wall_moves_.clear();
  for (Eigen::Index n = 0; 3 * n + 2 < u.size(); ++n) {
    const double d2 = (u.segment<3>(3 * n) - previous.segment<3>(3 * n)).squaredNorm();
    all2 = std::max(all2, d2);
    if (!wall_band_.empty() && wall_band_[static_cast<size_t>(n)]) wall_moves_.push_back(d2);
    else off2 = std::max(off2, d2);
  }
  if (!wall_moves_.empty()) {  // the ⌈0.95 n⌉-th smallest, as distanceStats' p95
    const size_t k = std::min(wall_moves_.size() - 1,
                              static_cast<size_t>(std::ceil(0.95 * static_cast<double>(wall_moves_.size()))) - 1);
    std::nth_element(wall_moves_.begin(), wall_moves_.begin() + static_cast<std::ptrdiff_t>(k), wall_moves_.end());
    m.wall_p95 = std::sqrt(wall_moves_[k]);
  }
  m.all_max = std::sqrt(all2);
  m.off_wall_max = std::sqrt(off2);
  previous = u;  // same size: no allocation
  return m;
}

double ProneToSupinePipeline::volumeChangePercent() const {
  double volume_percent = 0.0, max_u = 0.0;
  deformationMeasures(model_.mesh, simulator().state().displacement_m, volume_percent, max_u);
  return volume_percent;
}

void ProneToSupinePipeline::setTarget(const TargetSurface& target) {
  target.validate();
  // The grid covers where the model can go: its rest box, grown by the largest distance a vertex may
  // be pulled from (and the field's own margin around the target).
  Eigen::AlignedBox3d region;
  const Points x = positions();
  for (Eigen::Index i = 0; i < x.rows(); ++i) region.extend(x.row(i).transpose());
  auto distance = std::make_unique<SurfaceDistance>(target);  // validates the target first
  if (field_) {
    // A new frame (e.g. a tracker cloud): rebuild in place, reusing the grid storage (a fresh build
    // pays its page faults again); the field is unchanged if the rebuild throws.
    field_->rebuild(target, region, settings_.morphing.field);
  } else {
    field_ = std::make_shared<SurfaceVectorField>(target, region, settings_.morphing.field);
  }
  target_ = target;
  distance_ = std::move(distance);
  if (morphing_forces_) morphing_forces_->setField(field_);
  if (coarse_) coarse_->setTarget(target);
}

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
    if (!now) {
      step_start_ = simulator().state();
      step_start_factors_ = simulator().elements().modulusFactors();
    }
    const SimulationState& start = now ? now->simulation : step_start_;
    const Eigen::VectorXd& start_factors = now ? now->modulus_factors : step_start_factors_;
    const AlphaController::State start_alpha = now ? now->alpha : stiff_->controller().state();
    StiffeningStepResult r;
    for (int pass = 0;; ++pass) {
      slip_->beforeStep(simulator(), extra);
      r = stiff_->step();
      if (!r.advanced || pass >= kMaxFrictionPasses || slip_->stickReversed(simulator(), start.displacement_m) == 0) break;
      ++friction_repeats_;
      // Back to the step's start; resync() gives the stiffening driver its stress at that state (the
      // next moduli come from it) and drops the taken-back step from its history.
      simulator().restore(start);
      simulator().elements().setModulusFactors(start_factors);
      stiff_->controller().setState(start_alpha);
      stiff_->resync();
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
  // A new α search (the boundary conditions changed), from the initial α or from where it is.
  if (settings_.sliding_stage.alpha_restart == SlidingStageSettings::AlphaRestart::kCurrent)
    stiff_->controller().restart(stiff_->controller().alpha());
  else
    stiff_->restartAlphaSearch();
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

StageReport ProneToSupinePipeline::runGravity(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
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
    const bool settled = settings_.simulation.stiffening ? stiff_->stats().settled : quiet >= so.consecutive_steps;
    if (r.advanced && settled) {
      rep.converged = true;
      break;
    }
  }
  closeReport(rep, before, since(t0));
  rep.volume_change_percent = volumeChangePercent();
  gravity_ = rep;

  // Sliding on the chest wall after the fixed-wall settling: the wall nodes become moving
  // constraints, updated after every accepted step at the dynamics time step (the explicit
  // constraint update is tuned for it), until the wall stops moving and the tissue has settled.
  if (hasSliding() && rep.converged) {
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
    first = -1;
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
      quiet_steps = !moving && still ? quiet_steps + 1 : 0;
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
  stage_ = PipelineStage::kIdle;
  return gravityResult(gravity_, sliding_report_);
}

SurfaceMorphing& ProneToSupinePipeline::ensureMorphing() {
  if (!morphing_forces_) {
    std::vector<int> constrained;
    const std::vector<char>& dofs = simulator().constrainedDofs();
    for (int n = 0; n < model_.mesh.numNodes(); ++n)
      if (dofs[3 * n] || dofs[3 * n + 1] || dofs[3 * n + 2]) constrained.push_back(n);
    morphing_forces_ = std::make_unique<SurfaceMorphing>(model_.mesh, field_, model_.mesh.nodeSet(node_sets::kSkin),
                                                         constrained, settings_.morphing.forces);
    morphing_forces_->setAlongNormal(tracking_);
  }
  return *morphing_forces_;
}

void ProneToSupinePipeline::setTrackingMode(bool on) {
  tracking_ = on;
  if (slip_ && sliding_attached_) slip_->setHeld(on, simulator());
  if (morphing_forces_) morphing_forces_->setAlongNormal(on);
}

IterationReport ProneToSupinePipeline::iterate() {
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
      r.alpha_per_pa = stiff_->controller().alpha();
      mv = StepMoves{};  // back at the start: nothing moved
      it.pulled_increment_p95_m = 0.0;
    }
  }
  if (r.advanced) diverged_run_ = 0;
  last_advanced_ = r.advanced;
  it.advanced = r.advanced;
  it.reversals = r.reversals;
  it.alpha_per_pa = r.alpha_per_pa;
  it.increment_m = mv.all_max;
  it.off_wall_increment_m = mv.off_wall_max;
  it.wall_increment_p95_m = mv.wall_p95;
  it.seconds = since(t0);
  return it;
}

StageReport ProneToSupinePipeline::runMorphing(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
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
    quiet = it.alpha_held && still ? quiet + 1 : 0;
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

void ProneToSupinePipeline::run(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
  morphing_ = StageReport{};  // the reports are of this run: a cancelled gravity stage leaves morphing "not run"
  if (runGravity(progress, cancel).cancelled) return;
  if (settings_.morphing.enabled && field_ && runMorphing(progress, cancel).cancelled) return;
  stage_ = PipelineStage::kDone;
}

Points ProneToSupinePipeline::displacement() const { return simulator().displacement(); }
Points ProneToSupinePipeline::positions() const { return model_.mesh.nodes() + simulator().displacement(); }
Points ProneToSupinePipeline::lesionPositions() const { return model_.lesion_embedding.positions(positions()); }

Points ProneToSupinePipeline::slidingVectors() const {
  if (slip_) return slip_->slidingVectors(simulator());
  return sliding_ ? sliding_->slidingVectors() : Points(Points::Zero(model_.mesh.numNodes(), 3));
}

Eigen::VectorXd ProneToSupinePipeline::vonMisesStress() {
  simulator().elasticForces();  // stresses at the current state
  return simulator().elements().vonMisesStress();
}

Eigen::VectorXd ProneToSupinePipeline::modulusFactors() const { return simulator().elements().modulusFactors(); }

PipelineMetrics ProneToSupinePipeline::metrics() const {
  PipelineMetrics m;
  const Points x = positions();
  const QualityStats q = qualityStats(model_.mesh.tets(), x);
  m.inverted_elements = q.num_inverted;
  m.volume_change_percent = 100.0 * (q.total_volume_m3 / mesh_volume_m3_ - 1.0);
  m.max_displacement_m = maxNodalNorm(simulator().state().displacement_m);
  m.max_modulus_factor = modulusFactors().maxCoeff();
  m.final_alpha_per_pa = stiff_->controller().alpha();
  if (distance_) {
    m.has_target = true;
    m.surface = surfaceMatch(model_.mesh, x, model_.mesh.nodeSet(node_sets::kSkin), *distance_, target_);
  }
  return m;
}

PipelineState ProneToSupinePipeline::state() const {
  PipelineState s;
  fillState(s);
  return s;
}

void ProneToSupinePipeline::fillState(PipelineState& s) const {
  // Assignments into s's vectors reuse their storage when the sizes match.
  s.simulation = simulator().state();
  s.modulus_factors = simulator().elements().modulusFactors();
  s.alpha = stiff_->controller().state();
  if (sliding_) s.sliding_targets_m = sliding_->targets();
  if (slip_ && sliding_attached_) {
    s.sliding_targets_m = slip_->stickPoints();  // positions, not displacements
    s.sliding_slip_directions = slip_->slipDirections();
  }
  if (!sliding_ && !(slip_ && sliding_attached_)) {
    s.sliding_targets_m.resize(0, 3);
    s.sliding_slip_directions.resize(0, 3);
  }
  if (morphing_forces_) s.morphing_forces_n = morphing_forces_->accumulatedForces();
  else s.morphing_forces_n.resize(0, 3);
  s.stage = stage_;
  s.gravity_load_mps2 = gravityLoad();
}

void ProneToSupinePipeline::restore(const PipelineState& s) {
  const Eigen::Index n3 = 3 * static_cast<Eigen::Index>(model_.mesh.numNodes());
  if (s.simulation.displacement_m.size() != n3 || s.simulation.velocity_mps.size() != n3 ||
      s.modulus_factors.size() != model_.mesh.numTets())
    throw std::invalid_argument("pipeline state of another model: " + std::to_string(s.simulation.displacement_m.size() / 3) +
                                " nodes and " + std::to_string(s.modulus_factors.size()) + " elements, this model has " +
                                std::to_string(model_.mesh.numNodes()) + " and " + std::to_string(model_.mesh.numTets()));
  const size_t sliding_nodes = slip_ ? slip_->nodes().size() : sliding_ ? sliding_->nodes().size() : 0;
  if (s.sliding_targets_m.rows() > 0 && (!hasSliding() || s.sliding_targets_m.rows() != static_cast<Eigen::Index>(sliding_nodes)))
    throw std::invalid_argument("pipeline state has sliding targets for " + std::to_string(s.sliding_targets_m.rows()) +
                                " nodes, but sliding is " + (hasSliding() ? "on for " + std::to_string(sliding_nodes) + " nodes" : "off"));
  if (s.morphing_forces_n.rows() > 0 && !field_)
    throw std::invalid_argument("pipeline state has morphing forces, but no target surface is set");
  if (!s.gravity_load_mps2.allFinite())
    throw std::invalid_argument("pipeline state has a gravity load that is not finite (norm " +
                                std::to_string(s.gravity_load_mps2.norm()) + " m/s²)");
  simulator().restore(s.simulation);
  // Directly, not through setGravityLoad: the α controller's state below is the snapshot's, not a
  // restarted search.
  simulator().setGravity(s.gravity_load_mps2);
  simulator().elements().setModulusFactors(s.modulus_factors);
  stiff_->controller().setState(s.alpha);
  stiff_->resync();  // the stress the next moduli come from is this state's
  if (slip_ && s.sliding_targets_m.rows() > 0) {
    slip_->setStickPoints(s.sliding_targets_m, s.sliding_slip_directions);
    slip_->attach(simulator());
    sliding_attached_ = true;
  }
  if (sliding_ && s.sliding_targets_m.rows() > 0) {
    attachSliding();
    sliding_->setTargets(simulator(), s.sliding_targets_m);
  }
  simulator().clearExternalForces();
  if (s.morphing_forces_n.rows() > 0) ensureMorphing().restoreForces(simulator(), s.morphing_forces_n);
  last_advanced_ = true;
  coarse_ahead_ = false;  // this state is the one to go on from
  stage_ = s.stage;
}

void ProneToSupinePipeline::startFrom(const ProneToSupinePipeline& coarse, double snap_tolerance_m) {
  if (static_cast<bool>(slip_) != static_cast<bool>(coarse.slip_) || static_cast<bool>(sliding_) != static_cast<bool>(coarse.sliding_))
    throw std::invalid_argument(std::string("startFrom: sliding differs (coarse: ") +
                                (coarse.slip_ ? "implicit" : coarse.sliding_ ? "explicit" : "off") + ", this model: " +
                                (slip_ ? "implicit" : sliding_ ? "explicit" : "off") + "); use the same settings for both");
  if (coarse.morphing_forces_ && !field_)
    throw std::invalid_argument("startFrom: the coarse run has morphing forces, but this model has no target surface (setTarget first)");
  const TetMesh& cm = coarse.model_.mesh;
  const Points& rest = model_.mesh.nodes();
  // Rest nodes and element centroids of this model in the coarse rest mesh (everything is
  // validated before this pipeline changes).
  // They depend on the two rest meshes alone: kept for the next start from the same coarse mesh
  // (runGravity and runMorphing both start from the coarse model).
  const double fingerprint = meshFingerprint(cm);
  if (!coarse_embedding_ || coarse_embedding_->fingerprint != fingerprint ||
      coarse_embedding_->snap_tolerance_m != snap_tolerance_m) {
    auto e = std::make_unique<CoarseEmbedding>();
    e->nodes = PointEmbedding(cm, rest, {}, snap_tolerance_m);
    Points centroids(model_.mesh.numTets(), 3);
    const Tets& T = model_.mesh.tets();
    for (int t = 0; t < model_.mesh.numTets(); ++t)
      centroids.row(t) = 0.25 * (rest.row(T(t, 0)) + rest.row(T(t, 1)) + rest.row(T(t, 2)) + rest.row(T(t, 3)));
    e->centroids = PointEmbedding(cm, centroids, {}, snap_tolerance_m);
    e->fingerprint = fingerprint;
    e->snap_tolerance_m = snap_tolerance_m;
    coarse_embedding_ = std::move(e);
  }
  const PointEmbedding& at_nodes = coarse_embedding_->nodes;
  const PointEmbedding& at_centroids = coarse_embedding_->centroids;

  const SimulationState& cs = coarse.simulator().state();
  auto asPoints = [](const Eigen::VectorXd& v) {
    return Points(Eigen::Map<const Points>(v.data(), v.size() / 3, 3));
  };
  auto asVector = [](const Points& p) { return Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(p.data(), p.size())); };
  PipelineState s;
  const Points u = at_nodes.interpolate(asPoints(cs.displacement_m));
  s.simulation.displacement_m = asVector(u);
  s.simulation.velocity_mps = asVector(at_nodes.interpolate(asPoints(cs.velocity_mps)));
  s.simulation.time_s = cs.time_s;
  s.simulation.step = cs.step;
  const Eigen::VectorXd coarse_factors = coarse.modulusFactors();
  s.modulus_factors.resize(model_.mesh.numTets());
  for (int t = 0; t < model_.mesh.numTets(); ++t) s.modulus_factors[t] = coarse_factors[at_centroids.points()[t].tet];
  s.alpha = coarse.stiff_->controller().state();
  s.stage = coarse.stage_;
  if (coarse.sliding_attached_) {
    // Each wall node takes the friction state of the nearest coarse wall node (rest positions): its
    // stick point's (or explicit target's) offset from where that node is now, and its slip direction.
    const std::vector<int>& wall = slip_ ? slip_->nodes() : sliding_->nodes();
    const std::vector<int>& cwall = slip_ ? coarse.slip_->nodes() : coarse.sliding_->nodes();
    const Points& ctargets = slip_ ? coarse.slip_->stickPoints() : coarse.sliding_->targets();
    const Points cdirections = slip_ ? coarse.slip_->slipDirections() : Points();
    const Points cu = asPoints(cs.displacement_m);
    s.sliding_targets_m.resize(static_cast<Eigen::Index>(wall.size()), 3);
    if (slip_) s.sliding_slip_directions = Points::Zero(s.sliding_targets_m.rows(), 3);
    for (size_t i = 0; i < wall.size(); ++i) {
      const Eigen::Index row = static_cast<Eigen::Index>(i);
      size_t nearest = 0;
      double best = std::numeric_limits<double>::infinity();
      for (size_t j = 0; j < cwall.size(); ++j) {
        const double d2 = (cm.nodes().row(cwall[j]) - rest.row(wall[i])).squaredNorm();
        if (d2 < best) best = d2, nearest = j;
      }
      const Eigen::Index crow = static_cast<Eigen::Index>(nearest);
      // Stick points are positions, explicit targets displacements.
      Eigen::RowVector3d cnow = cu.row(cwall[nearest]), now = u.row(wall[i]);
      if (slip_) cnow += cm.nodes().row(cwall[nearest]), now += rest.row(wall[i]);
      s.sliding_targets_m.row(row) = now + (ctargets.row(crow) - cnow);
      if (slip_) s.sliding_slip_directions.row(row) = cdirections.row(crow);
    }
  }
  // The gravity load before the α state: a direction change would restart the α search.
  s.gravity_load_mps2 = coarse.gravityLoad();
  stiff_->setGravity(s.gravity_load_mps2);
  restore(s);

  if (!coarse.morphing_forces_) return;
  // Morphing forces as tractions, carried to this model's pulled vertices.
  const SurfaceMorphing& cmorph = *coarse.morphing_forces_;
  const std::vector<int>& cv = cmorph.vertices();
  const Points& cf = cmorph.accumulatedForces();
  const Eigen::VectorXd& ca = cmorph.vertexAreas();
  SurfaceMorphing& morph = ensureMorphing();
  const std::vector<int>& fv = morph.vertices();
  Points forces = Points::Zero(static_cast<Eigen::Index>(fv.size()), 3);
  constexpr int kNearest = 4;
  std::vector<std::pair<double, int>> d2(cv.size());
  for (size_t j = 0; j < fv.size(); ++j) {
    const Eigen::RowVector3d p = rest.row(fv[j]);
    for (size_t i = 0; i < cv.size(); ++i) d2[i] = {(cm.nodes().row(cv[i]) - p).squaredNorm(), static_cast<int>(i)};
    const size_t k = std::min<size_t>(kNearest, d2.size());
    std::partial_sort(d2.begin(), d2.begin() + static_cast<std::ptrdiff_t>(k), d2.end());
    Eigen::RowVector3d traction = Eigen::RowVector3d::Zero();
    double wsum = 0.0;
    for (size_t q = 0; q < k; ++q) {
      const int i = d2[q].second;
      // 1/d² weights; a coincident vertex (within 1 nm) gives its own traction.
      if (d2[q].first <= 1e-18) {
        traction = cf.row(i) / ca[i];
        wsum = 1.0;
        break;
      }
      const double w = 1.0 / d2[q].first;
      traction += w * cf.row(i) / ca[i];
      wsum += w;
    }
    if (wsum > 0) forces.row(static_cast<Eigen::Index>(j)) = traction / wsum * morph.vertexAreas()[static_cast<Eigen::Index>(j)];
  }
  morph.restoreForces(simulator(), forces);
}

namespace {
constexpr char kMagic[8] = {'B', 'S', 'S', 'T', 'A', 'T', 'E', '1'};

void writeVector(std::ofstream& out, const double* data, std::int64_t n) {
  out.write(reinterpret_cast<const char*>(&n), sizeof n);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(n * sizeof(double)));
}

Eigen::VectorXd readVector(std::ifstream& in, const std::string& path) {
  std::int64_t n = 0;
  in.read(reinterpret_cast<char*>(&n), sizeof n);
  if (!in || n < 0 || n > (std::int64_t{1} << 34)) throw std::runtime_error(path + ": truncated or corrupt state file");
  Eigen::VectorXd v(n);
  in.read(reinterpret_cast<char*>(v.data()), static_cast<std::streamsize>(n * sizeof(double)));
  if (!in) throw std::runtime_error(path + ": truncated state file");
  return v;
}

Points toPoints(const Eigen::VectorXd& v) {
  Points p(v.size() / 3, 3);
  for (Eigen::Index i = 0; i < p.rows(); ++i) p.row(i) = v.segment<3>(3 * i).transpose();
  return p;
}

Eigen::VectorXd flatten(const Points& p) {
  Eigen::VectorXd v(3 * p.rows());
  for (Eigen::Index i = 0; i < p.rows(); ++i) v.segment<3>(3 * i) = p.row(i).transpose();
  return v;
}
}  // namespace

void ProneToSupinePipeline::saveState(const std::string& path) const {
  const PipelineState s = state();
  std::ofstream out(path, std::ios::binary);
  if (!out) throw std::runtime_error(path + ": cannot write the state file (check the folder exists and is writable)");
  out.write(kMagic, sizeof kMagic);
  const double header[10] = {static_cast<double>(model_.mesh.numNodes()), static_cast<double>(model_.mesh.numTets()),
                             s.simulation.time_s, static_cast<double>(s.simulation.step), s.alpha.alpha_per_pa,
                             static_cast<double>(s.alpha.phase == AlphaController::Phase::kSettling), s.alpha.rate,
                             static_cast<double>(s.alpha.oscillations), static_cast<double>(s.stage),
                             meshFingerprint(model_.mesh)};
  writeVector(out, header, 10);
  const double runs[3] = {static_cast<double>(s.alpha.runs[0]), static_cast<double>(s.alpha.runs[1]), static_cast<double>(s.alpha.runs[2])};
  writeVector(out, runs, 3);
  writeVector(out, s.simulation.displacement_m.data(), s.simulation.displacement_m.size());
  writeVector(out, s.simulation.velocity_mps.data(), s.simulation.velocity_mps.size());
  writeVector(out, s.modulus_factors.data(), s.modulus_factors.size());
  const Eigen::VectorXd st = flatten(s.sliding_targets_m), mf = flatten(s.morphing_forces_n);
  writeVector(out, st.data(), st.size());
  writeVector(out, mf.data(), mf.size());
  // Appended after the first format (a file without it loads with every wall node sticking).
  const Eigen::VectorXd sd = flatten(s.sliding_slip_directions);
  writeVector(out, sd.data(), sd.size());
  // Appended after the second (a file without it loads under the supine gravity load).
  writeVector(out, s.gravity_load_mps2.data(), 3);
  if (!out) throw std::runtime_error(path + ": writing the state file failed (disk full?)");
}

void ProneToSupinePipeline::loadState(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot open the state file");
  char magic[8];
  in.read(magic, sizeof magic);
  if (!in || std::memcmp(magic, kMagic, sizeof kMagic) != 0)
    throw std::runtime_error(path + ": not a breast_sim state file (written by saveState / the node's save_state)");
  const Eigen::VectorXd h = readVector(in, path);
  const Eigen::VectorXd runs = readVector(in, path);
  if (h.size() != 10 || runs.size() != 3) throw std::runtime_error(path + ": corrupt state file header");
  if (static_cast<int>(h[0]) != model_.mesh.numNodes() || static_cast<int>(h[1]) != model_.mesh.numTets())
    throw std::runtime_error(path + ": the state is of a model with " + std::to_string(static_cast<long>(h[0])) + " nodes and " +
                             std::to_string(static_cast<long>(h[1])) + " elements; this model has " +
                             std::to_string(model_.mesh.numNodes()) + " and " + std::to_string(model_.mesh.numTets()) +
                             " (load the same case with the same meshing first)");
  if (h[9] != meshFingerprint(model_.mesh))
    throw std::runtime_error(path + (h[9] == 0.0 ? ": the state file was written by an older breast_sim, whose mesh "
                                                    "nodes were numbered differently; precompute the state again"
                                                  : ": the state is of a mesh with the same size but other nodes (another "
                                                    "case, meshing option or breast_sim version); load the case it was "
                                                    "saved with, or precompute again"));
  PipelineState s;
  s.simulation.time_s = h[2];
  s.simulation.step = static_cast<long>(h[3]);
  s.alpha.alpha_per_pa = h[4];
  s.alpha.phase = h[5] != 0.0 ? AlphaController::Phase::kSettling : AlphaController::Phase::kSearch;
  s.alpha.rate = h[6];
  s.alpha.oscillations = static_cast<int>(h[7]);
  s.stage = static_cast<PipelineStage>(std::clamp(static_cast<int>(h[8]), 0, static_cast<int>(PipelineStage::kDone)));
  for (int k = 0; k < 3; ++k) s.alpha.runs[k] = static_cast<int>(runs[k]);
  s.simulation.displacement_m = readVector(in, path);
  s.simulation.velocity_mps = readVector(in, path);
  s.modulus_factors = readVector(in, path);
  s.sliding_targets_m = toPoints(readVector(in, path));
  s.morphing_forces_n = toPoints(readVector(in, path));
  if (in.peek() != std::char_traits<char>::eof()) s.sliding_slip_directions = toPoints(readVector(in, path));
  s.gravity_load_mps2 = supineGravityLoad();
  if (in.peek() != std::char_traits<char>::eof()) {
    const Eigen::VectorXd g = readVector(in, path);
    if (g.size() != 3) throw std::runtime_error(path + ": corrupt state file (a gravity load of " + std::to_string(g.size()) + " values)");
    s.gravity_load_mps2 = g;
  }
  try {
    restore(s);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
}

}  // namespace breast_sim::core
