#pragma once
/// @file model_node.h
/// The breast_sim node at this stage: builds the simulation model of a case and publishes it.
///
/// Parameters (private namespace, see config/model_node.yaml):
///   ~case_file (string)       YAML case; default: the package's config/phantom_default.yaml
///   ~target_elements (int)    overrides the case's meshing.target_elements when > 0 (default 0)
///   ~frame_id (string)        frame of the model (default "breast_model")
/// Publishes (latched):
///   ~deformed_mesh (breast_sim/TetrahedralMesh)  the model (rest shape until a simulation runs)
///   ~lesions (breast_sim/LesionArray)            lesion positions [m]
/// Services:
///   ~load_case (breast_sim/LoadCase)  builds a new model and answers when it is published (seconds;
///                                     the node keeps serving its other callbacks meanwhile); the previous
///                                     model stays published if anything is wrong with the new case.
/// \note Shutting down while a model is being built waits for that build to end.

#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include <ros/ros.h>

#include <breast_sim/LoadCase.h>

#include "breast_sim/core/model/model_case.h"

namespace breast_sim::ros_interface {

class ModelNode {
 public:
  ModelNode(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~ModelNode();
  /// Reads parameters, advertises, and starts building the configured case.
  void initialize();

 private:
  bool loadCase(breast_sim::LoadCase::Request& req, breast_sim::LoadCase::Response& res);
  /// Builds a model into a temporary; publishes and swaps it in only when all of it succeeded.
  bool build(const std::string& case_file, int target_elements, std::string* message);

  ros::NodeHandle nh_, pnh_;
  ros::Publisher mesh_pub_, lesions_pub_;
  ros::ServiceServer load_srv_;
  std::string frame_id_;
  std::mutex model_mutex_;
  std::shared_ptr<const core::SimulationModel> model_;  // last good model
  std::thread initial_build_;
  std::atomic<bool> building_{false};
};

}  // namespace breast_sim::ros_interface
