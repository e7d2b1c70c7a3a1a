// The breast_sim navigation node: wiring only (see breast_sim_node.h); the science is in the core.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <cmath>
#include <malloc.h>
#include <limits>
#include <sstream>

#include <diagnostic_msgs/DiagnosticArray.h>
#include <ros/package.h>
#include <tf2/exceptions.h>

#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/phantom.h"

namespace breast_sim::ros_interface {

namespace {

using Clock = std::chrono::steady_clock;

double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

const char* stateName(uint8_t s) {
  switch (s) {
    case breast_sim::NodeState::IDLE: return "idle";
    case breast_sim::NodeState::LOADING: return "loading";
    case breast_sim::NodeState::PRECOMPUTING: return "precomputing";
    case breast_sim::NodeState::TRACKING: return "tracking";
    case breast_sim::NodeState::DEGRADED: return "degraded";
  }
  return "unknown";
}

std::string mm(double m, int precision = 2) {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(precision);
  s << 1e3 * m << " mm";
  return s.str();
}

template <typename T>
T param(const ros::NodeHandle& pnh, const std::string& name, const T& fallback) {
  T v;
  return pnh.getParam(name, v) ? v : fallback;
}

void require(bool ok, const std::string& name, const std::string& what) {
  if (!ok) throw std::invalid_argument("parameter ~" + name + ": " + what);
}

}  // namespace

NodeParams NodeParams::fromRos(const ros::NodeHandle& pnh) {
  NodeParams p;
  p.case_file = param<std::string>(pnh, "case_file", ros::package::getPath("breast_sim") + "/config/phantom_default.yaml");
  p.target_elements = param(pnh, "target_elements", p.target_elements);
  p.settings_file = param(pnh, "settings_file", p.settings_file);
  p.field_voxel_size_m = param(pnh, "field_voxel_size_m", p.field_voxel_size_m);
  p.frame_id = param(pnh, "frame_id", p.frame_id);
  p.precompute_on_start = param(pnh, "precompute_on_start", p.precompute_on_start);
  p.gravity_frame = param(pnh, "gravity/frame", p.gravity_frame);
  p.follow_patient_pose = param(pnh, "gravity/follow_patient_pose", p.follow_patient_pose);
  p.gravity_update_threshold_deg = param(pnh, "gravity/update_threshold_deg", p.gravity_update_threshold_deg);
  p.publish_pose_tf = param(pnh, "gravity/publish_pose_tf", p.publish_pose_tf);
  p.pose_jump.max_jump_m = param(pnh, "gravity/max_pose_jump_m", p.pose_jump.max_jump_m);
  p.pose_jump.max_jump_deg = param(pnh, "gravity/max_pose_jump_deg", p.pose_jump.max_jump_deg);
  p.pose_jump.window_s = param(pnh, "gravity/pose_jump_window_s", p.pose_jump.window_s);
  TrackerOptions& t = p.tracker;
  t.filter.voxel_leaf_m = param(pnh, "tracking/voxel_leaf_m", t.filter.voxel_leaf_m);
  t.filter.remove_outliers = param(pnh, "tracking/remove_outliers", t.filter.remove_outliers);
  t.filter.outlier_neighbours = param(pnh, "tracking/outlier_neighbours", t.filter.outlier_neighbours);
  t.filter.outlier_stddev = param(pnh, "tracking/outlier_stddev", t.filter.outlier_stddev);
  t.icp.enabled = param(pnh, "tracking/icp/enabled", t.icp.enabled);
  t.icp.max_iterations = param(pnh, "tracking/icp/max_iterations", t.icp.max_iterations);
  t.icp.max_points = param(pnh, "tracking/icp/max_points", t.icp.max_points);
  t.icp.max_correspondence_m = param(pnh, "tracking/icp/max_correspondence_m", t.icp.max_correspondence_m);
  t.icp.max_translation_m = param(pnh, "tracking/icp/max_translation_m", t.icp.max_translation_m);
  t.icp.max_rotation_deg = param(pnh, "tracking/icp/max_rotation_deg", t.icp.max_rotation_deg);
  t.icp.max_rms_m = param(pnh, "tracking/icp/max_rms_m", t.icp.max_rms_m);
  t.icp.min_inlier_fraction = param(pnh, "tracking/icp/min_inlier_fraction", t.icp.min_inlier_fraction);
  t.max_point_distance_m = param(pnh, "tracking/max_point_distance_m", t.max_point_distance_m);
  t.iterations_per_frame = param(pnh, "tracking/iterations_per_frame", t.iterations_per_frame);
  t.solver_relative_tolerance = param(pnh, "tracking/solver_relative_tolerance", t.solver_relative_tolerance);
  t.min_points = param(pnh, "tracking/min_points", t.min_points);
  t.hold_unseen_skin_m = param(pnh, "tracking/hold_unseen_skin_m", t.hold_unseen_skin_m);
  p.max_cloud_points = static_cast<size_t>(param(pnh, "tracking/max_cloud_points", static_cast<int>(p.max_cloud_points)));
  p.max_transform_age_s = param(pnh, "tracking/max_transform_age_s", p.max_transform_age_s);
  p.tf_wait_s = param(pnh, "tracking/tf_wait_s", p.tf_wait_s);
  p.require_precomputation = param(pnh, "tracking/require_precomputation", p.require_precomputation);
  MonitorLimits& m = p.monitor;
  m.refused_frames = param(pnh, "tracking/degraded_after_rejected", m.refused_frames);
  m.max_seen_mean_m = param(pnh, "tracking/monitor/max_seen_mean_m", m.max_seen_mean_m);
  m.max_seen_p95_m = param(pnh, "tracking/monitor/max_seen_p95_m", m.max_seen_p95_m);
  m.min_seen_fraction = param(pnh, "tracking/monitor/min_seen_fraction", m.min_seen_fraction);
  m.max_wall_drift_m = param(pnh, "tracking/monitor/max_wall_drift_m", m.max_wall_drift_m);
  m.max_rigid_drift_m = param(pnh, "tracking/monitor/max_rigid_drift_m", m.max_rigid_drift_m);
  m.max_lesion_offset_m = param(pnh, "tracking/monitor/max_lesion_offset_m", m.max_lesion_offset_m);
  m.max_lesion_jump_m = param(pnh, "tracking/monitor/max_lesion_jump_m", m.max_lesion_jump_m);
  m.recover_frames = param(pnh, "tracking/monitor/recover_frames", m.recover_frames);
  m.recover_fraction = param(pnh, "tracking/monitor/recover_fraction", m.recover_fraction);
  p.stamps.max_future_s = param(pnh, "tracking/max_future_stamp_s", p.stamps.max_future_s);
  p.stamps.max_age_s = param(pnh, "tracking/max_stamp_age_s", p.stamps.max_age_s);
  p.tracking_timeout_s = param(pnh, "tracking/timeout_s", p.tracking_timeout_s);
  p.mesh_rate_hz = param(pnh, "publish/mesh_rate_hz", p.mesh_rate_hz);
  p.marker_rate_hz = param(pnh, "publish/marker_rate_hz", p.marker_rate_hz);
  p.marker_max_triangles = param(pnh, "publish/marker_max_triangles", p.marker_max_triangles);
  p.publish_lesion_tf = param(pnh, "publish/lesion_tf", p.publish_lesion_tf);
  p.lesion_frame_prefix = param(pnh, "publish/lesion_frame_prefix", p.lesion_frame_prefix);
  p.sliding_arrow_scale = param(pnh, "publish/sliding_arrow_scale", p.sliding_arrow_scale);
  p.sliding_min_length_m = param(pnh, "publish/sliding_min_length_m", p.sliding_min_length_m);
  p.sliding_max_arrows = param(pnh, "publish/sliding_max_arrows", p.sliding_max_arrows);
  p.diagnostics_period_s = param(pnh, "publish/diagnostics_period_s", p.diagnostics_period_s);
  p.progress_rate_hz = param(pnh, "publish/progress_rate_hz", p.progress_rate_hz);
  p.warn_throttle_s = param(pnh, "warn_throttle_s", p.warn_throttle_s);

  require(p.target_elements >= 0, "target_elements", "must be ≥ 0 (0 keeps the case's meshing.target_elements)");
  require(p.field_voxel_size_m >= 0 && p.field_voxel_size_m < 0.1, "field_voxel_size_m", "must be in [0, 0.1) m");
  require(!p.frame_id.empty(), "frame_id", "must not be empty");
  require(t.filter.voxel_leaf_m >= 0 && t.filter.voxel_leaf_m < 0.1, "tracking/voxel_leaf_m", "must be in [0, 0.1) m");
  require(t.filter.outlier_neighbours >= 1, "tracking/outlier_neighbours", "must be ≥ 1");
  require(t.filter.outlier_stddev > 0, "tracking/outlier_stddev", "must be > 0");
  require(t.icp.max_iterations >= 1, "tracking/icp/max_iterations", "must be ≥ 1");
  require(t.icp.max_correspondence_m > 0, "tracking/icp/max_correspondence_m", "must be > 0 m");
  require(t.icp.max_rms_m > 0, "tracking/icp/max_rms_m", "must be > 0 m");
  require(t.icp.min_inlier_fraction >= 0 && t.icp.min_inlier_fraction <= 1, "tracking/icp/min_inlier_fraction",
          "must be in [0, 1]");
  require(t.max_point_distance_m >= 0, "tracking/max_point_distance_m", "must be ≥ 0 m (0 = keep every point)");
  require(p.stamps.max_future_s > 0, "tracking/max_future_stamp_s", "must be > 0 s");
  require(p.stamps.max_age_s > 0, "tracking/max_stamp_age_s", "must be > 0 s");
  require(p.pose_jump.max_jump_m > 0, "gravity/max_pose_jump_m", "must be > 0 m");
  require(p.pose_jump.max_jump_deg > 0, "gravity/max_pose_jump_deg", "must be > 0 deg");
  require(p.pose_jump.window_s >= 0, "gravity/pose_jump_window_s", "must be ≥ 0 s");
  m.validate();
  require(t.iterations_per_frame >= 1 && t.iterations_per_frame <= 100, "tracking/iterations_per_frame", "must be in [1, 100]");
  require(t.solver_relative_tolerance >= 0 && t.solver_relative_tolerance < 1, "tracking/solver_relative_tolerance",
          "must be in [0, 1) (0 = the case's simulation.solver_relative_tolerance)");
  require(t.min_points >= 10, "tracking/min_points", "must be ≥ 10");
  require(t.hold_unseen_skin_m >= 0, "tracking/hold_unseen_skin_m", "must be ≥ 0 m (0 = off)");
  require(p.max_cloud_points >= 1000, "tracking/max_cloud_points", "must be ≥ 1000");
  require(p.max_transform_age_s > 0, "tracking/max_transform_age_s", "must be > 0 s");
  require(p.tf_wait_s >= 0 && p.tf_wait_s <= 1.0, "tracking/tf_wait_s", "must be in [0, 1] s");
  require(p.mesh_rate_hz >= 0, "publish/mesh_rate_hz", "must be ≥ 0 Hz (0 = every frame)");
  require(p.marker_rate_hz > 0, "publish/marker_rate_hz", "must be > 0 Hz");
  require(p.diagnostics_period_s > 0, "publish/diagnostics_period_s", "must be > 0 s");
  require(p.progress_rate_hz > 0, "publish/progress_rate_hz", "must be > 0 Hz");
  require(p.warn_throttle_s >= 0, "warn_throttle_s", "must be ≥ 0 s");
  return p;
}

BreastSimNode::BreastSimNode(ros::NodeHandle nh, ros::NodeHandle pnh)
    : nh_(nh), pnh_(pnh), tf_buffer_(ros::Duration(30.0)) {}

BreastSimNode::~BreastSimNode() {
  cancel_ = true;
  {
    std::lock_guard<std::mutex> lock(cloud_mutex_);
    stop_ = true;
  }
  cloud_cv_.notify_all();
  if (tracking_thread_.joinable()) tracking_thread_.join();
  std::lock_guard<std::mutex> lock(job_mutex_);
  if (worker_.joinable()) worker_.join();
}

void BreastSimNode::initialize() {
  params_ = NodeParams::fromRos(pnh_);
  guard_ = GuardedTracker(params_.tracker, params_.monitor);
  throttle_.setPeriod(params_.warn_throttle_s);
  tf_listener_ = std::make_unique<tf2_ros::TransformListener>(tf_buffer_, nh_);
  mesh_pub_ = pnh_.advertise<breast_sim::TetrahedralMesh>("deformed_mesh", 1, /*latch=*/true);
  lesions_pub_ = pnh_.advertise<breast_sim::LesionArray>("lesions", 1, /*latch=*/true);
  lesion_markers_pub_ = pnh_.advertise<visualization_msgs::MarkerArray>("lesion_markers", 1, true);
  surface_pub_ = pnh_.advertise<visualization_msgs::Marker>("surface_marker", 1, true);
  sliding_pub_ = pnh_.advertise<visualization_msgs::MarkerArray>("sliding_vectors", 1, true);
  state_pub_ = pnh_.advertise<breast_sim::NodeState>("state", 1, true);
  diag_pub_ = nh_.advertise<diagnostic_msgs::DiagnosticArray>("/diagnostics", 10);
  services_.push_back(pnh_.advertiseService("load_case", &BreastSimNode::loadCaseSrv, this));
  services_.push_back(pnh_.advertiseService("start_precomputation", &BreastSimNode::startPrecomputationSrv, this));
  services_.push_back(pnh_.advertiseService("cancel_precomputation", &BreastSimNode::cancelSrv, this));
  services_.push_back(pnh_.advertiseService("reset", &BreastSimNode::resetSrv, this));
  services_.push_back(pnh_.advertiseService("save_state", &BreastSimNode::saveStateSrv, this));
  services_.push_back(pnh_.advertiseService("load_state", &BreastSimNode::loadStateSrv, this));
  action_ = std::make_unique<PrecomputeServer>(
      pnh_, "precompute", [this](PrecomputeServer::GoalHandle g) { goalCb(g); },
      [this](PrecomputeServer::GoalHandle g) { cancelGoalCb(g); }, false);
  action_->start();
  cloud_sub_ = pnh_.subscribe("surface_points", 2, &BreastSimNode::cloudCb, this);
  pose_sub_ = pnh_.subscribe("patient_pose", 10, &BreastSimNode::poseCb, this);
  window_start_ = Clock::now();
  diag_timer_ = nh_.createWallTimer(ros::WallDuration(params_.diagnostics_period_s), &BreastSimNode::publishDiagnostics, this);
  tracking_thread_ = std::thread([this] { trackingLoop(); });

  // The first case loads on the worker; the node answers at once.
  const std::string case_file = params_.case_file;
  const int target = params_.target_elements;
  const bool precompute = params_.precompute_on_start;
  std::string why;
  startJob([this, case_file, target, precompute] {
    std::string message;
    bool ok = false;
    loadCaseJob(case_file, target, &message, &ok);
    if (!ok) {
      ROS_ERROR_STREAM("breast_sim: " << message << "; no model until a case loads (~load_case)");
      return;
    }
    if (precompute) precomputeJob(false, std::nullopt);
  }, &why);
}

// ------------------------------------------------------------------------------------------------
// Long jobs

std::unique_ptr<BreastSimNode::Engine> BreastSimNode::buildEngine(const std::string& case_file, int target_elements) const {
  auto e = std::make_unique<Engine>();
  e->case_file = case_file;
  e->model_case = std::make_unique<core::ModelCase>(core::loadModelCase(case_file));
  if (target_elements > 0) e->model_case->meshing.target_elements = target_elements;
  e->model = std::make_unique<core::SimulationModel>(core::buildSimulationModel(*e->model_case));
  e->settings = core::loadPipelineSettings(params_.settings_file.empty() ? case_file : params_.settings_file);
  if (params_.field_voxel_size_m > 0) e->settings.morphing.field.voxel_size_m = params_.field_voxel_size_m;
  e->pipeline = std::make_unique<core::ProneToSupinePipeline>(*e->model_case, *e->model, e->settings);
  const core::TetMesh& mesh = e->model->mesh;
  e->display = decimateSurface(mesh.nodes(), core::skinTriangles(mesh, mesh.nodeSet(core::node_sets::kSkin)),
                               params_.marker_max_triangles);
  if (mesh.hasNodeSet(core::node_sets::kChestWall)) e->wall_nodes = mesh.nodeSet(core::node_sets::kChestWall);
  e->prone_gravity_mps2 = e->settings.simulation.gravity_mps2 * e->model_case->prone_gravity_direction.normalized();
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
  std::unique_ptr<Engine> e;
  try {
    e = buildEngine(case_file, target_elements);
  } catch (const std::exception& ex) {
    *ok = false;
    *message = std::string("cannot load case '") + case_file + "': " + ex.what();
    std::lock_guard<std::mutex> lock(engine_mutex_);
    endJob(breast_sim::NodeState::IDLE, *message + (engine_ ? "; the previous model stays" : "; no model loaded"));
    return;
  }
  std::ostringstream s;
  s << "case '" << e->model_case->name << "': " << e->model->mesh.numTets() << " tetrahedra, "
    << e->model->mesh.numNodes() << " nodes, " << e->model->lesions.size() << " lesions, built in "
    << seconds(Clock::now() - t0) << " s";
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

// ------------------------------------------------------------------------------------------------
// Services and action

bool BreastSimNode::loadCaseSrv(breast_sim::LoadCase::Request& req, breast_sim::LoadCase::Response& res) {
  // Answers when the model is built (seconds); other callbacks keep being served meanwhile.
  std::string message, why;
  bool ok = false;
  std::mutex m;
  std::condition_variable cv;
  bool done = false;
  const std::string file = req.case_file;
  const int target = req.target_elements;
  if (!startJob([&, file, target] {
        loadCaseJob(file, target, &message, &ok);
        std::lock_guard<std::mutex> l(m);
        done = true;
        cv.notify_all();
      }, &why)) {
    res.success = false;
    res.message = why;
    return true;
  }
  std::unique_lock<std::mutex> l(m);
  cv.wait(l, [&] { return done; });
  res.success = ok;
  res.message = message;
  if (!ok) ROS_WARN_STREAM("breast_sim: " << message << "; keeping the previous model");
  return true;
}

bool BreastSimNode::startPrecomputationSrv(breast_sim::StartPrecomputation::Request& req,
                                           breast_sim::StartPrecomputation::Response& res) {
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    if (!state_.model_loaded && !busy_) {
      res.accepted = false;
      res.message = "no model is loaded; load a case first (~load_case)";
      return true;
    }
  }
  const bool gravity_only = req.gravity_only;
  std::string why;
  res.accepted = startJob([this, gravity_only] { precomputeJob(gravity_only, std::nullopt); }, &why);
  res.message = res.accepted ? std::string("precomputation started (") + (gravity_only ? "gravity only" : "gravity and morphing") +
                                   "); progress on ~state"
                             : why;
  return true;
}

bool BreastSimNode::cancelSrv(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::lock_guard<std::mutex> sl(state_mutex_);
  if (state_.state != breast_sim::NodeState::PRECOMPUTING) {
    res.success = false;
    res.message = std::string("no precomputation is running (state: ") + state_.state_name + ")";
    return true;
  }
  cancel_ = true;
  res.success = true;
  res.message = "cancelling: the precomputation stops after its current step; ~state says when";
  return true;
}

bool BreastSimNode::resetSrv(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    if (!state_.model_loaded && !busy_) {
      res.success = false;
      res.message = "no model is loaded";
      return true;
    }
  }
  // Rebuilding the pipeline takes seconds (solver and multigrid levels): on the worker.
  std::string why;
  res.success = startJob([this] { resetJob(); }, &why);
  res.message = res.success ? "resetting to the prone rest shape on the worker; ~state says when it is done"
                            : "busy (loading or precomputing); cancel the precomputation first (~cancel_precomputation)";
  return true;
}

