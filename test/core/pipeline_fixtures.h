#pragma once
// Shared by the pipeline tests (test_pipeline, test_pipeline_morphing, test_pipeline_coarse_start):
// the small phantom, the case files, a temporary case file and its error, and the cancel checks.

#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <stdexcept>
#include <string>

#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::core::test_fixtures {

inline const std::string kConfigDir = std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/";
inline const std::string kPhantomCase = kConfigDir + "phantom_default.yaml";

/// The phantom case meshed to about `elements` tetrahedra.
struct SmallPhantom {
  ModelCase c;
  SimulationModel m;
  explicit SmallPhantom(int elements = 2000) {
    c = loadModelCase(kPhantomCase);
    c.meshing.target_elements = elements;
    m = buildSimulationModel(c);
  }
};

/// One 2000-element phantom per test executable.
inline const SmallPhantom& phantom() {
  static const SmallPhantom p;
  return p;
}

/// Writes `text` to `name` in the temporary folder; returns its path.
inline std::string writeTemp(const std::string& name, const std::string& text) {
  const std::filesystem::path p = std::filesystem::temp_directory_path() / name;
  std::ofstream(p) << text;
  return p.string();
}

/// The error loadPipelineSettings gives for a case file of this text ("no error" if none).
inline std::string message(const std::string& text) {
  try {
    loadPipelineSettings(writeTemp("breast_sim_pipeline_bad.yaml", text));
  } catch (const std::runtime_error& e) {
    return std::string(e.what());
  }
  return std::string("no error");
}

// --- Cancelling: a stage that is cancelled cancels the run, and the stages after it do not run. ---

/// Where a run is cancelled: the progress callback sets the flag once `step` steps of `stage` are
/// accepted. `fine`: only for the fine model's steps (with coarse_start, the coarse one reports first).
struct CancelAt {
  PipelineStage stage;
  int step;
  bool fine = false;
};

inline std::string describe(const CancelAt& at) {
  return std::string("cancelled at ") + (at.fine ? "fine " : "") + stageName(at.stage) + " step " + std::to_string(at.step);
}

inline PipelineProgressFn cancelAt(const ProneToSupinePipeline& pipe, CancelAt at, std::atomic<bool>& cancel) {
  return [&pipe, at, &cancel](const PipelineProgress& pr) {
    if (pr.stage == at.stage && pr.step >= at.step && (!at.fine || &pipe.running() == &pipe)) cancel = true;
  };
}

/// What a stopped run leaves must be usable: finite positions, no inverted element, metrics, and a
/// snapshot that restores to itself.
inline void expectAConsistentState(ProneToSupinePipeline& pipe) {
  EXPECT_TRUE(pipe.positions().allFinite());
  const PipelineMetrics m = pipe.metrics();
  EXPECT_EQ(m.inverted_elements, 0);
  EXPECT_TRUE(std::isfinite(m.volume_change_percent));
  const PipelineState s = pipe.state();
  pipe.restore(s);
  const PipelineState t = pipe.state();
  EXPECT_EQ(t.simulation.displacement_m, s.simulation.displacement_m);
  EXPECT_EQ(t.simulation.velocity_mps, s.simulation.velocity_mps);
  EXPECT_EQ(t.modulus_factors, s.modulus_factors);
  EXPECT_EQ(t.alpha.alpha_per_pa, s.alpha.alpha_per_pa);
  EXPECT_EQ(t.sliding_targets_m, s.sliding_targets_m);
  EXPECT_EQ(t.sliding_slip_directions, s.sliding_slip_directions);
  EXPECT_EQ(t.morphing_forces_n, s.morphing_forces_n);
  EXPECT_EQ(t.gravity_load_mps2, s.gravity_load_mps2);
}

/// With the flag cleared, run() goes through every stage to the end.
inline void expectARunCompletes(ProneToSupinePipeline& pipe, std::atomic<bool>& cancel) {
  cancel = false;
  pipe.run({}, &cancel);
  EXPECT_EQ(pipe.stage(), PipelineStage::kDone);
  for (const StageReport* r : {&pipe.gravityReport(), &pipe.slidingReport(), &pipe.morphingReport()}) {
    EXPECT_TRUE(r->ran);
    EXPECT_FALSE(r->cancelled);
  }
  EXPECT_GT(pipe.morphingReport().steps, 0);
  EXPECT_GE(pipe.morphingReport().surface_mean_m, 0.0);
  EXPECT_TRUE(invertedTets(pipe.model().mesh.tets(), pipe.positions()).empty());
}

}  // namespace breast_sim::core::test_fixtures
