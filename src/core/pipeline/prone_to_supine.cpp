// The prone-to-supine pipeline (seed Figure 2; see prone_to_supine.h): construction, the target,
// the gravity load, the per-step measures the stages share, run() and the state accessors. The
// stages are in gravity_stage.cpp, sliding_stage.cpp and morphing_stage.cpp, the nested iteration in
// coarse_start.cpp, snapshots and their files in pipeline_state.cpp.
#include "breast_sim/core/pipeline/prone_to_supine.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/thread_budget.h"

namespace breast_sim::core {
namespace {

/// The multigrid's coarse levels of the prone domain: `given`, or meshed here (`seconds` set); none
/// for the other solvers, which refuse given ones.
std::vector<TetMesh> coarseLevels(const ModelCase& model_case, const SimulationModel& prone, const PipelineSettings& settings,
                                  std::optional<std::vector<TetMesh>> given, double& seconds) {
  if (settings.simulation.solver.kind != SolverSettings::Kind::kMultigrid) {
    if (given && !given->empty())
      throw std::invalid_argument("ProneToSupinePipeline: " + std::to_string(given->size()) +
                                  " coarse meshes given, but they are used only by the solver 'multigrid' (the solver is '" +
                                  SolverSettings::kindName(settings.simulation.solver.kind) + "')");
    return {};
  }
  if (given) return std::move(*given);
  const auto t = std::chrono::steady_clock::now();
  std::vector<TetMesh> levels = buildCoarseMeshes(model_case, prone, settings.simulation.solver.coarsening);
  seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
  return levels;
}

/// X0 for reference_state unloaded (null for prone), recovered with the run's element, stiffening,
/// fixed wall and solver (the multigrid on `coarse`, the levels of the prone domain).
std::unique_ptr<SimulationModel> unloadedModel(const ModelCase& model_case, const SimulationModel& prone,
                                               const PipelineSettings& settings, const std::vector<TetMesh>& coarse,
                                               const Points& start, double tolerance_m, UnloadedStateResult& result) {
  if (settings.simulation.reference_state != SimulationSettings::ReferenceState::kUnloaded) return nullptr;
  const SimulationSettings& s = settings.simulation;
  UnloadedStateOptions options;
  options.stiffening = settings.stiffening;
  options.coarse_meshes = coarse;
  options.initial_unloaded_nodes_m = start;
  options.tolerance_m = tolerance_m;
  result = recoverUnloadedShape(prone.mesh, s, proneGravity(model_case, settings.simulation), options);
  if (!result.converged) {
    char best[160] = "";
    if (!result.history.empty())
      std::snprintf(best, sizeof best, "; the best one re-loads to within %.4f mm of the prone shape (mean %.4f mm, tolerance %.4f mm)",
                    1e3 * result.max_residual_m, 1e3 * result.mean_residual_m, 1e3 * options.tolerance_m);
    throw std::runtime_error("case '" + model_case.name + "': the unloaded (gravity-free) shape was not found: " +
                             result.failure + best +
                             ". Set simulation.reference_state: prone to take the prone shape as stress-free, or check "
                             "the material (tissue too soft for prone gravity folds when it is unloaded)");
  }
  auto model = std::make_unique<SimulationModel>(prone);
  model->mesh = withNodes(prone.mesh, result.unloaded_nodes_m);
  return model;
}

/// The settings validated, with the reference state resolved for the case.
PipelineSettings validated(const ModelCase& model_case, PipelineSettings settings, double unloaded_tolerance_m) {
  settings.validate();
  if (!(unloaded_tolerance_m > 0.0) || !std::isfinite(unloaded_tolerance_m))
    throw std::invalid_argument("ProneToSupinePipeline: unloaded_tolerance_m = " + std::to_string(unloaded_tolerance_m) +
                                " is invalid: expected a finite length > 0 [m], e.g. 1e-5");
  SimulationSettings& s = settings.simulation;
  s.reference_state = s.resolvedReferenceState(model_case.phantom != nullptr);
  return settings;
}

}  // namespace

Eigen::Vector3d proneGravity(const ModelCase& model_case, const SimulationSettings& settings) {
  return settings.gravity_mps2 * model_case.prone_gravity_direction.normalized();
}

void ProneToSupinePipeline::closeReport(StageReport& r, const RunStats& before, double seconds) const {
  const RunStats after = stiff_->stats();
  r.reversed_steps = after.reversed_steps - before.reversed_steps;
  r.reversal_limit_hits = after.reversal_limit_hits - before.reversal_limit_hits;
  r.shortened_steps = after.shortened_steps - before.shortened_steps;
  r.final_alpha_per_pa = stiff_->alpha();
  r.modulus_excess = after.max_modulus_excess;
  r.locally_stiffened_elements = after.locally_stiffened_elements;
  r.locally_stiffened_volume_percent = after.locally_stiffened_volume_percent;
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
                                             const PipelineSettings& settings,
                                             std::optional<std::vector<TetMesh>> coarse_meshes,
                                             const Points& unloaded_start_m, double unloaded_tolerance_m)
    : case_(model_case),
      settings_(validated(model_case, settings, unloaded_tolerance_m)),
      prone_model_(model),
      coarse_meshes_(coarseLevels(model_case, model, settings_, std::move(coarse_meshes), coarse_meshing_s_)),
      unloaded_tolerance_m_(unloaded_tolerance_m),
      unloaded_model_(unloadedModel(model_case, model, settings_, coarse_meshes_, unloaded_start_m, unloaded_tolerance_m,
                                    unloaded_)),
      model_(unloaded_model_ ? *unloaded_model_ : model) {
  if (unloaded_model_) gravity_offset_mps2_ = proneGravity(case_, settings_.simulation);
  settings_.simulation.dynamics.gravity_mps2 = supineGravityLoad() + gravity_offset_mps2_;
  std::optional<std::vector<TetMesh>> coarse;
  if (settings_.simulation.solver.kind == SolverSettings::Kind::kMultigrid) coarse = coarse_meshes_;
  // The levels mesh the prone domain: the multigrid on X0 takes the prone shape's prolongations.
  build_ = buildSimulator(case_, model_, settings_.simulation, std::move(coarse),
                          unloaded_model_ ? prone_model_.mesh.nodes() : Points());  // fixes the fixed node set
  build_.hierarchy_seconds += coarse_meshing_s_;
  if (unloaded_model_) {
    // The run starts at the prone shape, X0's equilibrium under prone gravity.
    SimulationState start = simulator().state();
    const Points& x0 = model_.mesh.nodes();
    const Points& prone = prone_model_.mesh.nodes();
    for (Eigen::Index n = 0; n < x0.rows(); ++n)
      start.displacement_m.segment<3>(3 * n) = (prone.row(n) - x0.row(n)).transpose();
    start.velocity_mps.setZero();
    simulator().restore(start);
  }
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
    coarse_ = std::make_unique<ProneToSupinePipeline>(*coarse_case_, *coarse_model_, cs, std::nullopt, Points(),
                                                      unloaded_tolerance_m_);
  }
}

