#pragma once
/// @file prone_to_supine.h
/// The combined prone-to-supine pipeline (seed paper, section 2.6 and Figure 2).
///
/// The rest shape (simulation.reference_state): by default, for a patient's image, MRI or mesh, the
/// shape X0 recovered at construction from the prone shape (fem/unloaded_state.h), so that X0 loaded
/// with prone gravity is the prone shape; the run starts at the prone shape (displacement prone − X0)
/// and loads supine gravity itself. With `prone` (the software phantom's default) the prone shape is
/// taken as stress-free and loaded with g_supine − g_prone (SimulationSettings::ReferenceState).
/// Either way the gravity *load* the API speaks of is g_now − g_prone, and
/// displacements are measured from the prone shape.
///
/// Two stages on one simulator:
///  1. Gravity precomputation: the model is loaded with supine gravity and settled with von Mises
///     stiffening and time-step reversal, the chest wall fixed; with sliding on, the wall nodes are then released to slide on the wall
///     and the run goes on until the wall stops moving and the tissue has settled again. The seed
///     advises exactly this order: morphing only after sliding and stiffening are macroscopically
///     stable.
///  2. Surface morphing to a target surface (the phantom's supine shape, a surface file, or a
///     tracker's point cloud), one Figure-2 iteration per step:
///       add morphing forces (accumulated, never reset)
///       → set element moduli E_r = 1 + α s_VM → simulate a step → inverted elements?
///           yes: restore the positions, increase α and repeat the step WITHOUT re-adding forces;
///           no:  decrease α — unless the surface distance already meets the tolerance, then α is
///                held (the material is "soft enough", seed 2.6) — and move the sliding constraints.
///     The stage ends when the mean and 95th-percentile distances of the pulled skin vertices to the
///     target are within tolerance and the step's move (MorphingStageSettings::increment_measure) is
///     within the increment tolerance.
///
/// Every part can be switched on or off and parameterised (PipelineSettings, from one YAML file).
/// Units: SI inside (m, Pa, s); YAML keys say theirs.

#include <atomic>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/fem/unloaded_state.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/surface_field.h"
#include "breast_sim/core/morphing/surface_morphing.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"
#include "breast_sim/core/sliding/wall_slip.h"

