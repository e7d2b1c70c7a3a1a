// BreastSimNode's long jobs on the worker thread: building a case's model and pipeline (an MRI case
// segmented first), the
// precomputation (with its progress on ~state and the action's feedback) and the reset to the rest
// shape. One job at a time; the state a job ends in is published once the worker is free.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <malloc.h>
#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>

#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/mri/mri_case.h"
#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;
using node_util::seconds;

using node_util::mm;

std::unique_ptr<BreastSimNode::Engine> BreastSimNode::buildEngine(const std::string& case_file, int target_elements,
                                                                 const std::function<void(const std::string&)>& stage) const {
  auto e = std::make_unique<Engine>();
  e->case_file = case_file;
  e->model_case = std::make_unique<core::ModelCase>(core::loadModelCaseWithMri(case_file, stage));
  // A case with its own mesh (mesh:) is not meshed: the element count is the file's.
  if (target_elements > 0 && e->model_case->mesh)
    ROS_WARN_STREAM("breast_sim: case '" << e->model_case->name << "' brings its own mesh (mesh:, "
                    << e->model_case->mesh->numTets() << " tetrahedra): target_elements " << target_elements
                    << " does not apply to it");
  else if (target_elements > 0)
    e->model_case->meshing.target_elements = target_elements;
  stage("meshing");
  e->model = std::make_unique<core::SimulationModel>(core::buildSimulationModel(*e->model_case));
  stage("setup");
  e->settings = core::loadPipelineSettings(params_.settings_file.empty() ? case_file : params_.settings_file);
  if (params_.field_voxel_size_m > 0) e->settings.morphing.field.voxel_size_m = params_.field_voxel_size_m;
  fingerprintEngine(*e);
  buildPipeline(*e);
  const core::TetMesh& mesh = e->model->mesh;
  e->display = decimateSurface(mesh.nodes(), core::skinTriangles(mesh, mesh.nodeSet(core::node_sets::kSkin)),
                               params_.marker_max_triangles);
  if (mesh.hasNodeSet(core::node_sets::kChestWall)) e->wall_nodes = mesh.nodeSet(core::node_sets::kChestWall);
  e->prone_gravity_mps2 = core::proneGravity(*e->model_case, e->settings.simulation);
  e->gravity_load_mps2 = e->pipeline->supineGravityLoad();
  return e;
}

bool BreastSimNode::startJob(std::function<void()> job, std::string* why) {
  std::lock_guard<std::mutex> lock(job_mutex_);
  if (busy_.exchange(true)) {
    *why = "the node is busy loading a case or precomputing; wait until ~state is idle, or cancel a "
           "precomputation with ~cancel_precomputation";
    return false;
  }
  if (worker_.joinable()) worker_.join();  // the previous job has ended (busy_ was false)
  cancel_ = false;
  worker_ = std::thread([this, job] {
    try {
      job();
    } catch (const std::exception& e) {
      ROS_ERROR_STREAM("breast_sim: a job failed: " << e.what());
    }
    // A job frees a whole pipeline or model (hundreds of MB at 20k elements) that glibc keeps in the
    // worker thread's arena; give it back, so that resets and reloads do not grow the node.
    malloc_trim(0);
    std::optional<std::pair<uint8_t, std::string>> end;
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      end.swap(job_end_);
    }
    busy_ = false;
    // Only now: a client that sees the job's end on ~state may start the next job at once.
    if (end) setState(end->first, end->second);
  });
  return true;
}

