// Lesion confidence regions (pipeline/lesion_uncertainty.h): the region radius, the region of
// samples against ellipsoids built by hand, the sample design, the case keys, and the ensemble on
// the small phantom against runs set up by hand.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <set>

#include <Eigen/Geometry>

#include "breast_sim/core/pipeline/lesion_uncertainty.h"
#include "pipeline_fixtures.h"

namespace breast_sim::core {
namespace {

using test_fixtures::kPhantomCase;
using test_fixtures::message;
using test_fixtures::phantom;
using test_fixtures::writeTemp;

// The prediction region's radius: Hotelling's T² with the F quantiles of the tables (NIST/SEMATECH
// handbook, upper 5 % and 1 % points), and the χ² radius with 3 degrees of freedom for many samples.
TEST(LesionUncertainty, RegionScaleIsThePredictionRadiusOfItsSampleCount) {
  EXPECT_NEAR(regionScale(0.95, 8), std::sqrt(3.0 * 8 / 6 * 4.757), 2e-3);    // F(3, 6) = 4.757
  EXPECT_NEAR(regionScale(0.99, 8), std::sqrt(3.0 * 8 / 6 * 9.780), 2e-3);    // F(3, 6) = 9.780
  EXPECT_NEAR(regionScale(0.95, 12), std::sqrt(3.0 * 12 / 10 * 3.708), 2e-3); // F(3, 10) = 3.708
  EXPECT_NEAR(regionScale(0.95, 1000000), std::sqrt(7.814728), 1e-4);         // χ²₃ at 0.95
  EXPECT_NEAR(regionScale(0.50, 1000000), std::sqrt(2.365974), 1e-4);
  double last = regionScale(0.95, 3);
  for (int n = 4; n < 200; ++n) {
    const double s = regionScale(0.95, n);
    EXPECT_LT(s, last) << n;  // more samples, a better known spread: a tighter region
    last = s;
  }
  EXPECT_THROW(regionScale(0.0, 8), std::invalid_argument);
  EXPECT_THROW(regionScale(1.0, 8), std::invalid_argument);
  EXPECT_THROW(regionScale(std::nan(""), 8), std::invalid_argument);
  EXPECT_THROW(regionScale(0.95, 2), std::invalid_argument);
}

// Six samples at ±a, ±b, ±c along rotated axes give C = R diag(a², b², c²)/3 Rᵀ: the region's
// semi-axes are s √(a²/3) … along R's columns, s the radius of six samples.
TEST(LesionUncertainty, RegionOfSamplesOnRotatedAxesIsTheEllipsoidBuiltByHand) {
  const Eigen::Vector3d centre(0.01, -0.02, 0.03);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Eigen::Vector3d half(3e-3, 2e-3, 0.5e-3);  // a > b > c [m]
  std::vector<Eigen::Vector3d> samples;
  for (int k = 0; k < 3; ++k)
    for (double s : {-1.0, 1.0}) samples.push_back(centre + s * half[k] * R.col(k));
  const LesionRegion r = lesionRegion(centre, samples, 0.95);
  const double q = regionScale(0.95, 6) * regionScale(0.95, 6);
  const Eigen::Matrix3d want = R * Eigen::Vector3d(half.array().square() / 3.0).asDiagonal() * R.transpose();
  EXPECT_LT((r.covariance_m2 - want).norm(), 1e-18);
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(r.semi_axes_m[k], std::sqrt(q / 3.0) * half[k], 1e-12) << k;
    EXPECT_NEAR(std::abs(r.axes.col(k).dot(R.col(k))), 1.0, 1e-9) << k;
  }
  EXPECT_NEAR(r.axes.determinant(), 1.0, 1e-12);
  EXPECT_NEAR(r.scale, std::sqrt(q), 1e-12);
  EXPECT_NEAR(r.max_sample_distance_m, half[0], 1e-15);
  // contains(): points just inside and just outside each semi-axis, and the samples themselves
  // (√3 < s so all six lie inside).
  for (int k = 0; k < 3; ++k)
    for (double s : {-1.0, 1.0}) {
      EXPECT_TRUE(r.contains(centre + s * 0.999 * r.semi_axes_m[k] * r.axes.col(k))) << k;
      EXPECT_FALSE(r.contains(centre + s * 1.001 * r.semi_axes_m[k] * r.axes.col(k))) << k;
    }
  for (const auto& p : samples) EXPECT_TRUE(r.contains(p));
  // Samples that are biased (all on one side) are counted about the centre, not their mean.
  const Eigen::Vector3d off = centre + Eigen::Vector3d(1e-3, 0, 0);
  const LesionRegion biased = lesionRegion(centre, {off, off, off}, 0.95);
  EXPECT_NEAR(biased.covariance_m2(0, 0), 1e-6, 1e-18);
  EXPECT_NEAR(biased.semi_axes_m[0], regionScale(0.95, 3) * 1e-3, 1e-12);
  EXPECT_EQ(biased.semi_axes_m[1], 0.0);
  // A degenerate region holds only points on its plane / line.
  EXPECT_TRUE(biased.contains(centre + Eigen::Vector3d(-2e-3, 0, 0)));
  EXPECT_FALSE(biased.contains(centre + Eigen::Vector3d(0, 1e-6, 0)));
  EXPECT_THROW(lesionRegion(centre, {}, 0.95), std::invalid_argument);
  EXPECT_THROW(lesionRegion(centre, {off, off}, 0.95), std::invalid_argument);
  EXPECT_THROW(lesionRegion(centre, samples, 1.0), std::invalid_argument);
}

TEST(LesionUncertainty, DesignIsTheHaltonSequenceMappedOntoTheRanges) {
  UncertaintySettings u;
  const auto d = uncertaintyDesign(u, 64);
  ASSERT_EQ(d.size(), 64u);
  // Index 1: the radical inverses 1/2, 1/3, 1/5.
  EXPECT_NEAR(d[0].youngs_modulus_factor, 0.5 * std::pow(4.0, 0.5), 1e-12);
  EXPECT_NEAR(d[0].poisson_ratio, 0.45 + 0.04 / 3.0, 1e-12);
  EXPECT_NEAR(d[0].time_step_factor, 0.67 * std::pow(1.5 / 0.67, 0.2), 1e-12);
  std::set<double> e;
  int below_one = 0;
  for (const auto& p : d) {
    EXPECT_GE(p.youngs_modulus_factor, 0.5);
    EXPECT_LE(p.youngs_modulus_factor, 2.0);
    EXPECT_GE(p.poisson_ratio, 0.45);
    EXPECT_LE(p.poisson_ratio, 0.49);
    EXPECT_GE(p.time_step_factor, 0.67);
    EXPECT_LE(p.time_step_factor, 1.5);
    e.insert(p.youngs_modulus_factor);
    below_one += p.youngs_modulus_factor < 1.0;
  }
  EXPECT_EQ(e.size(), 64u);
  EXPECT_EQ(below_one, 32);  // log-uniform: half the samples softer than nominal
  // A later start continues the same sequence.
  const auto later = uncertaintyDesign(u, 4, 61);
  for (int i = 0; i < 4; ++i) EXPECT_EQ(later[i].poisson_ratio, d[60 + i].poisson_ratio);
  EXPECT_THROW(uncertaintyDesign(u, 0), std::invalid_argument);
  EXPECT_THROW(uncertaintyDesign(u, 4, 0), std::invalid_argument);
}

TEST(LesionUncertainty, SampleSettingsScaleEveryModulusAndTimeStep) {
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.simulation.region_youngs_modulus_pa = {{4, 20000.0}};
  s.sliding_stage.time_step_s = 0.2;
  const PipelineSettings t = sampleSettings(s, {0.5, 0.46, 2.0});
  EXPECT_EQ(t.simulation.material.youngs_modulus_pa, 0.5 * s.simulation.material.youngs_modulus_pa);
  EXPECT_EQ(t.simulation.region_youngs_modulus_pa.at(4), 10000.0);
  EXPECT_EQ(t.simulation.material.poisson_ratio, 0.46);
  EXPECT_EQ(t.simulation.dynamics.time_step_s, 2.0 * s.simulation.dynamics.time_step_s);
  EXPECT_EQ(t.simulation.settle.time_step_s, 2.0 * s.simulation.settle.time_step_s);
  EXPECT_EQ(t.sliding_stage.time_step_s, 0.4);
  EXPECT_EQ(t.morphing.time_step_s, 2.0 * s.morphing.time_step_s);
  EXPECT_FALSE(t.uncertainty.enabled);
  // A time step beyond the validated range names the sample and the way out.
  try {
    sampleSettings(s, {1.0, 0.48, 100.0});
    FAIL() << "a 33 s step was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("time steps x 100"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("narrow the ranges"), std::string::npos) << e.what();
  }
}

TEST(LesionUncertainty, CaseKeysAreReadWithTheirRanges) {
  const PipelineSettings s = loadPipelineSettings(writeTemp(
      "breast_sim_uncertainty.yaml",
      "phantom: {}\nuncertainty: {enabled: true, samples: 12, youngs_modulus_factor_min: 0.7, youngs_modulus_factor_max: 1.4,\n"
      "  poisson_ratio_min: 0.46, poisson_ratio_max: 0.48, time_step_factor_min: 0.8, time_step_factor_max: 1.25, confidence: 0.9}\n"));
  const UncertaintySettings& u = s.uncertainty;
  EXPECT_TRUE(u.enabled);
  EXPECT_EQ(u.samples, 12);
  EXPECT_EQ(u.youngs_modulus_factor_min, 0.7);
  EXPECT_EQ(u.youngs_modulus_factor_max, 1.4);
  EXPECT_EQ(u.poisson_ratio_min, 0.46);
  EXPECT_EQ(u.poisson_ratio_max, 0.48);
  EXPECT_EQ(u.time_step_factor_min, 0.8);
  EXPECT_EQ(u.time_step_factor_max, 1.25);
  EXPECT_EQ(u.confidence, 0.9);
  EXPECT_FALSE(loadPipelineSettings(kPhantomCase).uncertainty.enabled);
  EXPECT_NE(message("phantom: {}\nuncertainty: {samples: 3}\n").find("uncertainty.samples"), std::string::npos);
  EXPECT_NE(message("phantom: {}\nuncertainty: {poisson_ratio_max: 0.5}\n").find("uncertainty.poisson_ratio_max"), std::string::npos);
  EXPECT_NE(message("phantom: {}\nuncertainty: {youngs_modulus_factor_min: 3}\n").find("youngs_modulus_factor_max"), std::string::npos);
  EXPECT_NE(message("phantom: {}\nuncertainty: {confidence: 1}\n").find("uncertainty.confidence"), std::string::npos);
  EXPECT_NE(message("phantom: {}\nuncertainty: {sample: 8}\n").find("sample"), std::string::npos);
}

/// The phantom's case with the wall fixed and gravity only: the ensemble's runs take well under a second.
PipelineSettings gravityOnly() {
  PipelineSettings s = loadPipelineSettings(kPhantomCase);
  s.simulation.sliding = false;
  s.morphing.enabled = false;
  s.uncertainty.samples = 4;
  return s;
}

Points nominalLesions(const PipelineSettings& s) {
  ProneToSupinePipeline pipe(phantom().c, phantom().m, s);
  pipe.run();
  return pipe.lesionPositions();
}

// With every range a single point at the nominal parameters, each sample is the nominal run: the
// regions collapse to their centre (a run is reproducible to the bit).
TEST(LesionUncertainty, EnsembleOfTheNominalParametersHasNoSpread) {
  PipelineSettings s = gravityOnly();
  UncertaintySettings& u = s.uncertainty;
  u.youngs_modulus_factor_min = u.youngs_modulus_factor_max = 1.0;
  u.poisson_ratio_min = u.poisson_ratio_max = s.simulation.material.poisson_ratio;
  u.time_step_factor_min = u.time_step_factor_max = 1.0;
  const Points nominal = nominalLesions(s);
  const LesionUncertainty r = estimateLesionUncertainty(phantom().c, phantom().m, s, nominal);
  ASSERT_TRUE(r.valid) << r.failure;
  ASSERT_EQ(r.samples.size(), 4u);
  ASSERT_EQ(r.lesions.size(), phantom().m.lesions.size());
  for (const auto& l : r.lesions) {
    EXPECT_EQ(l.max_sample_distance_m, 0.0);
    EXPECT_EQ(l.semi_axes_m.maxCoeff(), 0.0);
  }
}

// Each sample is the run a user would get by editing the case by hand; softer tissue sags more.
TEST(LesionUncertainty, EachSampleIsTheRunOfItsSettingsAndTheRegionHoldsTheSpread) {
  const PipelineSettings s = gravityOnly();
  const Points nominal = nominalLesions(s);
  int calls = 0, last_index = -1;
  const LesionUncertainty r = estimateLesionUncertainty(phantom().c, phantom().m, s, nominal,
                                                        [&](int index, int count, const PipelineProgress&) {
                                                          EXPECT_EQ(count, 4);
                                                          EXPECT_GE(index, last_index);
                                                          last_index = index;
                                                          ++calls;
                                                        });
  ASSERT_TRUE(r.valid) << r.failure;
  EXPECT_EQ(last_index, 3);
  EXPECT_GT(calls, 4);
  const auto design = uncertaintyDesign(s.uncertainty, 4);
  // The slow reference: sample 2 (index 3 of the sequence) set up and run by hand.
  {
    PipelineSettings by_hand = s;
    by_hand.simulation.material.youngs_modulus_pa *= design[2].youngs_modulus_factor;
    by_hand.simulation.material.poisson_ratio = design[2].poisson_ratio;
    by_hand.simulation.dynamics.time_step_s *= design[2].time_step_factor;
    by_hand.simulation.settle.time_step_s *= design[2].time_step_factor;
    by_hand.morphing.time_step_s *= design[2].time_step_factor;
    EXPECT_EQ((nominalLesions(by_hand) - r.samples[2].lesions_m).cwiseAbs().maxCoeff(), 0.0);
  }
  // The softest sample moves every lesion farther from prone than the stiffest one.
  int soft = 0, stiff = 0;
  for (int i = 0; i < 4; ++i) {
    if (design[i].youngs_modulus_factor < design[soft].youngs_modulus_factor) soft = i;
    if (design[i].youngs_modulus_factor > design[stiff].youngs_modulus_factor) stiff = i;
  }
  const Points prone = phantom().m.lesion_embedding.positions(phantom().m.mesh.nodes());
  for (Eigen::Index l = 0; l < prone.rows(); ++l) {
    const double soft_move = (r.samples[soft].lesions_m.row(l) - prone.row(l)).norm();
    const double stiff_move = (r.samples[stiff].lesions_m.row(l) - prone.row(l)).norm();
    EXPECT_GT(soft_move, 1.2 * stiff_move) << l;
    const LesionRegion& g = r.lesions[static_cast<size_t>(l)];
    EXPECT_EQ(g.centre_m, nominal.row(l).transpose());
    EXPECT_GT(g.semi_axes_m[0], 1e-4) << l;  // E × 0.5 … 2 spreads the sag by millimetres
    EXPECT_GE(g.semi_axes_m[0], g.semi_axes_m[1]);
    EXPECT_GE(g.semi_axes_m[1], g.semi_axes_m[2]);
    int inside = 0;
    for (const auto& smp : r.samples) inside += g.contains(smp.lesions_m.row(l).transpose());
    EXPECT_GE(inside, 3) << l;
  }
}

// A morphing stage that stalls short of its 95th-percentile tolerance but within its mean one still
// counts (with a note); one that ends farther than the mean tolerance does not.
TEST(LesionUncertainty, AMorphingStageShortOfItsMeanToleranceFailsTheSample) {
  PipelineSettings s = gravityOnly();
  s.morphing.enabled = true;
  s.morphing.max_steps = 15;
  s.morphing.tolerance_p95_m = 1e-9;  // never met
  s.morphing.tolerance_mean_m = 0.05;
  const Points nominal = nominalLesions(s);
  const LesionUncertainty near = estimateLesionUncertainty(phantom().c, phantom().m, s, nominal);
  ASSERT_TRUE(near.valid) << near.failure;
  for (const auto& smp : near.samples) {
    EXPECT_TRUE(smp.completed);
    EXPECT_NE(smp.note.find("mean tolerance"), std::string::npos) << smp.note;
  }
  s.morphing.tolerance_mean_m = 1e-9;
  const LesionUncertainty far = estimateLesionUncertainty(phantom().c, phantom().m, s, nominal);
  EXPECT_FALSE(far.valid);
  EXPECT_NE(far.failure.find("farther than its tolerance"), std::string::npos) << far.failure;
}

TEST(LesionUncertainty, AFailedSampleOrACancelLeavesNoRegion) {
  PipelineSettings s = gravityOnly();
  const Points nominal = nominalLesions(s);
  s.simulation.settle.max_steps = 2;  // no sample settles in 2 steps
  const LesionUncertainty r = estimateLesionUncertainty(phantom().c, phantom().m, s, nominal);
  EXPECT_FALSE(r.valid);
  EXPECT_TRUE(r.lesions.empty());
  EXPECT_FALSE(r.samples.front().completed);
  EXPECT_NE(r.failure.find("sample 1 of 4"), std::string::npos) << r.failure;
  EXPECT_NE(r.failure.find("did not converge"), std::string::npos) << r.failure;

  std::atomic<bool> cancel{false};
  const LesionUncertainty c = estimateLesionUncertainty(
      phantom().c, phantom().m, gravityOnly(), nominal,
      [&](int index, int, const PipelineProgress& p) { if (index == 1 && p.step >= 2) cancel = true; }, &cancel);
  EXPECT_FALSE(c.valid);
  EXPECT_TRUE(c.cancelled);
  EXPECT_EQ(c.samples.size(), 1u);
  EXPECT_NE(c.failure.find("cancelled after 1 of 4"), std::string::npos) << c.failure;

  EXPECT_THROW(estimateLesionUncertainty(phantom().c, phantom().m, gravityOnly(), Points::Zero(5, 3)), std::invalid_argument);
}

// With the unloaded rest shape every sample recovers its own X0. Given the nominal run, a sample
// takes its multigrid levels and starts from the nominal X0 scaled to the sample's modulus; the slow
// reference beside it is the same ensemble without the nominal run (levels meshed again, each
// recovery started at the prone shape). Both recover X0 to the samples' tolerance, so the lesions
// agree to within about as much, and the scaled start needs fewer loadings.
TEST(LesionUncertainty, SamplesGivenTheNominalRunStartFromItsUnloadedShapeAndLevels) {
  PipelineSettings s = gravityOnly();
  s.simulation.reference_state = SimulationSettings::ReferenceState::kUnloaded;
  ProneToSupinePipeline nominal(phantom().c, phantom().m, s);
  ASSERT_TRUE(nominal.unloadedState().converged) << nominal.unloadedState().failure;
  nominal.run();
  const Points p0 = nominal.lesionPositions();
  const LesionUncertainty fresh = estimateLesionUncertainty(phantom().c, phantom().m, s, p0);
  const LesionUncertainty reused = estimateLesionUncertainty(phantom().c, phantom().m, s, p0, {}, nullptr, 1, &nominal);
  ASSERT_TRUE(fresh.valid) << fresh.failure;
  ASSERT_TRUE(reused.valid) << reused.failure;
  int fresh_loadings = 0, reused_loadings = 0;
  double gap = 0.0;
  for (size_t k = 0; k < fresh.samples.size(); ++k) {
    const UncertaintySample &a = fresh.samples[k], &b = reused.samples[k];
    EXPECT_GT(a.unloaded_loadings, 0);
    EXPECT_GT(b.unloaded_loadings, 0);
    EXPECT_LE(a.unloaded_residual_m, kSampleUnloadedTolerance);
    EXPECT_LE(b.unloaded_residual_m, kSampleUnloadedTolerance);
    EXPECT_GT(a.unloaded_residual_m, 0.0);
    fresh_loadings += a.unloaded_loadings;
    reused_loadings += b.unloaded_loadings;
    gap = std::max(gap, (a.lesions_m - b.lesions_m).rowwise().norm().maxCoeff());
    std::printf("[ measure  ] sample %zu (E x %.2f): X0 in %d loadings from prone, %d from the nominal X0\n", k + 1,
                a.params.youngs_modulus_factor, a.unloaded_loadings, b.unloaded_loadings);
  }
  std::printf("[ measure  ] lesions of the two ensembles within %.4f mm; %.2f s against %.2f s\n", 1e3 * gap,
              reused.seconds, fresh.seconds);
  EXPECT_LT(gap, kSampleUnloadedTolerance);
  EXPECT_LT(reused_loadings, fresh_loadings);

  PipelineSettings other = s;
  other.simulation.solver.kind = SolverSettings::Kind::kCholmod;
  EXPECT_THROW(estimateLesionUncertainty(phantom().c, phantom().m, other, p0, {}, nullptr, 1, &nominal), std::invalid_argument);
  for (double bad : {0.0, -1e-5, std::nan("")})
    EXPECT_THROW(ProneToSupinePipeline(phantom().c, phantom().m, s, std::nullopt, Points(), bad), std::invalid_argument) << bad;
  const SimulationModel copy = phantom().m;
  EXPECT_THROW(estimateLesionUncertainty(phantom().c, copy, s, p0, {}, nullptr, 1, &nominal), std::invalid_argument);
}

}  // namespace
}  // namespace breast_sim::core
