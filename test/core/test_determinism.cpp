// The same answer on any machine: the whole prone-to-supine pipeline (gravity with the wall fixed,
// sliding, morphing; stiffening with reversal, the multigrid) on the phantom at ~8k elements gives
// the same bits on one thread, on two and on sixteen (more threads than this machine's cores), for
// both element formulations. The thread count is not chosen from the load here (the sampler is
// off), so each run uses exactly the count it names. Every sum over a range
// runs in a fixed order (util/ordered_sum.h, the node forces' chunks, the rank-one sum's passes),
// and no decision reads the clock.
#include <gtest/gtest.h>

#include <omp.h>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/thread_budget.h"
#include "pipeline_fixtures.h"

using namespace breast_sim::core;
using namespace breast_sim::core::test_fixtures;

namespace {

struct RunResult {
  Points positions, lesions;
  int steps[3];
  long reversed[3];
};

RunResult runOn(int threads, const SmallPhantom& p, const PipelineSettings& s) {
  const int saved = omp_get_max_threads();
  omp_set_num_threads(threads);
  LoadSampler::instance().setEnabled(false);
  ProneToSupinePipeline pipe(p.c, p.m, s);
  pipe.run();
  LoadSampler::instance().setEnabled(true);
  omp_set_num_threads(saved);
  RunResult r;
  r.positions = pipe.positions();
  r.lesions = pipe.lesionPositions();
  const StageReport* reports[3] = {&pipe.gravityReport(), &pipe.slidingReport(), &pipe.morphingReport()};
  for (int k = 0; k < 3; ++k) {
    r.steps[k] = reports[k]->steps;
    r.reversed[k] = reports[k]->reversed_steps;
  }
  return r;
}

}  // namespace

TEST(Determinism, ThePipelineGivesTheSameBitsOnOneTwoAndSixteenThreads) {
  // Large enough that the products, the multigrid's levels and the node forces run in parallel.
  const SmallPhantom p(8000);
  for (const char* element : {"linear", "anp"}) {
    SCOPED_TRACE(element);
    PipelineSettings s = loadPipelineSettings(kPhantomCase);
    if (std::string(element) == "anp") {
      s.simulation.element = SimulationSettings::Element::kAnpTet;
      s.simulation.anp_inversion_barrier = 0.3;
    }
    const RunResult one = runOn(1, p, s);
    for (int threads : {2, 16}) {
      SCOPED_TRACE(std::to_string(threads) + " threads");
      const RunResult other = runOn(threads, p, s);
      for (int k = 0; k < 3; ++k) {
        EXPECT_EQ(one.steps[k], other.steps[k]) << "stage " << k;
        EXPECT_EQ(one.reversed[k], other.reversed[k]) << "stage " << k;
      }
      ASSERT_EQ(one.positions.rows(), other.positions.rows());
      EXPECT_TRUE((one.positions.array() == other.positions.array()).all())
          << "largest difference " << (one.positions - other.positions).cwiseAbs().maxCoeff() << " m";
      EXPECT_TRUE((one.lesions.array() == other.lesions.array()).all());
    }
  }
}