void BreastSimNode::resetJob() {
  setState(breast_sim::NodeState::LOADING, "resetting to the prone rest shape");
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    endJob(breast_sim::NodeState::IDLE, "reset: no model is loaded");
    return;
  }
  try {
    // The new pipeline is built beside the old one and replaces it only when complete.
    auto pipeline = std::make_unique<core::ProneToSupinePipeline>(*engine_->model_case, *engine_->model, engine_->settings);
    engine_->pipeline = std::move(pipeline);
    engine_->precomputed = false;
    engine_->gravity_load_mps2 = engine_->pipeline->supineGravityLoad();
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

bool BreastSimNode::saveStateSrv(breast_sim::StateFile::Request& req, breast_sim::StateFile::Response& res) {
  if (busy_) {
    res.success = false;
    res.message = "busy (loading or precomputing); save when ~state is idle or tracking";
    return true;
  }
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    res.success = false;
    res.message = "no model is loaded";
    return true;
  }
  try {
    engine_->pipeline->saveState(req.path);
    res.success = true;
    res.message = "saved the state of case '" + engine_->model_case->name + "' (" +
                  std::to_string(engine_->model->mesh.numNodes()) + " nodes) to " + req.path;
  } catch (const std::exception& ex) {
    res.success = false;
    res.message = ex.what();
  }
  return true;
}