namespace breast_sim::core {

/// The morphing stage (YAML map `morphing:`; keys with their units in config/phantom_default.yaml).
/// The measurements behind the defaults: docs/pipeline.md, "Settings: the morphing stage".
struct MorphingStageSettings {
  bool enabled = true;  ///< false: run() skips the stage (iterate() and runMorphing() still work with a target)
  /// The target surface, read by the pipeline's constructor: "auto" = the phantom's supine skin
  /// surface for a phantom case, none for an image case; "phantom" = the phantom's (for an image case
  /// the constructor throws std::invalid_argument); otherwise a surface file (.obj, .stl, .ply, .vtp,
  /// .vtk; relative paths from the case file); "" = no target (the stage is skipped).
  std::string target = "auto";
  double target_length_unit_m = 1e-3;  ///< metres per unit of a target file, > 0 (1e-3: the file is in mm)
  /// The morphing forces (MorphingOptions: gain and implicit pull spring_pa_per_m [Pa/m], traction
  /// cap [Pa], outlier distance [m], which vertices). The stage doubles MorphingOptions' gain to
  /// 4e4 Pa/m, which reaches the tolerances in fewer steps; the implicit pull stays off (0).
  MorphingOptions forces = [] {
    MorphingOptions o;
    o.gain_pa_per_m = 4e4;
    return o;
  }();
  SurfaceFieldOptions field;           ///< the distance-field grid (voxel size [m], voxels per axis)
  double time_step_s = 0.1;            ///< dynamics time step while morphing [s], in (0, 10]
  double tolerance_mean_m = 0.5e-3;    ///< mean distance of the pulled vertices to the target to reach [m], > 0
  double tolerance_p95_m = 1.5e-3;     ///< 95th percentile of those distances to reach [m], > 0
  /// The stage has converged when, for 3 accepted steps in a row, the tolerances hold and the step's
  /// move (increment_measure) is at most this [m], > 0.
  double increment_tolerance_m = 1e-4;
  /// The move compared with increment_tolerance_m:
  ///  - kAllMax: the largest move of any node;
  ///  - kPulledP95: the 95th percentile of the pulled skin vertices' moves;
  ///  - kOffWall: the largest move of a node off the wall band (wallBandNodes()) and the 95th
  ///    percentile of the band's moves, both; without sliding the band is empty and this is kAllMax.
  /// kOffWall (default): the tissue must be at rest, but single wall nodes' stick–slip jumps do not hold the stage.
  enum class IncrementMeasure { kAllMax, kPulledP95, kOffWall } increment_measure = IncrementMeasure::kOffWall;
  /// Volume condition of the stop: also |V − V0| / V0 within this [%], in [0, 100]; 0 = none. For a
  /// target that encloses the model's rest volume (the phantom's case file sets 0.5); off by
  /// default because a measured surface need not have that volume.
  double volume_tolerance_percent = 0.0;
  /// Divergence guard: a step in which a node moves more than this [m] (≥ 0; 0 = no bound) is a
  /// failed step like one that inverts an element: the state before it is restored, α raised, and
  /// the step repeated without new forces. The bound lies between the largest converging move and a run-away's.
  double max_step_move_m = 0.04;
  /// ... and so is a step that changes the volume by more than this [percentage points], ≥ 0; 0 = no bound.
  double max_step_volume_change_percent = 30.0;
  int max_steps = 300;                 ///< accepted steps at most, ≥ 1 (and 2 × max_steps calls at most)
  /// AlphaControllerParams::reversal_growth during this stage, ≥ 1 (1: each repeated reversal
  /// multiplies α by increase_factor only); the controller's own value is back after the stage.
  /// Above 1 because the stage starts at the α the settle left, far below what its first pulls need.
  double alpha_reversal_growth = 2.0;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// The sliding stage after the fixed-wall settle (YAML keys in `sliding:`: time_step_s,
/// settle_increment_tolerance_mm, settle_increment_measure). Releasing the wall starts a new α search
/// at the α the fixed-wall settle ended at. The measurements behind
/// the defaults: docs/pipeline.md, "Settings: the sliding stage".
struct SlidingStageSettings {
  /// Time step of the sliding stage [s], in [0, 10]; 0 = the dynamics time step
  /// (simulation.time_step_s). The default is the dynamics step: a long step changes the friction path.
  double time_step_s = 0.0;
  /// Settled when the step's move (increment_measure) is at most this [m], ≥ 0, for 3 accepted steps
  /// in a row (explicit method: and the constraints have stopped moving); 0 = the gravity stage's
  /// simulation.settle_increment_tolerance_mm.
  double increment_tolerance_m = 0.0;
  /// The move compared with increment_tolerance_m: kAllMax, the largest move of any node; kOffWall,
  /// the largest move of a node off the wall band (wallBandNodes()) and the 95th percentile of the
  /// band's moves, both (single wall nodes' stick–slip creep does not hold the stage).
  enum class IncrementMeasure { kAllMax, kOffWall } increment_measure = IncrementMeasure::kAllMax;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Nested iteration (YAML map `coarse_start:`): gravity, sliding and most of the morphing run on a
/// coarser mesh of the same case, and the model takes that state (startFrom) and only finishes the
/// morphing stage, which is its settle. Off by default: the lesions then land where the coarse mesh
/// puts them (docs/pipeline.md, "Nested iteration").
struct CoarseStartSettings {
  /// Target element count of the coarse mesh (its meshing.target_elements), in [0, 1e8]; 0 = off.
  /// Used only when, at construction, the model has at least twice as many elements, the morphing
  /// stage is enabled and a target is set; otherwise the model runs alone (a case file serves models
  /// of any size).
  int elements = 0;
  /// How far outside the coarse prone mesh a prone node or element centroid of the model may lie [m],
  /// in (0, 0.1]; such a point takes the value at the closest point of the coarse mesh. The two
  /// meshes' surfaces differ by up to the meshing's facet distance.
  double snap_tolerance_m = 5e-3;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// The lesions' confidence regions (YAML map `uncertainty:`; pipeline/lesion_uncertainty.h): an
/// ensemble of whole runs over Young's modulus, Poisson's ratio and the time steps (the stick/slip
/// path). Off by default: it costs `samples` runs besides the nominal one (docs/uncertainty.md).
struct UncertaintySettings {
  bool enabled = false;
  int samples = 8;                          ///< runs of the ensemble, in [4, 1000]
  double youngs_modulus_factor_min = 0.5;   ///< every tissue's E × f, f log-uniform in [min, max], 0 < min ≤ max ≤ 100
  double youngs_modulus_factor_max = 2.0;
  double poisson_ratio_min = 0.45;          ///< ν uniform in [min, max], 0 < min ≤ max < 0.5
  double poisson_ratio_max = 0.49;
  double time_step_factor_min = 0.67;       ///< every stage's time step × k, k log-uniform in [min, max], 0 < min ≤ max ≤ 10
  double time_step_factor_max = 1.5;
  double confidence = 0.95;                 ///< of the regions, in (0, 1)
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Everything the pipeline needs besides the case and the model.
struct PipelineSettings {
  SimulationSettings simulation;   ///< `simulation:`: material, solver, gravity stage, stiffening, sliding on/off
  /// `stiffening:` α control and the fixed-wall settle criterion (defaults: the robust preset of the
  /// stability map). The morphing stage replaces reversal_growth by morphing.alpha_reversal_growth.
  StiffeningParams stiffening;
  SlidingSettings sliding;         ///< `sliding:` (node set, limiting factors, friction; the explicit update)
  /// How the wall nodes slide: implicit (wall_slip.h: springs solved with the tissue; default) or
  /// explicit (chest_wall_sliding.h: moving constraints updated after each step, seed 2.4).
  enum class SlidingMethod { kImplicit, kExplicit } sliding_method = SlidingMethod::kImplicit;
  /// The implicit method's springs (`sliding:`); its friction coefficients and threshold are taken
  /// from `sliding` (static_friction, kinetic_friction, static_threshold_pa).
  WallSlipSettings wall_slip;
  SlidingStageSettings sliding_stage;  ///< the sliding stage's time step, α restart and settle rule (`sliding:`)
  MorphingStageSettings morphing;  ///< `morphing:`
  CoarseStartSettings coarse_start;  ///< `coarse_start:`
  UncertaintySettings uncertainty;  ///< `uncertainty:` (used by the caller of estimateLesionUncertainty)
  /// Every part's validate(); sliding also needs simulation.stiffening and a fixed_node_set.
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Reads `simulation:`, `stiffening:`, `sliding:`, `morphing:`, `coarse_start:` and `uncertainty:` of a case file
/// (absent maps and keys = the structs' defaults). The keys, their units and defaults are documented
/// in config/phantom_default.yaml. `stiffening:` (StiffeningParams; used when simulation.stiffening
/// is true), with accepted ranges:
///   initial_alpha_per_pa   α at the start and at every restart of the search [1/Pa], in
///                          [min_alpha_per_pa, max_alpha_per_pa]
///   min_alpha_per_pa       floor of α [1/Pa], > 0
///   max_alpha_per_pa       ceiling of α [1/Pa], ≥ min_alpha_per_pa
///   decrease_factor        α ← α · this after an accepted step (search phase), in (0, 1)
///   increase_factor        α ← α · this on a reversal, > 1
///   reversal_growth        the k-th repeated reversal of one step multiplies α by increase_factor ·
///                          this^(k−1), in [1, 100] (gravity and sliding stages; the morphing stage
///                          uses morphing.alpha_reversal_growth)
///   rate_halving           settling phase: the rate is multiplied by this per oscillation, in (0, 1)
///   min_rate               settling phase: smallest rate, in [0, 1 − decrease_factor]
///   max_reversals_per_step a step still inverting after this many reversals is not taken, [1, 1000]
///   settle_max_speed_mm_per_s     fixed-wall settle: every free node slower than this [mm/s], > 0
///   settle_max_relative_residual  ... and the relative static residual below this, in (0, 1]
///   settle_consecutive_steps      ... for this many accepted steps in a row, [1, 1000]
/// @throws std::runtime_error naming the file, the key, its value and the accepted range.
PipelineSettings loadPipelineSettings(const std::string& yaml_path);

enum class PipelineStage { kIdle, kGravity, kSliding, kMorphing, kDone };
const char* stageName(PipelineStage stage);

/// Reported after every step.
struct PipelineProgress {
  PipelineStage stage = PipelineStage::kIdle;
  int step = 0;                ///< accepted steps of this stage so far
  int max_steps = 0;
  double increment_m = 0.0;    ///< largest nodal displacement change of the last step [m]
  double surface_mean_m = -1;  ///< mean distance of the pulled vertices to the target [m]; −1 before morphing
  double surface_p95_m = -1;
  double alpha_per_pa = 0.0;
  /// Rough completion of the stage in [0, 1] (log-scale approach of the increment to its tolerance).
  double fraction = 0.0;
};
using PipelineProgressFn = std::function<void(const PipelineProgress&)>;

/// What one stage did.
struct StageReport {
  bool ran = false;
  bool converged = false;     ///< settled (gravity, sliding) or within tolerance (morphing)
  /// The cancel flag stopped the stage (runGravity's returned report: the settle or the sliding stage,
  /// on the coarse model with coarse_start; runMorphing's: the coarse or the fine model's steps).
  bool cancelled = false;
  /// Stopped because several stiffening calls in a row could not advance (reversal limit each time):
  /// no α lets the state go on without inverting an element.
  bool stuck = false;
  int steps = 0;              ///< accepted steps
  long reversed_steps = 0;    ///< trial steps reverted (time-step reversal)
  long reversal_limit_hits = 0;
  /// Accepted steps shortened to keep elements off their collapsed volume ratio (the
  /// average-nodal-pressure element; StiffeningSimulation, "Shortened steps"), counted in steps too.
  long shortened_steps = 0;
  /// Morphing: trial steps the divergence guard rejected (max_step_move_m, max_step_volume_change_percent;
  /// counted in reversed_steps too).
  long diverged_steps = 0;
  /// Implicit sliding: trial steps repeated because slipping wall nodes reversed (WallSlip::stickReversed);
  /// each costs a solve, not counted in reversed_steps.
  long friction_repeats = 0;
  double seconds = 0.0;       ///< wall time [s]
  double last_increment_m = 0.0;
  double final_alpha_per_pa = 0.0;
  /// Largest E_r − 1 at the end over the elements without a local α [1]: the state is within this
  /// (relative, linearised) of the base material's equilibrium (SettleCriterion::max_modulus_excess).
  double modulus_excess = 0.0;
  /// Elements kept stiffer than the rest at the end because the base material inverts them there
  /// (StiffeningSimulation, "Release"), and their share of the model's rest volume [%].
  int locally_stiffened_elements = 0;
  double locally_stiffened_volume_percent = 0.0;
  double surface_mean_m = -1; ///< morphing: pulled vertices → target at the end [m]
  double surface_p95_m = -1;
  double max_slide_m = 0.0;   ///< sliding: largest total slide of a wall node [m]
  double volume_change_percent = 0.0;  ///< (V − V0) / V0 at the end of the stage [%]
  int elements = 0;           ///< elements of the model the stage's steps ran on (the coarse one with coarse_start)
  /// Morphing with coarse_start: the coarse model's morphing steps before the fine ones (steps and
  /// reversed_steps count the fine model's only; seconds is the whole stage, both models).
  int coarse_steps = 0;
  long coarse_reversed_steps = 0;
  long coarse_friction_repeats = 0;
  int coarse_elements = 0;
};

/// One Figure-2 iteration (PipelineStage::kMorphing), for callers that drive it themselves.
struct IterationReport {
  bool advanced = false;      ///< a step without inversion was taken
  bool forces_added = false;  ///< false after a call that could not advance (seed: skip the forces)
  bool diverged = false;      ///< the step ran away (divergence guard) and was taken back
  int reversals = 0;
  /// The share of the solved step that was taken (< 1: shortened, StiffeningStepResult::step_fraction;
  /// such a step does not count as a quiet one for the stop rule).
  double step_fraction = 1.0;
  double increment_m = 0.0;
  double pulled_increment_p95_m = 0.0;  ///< 95th percentile of the pulled vertices' moves in the step [m]
  double off_wall_increment_m = 0.0;    ///< largest move of a node off the wall band [m] (all nodes without sliding; wallBandNodes())
  double wall_increment_p95_m = 0.0;    ///< 95th percentile of the wall band's moves [m] (0 without sliding)
  double surface_mean_m = -1, surface_p95_m = -1;  ///< before the step, of the pulled vertices [m]
  double alpha_per_pa = 0.0;
  bool alpha_held = false;    ///< the tolerance held, so α was not decreased
  double seconds = 0.0;
};

/// Deformation measures at the current state.
struct PipelineMetrics {
  int inverted_elements = 0;
  double volume_change_percent = 0.0;
  double max_displacement_m = 0.0;
  double max_modulus_factor = 1.0;
  double final_alpha_per_pa = 0.0;
  bool has_target = false;
  SurfaceMatch surface;       ///< exact, both ways (skin ↔ target); valid when has_target
};

/// A restorable snapshot (the node's "save / load a precomputed state").
struct PipelineState {
  SimulationState simulation;
  Eigen::VectorXd modulus_factors;
  AlphaController::State alpha;
  /// Local α per element [1/Pa] (StiffeningSimulation::elementAlpha), #T; empty for none.
  Eigen::VectorXd element_alpha_per_pa;
  /// #sliding nodes × 3 (empty when sliding is not attached): the explicit method's constraint
  /// targets (displacements [m]), the implicit method's stick points (positions [m]).
  Points sliding_targets_m;
  /// Implicit method: slip direction per wall node (unit; a zero row while it sticks); else empty.
  Points sliding_slip_directions;
  Points morphing_forces_n;     ///< accumulated per pulled vertex (empty without morphing)
  PipelineStage stage = PipelineStage::kIdle;
  /// The gravity load the state was computed under, g_now − g_prone [m/s²] (setGravityLoad). A
  /// state restored under another load would start its next step out of equilibrium, and a tracking
  /// run's gravity-update rule, which compares the pose's load with the current one, would see the
  /// wrong current load.
  Eigen::Vector3d gravity_load_mps2 = Eigen::Vector3d::Zero();
};

/// The gravity of a case's prone image [m/s²]: settings.gravity_mps2 along its prone direction.
Eigen::Vector3d proneGravity(const ModelCase& model_case, const SimulationSettings& settings);

class ProneToSupinePipeline {
 public:
  /// Resolves the default reference_state for the case (settings().simulation has kUnloaded or
  /// kProne). With reference_state unloaded, first recovers X0 (recoverUnloadedShape with the run's element,
  /// stiffening, fixed wall and solver; the multigrid's coarse levels are meshed of the prone domain,
  /// its prolongations the prone shape's). Then builds the
  /// simulator (solver, multigrid levels) on the rest shape, the stiffening driver and, with sliding
  /// on, the chest-wall surface. `model_case` and `model` (the prone model) are kept by reference and
  /// must outlive this. The target of settings.morphing.target is read here ("phantom" needs a
  /// phantom case).
  /// @param coarse_meshes  solver 'multigrid': the coarse levels of the prone domain as coarseMeshes()
  ///        of an earlier pipeline of the same case, model and settings returned them (read back from
  ///        a file, so that a restart does not mesh them again: meshing is most of the build); nullopt
  ///        meshes them. Levels that do not nest are refused (MeshHierarchy).
  /// @param unloaded_start_m  reference_state unloaded: where the recovery of X0 starts, #N×3 [m]
  ///        (the X0 of an earlier pipeline of the same case, model and settings, kept so that a
  ///        restart confirms it in one loading instead of recovering it again); empty = the prone shape.
  /// @param unloaded_tolerance_m  reference_state unloaded: how close X0 loaded with prone gravity must
  ///        come to the prone shape at every node (UnloadedStateOptions::tolerance_m) [m], > 0
  /// @throws std::invalid_argument / std::runtime_error for bad settings or a missing target;
  ///         std::invalid_argument for a start of the wrong size or with inverted elements, or an
  ///         unloaded_tolerance_m that is not a finite length > 0;
  ///         std::runtime_error when X0 is not found (the recovery's reason, its residual, and the
  ///         way out: reference_state prone, or a stiffer material).
  ProneToSupinePipeline(const ModelCase& model_case, const SimulationModel& model, const PipelineSettings& settings,
                        std::optional<std::vector<TetMesh>> coarse_meshes = std::nullopt,
                        const Points& unloaded_start_m = Points(),
                        double unloaded_tolerance_m = UnloadedStateOptions().tolerance_m);
  ~ProneToSupinePipeline();

