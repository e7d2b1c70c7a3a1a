#pragma once
/// @file lesion_uncertainty.h
/// Each lesion's supine position with a confidence region, from an ensemble of pipeline runs.
///
/// Breast stiffness is known to a factor of about two, ν only roughly, and a run's stick/slip path
/// on the chest wall moves lesions by about a millimetre. The ensemble runs the whole pipeline
/// (ProneToSupinePipeline::run) once per sample of
///   - Young's modulus: every tissue's E × f, f log-uniform in [youngs_modulus_factor_min, max];
///   - Poisson's ratio ν uniform in [poisson_ratio_min, max];
///   - the path: every stage's time step × k, k log-uniform in [time_step_factor_min, max]
///     (a longer step takes another stick/slip path and another reversal history);
/// at the points of a Halton sequence (bases 2, 3, 5), so the same settings give the same samples on
/// any machine. Each lesion's region is centred on the nominal run's position p0 (the one the
/// package publishes), with C = (1/n) Σ (p_k − p0)(p_k − p0)ᵀ over the n samples (bias included),
/// and is the ellipsoid (x − p0)ᵀ C⁻¹ (x − p0) ≤ s², s = regionScale(confidence, n): semi-axes
/// s √λ_i along C's eigenvectors. Measured coverage and cost: docs/uncertainty.md.
/// Units: m, m²; the factors are dimensionless.

#include <atomic>
#include <functional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::core {

/// How close a sample's X0 loaded with prone gravity must come to the prone shape at every node [m]
/// (the nominal run: UnloadedStateOptions' 0.01 mm). A sample is one draw of parameters whose lesion
/// spread is millimetres; its X0 off by this at its worst node moves its lesion by about as much,
/// within the scatter the stick/slip path gives two ensembles of the same parameters (0.19 mm on the
/// VICTRE image's case with every X0 to 0.01 mm), and soft samples of an MRI case reach it where
/// 0.01 mm takes the recovery 30 loadings or stalls (docs/uncertainty.md, "A patient's image").
inline constexpr double kSampleUnloadedTolerance = 0.25e-3;

/// One ensemble member's parameters.
struct UncertaintySampleParams {
  double youngs_modulus_factor = 1.0;  ///< every tissue's E × this
  double poisson_ratio = 0.48;         ///< ν of the sample
  double time_step_factor = 1.0;       ///< every stage's time step × this
};

/// The `n` samples of the ensemble: Halton points `first_index` … `first_index + n − 1` (≥ 1)
/// mapped onto the settings' ranges. @throws std::invalid_argument for n < 1 or first_index < 1.
std::vector<UncertaintySampleParams> uncertaintyDesign(const UncertaintySettings& settings, int n, int first_index = 1);

/// `nominal` with one sample's parameters applied (uncertainty off in the copy).
/// @throws std::invalid_argument when the sample's settings are out of range (e.g. a time step over 10 s).
PipelineSettings sampleSettings(const PipelineSettings& nominal, const UncertaintySampleParams& sample);

/// The Mahalanobis radius of a region from `samples` runs that holds a further run with probability
/// `confidence` (a prediction region; normal spread about the known centre): √(3n/(n−2) F₃,ₙ₋₂(c)),
/// 4.36 for 8 samples at 0.95, 3.06 for 32, and √χ²₃ = 2.80 for many. With few samples the spread
/// itself is uncertain, and a χ² region would hold fewer further runs than it says.
/// @throws std::invalid_argument for a confidence outside (0, 1) or fewer than 3 samples.
double regionScale(double confidence, int samples);

/// A lesion's confidence region.
struct LesionRegion {
  Eigen::Vector3d centre_m = Eigen::Vector3d::Zero();        ///< the nominal position p0 [m]
  Eigen::Matrix3d covariance_m2 = Eigen::Matrix3d::Zero();   ///< C about p0 [m²]
  Eigen::Vector3d semi_axes_m = Eigen::Vector3d::Zero();     ///< of the ellipsoid, largest first [m]
  /// Columns: the unit axis of each semi-axis, a right-handed rotation (det +1).
  Eigen::Matrix3d axes = Eigen::Matrix3d::Identity();
  double confidence = 0.95;
  double scale = 0.0;                 ///< regionScale(confidence, samples): the region's Mahalanobis radius
  double max_sample_distance_m = 0.0; ///< the farthest sample from p0 [m]
  /// True when p lies in the ellipsoid (on a degenerate axis, within 1e-9 m of the centre's plane).
  bool contains(const Eigen::Vector3d& p_m) const;
};