bool BreastSimNode::loadStateSrv(breast_sim::StateFile::Request& req, breast_sim::StateFile::Response& res) {
  if (busy_) {
    res.success = false;
    res.message = "busy (loading or precomputing); load when ~state is idle or tracking";
    return true;
  }
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    res.success = false;
    res.message = "no model is loaded; load the case the state belongs to first (~load_case)";
    return true;
  }
  try {
    engine_->pipeline->loadState(req.path);
    engine_->gravity_load_mps2 = engine_->pipeline->gravityLoad();  // the state's, for the pose-update rule
    engine_->precomputed = true;
    restartTracking();
    {
      std::lock_guard<std::mutex> sl(state_mutex_);
      state_.precomputed = true;
      state_.stage = "done";
      state_.progress = 1.0;
    }
    publishModel(*engine_, ros::Time::now(), true, true, "loaded state " + req.path);
    res.success = true;
    res.message = "loaded " + req.path + "; the model is precomputed and follows surface clouds";
    setState(breast_sim::NodeState::IDLE, res.message);
  } catch (const std::exception& ex) {
    res.success = false;
    res.message = std::string(ex.what()) + "; the previous state is kept";
  }
  return true;
}

void BreastSimNode::goalCb(PrecomputeServer::GoalHandle goal) {
  const bool gravity_only = goal.getGoal()->gravity_only;
  std::string why;
  bool loaded;
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    loaded = state_.model_loaded;
  }
  breast_sim::PrecomputeResult r;
  if (!loaded && !busy_) {
    r.message = "no model is loaded; load a case first (~load_case)";
    goal.setRejected(r, r.message);
    return;
  }
  if (busy_) {
    r.message = "the node is busy loading a case or precomputing; send the goal when ~state is idle";
    goal.setRejected(r, r.message);
    return;
  }
  goal.setAccepted("accepted");
  if (!startJob([this, gravity_only, goal] { precomputeJob(gravity_only, goal); }, &why)) {
    r.message = why;
    goal.setAborted(r, why);
  }
}