  /// Both stages in order (the morphing stage only with a target and morphing enabled); a cancelled
  /// stage ends the run (its report says cancelled, the later stages' reports say not run, stage() is
  /// not kDone).
  /// @param cancel  polled between steps; set it to stop early (the state stays consistent)
  void run(const PipelineProgressFn& progress = {}, const std::atomic<bool>* cancel = nullptr);
  /// Stage 1 (and the sliding continuation when sliding is on). Returns the fixed-wall settle's
  /// report (gravityReport()), but `cancelled` when any part was cancelled (the sliding stage, or with
  /// coarse_start the coarse model's stage, whose unfinished state is then not carried over).
  StageReport runGravity(const PipelineProgressFn& progress = {}, const std::atomic<bool>* cancel = nullptr);
  /// Stage 2. With the cancel flag already set it returns cancelled before its first step, with the
  /// distances at the current state. @throws std::logic_error without a target.
  StageReport runMorphing(const PipelineProgressFn& progress = {}, const std::atomic<bool>* cancel = nullptr);
  /// One Figure-2 iteration against the current target (the node calls it per tracker frame).
  /// @throws std::logic_error without a target.
  IterationReport iterate();

  /// Replaces the target (e.g. a new tracker cloud): rebuilds the distance field in place over the
  /// model's current box (SurfaceVectorField::rebuild reuses its storage); the accumulated morphing
  /// forces are kept (they are what holds the current shape). On a bad target it throws and the
  /// previous target stays.
  void setTarget(const TargetSurface& target);
  bool hasTarget() const { return static_cast<bool>(field_); }
  const TargetSurface& target() const { return target_; }
  const SurfaceVectorField* field() const { return field_.get(); }