void BreastSimNode::loadCaseJob(const std::string& case_file, int target_elements, std::string* message, bool* ok) {
  setState(breast_sim::NodeState::LOADING, "loading case '" + case_file + "'");
  const auto t0 = Clock::now();
  breast_sim::NodeState before;  // the stage and progress a failed load leaves as they were
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    before = state_;
  }
  // Each stage of the load on ~state: reading (the case and its image), segmentation (an MRI case),
  // meshing, setup (solver, multigrid levels, sliding).
  auto stage = [&](const std::string& name) {
    static const std::map<std::string, std::string> what = {
        {"reading", "reading the case and its image"},
        {"segmentation", "segmenting the prone MRI"},
        {"meshing", "meshing the model"},
        {"setup", "setting up the solver, the multigrid levels, the rest shape and the chest wall"}};
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.stage = name;
      state_.progress = 0;
      state_.step = 0;
      state_.max_steps = 0;
    }
    const auto it = what.find(name);
    setState(breast_sim::NodeState::LOADING,
             "loading case '" + case_file + "': " + (it == what.end() ? name : it->second));
  };
  std::unique_ptr<Engine> e;
  try {
    e = buildEngine(case_file, target_elements, stage);
  } catch (const std::exception& ex) {
    *ok = false;
    *message = std::string("cannot load case '") + case_file + "': " + ex.what();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.stage = before.stage;
      state_.progress = before.progress;
      state_.step = before.step;
      state_.max_steps = before.max_steps;
    }
    std::lock_guard<std::mutex> lock(engine_mutex_);
    endJob(breast_sim::NodeState::IDLE, *message + (engine_ ? "; the previous model stays" : "; no model loaded"));
    return;
  }
  std::ostringstream s;
  s << "case '" << e->model_case->name << "': ";
  if (e->model_case->mri) {
    // What the segmentation found, and against a truth how well.
    const core::MriCase& mri = *e->model_case->mri;
    const core::SegmentationReport& r = mri.segmentation.report;
    s.setf(std::ios::fixed);
    s.precision(1);
    s << "MRI " << mri.source.path << " segmented in " << r.seconds_total << " s (fat " << r.volume_ml[1]
      << " ml, fibroglandular " << r.volume_ml[2] << " ml, chest wall measured in " << 100 * r.boundary_coverage
      << " % of the breast's columns";
    if (mri.scores) {
      s.precision(3);
      s << "; against the truth: breast Dice " << mri.scores->score("breast").dice << ", chest-wall boundary mean ";
      s.precision(2);
      s << mri.scores->boundary.mean_mm << " mm, p95 " << mri.scores->boundary.p95_mm << " mm";
    }
    s << "); ";
    s.unsetf(std::ios::fixed);
    s.precision(6);
  }
  s << e->model->mesh.numTets() << " tetrahedra, " << e->model->mesh.numNodes() << " nodes, " << e->model->lesions.size()
    << " lesions, built in " << seconds(Clock::now() - t0) << " s; rest shape: ";
  // Which rest shape the lesions are simulated from (simulation.reference_state): it moves them.
  if (e->pipeline->settings().simulation.reference_state == core::SimulationSettings::ReferenceState::kUnloaded) {
    const core::UnloadedStateResult& u = e->pipeline->unloadedState();
    s << "unloaded (gravity-free; loadings " << u.iterations << ", " << u.seconds << " s, re-loaded within "
      << 1e3 * u.max_residual_m << " mm of the prone shape)";
  } else {
    s << "prone (taken as stress-free)";
  }
  *message = s.str();
  *ok = true;
  {
    std::lock_guard<std::mutex> lock(engine_mutex_);
    engine_ = std::move(e);
    restartTracking();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.case_name = engine_->model_case->name;
      state_.model_loaded = true;
      state_.precomputed = false;
      state_.stage = "idle";
      state_.progress = 0;
    }
    publishModel(*engine_, ros::Time::now(), true, false, "prone rest shape: not precomputed");
  }
  ROS_INFO_STREAM("breast_sim: " << *message);
  endJob(breast_sim::NodeState::IDLE, *message + "; request ~start_precomputation (or the ~precompute action)");
}

