#pragma once
// Test fixture of the tracking tests (test_surface_tracker, test_tracking_monitor): the phantom at
// rest and without load (2000 elements; the rest shape is its equilibrium), pipeline settings for
// tracking it (no case target, a 3 mm distance field), and scans of its own rest skin, so the truth
// is known: tracking should keep the lesions at rest, up to what the breathing moves.
#include <cmath>
#include <memory>
#include <string>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

namespace breast_sim::test_fixtures {

struct RestPhantom {
  core::ModelCase model_case;
  core::SimulationModel model;
  core::PipelineSettings settings;
  std::unique_ptr<ros_interface::SkinScanner> scanner;
  core::Points rest_lesions;  ///< lesion positions at rest [m]

  explicit RestPhantom(unsigned seed = 7) {
    model_case = core::loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
    model_case.meshing.target_elements = 2000;
    model = core::buildSimulationModel(model_case);
    settings.morphing.target = "";
    settings.morphing.field.voxel_size_m = 0.003;
    scanner = std::make_unique<ros_interface::SkinScanner>(
        model.mesh.nodes(), core::skinTriangles(model.mesh, model.mesh.nodeSet(core::node_sets::kSkin)), seed);
    rest_lesions = model.lesion_embedding.positions(model.mesh.nodes());
  }
  /// A pipeline on the model without load.
  std::unique_ptr<core::ProneToSupinePipeline> pipeline() const {
    auto p = std::make_unique<core::ProneToSupinePipeline>(model_case, model, settings);
    p->setGravityLoad(Eigen::Vector3d::Zero());
    return p;
  }
  /// Scan k of the rest skin [m]: 0.5 mm noise, 2 mm breathing over 40 scans, slid `slide_m` along x.
  core::Points scan(int k, int points = 4000, double slide_m = 0) {
    return scanner->scan(points, 2e-3 * std::sin(2 * M_PI * k / 40.0), Eigen::Vector3d(slide_m, 0, 0), 0.5e-3);
  }
  /// Largest lesion distance from rest [mm] at the pipeline's state.
  double lesionErrorMm(const core::ProneToSupinePipeline& p) const {
    return 1e3 * (p.lesionPositions() - rest_lesions).rowwise().norm().maxCoeff();
  }
};

}  // namespace breast_sim::test_fixtures