  /// Tracking a surface scan (iterate() per frame; the stages switch it off): the chest wall is held
  /// where it is (implicit sliding: no wall node starts to slip, WallSlip::setHeld; explicit: the
  /// constraints are not moved) and the skin is pulled along its normal only
  /// (SurfaceMorphing::setAlongNormal): a scan sees part of the anterior skin and only its distance
  /// to the surface, so tracking must not move what it cannot observe (measured: docs/tracking.md).
  void setTrackingMode(bool on);
  bool trackingMode() const { return tracking_; }

  /// Sets the gravity load [m/s²] (e.g. a table tilt: g_now − g_prone); a direction change beyond
  /// StiffeningParams::gravity_direction_tolerance_deg restarts the α search.
  void setGravityLoad(const Eigen::Vector3d& g_mps2);
  /// The current gravity load [m/s²].
  Eigen::Vector3d gravityLoad() const;
  /// The load of the supine position for this case: g_supine − g_prone [m/s²] (the phantom's own
  /// tilted supine gravity; an image case turns its prone direction around).
  Eigen::Vector3d supineGravityLoad() const;

  PipelineStage stage() const { return stage_; }
  const StageReport& gravityReport() const { return gravity_; }
  const StageReport& slidingReport() const { return sliding_report_; }
  const StageReport& morphingReport() const { return morphing_; }
  PipelineMetrics metrics() const;