void BreastSimNode::cancelGoalCb(PrecomputeServer::GoalHandle goal) {
  std::lock_guard<std::mutex> lock(goal_mutex_);
  if (goal_ && *goal_ == goal) cancel_ = true;
}

// ------------------------------------------------------------------------------------------------
// Tracking

void BreastSimNode::cloudCb(const sensor_msgs::PointCloud2ConstPtr& msg) {
  {
    std::lock_guard<std::mutex> lock(cloud_mutex_);
    if (pending_cloud_) {
      std::lock_guard<std::mutex> sl(stats_mutex_);
      ++window_.dropped;  // the tracking thread had not taken the previous one: newest wins
    }
    pending_cloud_ = msg;
    pending_received_ = Clock::now();
  }
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    ++window_.clouds;
  }
  cloud_cv_.notify_one();
}

void BreastSimNode::poseCb(const geometry_msgs::PoseStampedConstPtr& msg) {
  const std::string stamp_why =
      checkStamp(msg->header.stamp.toSec(), ros::Time::now().toSec(), params_.stamps, "~patient_pose");
  if (!stamp_why.empty()) {
    warn("pose stamp", "breast_sim: ~patient_pose refused: " + stamp_why + "; gravity and transforms keep their last values");
    return;
  }
  Eigen::Isometry3d t;
  try {
    t = isometryFromPose(msg->pose);  // refuses non-finite values and quaternions not of unit length
  } catch (const std::exception& ex) {
    warn("pose value", std::string("breast_sim: ~patient_pose refused: ") + ex.what() +
                           "; gravity and transforms keep their last values");
    return;
  }
  if (msg->header.frame_id.empty() || msg->header.frame_id == params_.frame_id) {
    warn("pose frame", "breast_sim: ~patient_pose must give the pose of '" + params_.frame_id +
                           "' in another frame (header.frame_id = '" + msg->header.frame_id +
                           "'); refused, gravity and transforms keep their last values");
    return;
  }
  geometry_msgs::TransformStamped ts;
  ts.header = msg->header;
  ts.child_frame_id = params_.frame_id;
  ts.transform = transformFromIsometry(t);
  const double stamp = msg->header.stamp.toSec();
  bool broadcast = false;
  {
    std::lock_guard<std::mutex> lock(pose_mutex_);
    // Time went back (a bag played again, a simulator restarted), or another frame: the kept poses
    // are of another run.
    if (pose_ && (msg->header.stamp + ros::Duration(1.0) < pose_->header.stamp ||
                  msg->header.frame_id != pose_->header.frame_id)) {
      pose_history_.clear();
      pose_.reset();
      last_pose_tf_stamp_ = ros::Time();
      time_went_back_ = true;  // publishModel forgets its newest lesion stamp too
    }
    // A jump is measured from the last accepted pose, or, without one close in time, from the pose
    // tf2 has for the model frame (another source of the same pose: they must agree).
    Eigen::Isometry3d reference;
    double reference_stamp = 0;
    bool have_reference = false;
    if (pose_ && std::abs(stamp - pose_->header.stamp.toSec()) <= params_.pose_jump.window_s) {
      reference = pose_accepted_;
      reference_stamp = pose_->header.stamp.toSec();
      have_reference = true;
    } else {
      for (const ros::Time& at : {msg->header.stamp, ros::Time(0)}) {
        if (!tf_buffer_.canTransform(msg->header.frame_id, params_.frame_id, at)) continue;
        const geometry_msgs::TransformStamped tf = tf_buffer_.lookupTransform(msg->header.frame_id, params_.frame_id, at);
        reference = isometryFromTransform(tf.transform);
        reference_stamp = tf.header.stamp.isZero() ? stamp : tf.header.stamp.toSec();
        have_reference = true;
        break;
      }
    }
    if (have_reference) {
      const std::string jump = checkPoseJump(reference, reference_stamp, t, stamp, params_.pose_jump);
      if (!jump.empty()) {
        warn("pose jump", "breast_sim: ~patient_pose refused: " + jump + "; gravity and transforms keep their last values");
        return;
      }
    }
    pose_history_.add(stamp, t);
    if (!pose_ || msg->header.stamp >= pose_->header.stamp) {
      pose_ = msg;
      pose_accepted_ = t;
    }
    // Every tf2 listener drops data older than what it has: broadcast only newer stamps.
    if (params_.publish_pose_tf && msg->header.stamp > last_pose_tf_stamp_) {
      last_pose_tf_stamp_ = msg->header.stamp;
      broadcast = true;
    }
  }
  if (broadcast) tf_broadcaster_.sendTransform(ts);
}