void BreastSimNode::precomputeJob(bool gravity_only, std::optional<PrecomputeServer::GoalHandle> goal) {
  {
    std::lock_guard<std::mutex> lock(goal_mutex_);
    goal_ = goal;
  }
  breast_sim::PrecomputeResult result;
  auto finish = [&](bool success, bool cancelled, const std::string& message) {
    result.success = success;
    result.message = message;
    std::lock_guard<std::mutex> lock(goal_mutex_);
    if (goal_) {
      if (cancelled) goal_->setCanceled(result, message);
      else if (success) goal_->setSucceeded(result, message);
      else goal_->setAborted(result, message);
      goal_.reset();
    }
  };
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    finish(false, false, "no model is loaded; load a case first (~load_case)");
    return;
  }
  Engine& e = *engine_;
  const auto t0 = Clock::now();
  setState(breast_sim::NodeState::PRECOMPUTING, "precomputation started");
  auto progress = [&](const core::PipelineProgress& p) {
    const auto now = Clock::now();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.stage = core::stageName(p.stage);
      state_.progress = p.fraction;
      state_.step = p.step;
      state_.max_steps = p.max_steps;
    }
    if (seconds(now - last_progress_pub_) >= 1.0 / params_.progress_rate_hz) {
      last_progress_pub_ = now;
      std::ostringstream s;
      s << core::stageName(p.stage) << " step " << p.step << ", increment " << mm(p.increment_m, 3);
      if (p.surface_mean_m >= 0) s << ", surface mean " << mm(p.surface_mean_m) << " p95 " << mm(p.surface_p95_m);
      setState(breast_sim::NodeState::PRECOMPUTING, s.str());
      std::lock_guard<std::mutex> gl(goal_mutex_);
      if (goal_) {
        breast_sim::PrecomputeFeedback f;
        f.stage = core::stageName(p.stage);
        f.step = p.step;
        f.max_steps = p.max_steps;
        f.fraction = p.fraction;
        f.increment_m = p.increment_m;
        f.surface_mean_m = p.surface_mean_m;
        f.alpha_per_pa = p.alpha_per_pa;
        goal_->publishFeedback(f);
      }
    }
    if (seconds(now - last_marker_pub_) >= 1.0 / params_.marker_rate_hz) {
      last_marker_pub_ = now;
      surface_pub_.publish(surfaceMarker(e.display, e.pipeline->positions(), params_.frame_id, ros::Time::now()));
    }
  };
  try {
    e.pipeline->setGravityLoad(e.pipeline->supineGravityLoad());
    e.gravity_load_mps2 = e.pipeline->supineGravityLoad();
    const core::StageReport g = e.pipeline->runGravity(progress, &cancel_);
    result.gravity_steps = g.steps;
    bool cancelled = g.cancelled;  // of the settle or the sliding stage after it
    const core::StageReport& sl = e.pipeline->slidingReport();
    bool converged = g.converged && (!sl.ran || sl.converged);
    std::ostringstream s;
    s << "gravity: " << g.steps << " steps in " << g.seconds << " s" << (g.converged ? "" : " (not settled)");
    result.surface_mean_m = result.surface_p95_m = -1;
    if (!cancelled && !gravity_only && e.settings.morphing.enabled && e.pipeline->hasTarget()) {
      const core::StageReport m = e.pipeline->runMorphing(progress, &cancel_);
      result.morphing_steps = m.steps;
      result.surface_mean_m = m.surface_mean_m;
      result.surface_p95_m = m.surface_p95_m;
      cancelled = m.cancelled;
      converged = converged && m.converged;
      s << "; morphing: " << m.steps << " steps in " << m.seconds << " s, surface mean " << mm(m.surface_mean_m)
        << " p95 " << mm(m.surface_p95_m) << (m.converged ? "" : " (tolerance not reached)");
    }
    const core::QualityStats q = core::qualityStats(e.model->mesh.tets(), e.pipeline->positions());
    result.inverted_elements = q.num_inverted;
    inverted_elements_ = q.num_inverted;
    result.seconds = seconds(Clock::now() - t0);
    s << "; " << q.num_inverted << " inverted elements; " << result.seconds << " s";
    e.precomputed = !cancelled;
    e.regions.clear();
    e.region_status = !e.settings.uncertainty.enabled ? "not computed (uncertainty: disabled in the case)"
                      : gravity_only                  ? "not computed (gravity-only precomputation)"
                      : cancelled                     ? "not computed (precomputation cancelled)"
                      : !converged                    ? "not computed (the precomputation missed a tolerance)"
                      : e.model->lesions.empty()      ? "not computed (the case has no lesions)"
                                                      : "";
    if (e.region_status.empty()) {
      // The nominal supine state is shown while the ensemble runs.
      publishModel(e, ros::Time::now(), true, false, "precomputed; computing the lesion regions");
      s << "; " << lesionRegionsJob(e);
      result.seconds = seconds(Clock::now() - t0);
      s << " (" << result.seconds << " s in all)";
    }
    restartTracking();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.precomputed = e.precomputed;
      state_.stage = cancelled ? "idle" : "done";
      state_.progress = cancelled ? state_.progress : 1.0;
    }
    publishModel(e, ros::Time::now(), true, e.precomputed,
                 e.precomputed ? "precomputed" : "precomputation cancelled: the model is not precomputed");
    if (cancelled) {
      endJob(breast_sim::NodeState::IDLE, "precomputation cancelled (" + s.str() + "); the model shows where it "
               "stopped; ~reset returns to the rest shape, ~start_precomputation starts again");
      finish(false, true, "cancelled: " + s.str());
    } else {
      writeCheckpoint(e, "the precomputation");
      endJob(breast_sim::NodeState::IDLE, "precomputed (" + s.str() + "); waiting for surface clouds");
      finish(true, false, s.str() + (converged ? "" : " (finished without meeting every tolerance)"));
    }
    ROS_INFO_STREAM("breast_sim: precomputation " << (cancelled ? "cancelled" : "done") << ": " << s.str());
  } catch (const std::exception& ex) {
    const std::string msg = std::string("precomputation failed: ") + ex.what() + "; ~reset returns to the rest shape";
    ROS_ERROR_STREAM("breast_sim: " << msg);
    e.precomputed = false;
    endJob(breast_sim::NodeState::DEGRADED, msg);
    finish(false, false, msg);
  }
}

