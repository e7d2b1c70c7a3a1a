// BreastSimNode's checkpoints: the state written to ~state_folder after each precomputation, after a
// loaded state and periodically while tracking, and read back on start, so that a node restarted
// after a crash (the launch file respawns it) tracks again without precomputing; and the multigrid's
// coarse levels and a patient case's unloaded rest shape kept beside them, so that it neither meshes
// the levels again nor recovers the shape anew (it confirms it in one loading).
#include "breast_sim/ros_interface/breast_sim_node.h"

#include "breast_sim/core/pipeline/case_file.h"
#include "breast_sim/ros_interface/node_checkpoint.h"
#include "breast_sim_node_util.h"

namespace breast_sim::ros_interface {

using node_util::Clock;
using node_util::seconds;

void BreastSimNode::fingerprintEngine(Engine& e) const {
  e.fingerprint = 0;
  try {
    const std::string settings = core::effectiveCaseYaml(e.case_file, e.model_case->meshing,
                                                         e.model_case->lesion_snap_tolerance_m, e.settings);
    e.fingerprint = caseFingerprint(e.model->mesh, settings);
  } catch (const std::exception& ex) {
    ROS_WARN_STREAM("breast_sim: case '" << e.model_case->name << "' has no fingerprint (" << ex.what()
                    << "): its state is not checkpointed, and a restarted node precomputes it again");
  }
}

void BreastSimNode::buildPipeline(Engine& e) const {
  const bool multigrid = e.settings.simulation.solver.kind == core::SolverSettings::Kind::kMultigrid;
  std::optional<std::vector<core::TetMesh>> kept;
  core::Points start;  // X0 kept by an earlier start of this case (reference_state unloaded)
  if (e.fingerprint != 0) {
    if (multigrid) {
      try {
        kept = readMultigridLevels(*state_folder_, e.fingerprint);
      } catch (const std::exception& ex) {
        ROS_WARN_STREAM("breast_sim: " << ex.what() << "; the multigrid levels are meshed again");
      }
    }
    try {
      if (std::optional<core::Points> x0 = readUnloadedShape(*state_folder_, e.fingerprint)) start = std::move(*x0);
    } catch (const std::exception& ex) {
      ROS_WARN_STREAM("breast_sim: " << ex.what() << "; the unloaded shape is recovered anew");
    }
  }
  bool had_start = start.size() > 0;
  auto keepUnloadedShape = [&] {
    // A recovered X0 (one confirmed from the kept file is that file's).
    if (e.fingerprint == 0 || had_start ||
        e.pipeline->settings().simulation.reference_state != core::SimulationSettings::ReferenceState::kUnloaded)
      return;
    try {
      writeUnloadedShape(*state_folder_, e.fingerprint, e.pipeline->model().mesh);
    } catch (const std::exception& ex) {
      ROS_WARN_STREAM("breast_sim: the unloaded shape could not be kept (" << ex.what()
                      << "); a restarted node recovers it again");
    }
  };
  if (kept) {
    const auto t0 = Clock::now();
    const size_t levels = kept->size();
    try {
      e.pipeline =
          std::make_unique<core::ProneToSupinePipeline>(*e.model_case, *e.model, e.settings, std::move(kept), start);
      e.levels_read = static_cast<int>(levels);
      ROS_INFO_STREAM("breast_sim: case '" << e.model_case->name << "': " << levels << " multigrid levels read from "
                      << state_folder_->root() << (had_start ? ", its unloaded shape confirmed" : "") << ", built in "
                      << seconds(Clock::now() - t0) << " s");
      keepUnloadedShape();
      return;
    } catch (const std::invalid_argument& ex) {
      ROS_WARN_STREAM("breast_sim: the multigrid levels kept in " << state_folder_->root()
                      << " do not fit the model (" << ex.what() << "); they are meshed again");
    }
  }
  try {
    e.pipeline = std::make_unique<core::ProneToSupinePipeline>(*e.model_case, *e.model, e.settings, std::nullopt, start);
  } catch (const std::invalid_argument& ex) {
    if (!had_start) throw;
    ROS_WARN_STREAM("breast_sim: the unloaded shape kept in " << state_folder_->root() << " does not fit the model ("
                    << ex.what() << "); it is recovered anew");
    had_start = false;
    e.pipeline = std::make_unique<core::ProneToSupinePipeline>(*e.model_case, *e.model, e.settings);
  }
  keepUnloadedShape();
  if (!multigrid || e.fingerprint == 0 || e.pipeline->coarseMeshes().empty()) return;
  try {
    writeMultigridLevels(*state_folder_, e.fingerprint, e.pipeline->coarseMeshes());
  } catch (const std::exception& ex) {
    ROS_WARN_STREAM("breast_sim: the multigrid levels could not be kept (" << ex.what()
                    << "); a restarted node meshes them again");
  }
}

bool BreastSimNode::writeCheckpoint(Engine& e, const char* after) {
  if (e.fingerprint == 0 || !e.precomputed) return false;
  const auto t0 = Clock::now();
  try {
    const std::string path = state_folder_->writeFile(checkpointName(e.fingerprint), true,
                                                      [&](const std::string& temp) { e.pipeline->saveState(temp); });
    last_checkpoint_ = Clock::now();
    const double took_s = seconds(last_checkpoint_ - t0);
    if (guard_.started())  // while tracking: once a minute
      ROS_INFO_STREAM_THROTTLE(60.0, "breast_sim: checkpoint after " << after << " written to " << path << " in "
                               << took_s << " s (every " << params_.checkpoint_period_s << " s while tracking)");
    else
      ROS_INFO_STREAM("breast_sim: checkpoint after " << after << " written to " << path << " in " << took_s << " s");
    return true;
  } catch (const std::exception& ex) {
    warn("checkpoint", std::string("breast_sim: the checkpoint after ") + after + " could not be written: " + ex.what() +
                           "; a restarted node resumes from an older one or precomputes again");
    return false;
  }
}

bool BreastSimNode::resumeFromCheckpoint(Engine& e) {
  if (e.fingerprint == 0) return false;
  std::vector<std::string> files;
  try {
    files = state_folder_->newestFirst(checkpointPrefix(e.fingerprint), kCheckpointSuffix);
  } catch (const std::exception& ex) {
    ROS_WARN_STREAM("breast_sim: no checkpoint could be looked for: " << ex.what());
    return false;
  }
  for (const std::string& file : files) {
    try {
      e.pipeline->loadState(file);  // checks the whole file before it touches the pipeline
    } catch (const std::exception& ex) {
      ROS_WARN_STREAM("breast_sim: checkpoint " << file << " does not load (" << ex.what() << "); trying an older one");
      continue;
    }
    adoptLoadedState(e, file);
    last_checkpoint_ = Clock::now();
    const std::string levels = e.levels_read > 0 ? " (its " + std::to_string(e.levels_read) +
                                                       " multigrid levels read from the state folder, not meshed)"
                                                 : std::string();
    const std::string message = "resumed case '" + e.model_case->name + "' from checkpoint " + file + levels +
                                "; the model is precomputed and follows surface clouds";
    ROS_INFO_STREAM("breast_sim: " << message);
    endJob(breast_sim::NodeState::IDLE, message);
    return true;
  }
  return false;
}

void BreastSimNode::forgetCheckpoint(Engine& e) {
  if (e.fingerprint == 0) return;
  try {
    state_folder_->removeFile(checkpointName(e.fingerprint));
  } catch (const std::exception& ex) {
    warn("checkpoint", std::string("breast_sim: the checkpoint could not be removed: ") + ex.what() +
                           "; a restarted node would resume from it");
  }
}

}  // namespace breast_sim::ros_interface