void BreastSimNode::warn(const std::string& key, const std::string& text) {
  long suppressed;
  {
    std::lock_guard<std::mutex> lock(warn_mutex_);
    suppressed = throttle_.suppressed(key);
    if (!throttle_.allow(key, ros::WallTime::now().toSec())) return;
  }
  if (suppressed > 0) ROS_WARN_STREAM(text << " (" << suppressed << " more like it in the last " << params_.warn_throttle_s << " s)");
  else ROS_WARN_STREAM(text);
}

void BreastSimNode::restartTracking() {
  guard_.stop();
  last_lesion_tf_stamp_ = ros::Time();
}

bool BreastSimNode::lookup(const std::string& target, const std::string& source, const ros::Time& stamp,
                           Eigen::Isometry3d* t, std::string* why) {
  std::string err;
  const auto deadline = Clock::now() + std::chrono::duration<double>(params_.tf_wait_s);
  while (true) {
    err.clear();  // tf2 appends its reason to the string on every failed call
    if (tf_buffer_.canTransform(target, source, stamp, &err)) {
      *t = isometryFromTransform(tf_buffer_.lookupTransform(target, source, stamp).transform);
      return true;
    }
    if (Clock::now() >= deadline) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  // Not at the cloud's time: the newest transform, if recent enough (or static).
  std::string err0;
  if (tf_buffer_.canTransform(target, source, ros::Time(0), &err0)) {
    const geometry_msgs::TransformStamped latest = tf_buffer_.lookupTransform(target, source, ros::Time(0));
    const double age = std::abs((stamp - latest.header.stamp).toSec());
    if (latest.header.stamp.isZero() || age <= params_.max_transform_age_s) {
      *t = isometryFromTransform(latest.transform);
      return true;
    }
    std::ostringstream s;
    s << "stale transform '" << source << "' -> '" << target << "': the newest is " << age
      << " s away from the cloud's stamp (tracking/max_transform_age_s = " << params_.max_transform_age_s << " s)";
    *why = s.str();
    return false;
  }
  *why = "no transform '" + source + "' -> '" + target + "' (" + (err.empty() ? err0 : err) + ")";
  return false;
}

bool BreastSimNode::cloudTransform(const std::string& frame, const ros::Time& stamp, Eigen::Isometry3d* t,
                                   std::string* why) {
  if (frame.empty()) {
    *why = "the cloud has no header.frame_id";
    return false;
  }
  if (frame == params_.frame_id) {
    *t = Eigen::Isometry3d::Identity();
    return true;
  }
  Eigen::Isometry3d pose_frame_from_model;
  std::string pose_frame;
  if (poseAt(stamp, params_.max_transform_age_s, &pose_frame_from_model, &pose_frame)) {
    const Eigen::Isometry3d model_from_pose_frame = pose_frame_from_model.inverse();
    if (frame == pose_frame) {
      *t = model_from_pose_frame;
      return true;
    }
    Eigen::Isometry3d pose_from_cloud;
    if (lookup(pose_frame, frame, stamp, &pose_from_cloud, why)) {
      *t = model_from_pose_frame * pose_from_cloud;
      return true;
    }
    return false;
  }
  return lookup(params_.frame_id, frame, stamp, t, why);
}

bool BreastSimNode::poseAt(const ros::Time& stamp, double max_age_s, Eigen::Isometry3d* frame_from_model,
                           std::string* frame) {
  std::lock_guard<std::mutex> lock(pose_mutex_);
  if (!pose_) return false;
  *frame = pose_->header.frame_id;
  // Between two poses at most twice the allowed age apart, else the nearest within the age.
  return pose_history_.at(stamp.toSec(), 2 * params_.max_transform_age_s, max_age_s, frame_from_model);
}

bool BreastSimNode::gravityRotation(const ros::Time& stamp, Eigen::Matrix3d* r) {
  if (!params_.follow_patient_pose) return false;
  Eigen::Isometry3d pose_frame_from_model;
  std::string pose_frame;
  // A pose of any age: the newest known table orientation is the best guess of gravity.
  if (poseAt(stamp, std::numeric_limits<double>::infinity(), &pose_frame_from_model, &pose_frame)) {
    const Eigen::Matrix3d model_from_pose = pose_frame_from_model.linear().transpose();
    if (pose_frame == params_.gravity_frame) {
      *r = model_from_pose;
      return true;
    }
    for (const ros::Time& at : {stamp, ros::Time(0)})  // at the cloud's time, else the newest
      if (tf_buffer_.canTransform(pose_frame, params_.gravity_frame, at)) {
        *r = model_from_pose *
             isometryFromTransform(tf_buffer_.lookupTransform(pose_frame, params_.gravity_frame, at).transform).linear();
        return true;
      }
  }
  for (const ros::Time& at : {stamp, ros::Time(0)})
    if (tf_buffer_.canTransform(params_.frame_id, params_.gravity_frame, at)) {
      *r = isometryFromTransform(tf_buffer_.lookupTransform(params_.frame_id, params_.gravity_frame, at).transform).linear();
      return true;
    }
  return false;
}

void BreastSimNode::applyGravity(Engine& e, const ros::Time& stamp) {
  Eigen::Matrix3d r;
  if (!gravityRotation(stamp, &r)) return;  // no pose and no tf: the precomputed (case) gravity stays
  const Eigen::Vector3d load = gravityLoad(r, e.settings.simulation.gravity_mps2, e.prone_gravity_mps2);
  if (gravityLoadChanged(load, e.gravity_load_mps2, params_.gravity_update_threshold_deg, e.settings.simulation.gravity_mps2)) {
    e.pipeline->setGravityLoad(load);
    e.gravity_load_mps2 = load;
  }
}

void BreastSimNode::countRejected(const std::string& reason) {
  std::lock_guard<std::mutex> sl(stats_mutex_);
  ++window_.rejected;
  ++total_rejected_;
  last_reject_ = reason;
}

void BreastSimNode::rejectFrame(const std::string& reason) {
  countRejected(reason);
  std::lock_guard<std::mutex> lock(engine_mutex_);
  if (!engine_ || !engine_->precomputed) return;
  const bool was_valid = guard_.valid();
  guard_.refused(reason);
  if (was_valid && !guard_.valid()) {
    // The lesions last published were valid; say at once that they no longer are.
    publishModel(*engine_, ros::Time::now(), false, false, guard_.reason());
    setState(breast_sim::NodeState::DEGRADED, guard_.reason() + "; the model keeps its last good state and the "
             "lesions are not valid until tracking recovers");
  }
}

void BreastSimNode::trackingLoop() {
  while (true) {
    sensor_msgs::PointCloud2ConstPtr msg;
    Clock::time_point received;
    {
      std::unique_lock<std::mutex> lock(cloud_mutex_);
      cloud_cv_.wait(lock, [this] { return stop_ || pending_cloud_; });
      if (stop_) return;
      msg = pending_cloud_;
      received = pending_received_;
      pending_cloud_.reset();
    }
    try {
      processCloud(msg, received);
    } catch (const std::exception& ex) {
      // Nothing a cloud holds may stop the node: report and go on with the next one.
      warn("cloud exception", std::string("breast_sim: a cloud could not be tracked: ") + ex.what() +
                                  "; the model keeps its last good state, the next cloud is tried");
      rejectFrame(ex.what());
    }
  }
}

void BreastSimNode::processCloud(const sensor_msgs::PointCloud2ConstPtr& msg, Clock::time_point received) {
  if (busy_) {
    ROS_INFO_STREAM_THROTTLE(params_.warn_throttle_s,
                             "breast_sim: a job (loading, precomputing, reset) runs; clouds are ignored until it ends");
    return;
  }
  // 0. When it was measured: a future stamp would be re-broadcast with the lesion frames and break
  // every tf2 listener; a stale one no longer shows the patient.
  const std::string stamp_why = checkStamp(msg->header.stamp.toSec(), ros::Time::now().toSec(), params_.stamps, "cloud");
  if (!stamp_why.empty()) {
    warn("cloud stamp", "breast_sim: cloud on ~surface_points refused: " + stamp_why + "; the model keeps its last state");
    rejectFrame(stamp_why);
    return;
  }
  // 1. Points, in the cloud's frame.
  CloudPoints cp;
  try {
    cp = pointsFromCloud(*msg, params_.max_cloud_points);
  } catch (const std::invalid_argument& ex) {
    warn("cloud malformed", std::string("breast_sim: malformed cloud on ~surface_points: ") + ex.what() +
                                "; it is dropped and the model keeps its last state");
    rejectFrame(ex.what());
    return;
  }
  if (cp.total == 0) {
    warn("cloud empty", "breast_sim: empty cloud on ~surface_points; it is dropped and the model keeps its last state");
    rejectFrame("empty cloud");
    return;
  }
  if (cp.stride > 1)
    warn("cloud large", "breast_sim: cloud of " + std::to_string(cp.total) + " points, more than tracking/max_cloud_points = " +
                            std::to_string(params_.max_cloud_points) + "; every " + std::to_string(cp.stride) +
                            "th point is used");
  if (cp.non_finite > 0 && cp.points_m.rows() < params_.tracker.min_points) {
    warn("cloud non-finite", "breast_sim: " + std::to_string(cp.non_finite) + " of " + std::to_string(cp.total) +
                                 " cloud points are NaN/inf, too few remain; the cloud is dropped and the model keeps "
                                 "its last state");
    rejectFrame("cloud of non-finite points");
    return;
  }
  // (Finite points among NaN padding, as an organized depth image has them, are tracked as they are.)
  // 2. Into the model frame.
  Eigen::Isometry3d model_from_cloud;
  std::string why;
  if (!cloudTransform(msg->header.frame_id, msg->header.stamp, &model_from_cloud, &why)) {
    warn("cloud transform " + msg->header.frame_id,
         "breast_sim: cloud in frame '" + msg->header.frame_id + "' cannot be put into '" + params_.frame_id + "': " + why +
             "; it is dropped and the model keeps its last state");
    rejectFrame(why);
    return;
  }
  const core::Points cloud = transformPoints(model_from_cloud, cp.points_m);

  // 3. Track, guarded by the monitor.
  std::unique_lock<std::mutex> lock(engine_mutex_);
  if (!engine_) {
    ROS_WARN_STREAM_THROTTLE(params_.warn_throttle_s, "breast_sim: no model is loaded; clouds are ignored until a case loads (~load_case)");
    return;
  }
  Engine& e = *engine_;
  if (params_.require_precomputation && !e.precomputed) {
    ROS_WARN_STREAM_THROTTLE(params_.warn_throttle_s, "breast_sim: the model is not precomputed; clouds are ignored until "
                             "~start_precomputation (or ~load_state) has run");
    return;
  }
  applyGravity(e, msg->header.stamp);
  const bool was_valid = guard_.valid();
  const GuardedFrame f = guard_.frame(*e.pipeline, cloud);
  e.gravity_load_mps2 = e.pipeline->gravityLoad();  // a frame taken back restores the load it had
  if (!f.track.tracked) {
    lock.unlock();
    warn("cloud refused", "breast_sim: cloud refused: " + f.track.reason + "; the model keeps its last state");
    countRejected(f.track.reason);
    if (was_valid && !f.valid) {
      std::lock_guard<std::mutex> relock(engine_mutex_);
      if (engine_) publishModel(*engine_, ros::Time::now(), false, false, f.status);
      setState(breast_sim::NodeState::DEGRADED, f.status + "; the model keeps its last good state and the lesions are "
               "not valid until tracking recovers");
    }
    return;
  }
  if (f.restored)
    warn("monitor " + std::to_string(static_cast<int>(f.verdict.recovery)),
         "breast_sim: tracking frame past a limit: " + f.verdict.reason + "; " +
             (f.verdict.recovery == Recovery::kReference ? "the model is back at its precomputed state"
                                                          : "the frame was taken back") +
             ", the lesions are not valid until " + std::to_string(params_.monitor.recover_frames) +
             " good frames in a row");
  // 4. Publish (header stamp = the cloud's, so consumers can match them).
  publishModel(e, msg->header.stamp, false, f.valid, f.status);
  const double latency = seconds(Clock::now() - received);
  const auto now = Clock::now();
  inverted_elements_ = f.quality.inverted_elements;
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    ++window_.tracked;
    ++total_tracked_;
    if (f.restored) ++total_taken_back_;
    window_.latency_sum_s += latency;
    window_.latency_max_s = std::max(window_.latency_max_s, latency);
    window_.step_sum_s += f.track.iterate_s;
    window_.field_sum_s += f.track.field_s;
    window_.icp_sum_s += f.track.icp_s;
    window_.filter_sum_s += f.track.filter_s;
    window_.points_in += f.track.points_in;
    window_.points_used += f.track.points_used;
    surface_mean_m_ = f.track.seen_mean_m;
    surface_p95_m_ = f.track.seen_p95_m;
    alpha_ = f.track.last.alpha_per_pa;
    icp_rms_m_ = f.track.icp_rms_m;
    skin_seen_ = f.track.skin_seen;
    skin_held_ = f.track.skin_held;
    quality_ = f.quality;
    lesions_valid_ = f.valid;
    lesion_status_ = f.status;
    last_tracked_ = now;
  }
  lock.unlock();
  if (f.valid) setState(breast_sim::NodeState::TRACKING, "tracking: " + f.status, false);
  else setState(breast_sim::NodeState::DEGRADED, f.status + "; the lesions are not valid", false);
}

