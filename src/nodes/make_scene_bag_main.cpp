// Writes a recorded tracking scene of a case (ros_interface/scene_recording.h: a depth camera and a
// hand-held scanner of its own, a hand, the torso, the pose on tf only, bad inputs at known times and
// a drift at the end), reproducibly for a seed:
//   make_scene_bag [--case FILE] [--target-elements N] [--settings FILE] [--out BAG] [--seed N] [--start S]
// The case is meshed and precomputed with the core pipeline (as the node does, with its 3 mm
// distance field); the scene is made of the precomputed skin. Beside the bag, BAG.yaml describes it
// (segments, clouds, the times of the bad inputs).
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <string>

#include <ros/package.h>
#include <ros/time.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/scene_recording.h"

using namespace breast_sim;

int main(int argc, char** argv) {
  ros::Time::init();
  std::string case_file = ros::package::getPath("breast_sim") + "/config/phantom_default.yaml", settings_file;
  std::string out = "scene.bag";
  int target = 0;
  ros_interface::SceneOptions o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::cerr << a << " needs a value\n";
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--case") case_file = next();
    else if (a == "--settings") settings_file = next();
    else if (a == "--target-elements") target = std::stoi(next());
    else if (a == "--out") out = next();
    else if (a == "--seed") o.seed = static_cast<unsigned>(std::stoul(next()));
    else if (a == "--start") o.start_s = std::stod(next());
    else {
      std::cerr << "usage: make_scene_bag [--case FILE] [--target-elements N] [--settings FILE] [--out BAG] [--seed N]"
                   " [--start S]\n";
      return a == "--help" ? 0 : 2;
    }
  }
  try {
    core::ModelCase c = core::loadModelCase(case_file);
    if (target > 0) c.meshing.target_elements = target;
    const core::SimulationModel model = core::buildSimulationModel(c);
    core::PipelineSettings settings = core::loadPipelineSettings(settings_file.empty() ? case_file : settings_file);
    settings.morphing.field.voxel_size_m = 0.003;  // the node's field_voxel_size_m (config/node.yaml)
    core::ProneToSupinePipeline p(c, model, settings);
    p.run();
    const core::Points x = p.positions();
    const core::Triangles skin = core::skinTriangles(model.mesh, model.mesh.nodeSet(core::node_sets::kSkin));
    o.gravity_in_model = ros_interface::supineGravityDirection(c);
    const ros_interface::SceneDescription d = ros_interface::writeSceneBag(out, x, skin, o);
    std::ofstream(out + ".yaml") << d.toYaml();
    int depth = 0;
    for (const auto& cl : d.clouds) depth += cl.depth_camera;
    std::cout << "wrote " << out << " (" << model.mesh.numTets() << " elements precomputed): " << d.end_s - d.start_s
              << " s from t = " << d.start_s << " s, " << depth << " depth-camera and " << d.clouds.size() - depth
              << " scanner clouds, " << d.bad_inputs.size() << " bad inputs, drift from t = " << d.drift_begin_s
              << " s; described in " << out << ".yaml\n";
  } catch (const std::exception& e) {
    std::cerr << "make_scene_bag: " << e.what() << "\n";
    return 2;
  }
  return 0;
}