  Points displacement() const;   ///< from the prone shape, #N×3 [m]
  Points positions() const;      ///< #N×3 [m]
  Points lesionPositions() const;  ///< #lesions×3 [m]
  /// Sliding vector per node [m] (zero without sliding).
  Points slidingVectors() const;
  /// Per element, at the current state: von Mises stress [Pa] and modulus factor E_r.
  Eigen::VectorXd vonMisesStress();
  Eigen::VectorXd modulusFactors() const;

  PipelineState state() const;
  /// state() into `s`, reusing its storage (no allocation once `s` has the sizes).
  void copyState(PipelineState& s) const { fillState(s); }
  /// Every part is checked before any is applied (the morphing forces against the skin vertices the
  /// snapshot's wall leaves free), so a refused snapshot leaves the state as it was. A snapshot
  /// without morphing forces drops the force generator and what it accumulated.
  /// @throws std::invalid_argument when the snapshot does not fit this model (sizes, values).
  void restore(const PipelineState& s);
  /// Nested iteration: takes the state of a pipeline on a coarser model of the same case (another
  /// mesh of the same tissue, not nested in this one) onto this model, so that only the last steps
  /// run on the fine mesh. Carried over, each by its own rule:
  ///  - displacement and velocity: interpolated at this model's prone nodes (barycentric in the
  ///    coarse prone mesh; a node outside it, the two meshes' surfaces differ by up to a facet
  ///    distance, takes the value at the closest point of the coarse surface). The models meet in
  ///    the prone shape, which both mesh: with reference_state unloaded each has its own X0, so the
  ///    move from prone is carried and each model's displacement is from its own X0;
  ///  - modulus factors: of the coarse element holding each element's centroid;
  ///  - α controller state, gravity load, stage, simulated time;
  ///  - sliding (when the coarse wall was released): each wall node takes the friction state of the
  ///    nearest coarse wall node (prone positions): its stick point's (explicit method: its target's)
  ///    offset from that node's current position, and its slip direction;
  ///  - morphing forces: as tractions (force / vertex area [Pa]), inverse-square-distance weighted
  ///    from the four nearest coarse pulled vertices (prone positions; a coincident one gives its
  ///    own), times this model's vertex areas.
  /// Nothing else of the coarse run is kept (its reports stay its own).
  /// @param snap_tolerance_m  a prone node this far outside the coarse prone mesh at most [m]
  /// @throws std::invalid_argument when the two pipelines differ in sliding (on / off, method) or
  ///         morphing (forces without a target here), or a node lies farther outside.
  void startFrom(const ProneToSupinePipeline& coarse, double snap_tolerance_m = 5e-3);
  /// Binary snapshot file (magic, version, sizes, a fingerprint of the prone mesh, then the vectors
  /// and the rest shape). A state of another rest shape (reference_state, or a material that gives
  /// another X0) is refused.
  /// A file written before the gravity load was saved loads with the supine load (supineGravityLoad),
  /// the load every precomputation ends under.
  /// @throws std::runtime_error naming the file on an I/O error or a snapshot of another model
  ///         (other sizes, or the same sizes with other node positions or numbering).
  void saveState(const std::string& path) const;
  void loadState(const std::string& path);