// ------------------------------------------------------------------------------------------------
// Publishing

void BreastSimNode::publishModel(Engine& e, const ros::Time& stamp, bool force_all, bool valid,
                                 const std::string& status) {
  const auto now = Clock::now();
  const core::Points x = e.pipeline->positions();
  const core::Points lesions = e.model->lesion_embedding.positions(x);
  if (force_all || params_.mesh_rate_hz <= 0 || seconds(now - last_mesh_pub_) >= 1.0 / params_.mesh_rate_hz) {
    last_mesh_pub_ = now;
    mesh_pub_.publish(toMessage(e.model->mesh, x - e.model->mesh.nodes(), params_.frame_id, stamp));
  }
  lesions_pub_.publish(lesionsMessage(e.model->lesions, lesions, params_.frame_id, stamp, valid, status));
  if (time_went_back_.exchange(false)) last_lesion_tf_stamp_ = ros::Time();
  // Frames only for lesions the node vouches for, and only newer stamps (a tf2 listener drops a
  // frame older than the newest it holds and warns about one at the same stamp).
  if (params_.publish_lesion_tf && valid && !e.model->lesions.empty() && stamp > last_lesion_tf_stamp_) {
    last_lesion_tf_stamp_ = stamp;
    tf_broadcaster_.sendTransform(lesionTransforms(e.model->lesions, lesions, params_.frame_id,
                                                   params_.lesion_frame_prefix, stamp));
  }
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    lesions_valid_ = valid;
    lesion_status_ = status;
  }
  if (force_all || seconds(now - last_marker_pub_) >= 1.0 / params_.marker_rate_hz) {
    last_marker_pub_ = now;
    surface_pub_.publish(surfaceMarker(e.display, x, params_.frame_id, stamp));
    lesion_markers_pub_.publish(lesionMarkers(e.model->lesions, lesions, params_.frame_id, stamp));
    if (e.pipeline->sliding())
      sliding_pub_.publish(slidingMarkers(x, e.pipeline->slidingVectors(), e.wall_nodes, params_.sliding_arrow_scale,
                                          params_.sliding_min_length_m, params_.sliding_max_arrows, params_.frame_id,
                                          stamp));
    else if (force_all)
      sliding_pub_.publish(slidingMarkers(x, core::Points::Zero(x.rows(), 3), {}, 1.0, 1.0, 0, params_.frame_id, stamp));
  }
}