std::string BreastSimNode::lesionRegionsJob(Engine& e) {
  const auto t0 = Clock::now();
  auto progress = [&](int index, int count, const core::PipelineProgress& p) {
    const auto now = Clock::now();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.stage = "uncertainty";
      state_.progress = (index + std::clamp(p.fraction, 0.0, 1.0)) / count;
      state_.step = index + 1;
      state_.max_steps = count;
    }
    if (seconds(now - last_progress_pub_) < 1.0 / params_.progress_rate_hz) return;
    last_progress_pub_ = now;
    std::ostringstream s;
    s << "lesion regions: sample " << index + 1 << " of " << count << ", " << core::stageName(p.stage) << " step " << p.step;
    setState(breast_sim::NodeState::PRECOMPUTING, s.str());
    std::lock_guard<std::mutex> gl(goal_mutex_);
    if (goal_) {
      breast_sim::PrecomputeFeedback f;
      f.stage = "uncertainty";
      f.step = index + 1;
      f.max_steps = count;
      f.fraction = (index + std::clamp(p.fraction, 0.0, 1.0)) / count;
      f.increment_m = p.increment_m;
      f.surface_mean_m = p.surface_mean_m;
      f.alpha_per_pa = p.alpha_per_pa;
      goal_->publishFeedback(f);
    }
  };
  std::ostringstream s;
  try {
    const core::Points nominal = e.model->lesion_embedding.positions(e.pipeline->positions());
    const core::LesionUncertainty u =
        core::estimateLesionUncertainty(*e.model_case, *e.model, e.settings, nominal, progress, &cancel_, 1,
                                        e.pipeline.get());
    if (u.valid) {
      e.regions = u.lesions;
      double largest = 0;
      for (const core::LesionRegion& r : u.lesions) largest = std::max(largest, r.semi_axes_m.x());
      s << std::lround(100 * e.settings.uncertainty.confidence) << "% regions from " << u.samples.size()
        << " runs in " << u.seconds << " s, largest semi-axis " << node_util::mm(largest);
      e.region_status = s.str();
    } else {
      s << "no lesion regions: " << u.failure;
      e.region_status = s.str();
    }
  } catch (const std::exception& ex) {
    s << "no lesion regions: " << ex.what();
    e.region_status = s.str();
  }
  ROS_INFO_STREAM("breast_sim: " << e.region_status << " (" << seconds(Clock::now() - t0) << " s)");
  return e.region_status;
}

void BreastSimNode::resetJob() {
  setState(breast_sim::NodeState::LOADING, "resetting to the prone rest shape");
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    endJob(breast_sim::NodeState::IDLE, "reset: no model is loaded");
    return;
  }
  try {
    // The new pipeline is built beside the old one and replaces it only when complete. It takes the
    // old one's multigrid levels and unloaded rest shape (the same case, model and settings): no
    // meshing, and X0 confirmed in one loading.
    const core::ProneToSupinePipeline& old = *engine_->pipeline;
    std::optional<std::vector<core::TetMesh>> levels;
    if (engine_->settings.simulation.solver.kind == core::SolverSettings::Kind::kMultigrid) levels = old.coarseMeshes();
    const bool unloaded =
        old.settings().simulation.reference_state == core::SimulationSettings::ReferenceState::kUnloaded;
    auto pipeline = std::make_unique<core::ProneToSupinePipeline>(
        *engine_->model_case, *engine_->model, engine_->settings, std::move(levels),
        unloaded ? old.model().mesh.nodes() : core::Points());
    engine_->pipeline = std::move(pipeline);
    engine_->precomputed = false;
    engine_->regions.clear();
    engine_->region_status = "not computed (reset to the rest shape)";
    engine_->gravity_load_mps2 = engine_->pipeline->supineGravityLoad();
    forgetCheckpoint(*engine_);
    restartTracking();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.precomputed = false;
      state_.stage = "idle";
      state_.progress = 0;
    }
    publishModel(*engine_, ros::Time::now(), true, false, "prone rest shape: not precomputed");
    endJob(breast_sim::NodeState::IDLE, "reset to the prone rest shape; request ~start_precomputation to precompute again");
  } catch (const std::exception& ex) {
    endJob(breast_sim::NodeState::IDLE, std::string("reset failed: ") + ex.what() + "; the previous state stays");
  }
}

void BreastSimNode::endJob(uint8_t state, const std::string& message) {
  std::lock_guard<std::mutex> sl(state_mutex_);
  job_end_ = std::make_pair(state, message);
}

}  // namespace breast_sim::ros_interface