  const SimulatorBuild& build() const { return build_; }
  /// Solver 'multigrid': its coarse levels of the prone domain (coarsest last; empty when the fine
  /// level is small enough to be the only one), as meshed or given to the constructor. Else empty.
  const std::vector<TetMesh>& coarseMeshes() const { return coarse_meshes_; }
  DynamicSimulator& simulator() { return *build_.simulator; }
  const DynamicSimulator& simulator() const { return *build_.simulator; }
  StiffeningSimulation& stiffening() { return *stiff_; }
  const StiffeningSimulation& stiffening() const { return *stiff_; }
  /// The chest-wall sliding geometry and limiting weights when sliding is on (for the implicit
  /// method: its geometry, whose targets are unused), else null.
  const ChestWallSliding* sliding() const { return slip_ ? &slip_->geometry() : sliding_.get(); }
  const WallSlip* wallSlip() const { return slip_.get(); }  ///< the implicit sliding, or null
  /// With sliding: the wall band, where the stop rules' off_wall measures take a 95th percentile
  /// instead of the largest move: the sliding wall nodes and every node of an element touching one
  /// (the first layer of tissue, which the wall's stick–slip drags along). Empty without sliding.
  const std::vector<int>& wallBandNodes() const { return wall_band_nodes_; }
  const SurfaceMorphing* morphing() const { return morphing_forces_.get(); }
  const PipelineSettings& settings() const { return settings_; }
  /// The model the simulator runs on: its mesh's nodes are the rest shape (X0 with reference_state
  /// unloaded, else the prone shape); elements, node sets and lesions are the prone model's.
  const SimulationModel& model() const { return model_; }
  /// The prone model given to the constructor.
  const SimulationModel& proneModel() const { return prone_model_; }
  /// The recovery of X0 (reference_state unloaded; else empty with iterations 0).
  const UnloadedStateResult& unloadedState() const { return unloaded_; }
  /// With coarse_start: the pipeline on the coarse model (its model(), reports and state), else null.
  const ProneToSupinePipeline* coarse() const { return coarse_.get(); }
  /// The pipeline whose steps the progress callback is reporting: the coarse one while it runs
  /// (its model(), positions()), else this one.
  const ProneToSupinePipeline& running() const { return coarse_running_ ? *coarse_ : *this; }

