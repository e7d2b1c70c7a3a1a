// BreastSimNode's services and the ~precompute action: each answers at once (loading a case waits
// for the model, writing a file for the file) and hands long work to the worker; while a job runs
// they refuse with the reason.
#include "breast_sim/ros_interface/breast_sim_node.h"

#include <condition_variable>
#include <filesystem>
#include <mutex>
#include <sstream>

#include "breast_sim/core/mri/mri_case.h"

namespace breast_sim::ros_interface {

bool BreastSimNode::loadCaseSrv(breast_sim::LoadCase::Request& req, breast_sim::LoadCase::Response& res) {
  // Answers when the model is built (seconds); other callbacks keep being served meanwhile.
  std::string message, why;
  bool ok = false;
  std::mutex m;
  std::condition_variable cv;
  bool done = false;
  std::string file;
  try {
    file = data_folder_->existingFile(req.case_file);
  } catch (const std::exception& ex) {
    res.success = false;
    res.message = std::string("cannot load case: ") + ex.what();
    ROS_WARN_STREAM("breast_sim: " << res.message << "; keeping the previous model");
    return true;
  }
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
    Engine& e = *engine_;
    const std::string path =
        state_folder_->writeFile(req.path, req.replace, [&](const std::string& temp) { e.pipeline->saveState(temp); });
    res.success = true;
    res.message = "saved the state of case '" + e.model_case->name + "' (" + std::to_string(e.model->mesh.numNodes()) +
                  " nodes) to " + path;
  } catch (const ConfinementError& ex) {
    res.success = false;
    res.message = std::string("not saved: ") + ex.what();
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
    const std::string file = state_folder_->existingFile(req.path);
    engine_->pipeline->loadState(file);
    adoptLoadedState(*engine_, file);
    res.success = true;
    res.message = "loaded " + file + "; the model is precomputed and follows surface clouds";
    setState(breast_sim::NodeState::IDLE, res.message);
    writeCheckpoint(*engine_, "a loaded state");
  } catch (const std::exception& ex) {
    res.success = false;
    res.message = std::string(ex.what()) + "; the previous state is kept";
  }
  return true;
}

void BreastSimNode::adoptLoadedState(Engine& e, const std::string& file) {
  e.gravity_load_mps2 = e.pipeline->gravityLoad();  // the state's, for the pose-update rule
  e.precomputed = true;
  // A state file holds the shape, not the ensemble: its regions are unknown.
  e.regions.clear();
  e.region_status = "not computed (state loaded from " + file + ")";
  restartTracking();
  {
    std::lock_guard<std::mutex> sl(state_mutex_);
    state_.precomputed = true;
    state_.stage = "done";
    state_.progress = 1.0;
  }
  publishModel(e, ros::Time::now(), true, true, "loaded state " + file);
}

bool BreastSimNode::writeSupineMriSrv(breast_sim::WriteSupineMri::Request& req, breast_sim::WriteSupineMri::Response& res) {
  res.success = false;
  if (busy_) {
    res.message = "busy (loading or precomputing); write the supine MRI when ~state is idle or tracking";
    return true;
  }
  // writeMriVolume's single-file formats (a .mhd or .nhdr would leave its data in a second file).
  static const std::vector<std::string> kExtensions = {".nii.gz", ".nii", ".nrrd", ".mha"};
  const std::string& name = req.file_name;
  std::string extension, list;
  for (const std::string& e : kExtensions) {
    list += (list.empty() ? "" : ", ") + e;
    if (extension.empty() && name.size() > e.size() && name.compare(name.size() - e.size(), e.size(), e) == 0) extension = e;
  }
  if (!name.empty() && extension.empty()) {  // an empty name: output_folder_ says so
    res.message = "not written: '" + name + "' has no known extension; end it in one of " + list;
    return true;
  }
  // The state to resample, copied under the lock: the resampling runs while tracking goes on.
  std::shared_ptr<const core::MriCase> mri;
  core::TetMesh rest;
  core::Points displacement;
  std::string case_name, shows;
  {
    std::lock_guard<std::mutex> lock(engine_mutex_);
    if (!engine_) {
      res.message = "no model is loaded; load an MRI case first (~load_case)";
      return true;
    }
    case_name = engine_->model_case->name;
    if (!engine_->model_case->mri) {
      res.message = "case '" + case_name + "' is not an MRI case (mri:): there is no prone MRI to resample; load one";
      return true;
    }
    mri = engine_->model_case->mri;
    rest = engine_->model->mesh;
    displacement = engine_->pipeline->positions() - rest.nodes();
    std::lock_guard<std::mutex> sl(state_mutex_);
    shows = state_.state == breast_sim::NodeState::TRACKING ? "the tracked state"
            : engine_->precomputed                          ? "the precomputed supine state"
                                                            : "the prone rest shape (not precomputed)";
  }
  try {
    core::SupineImages supine;
    // The name is checked before the resampling; the temporary the folder gives has no extension, and
    // ITK picks the format by it: written under the temporary's name plus the extension, then renamed
    // onto the temporary, which the folder flushes and moves into place.
    const std::string path = output_folder_->writeFile(name, req.replace, [&](const std::string& temp) {
      supine = core::simulatedSupineMri(*mri, rest, displacement);
      const std::string with_extension = temp + extension;
      try {
        core::writeMriVolume(with_extension, supine.image);
        std::filesystem::rename(with_extension, temp);
      } catch (...) {
        std::error_code ignored;
        std::filesystem::remove(with_extension, ignored);
        throw;
      }
    });
    const core::ImageGeometry& g = supine.image.geometry;
    std::ostringstream s;
    s.precision(3);
    s << "wrote the simulated supine MRI of case '" << case_name << "' (" << shows << ") to " << path << ": " << g.size.x()
      << " x " << g.size.y() << " x " << g.size.z() << " voxels of " << 1e3 * g.spacing_m.minCoeff() << " mm, "
      << supine.body_voxels << " in the body, resampled in " << supine.seconds << " s";
    res.success = true;
    res.path = path;
    res.message = s.str();
    ROS_INFO_STREAM("breast_sim: " << res.message);
  } catch (const ConfinementError& ex) {
    res.message = std::string("not written: ") + ex.what();
  } catch (const std::exception& ex) {
    res.message = std::string("cannot write the supine MRI '") + name + "': " + ex.what();
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

}  // namespace breast_sim::ros_interface