/// The region of samples around `centre_m` (slow reference and fast path are the same few lines:
/// the tests check it against ellipsoids built by hand). @throws std::invalid_argument for fewer
/// than 3 samples or a confidence outside (0, 1).
LesionRegion lesionRegion(const Eigen::Vector3d& centre_m, const std::vector<Eigen::Vector3d>& samples_m, double confidence);

/// One ensemble member's run.
struct UncertaintySample {
  UncertaintySampleParams params;
  /// Its lesions count: the gravity and sliding stages converged, the morphing stage converged or
  /// ended within its mean tolerance (tolerance_mean_mm), no element ended inverted.
  bool completed = false;
  std::string failure;      ///< why not completed (empty when completed)
  std::string note;         ///< a tolerance missed by a completed sample (empty when none)
  Points lesions_m;         ///< #lesions×3 at the run's end [m]
  int unloaded_loadings = 0;  ///< forward loadings of its X0 recovery (0 with the prone rest shape)
  double unloaded_residual_m = 0.0;  ///< its X0 loaded with prone gravity: largest distance to the prone shape [m]
  double seconds = 0.0;
};

struct LesionUncertainty {
  /// Regions exist for every lesion: all samples completed and none was cancelled.
  bool valid = false;
  bool cancelled = false;
  std::string failure;      ///< the first failed sample and its parameters, or "cancelled"
  std::vector<UncertaintySample> samples;
  std::vector<LesionRegion> lesions;  ///< one per lesion when valid, else empty
  double seconds = 0.0;               ///< the whole ensemble [s]
};

/// Progress of the ensemble: sample `index` (0-based) of `count`, and that run's own progress.
using UncertaintyProgressFn = std::function<void(int index, int count, const PipelineProgress&)>;

/// Runs the ensemble of settings.uncertainty (whether or not `enabled`: the caller decides) for the
/// case and model the nominal run used, with that run's final lesion positions `nominal_lesions_m`
/// (#lesions×3 [m], e.g. ProneToSupinePipeline::lesionPositions()). Each sample builds its own
/// pipeline; the caller's pipeline is not touched. A sample that does not complete (see
/// UncertaintySample::completed) or that throws ends the ensemble not valid, naming the sample
/// (narrow the ranges or fix the case). A morphing stage that stalls within the mean tolerance but
/// short of the 95th-percentile one (a few skin vertices the stiffer sample cannot bring to the
/// target) still counts: its lesions lie where such a fit puts them, and the note says so.
/// @param first_index  the Halton index of the first sample (1 for a case's ensemble)
/// @param nominal_run  the pipeline that ran `settings` on this case and model, or null. Given, every
///        sample takes its multigrid levels (ProneToSupinePipeline::coarseMeshes) instead of meshing
///        them, and with the unloaded rest shape starts its recovery of X0 from the nominal X0 with
///        the move from the prone shape divided by the sample's modulus factor f (a linear material
///        hangs 1/f as far; where that start would invert an element, from the nominal X0 itself).
///        The start saves loadings, not accuracy.
/// With the unloaded rest shape each sample recovers its own X0 to kSampleUnloadedTolerance.
/// @throws std::invalid_argument when the nominal positions do not match the model's lesions, or
///         nominal_run ran another model or solver.
LesionUncertainty estimateLesionUncertainty(const ModelCase& model_case, const SimulationModel& model,
                                            const PipelineSettings& settings, const Points& nominal_lesions_m,
                                            const UncertaintyProgressFn& progress = {},
                                            const std::atomic<bool>* cancel = nullptr, int first_index = 1,
                                            const ProneToSupinePipeline* nominal_run = nullptr);

}  // namespace breast_sim::core