 private:
  void attachSliding();
  void fillState(PipelineState& s) const;  // state() into s, reusing its storage
  SurfaceMorphing& ensureMorphing();  // the force generator, on first use
  // A force generator pulling the skin nodes that `fixed` (per node) leaves free.
  std::unique_ptr<SurfaceMorphing> makeMorphing(const std::vector<char>& fixed) const;
  /// Reversal counts since `before`, the final α and the wall time of a stage.
  void closeReport(StageReport& r, const RunStats& before, double seconds) const;
  bool slideAfter(const StiffeningStepResult& r, int* stalls);
  // The sliding stage after a converged fixed-wall settle: releases the wall and steps until it has
  // settled; sets sliding_report_. `previous`: the displacement at the settle's end (kept per step).
  void runSlidingStage(Eigen::VectorXd& previous, const PipelineProgressFn& progress, const std::atomic<bool>* cancel);
  // One stiffening call with the sliding around it: the implicit springs set from the current
  // state before, the explicit constraint update or the friction update after. *moving: the wall
  // still moves (explicit: by more than the increment tolerance).
  // `extra`: springs set for the step besides the wall's (the morphing's implicit pull), or null.
  // `now`: the caller's snapshot of the current state (the friction repeat's start), or null to copy it.
  StiffeningStepResult stepWithSliding(int* stalls, bool* moving, const NodeSprings* extra = nullptr,
                                       const PipelineState* now = nullptr);
  bool hasSliding() const { return sliding_ || slip_; }
  WallSlipSettings wallSlipSettings() const;
  void setTimeStep(double dt_s);
  double increment(Eigen::VectorXd& previous) const;
  /// The step's moves since `previous` (then set to the current displacement) [m].
  struct StepMoves {
    double all_max = 0.0, off_wall_max = 0.0, wall_p95 = 0.0;
  };
  StepMoves stepMoves(Eigen::VectorXd& previous);
  double volumeChangePercent() const;