ProneToSupinePipeline::~ProneToSupinePipeline() = default;

Eigen::Vector3d ProneToSupinePipeline::supineGravityLoad() const {
  const Eigen::Vector3d prone = proneGravity(case_, settings_.simulation);
  // The phantom brings its supine direction (tilted, seed 3.3); the magnitude is the settings' for both.
  const Eigen::Vector3d supine = case_.phantom && case_.phantom->gravity_supine_mps2.norm() > 0
                                     ? Eigen::Vector3d(settings_.simulation.gravity_mps2 * case_.phantom->gravity_supine_mps2.normalized())
                                     : Eigen::Vector3d(-prone);
  return supine - prone;
}

void ProneToSupinePipeline::setGravityLoad(const Eigen::Vector3d& g_mps2) { stiff_->setGravity(g_mps2 + gravity_offset_mps2_); }

Eigen::Vector3d ProneToSupinePipeline::gravityLoad() const { return simulator().params().gravity_mps2 - gravity_offset_mps2_; }

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
  // Of the prone volume (the rest shape's differs with reference_state unloaded).
  return 100.0 * (model_.mesh.volume() * (1.0 + 0.01 * volume_percent) / prone_model_.mesh.volume() - 1.0);
}

void ProneToSupinePipeline::setTarget(const TargetSurface& target) {
  const ThreadCountScope threads(ThreadCountScope::Sample::reuse);  // as many threads as the steps
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

void ProneToSupinePipeline::run(const PipelineProgressFn& progress, const std::atomic<bool>* cancel) {
  morphing_ = StageReport{};  // the reports are of this run: a cancelled gravity stage leaves morphing "not run"
  if (runGravity(progress, cancel).cancelled) return;
  if (settings_.morphing.enabled && field_ && runMorphing(progress, cancel).cancelled) return;
  stage_ = PipelineStage::kDone;
}

Points ProneToSupinePipeline::displacement() const {
  Points u = simulator().displacement();  // from the rest shape
  if (unloaded_model_) u += model_.mesh.nodes() - prone_model_.mesh.nodes();
  return u;
}
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
  m.volume_change_percent = 100.0 * (q.total_volume_m3 / prone_model_.mesh.volume() - 1.0);
  m.max_displacement_m = displacement().rowwise().norm().maxCoeff();
  m.max_modulus_factor = modulusFactors().maxCoeff();
  m.final_alpha_per_pa = stiff_->alpha();
  if (distance_) {
    m.has_target = true;
    m.surface = surfaceMatch(model_.mesh, x, model_.mesh.nodeSet(node_sets::kSkin), *distance_, target_);
  }
  return m;
}

}  // namespace breast_sim::core
