// Lesion confidence regions from an ensemble of pipeline runs (pipeline/lesion_uncertainty.h).
#include "breast_sim/core/pipeline/lesion_uncertainty.h"

#include <chrono>
#include <optional>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include <Eigen/Eigenvalues>
#include <boost/math/distributions/fisher_f.hpp>

#include "breast_sim/core/mesh/tet_quality.h"

namespace breast_sim::core {
namespace {

/// The radical inverse of `index` in `base`: the Halton coordinate in (0, 1).
double radicalInverse(int index, int base) {
  double f = 1.0, r = 0.0;
  for (int i = index; i > 0; i /= base) {
    f /= base;
    r += f * (i % base);
  }
  return r;
}

double logUniform(double lo, double hi, double u) { return lo * std::pow(hi / lo, u); }

std::string describe(const UncertaintySampleParams& p) {
  std::ostringstream s;
  s.precision(3);
  s << "E x " << p.youngs_modulus_factor << ", nu " << p.poisson_ratio << ", time steps x " << p.time_step_factor;
  return s.str();
}

/// Where a sample of modulus factor f starts its recovery of X0 (see estimateLesionUncertainty's
/// nominal_run): the nominal X0's move from the prone shape divided by f, or the nominal X0 where
/// that would invert an element. Empty when the nominal run has the prone rest shape.
Points unloadedStart(const ProneToSupinePipeline& nominal, double f) {
  if (nominal.unloadedState().iterations == 0) return {};
  const Points& prone = nominal.proneModel().mesh.nodes();
  const Points& x0 = nominal.model().mesh.nodes();
  Points start = prone + (x0 - prone) / f;
  if (!invertedTets(nominal.model().mesh.tets(), start).empty()) return x0;
  return start;
}

}  // namespace

std::vector<UncertaintySampleParams> uncertaintyDesign(const UncertaintySettings& u, int n, int first_index) {
  if (n < 1 || first_index < 1)
    throw std::invalid_argument("uncertaintyDesign: " + std::to_string(n) + " samples from index " +
                                std::to_string(first_index) + "; expected at least 1 sample from index 1 or later");
  std::vector<UncertaintySampleParams> out(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) {
    const int h = first_index + i;
    UncertaintySampleParams& p = out[static_cast<size_t>(i)];
    p.youngs_modulus_factor = logUniform(u.youngs_modulus_factor_min, u.youngs_modulus_factor_max, radicalInverse(h, 2));
    p.poisson_ratio = u.poisson_ratio_min + (u.poisson_ratio_max - u.poisson_ratio_min) * radicalInverse(h, 3);
    p.time_step_factor = logUniform(u.time_step_factor_min, u.time_step_factor_max, radicalInverse(h, 5));
  }
  return out;
}

PipelineSettings sampleSettings(const PipelineSettings& nominal, const UncertaintySampleParams& p) {
  PipelineSettings s = nominal;
  s.uncertainty.enabled = false;
  SimulationSettings& sim = s.simulation;
  sim.material.youngs_modulus_pa *= p.youngs_modulus_factor;
  for (auto& kv : sim.region_youngs_modulus_pa) kv.second *= p.youngs_modulus_factor;
  sim.material.poisson_ratio = p.poisson_ratio;
  // Every stage's step; a 0 (= "the dynamics step") stays 0 and follows the scaled dynamics step.
  sim.dynamics.time_step_s *= p.time_step_factor;
  sim.settle.time_step_s *= p.time_step_factor;
  s.sliding_stage.time_step_s *= p.time_step_factor;
  s.morphing.time_step_s *= p.time_step_factor;
  try {
    s.validate();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("uncertainty sample (" + describe(p) + "): " + e.what() +
                                "; narrow the ranges of 'uncertainty:'");
  }
  return s;
}

double regionScale(double confidence, int samples) {
  if (!(confidence > 0) || !(confidence < 1))
    throw std::invalid_argument("regionScale: confidence " + std::to_string(confidence) + " is not in (0, 1)");
  if (samples < 3)
    throw std::invalid_argument("regionScale: " + std::to_string(samples) +
                                " samples cannot span a region in 3-D; give at least 3");
  const double n = samples;
  // T²(3, n) = 3n / (n − 2) · F(3, n − 2): the Mahalanobis distance of a new sample under the
  // covariance of n samples about the known centre.
  const boost::math::fisher_f f(3.0, n - 2.0);
  return std::sqrt(3.0 * n / (n - 2.0) * boost::math::quantile(f, confidence));
}

bool LesionRegion::contains(const Eigen::Vector3d& p_m) const {
  const Eigen::Vector3d d = axes.transpose() * (p_m - centre_m);  // in the axes' frame
  double r2 = 0.0;
  for (int k = 0; k < 3; ++k) {
    if (semi_axes_m[k] > 0) r2 += (d[k] / semi_axes_m[k]) * (d[k] / semi_axes_m[k]);
    else if (std::abs(d[k]) > 1e-9) return false;
  }
  return r2 <= 1.0;
}

LesionRegion lesionRegion(const Eigen::Vector3d& centre_m, const std::vector<Eigen::Vector3d>& samples_m, double confidence) {
  LesionRegion r;
  r.centre_m = centre_m;
  r.confidence = confidence;
  r.scale = regionScale(confidence, static_cast<int>(samples_m.size()));
  for (const Eigen::Vector3d& p : samples_m) {
    const Eigen::Vector3d d = p - centre_m;
    r.covariance_m2 += d * d.transpose();
    r.max_sample_distance_m = std::max(r.max_sample_distance_m, d.norm());
  }
  r.covariance_m2 /= static_cast<double>(samples_m.size());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(r.covariance_m2);
  // Eigen orders the eigenvalues ascending: largest first here.
  for (int k = 0; k < 3; ++k) {
    const double lambda = std::max(0.0, eig.eigenvalues()[2 - k]);
    r.semi_axes_m[k] = r.scale * std::sqrt(lambda);
    r.axes.col(k) = eig.eigenvectors().col(2 - k);
  }
  if (r.axes.determinant() < 0) r.axes.col(2) = -r.axes.col(2);
  return r;
}

LesionUncertainty estimateLesionUncertainty(const ModelCase& model_case, const SimulationModel& model,
                                            const PipelineSettings& settings, const Points& nominal_lesions_m,
                                            const UncertaintyProgressFn& progress, const std::atomic<bool>* cancel,
                                            int first_index, const ProneToSupinePipeline* nominal_run) {
  using Clock = std::chrono::steady_clock;
  const auto since = [](Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); };
  const Eigen::Index lesions = static_cast<Eigen::Index>(model.lesions.size());
  if (nominal_lesions_m.rows() != lesions || nominal_lesions_m.cols() != 3)
    throw std::invalid_argument("estimateLesionUncertainty: " + std::to_string(nominal_lesions_m.rows()) + "x" +
                                std::to_string(nominal_lesions_m.cols()) + " nominal positions for " +
                                std::to_string(lesions) + " lesions (expected #lesions x 3)");
  settings.uncertainty.validate();
  if (nominal_run && (&nominal_run->proneModel() != &model ||
                      nominal_run->settings().simulation.solver.kind != settings.simulation.solver.kind))
    throw std::invalid_argument("estimateLesionUncertainty: the nominal run given ran another model or solver; give the "
                                "pipeline that ran these settings on this model, or none");
  const auto t0 = Clock::now();
  LesionUncertainty out;
  const std::vector<UncertaintySampleParams> design =
      uncertaintyDesign(settings.uncertainty, settings.uncertainty.samples, first_index);
  const int count = static_cast<int>(design.size());
  for (int i = 0; i < count; ++i) {
    if (cancel && cancel->load()) {
      out.cancelled = true;
      break;
    }
    UncertaintySample sample;
    sample.params = design[static_cast<size_t>(i)];
    const auto ts = Clock::now();
    try {
      std::optional<std::vector<TetMesh>> levels;
      Points start;
      if (nominal_run) {
        if (settings.simulation.solver.kind == SolverSettings::Kind::kMultigrid) levels = nominal_run->coarseMeshes();
        start = unloadedStart(*nominal_run, sample.params.youngs_modulus_factor);
      }
      ProneToSupinePipeline pipe(model_case, model, sampleSettings(settings, sample.params), std::move(levels), start,
                                 kSampleUnloadedTolerance);
      sample.unloaded_loadings = pipe.unloadedState().iterations;
      sample.unloaded_residual_m = pipe.unloadedState().max_residual_m;
      pipe.run([&](const PipelineProgress& p) { if (progress) progress(i, count, p); }, cancel);
      if (cancel && cancel->load() && pipe.stage() != PipelineStage::kDone) {
        out.cancelled = true;
        break;
      }
      sample.lesions_m = pipe.lesionPositions();
      const StageReport& g = pipe.gravityReport();
      const StageReport& sl = pipe.slidingReport();
      const StageReport& mo = pipe.morphingReport();
      const int inverted = qualityStats(model.mesh.tets(), pipe.positions()).num_inverted;
      if (!g.converged) sample.failure = "the gravity settle did not converge";
      else if (sl.ran && !sl.converged) sample.failure = "the sliding stage did not settle";
      else if (mo.ran && !mo.converged && !(mo.surface_mean_m >= 0 && mo.surface_mean_m <= settings.morphing.tolerance_mean_m))
        sample.failure = "the morphing stage ended " + std::to_string(mo.surface_mean_m * 1e3) +
                         " mm (mean) from the target, farther than its tolerance";
      else if (inverted > 0) sample.failure = std::to_string(inverted) + " elements ended inverted";
      else if (!sample.lesions_m.allFinite()) sample.failure = "a lesion position is not finite";
      if (sample.failure.empty() && mo.ran && !mo.converged) {
        std::ostringstream n;
        n << "the morphing stage ended within its mean tolerance but not every other one (mean " << mo.surface_mean_m * 1e3
          << " mm, p95 " << mo.surface_p95_m * 1e3 << " mm, after " << mo.steps << " steps)";
        sample.note = n.str();
      }
    } catch (const std::exception& e) {
      sample.failure = e.what();
    }
    sample.completed = sample.failure.empty();
    sample.seconds = since(ts);
    if (!sample.completed && out.failure.empty())
      out.failure = "sample " + std::to_string(i + 1) + " of " + std::to_string(count) + " (" + describe(sample.params) +
                    "): " + sample.failure + "; narrow the ranges of 'uncertainty:' or check the case";
    out.samples.push_back(std::move(sample));
  }
  out.seconds = since(t0);
  if (out.cancelled) {
    out.failure = "cancelled after " + std::to_string(out.samples.size()) + " of " + std::to_string(count) + " samples";
    return out;
  }
  if (!out.failure.empty()) return out;
  for (Eigen::Index l = 0; l < lesions; ++l) {
    std::vector<Eigen::Vector3d> at;
    at.reserve(out.samples.size());
    for (const UncertaintySample& s : out.samples) at.push_back(s.lesions_m.row(l).transpose());
    out.lesions.push_back(lesionRegion(nominal_lesions_m.row(l).transpose(), at, settings.uncertainty.confidence));
  }
  out.valid = true;
  return out;
}

}  // namespace breast_sim::core