  const ModelCase& case_;
  PipelineSettings settings_;  // validated first: the recovery of X0 below uses it
  const SimulationModel& prone_model_;
  double coarse_meshing_s_ = 0.0;       // meshing the coarse levels [s] (0 when they were given)
  std::vector<TetMesh> coarse_meshes_;  // the multigrid's coarse levels of the prone domain (before X0: it uses them)
  UnloadedStateResult unloaded_;
  double unloaded_tolerance_m_;  // the recovery's tolerance (the coarse start's model takes it too)
  std::unique_ptr<SimulationModel> unloaded_model_;  // prone_model_ with the nodes of X0 (reference_state unloaded)
  const SimulationModel& model_;                    // the rest model: *unloaded_model_ or prone_model_
  /// Gravity the rest shape feels besides the load (g_prone with reference_state unloaded, else 0)
  /// [m/s²]: the simulator's gravity is load + this.
  Eigen::Vector3d gravity_offset_mps2_ = Eigen::Vector3d::Zero();
  SimulatorBuild build_;
  std::unique_ptr<StiffeningSimulation> stiff_;
  std::unique_ptr<ChestWallSliding> sliding_;
  std::unique_ptr<WallSlip> slip_;
  TargetSurface target_;
  std::shared_ptr<SurfaceVectorField> field_;  // rebuilt in place for a new target
  std::unique_ptr<SurfaceMorphing> morphing_forces_;
  std::unique_ptr<SurfaceDistance> distance_;
  NodeSprings morph_springs_;  // the morphing's implicit pull of the current iteration
  std::vector<double> pulled_moves_;  // iterate(): squared moves of the pulled vertices (kept buffer)
  std::vector<char> wall_band_;       // per node: in the wall band (empty without sliding)
  std::vector<int> wall_band_nodes_;
  std::vector<double> wall_moves_;    // stepMoves(): squared moves of the wall nodes (kept buffer)
  PipelineStage stage_ = PipelineStage::kIdle;
  StageReport gravity_, sliding_report_, morphing_;
  bool last_advanced_ = true;
  long diverged_steps_ = 0;    // iterate(): steps the divergence guard took back, all stages
  int diverged_run_ = 0;       // iterate(): run-away steps in a row (the attempt count for α)
  long friction_repeats_ = 0;  // stepWithSliding(): steps repeated with reversed wall nodes sticking
  Eigen::VectorXd iterate_previous_;  // iterate(): displacement before the step (kept to avoid a per-frame allocation)
  bool sliding_attached_ = false;  // the wall nodes are moving constraints (after the fixed-wall settle)
  bool tracking_ = false;          // setTrackingMode
  // coarse_start: the coarse case (a copy with its own target element count), model and pipeline;
  // coarse_ahead_: runGravity took the coarse state, so runMorphing starts on the coarse model too.
  std::unique_ptr<ModelCase> coarse_case_;
  std::unique_ptr<SimulationModel> coarse_model_;
  std::unique_ptr<ProneToSupinePipeline> coarse_;
  /// startFrom(): this model's prone nodes and element centroids in a coarse prone mesh, kept for
  /// the next start from the same mesh (meshFingerprint) and snap tolerance.
  struct CoarseEmbedding {
    double fingerprint = 0.0;
    double snap_tolerance_m = 0.0;
    PointEmbedding nodes, centroids;
  };
  std::unique_ptr<CoarseEmbedding> coarse_embedding_;
  bool coarse_ahead_ = false;
  bool coarse_running_ = false;
  // Kept buffers of the per-step copies (no allocation per step): the friction repeat's step start
  // (when the caller has no snapshot), the divergence guard's state before the step.
  StiffeningSimulation::HistoryEntry step_start_;
  PipelineState guard_before_;
};

}  // namespace breast_sim::core
