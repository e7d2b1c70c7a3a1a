#include "breast_sim/ros_interface/model_node.h"

#include <chrono>
#include <sstream>

#include <breast_sim/LesionArray.h>
#include <breast_sim/TetrahedralMesh.h>
#include <ros/package.h>

#include "breast_sim/ros_interface/conversions.h"

namespace breast_sim::ros_interface {

ModelNode::ModelNode(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh), pnh_(pnh) {}

ModelNode::~ModelNode() {
  if (initial_build_.joinable()) initial_build_.join();
}

void ModelNode::initialize() {
  std::string case_file;
  int target_elements = 0;
  pnh_.param<std::string>("case_file", case_file, ros::package::getPath("breast_sim") + "/config/phantom_default.yaml");
  pnh_.param("target_elements", target_elements, 0);
  pnh_.param<std::string>("frame_id", frame_id_, "breast_model");
  mesh_pub_ = pnh_.advertise<breast_sim::TetrahedralMesh>("deformed_mesh", 1, /*latch=*/true);
  lesions_pub_ = pnh_.advertise<breast_sim::LesionArray>("lesions", 1, /*latch=*/true);
  load_srv_ = pnh_.advertiseService("load_case", &ModelNode::loadCase, this);
  // The first model is built off the main thread so the node answers at once.
  building_ = true;
  initial_build_ = std::thread([this, case_file, target_elements] {
    std::string message;
    if (!build(case_file, target_elements, &message))
      ROS_ERROR_STREAM("breast_sim: " << message << "; no model is published until a case loads (~load_case)");
    building_ = false;
  });
}

bool ModelNode::loadCase(breast_sim::LoadCase::Request& req, breast_sim::LoadCase::Response& res) {
  if (building_.exchange(true)) {
    res.success = false;
    res.message = "a model is being built; try again when it is published";
    return true;
  }
  res.success = build(req.case_file, req.target_elements, &res.message);
  building_ = false;
  if (!res.success) ROS_WARN_STREAM("breast_sim: " << res.message << "; keeping the previous model");
  return true;
}

bool ModelNode::build(const std::string& case_file, int target_elements, std::string* message) {
  const auto t0 = std::chrono::steady_clock::now();
  try {
    core::ModelCase c = core::loadModelCase(case_file);
    if (target_elements > 0) c.meshing.target_elements = target_elements;
    auto model = std::make_shared<const core::SimulationModel>(core::buildSimulationModel(c));
    // Everything that can fail happens before the swap, so a failure keeps the last good model.
    const ros::Time now = ros::Time::now();
    const auto mesh_msg = toMessage(model->mesh, core::Points(), frame_id_, now);
    const auto lesion_msg = toMessage(model->lesions, model->lesion_embedding, core::Points(), frame_id_, now);
    {
      std::lock_guard<std::mutex> lock(model_mutex_);
      model_ = model;
    }
    mesh_pub_.publish(mesh_msg);
    lesions_pub_.publish(lesion_msg);
    std::ostringstream s;
    s << "case '" << c.name << "': " << model->mesh.numTets() << " tetrahedra, " << model->mesh.numNodes()
      << " nodes, " << model->lesions.size() << " lesions, built in "
      << std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() << " s";
    *message = s.str();
    ROS_INFO_STREAM("breast_sim: " << *message);
    return true;
  } catch (const std::exception& e) {
    *message = std::string("cannot load case '") + case_file + "': " + e.what();
    return false;
  }
}

}  // namespace breast_sim::ros_interface