void BreastSimNode::endJob(uint8_t state, const std::string& message) {
  std::lock_guard<std::mutex> sl(state_mutex_);
  job_end_ = std::make_pair(state, message);
}

void BreastSimNode::setState(uint8_t state, const std::string& message, bool force) {
  std::lock_guard<std::mutex> sl(state_mutex_);
  const bool changed = state_.state != state || state_.state_name.empty();
  state_.state = state;
  state_.state_name = stateName(state);
  state_.message = message;
  const auto now = Clock::now();
  // Tracking updates come per frame: republish on a change or at the progress rate.
  if (force || changed || seconds(now - last_progress_pub_) >= 1.0 / params_.progress_rate_hz) {
    if (!force) last_progress_pub_ = now;
    state_.header.stamp = ros::Time::now();
    state_pub_.publish(state_);
  }
}

void BreastSimNode::publishDiagnostics(const ros::WallTimerEvent&) {
  Window w;
  double window_s;
  long total_tracked, total_rejected;
  double mean_m, p95_m, alpha, icp_rms;
  Clock::time_point last_tracked;
  std::string last_reject, lesion_status;
  FrameQuality quality;
  bool lesions_valid;
  long taken_back;
  {
    std::lock_guard<std::mutex> sl(stats_mutex_);
    quality = quality_;
    lesions_valid = lesions_valid_;
    lesion_status = lesion_status_;
    taken_back = total_taken_back_;
    w = window_;
    window_ = Window();
    const auto now = Clock::now();
    window_s = std::max(1e-9, seconds(now - window_start_));
    window_start_ = now;
    total_tracked = total_tracked_;
    total_rejected = total_rejected_;
    mean_m = surface_mean_m_;
    p95_m = surface_p95_m_;
    alpha = alpha_;
    icp_rms = icp_rms_m_;
    last_tracked = last_tracked_;
    last_reject = last_reject_;
  }
  // No clouds for a while: back to idle.
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    // (A degraded state stays: its reason must stay visible until tracking recovers.)
    if (state_.state == breast_sim::NodeState::TRACKING && w.clouds == 0 &&
        seconds(Clock::now() - last_tracked) > params_.tracking_timeout_s) {
      state_.state = breast_sim::NodeState::IDLE;
      state_.state_name = stateName(state_.state);
      state_.message = "no surface cloud for " + std::to_string(params_.tracking_timeout_s) +
                       " s; the model holds its last state and tracking resumes with the next cloud";
      state_.header.stamp = ros::Time::now();
      state_pub_.publish(state_);
    }
  }
  breast_sim::NodeState st;
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    st = state_;
  }
  diagnostic_msgs::DiagnosticStatus s;
  s.name = ros::this_node::getName() + ": navigation";
  s.hardware_id = st.case_name.empty() ? "breast_sim" : st.case_name;
  // ERROR: the node cannot vouch for its lesions; WARN: tracking, but clouds were refused or a frame
  // taken back in this window.
  s.level = st.state == breast_sim::NodeState::DEGRADED ? diagnostic_msgs::DiagnosticStatus::ERROR
            : (st.state == breast_sim::NodeState::TRACKING && w.rejected > 0) ? diagnostic_msgs::DiagnosticStatus::WARN
                                                                             : diagnostic_msgs::DiagnosticStatus::OK;
  if (!st.model_loaded && st.state != breast_sim::NodeState::LOADING) s.level = diagnostic_msgs::DiagnosticStatus::ERROR;
  s.message = st.state_name + ": " + st.message;
  auto kv = [&s](const std::string& k, const std::string& v) {
    diagnostic_msgs::KeyValue x;
    x.key = k;
    x.value = v;
    s.values.push_back(x);
  };
  auto num = [](double v, int precision = 3) {
    std::ostringstream o;
    o.setf(std::ios::fixed);
    o.precision(precision);
    o << v;
    return o.str();
  };
  const double n = std::max(1, w.tracked);
  kv("state", st.state_name);
  kv("lesions valid", lesions_valid ? "true" : "false");
  kv("lesion status", lesion_status);
  kv("precomputed", st.precomputed ? "true" : "false");
  kv("cloud rate in [Hz]", num(w.clouds / window_s, 2));
  kv("tracked rate [Hz]", num(w.tracked / window_s, 2));
  kv("clouds dropped (newest wins) in window", std::to_string(w.dropped));
  kv("clouds rejected in window", std::to_string(w.rejected));
  kv("clouds tracked total", std::to_string(total_tracked));
  kv("clouds rejected total", std::to_string(total_rejected));
  kv("last rejection", last_reject);
  kv("latency mean [ms]", w.tracked ? num(1e3 * w.latency_sum_s / n, 2) : "-");
  kv("latency max [ms]", w.tracked ? num(1e3 * w.latency_max_s, 2) : "-");
  kv("step time mean [ms]", w.tracked ? num(1e3 * w.step_sum_s / n, 2) : "-");
  kv("field build mean [ms]", w.tracked ? num(1e3 * w.field_sum_s / n, 2) : "-");
  kv("icp mean [ms]", w.tracked ? num(1e3 * w.icp_sum_s / n, 2) : "-");
  kv("cloud filter mean [ms]", w.tracked ? num(1e3 * w.filter_sum_s / n, 2) : "-");
  kv("points in mean", w.tracked ? num(w.points_in / n, 0) : "-");
  kv("points used mean", w.tracked ? num(w.points_used / n, 0) : "-");
  kv("inverted elements", std::to_string(inverted_elements_));
  // The seen skin's distance to the last tracked cloud before its step (along the skin normal).
  kv("seen skin to cloud mean [mm]", mean_m >= 0 ? num(1e3 * mean_m) : "-");
  kv("seen skin to cloud p95 [mm]", p95_m >= 0 ? num(1e3 * p95_m) : "-");
  kv("seen skin share", num(quality.seen_fraction, 3));
  kv("chest wall drift from precomputed [mm]", num(1e3 * quality.wall_drift_m));
  kv("model drift from precomputed [mm]", num(1e3 * quality.rigid_drift_m));
  kv("lesion offset from precomputed [mm]", num(1e3 * quality.lesion_offset_m));
  kv("lesion move in the last frame [mm]", num(1e3 * quality.lesion_jump_m));
  kv("frames taken back total", std::to_string(taken_back));
  kv("icp rms [mm]", icp_rms >= 0 ? num(1e3 * icp_rms) : "-");
  kv("skin vertices seen / held", std::to_string(skin_seen_) + " / " + std::to_string(skin_held_));
  kv("alpha [1/Pa]", num(alpha, 6));
  diagnostic_msgs::DiagnosticArray a;
  a.header.stamp = ros::Time::now();
  a.status.push_back(s);
  diag_pub_.publish(a);
}

}  // namespace breast_sim::ros_interface
