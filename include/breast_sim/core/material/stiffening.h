#pragma once
/// @file stiffening.h
/// Non-linear material by von Mises stiffening with time-step reversal (seed paper, sections 2.3,
/// 2.6 and 3.1): per element the modulus factor E_r = 1 + α · s_VM is set between time steps; a step
/// that inverts an element is reverted and repeated with a larger α; α is decreased again after good
/// steps, with an oscillation detector that makes it settle; an undo history of n states. With a
/// formulation that has a collapsed volume ratio (ElementFormulation::collapsedVolumeRatio > 0: the
/// average-nodal-pressure element with its inversion barrier), a step that would leave an element at
/// or below it is first shortened (admissibleStepFraction), and repeated stiffer only when that fails.
///
/// Units: α in 1/Pa, stresses in Pa, E_r dimensionless (E = E_r · E0), speeds in m/s.
///
/// Which stress: s_VM is the von Mises norm of the co-rotated Cauchy stress of the BASE material
/// (modulus E0) at the element's current strain, i.e. ElementFormulation::vonMisesStress() divided by
/// the element's current factor E_r (the element's stress scales with E_r). So E_r is a function of
/// the strain alone, E_r = 1 + α · s_VM(E0, ε), and does not feed back on itself from one step to the
/// next (with the stiffened stress, E_r(t+1) = 1 + α E_r(t) s0 would grow without bound for α s0 ≥ 1).
///
/// Which state: the moduli of a step are set from the stress at the start of the step. When a step
/// is reverted, the per-element stress used for the repeat is the larger of the stress at the start
/// and at the rejected (inverted) end of the trial step. Without this, a step from an unstressed
/// state (the first step from the rest shape, s_VM = 0 everywhere) could not be stiffened by any α.

#include <deque>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// How α moves (seed 2.3). The defaults are the "robust general preset": they are used unchanged
/// for every material, time step and load of the stability map (docs/stability_map).
struct AlphaControllerParams {
  /// Starting α [1/Pa]. The seed starts "knowingly too high" and lets the controller decrease it:
  /// 1e-2 /Pa gives E_r ≈ 8 at the ≈ 700 Pa (ρ g · 7 cm) that gravity puts on the default phantom.
  double initial_alpha_per_pa = 1e-2;
  double min_alpha_per_pa = 1e-7;   ///< floor [1/Pa]: below it stiffening is negligible (E_r − 1 < 1e-4 at 1 kPa)
  double max_alpha_per_pa = 1e4;    ///< ceiling [1/Pa]: E_r up to 1e7 at 1 kPa
  double decrease_factor = 0.8;     ///< search phase: α ← α · this after an accepted step, in (0, 1)
  double increase_factor = 2.0;     ///< α ← α · this on a reversal in the search phase (and from the
                                    ///< third reversal of the same step in the settling phase), > 1
  /// Repeated reversals of the same step grow geometrically: the k-th (k ≥ 2) multiplies α by
  /// increase_factor · reversal_growth^(k−1), ≥ 1 (1: by increase_factor each time, the seed's
  /// doubling). With 2, α climbs by 2, 4, 8, 16, … (×1024 in 4 reversals instead of 10): a stage that
  /// starts with α at the floor under a new load (the morphing forces) finds a working α in fewer
  /// reverted solves; it may overshoot by up to that factor, and falls ×decrease_factor per good step.
  double reversal_growth = 1.0;
  /// Settling phase (entered at the first oscillation: a decrease, an increase, a decrease): α changes
  /// by a rate ρ proportional to its magnitude, Δα = ρ α down after an accepted step and
  /// k ρ α up on the first reversal of a step, k = (increase_factor − 1) / (1 − decrease_factor) (the
  /// search phase's up/down ratio); a second reversal of the same step by 2 k ρ α, a third and later
  /// ones as in the search phase. ρ starts at (1 − decrease_factor) · rate_halving and is multiplied
  /// by rate_halving at every further oscillation, so α converges to just above the smallest α that
  /// does not invert. In (0, 1).
  double rate_halving = 0.5;
  double min_rate = 1e-3;           ///< ρ never falls below this, in [0, 1 − decrease_factor]
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// The α controller alone (no simulation): tell it what each step did; it moves α.
class AlphaController {
 public:
  enum class Phase { kSearch, kSettling };
  /// Everything that defines the controller (for the undo history).
  struct State {
    double alpha_per_pa = 0.0;
    Phase phase = Phase::kSearch;
    double rate = 0.0;         ///< ρ of the settling phase
    int oscillations = 0;      ///< decrease–increase–decrease patterns seen since the last restart
    /// Directions of the last three runs of equal changes, newest first: −1 decrease, +1 increase,
    /// 0 none yet (since the last restart). (−1, +1, −1) is an oscillation.
    int runs[3] = {0, 0, 0};
  };

  /// @throws std::invalid_argument as AlphaControllerParams::validate.
  explicit AlphaController(const AlphaControllerParams& params = {});
  const AlphaControllerParams& params() const { return params_; }
  double alpha() const { return s_.alpha_per_pa; }  ///< [1/Pa]
  Phase phase() const { return s_.phase; }
  double rate() const { return s_.rate; }
  int oscillations() const { return s_.oscillations; }

  /// A step was accepted (no inversion): decrease α (never below min_alpha_per_pa).
  void onAccepted();
  /// A step was reverted. @param attempt 1 for the first reversal of this step, 2 for the next, …:
  /// repeated reversals of the same step multiply α by increase_factor · reversal_growth^(attempt−1)
  /// (never above max).
  void onReversed(int attempt);
  /// Replaces the parameters (a stage with its own reversal growth); α and the phase stay.
  /// @throws std::invalid_argument as AlphaControllerParams::validate; the old ones stay then.
  void setParams(const AlphaControllerParams& params) {
    params.validate();
    params_ = params;
  }
  /// New search from the initial α (boundary conditions changed).
  void restart();
  /// Starts over from a given α [1/Pa] (clamped to [min, max]) in the search phase.
  void restart(double alpha_per_pa);

  const State& state() const { return s_; }
  void setState(const State& s) { s_ = s; }

 private:
  void recordChange(int direction);
  AlphaControllerParams params_;
  State s_;
};

/// When a run counts as settled: max nodal speed and the relative static residual, per step, and the
/// stiffening faded out (StiffeningSimulation, "Release").
struct SettleCriterion {
  double max_speed_mps = 1e-3;         ///< every free node slower than this [m/s]
  /// ‖f_el + f_ext + M g‖ / ‖f_ext + M g‖ over the free DOFs below this (static equilibrium).
  double max_relative_residual = 1e-2;
  int consecutive_steps = 3;           ///< both hold for this many accepted steps in a row
  /// … and no element is stiffer than its base material by more than this share, E_r − 1 ≤ δ [1]
  /// (the locally stiffened elements of the release excepted). Then K0 ≤ K ≤ (1 + δ) K0, so the
  /// linearised state is within δ (relative, energy norm) of the base material's equilibrium:
  /// the state is the material law's answer, not that of a material stiffened to avoid inversion.
  double max_modulus_excess = 1e-3;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// One evaluation of the settle criterion.
struct SettleCheck {
  double max_speed_mps = 0.0;       ///< over free nodes [m/s]
  double relative_residual = 0.0;   ///< see SettleCriterion
  bool below = false;               ///< both below their thresholds at this step
};

/// Evaluates the criterion at one state. Usable with any integrator.
/// @param velocity_mps   3N [m/s]
/// @param elastic_force_n 3N elastic forces at the same state [N] (ElementFormulation::update)
/// @param external_force_n 3N other forces [N], or an empty vector for none
/// @param mass_kg        N lumped masses [kg]
/// @param fixed_node     N flags: 1 = the node is constrained (left out of both measures)
SettleCheck evaluateSettle(const SettleCriterion& criterion, const Eigen::VectorXd& velocity_mps,
                           const Eigen::VectorXd& elastic_force_n, const Eigen::VectorXd& external_force_n,
                           const Eigen::VectorXd& mass_kg, const Eigen::Vector3d& gravity_mps2,
                           const std::vector<char>& fixed_node);

/// Parameters of the stiffening driver.
struct StiffeningParams {
  AlphaControllerParams alpha;
  SettleCriterion settle;
  bool update_moduli = true;        ///< false: E stays E0 (co-rotated with fixed E, or linear)
  bool reversal = true;             ///< false: von Mises update with α fixed, no inversion check/undo
  int max_reversals_per_step = 10;  ///< a step still inverting after this many reversals is not taken
  int history_size = 8;             ///< undo history: this many accepted states, round-robin, ≥ 1
  /// A gravity change by more than this angle [degrees] restarts the α search (seed 2.3).
  double gravity_direction_tolerance_deg = 5.0;
  /// Modulus factors are clamped to this [1]: keeps the system matrix well conditioned.
  double max_modulus_factor = 1e6;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// What one call of StiffeningSimulation::step() did.
struct StiffeningStepResult {
  bool advanced = false;       ///< a step without inversion was taken (or reversal is off)
  int reversals = 0;           ///< trial steps reverted in this call
  bool reversal_limit_hit = false;  ///< the reversal limit reached: state left at the start of the call
  int inverted_elements = 0;   ///< at the end of the call (0 with reversal on, unless the start had some)
  double alpha_per_pa = 0.0;   ///< after the call [1/Pa]
  /// The share of the solved step that was taken, in (0, 1]: below 1 when the step was shortened to
  /// keep every element off its collapsed volume ratio (StiffeningSimulation, "Shortened steps").
  double step_fraction = 1.0;
  /// Elements that were already invalid (inverted, or at or below the collapsed volume ratio) at the
  /// start of the accepted step and gained volume in it (StiffeningSimulation, "Recovering elements").
  int recovering_elements = 0;
  SettleCheck settle;          ///< at the end of the call
};

/// Statistics of a run (the same for every method, explicit Euler included).
struct RunStats {
  long steps = 0;                   ///< accepted steps
  long reversed_steps = 0;          ///< trial steps reverted
  double reversal_fraction = 0.0;   ///< reversed / (accepted + reversed)
  long reversal_limit_hits = 0;     ///< calls that could not advance
  long shortened_steps = 0;         ///< accepted steps that were shortened ("Shortened steps")
  double final_alpha_per_pa = 0.0;  ///< 0 when α is not used
  int inverted_elements = 0;        ///< at the end
  bool nan = false;                 ///< non-finite displacement at the end (or the run stopped on one)
  bool exploded = false;            ///< explicit Euler: displacement or speed past the divergence limits
  double max_displacement_m = 0.0;  ///< largest nodal displacement at the end [m]
  double volume_change_percent = 0.0;  ///< (V − V0) / V0 · 100 at the end [%]
  double max_modulus_factor = 1.0;  ///< largest E_r at the end [1]
  bool settled = false;             ///< the settle criterion held (consecutive_steps in a row)
  /// Largest E_r − 1 of the last accepted step over the elements without a local α [1]: how far the
  /// state is from the base material's equilibrium (SettleCriterion::max_modulus_excess).
  double max_modulus_excess = 0.0;
  int locally_stiffened_elements = 0;  ///< elements with a local α above the global one (release)
  double locally_stiffened_volume_percent = 0.0;  ///< their share of the rest volume [%]
  bool releasing = false;           ///< the release has started (and not been restarted)
  long steps_to_settle = -1;        ///< accepted steps until then, −1 if never
  double simulated_time_s = 0.0;
  double wall_seconds = 0.0;
};

/// Signed volume change [%] and largest displacement [m] of a displacement field (3N [m]).
void deformationMeasures(const TetMesh& mesh, const Eigen::VectorXd& displacement_m, double& volume_change_percent,
                         double& max_displacement_m);

/// Shortening a step whose elements would collapse (the fraction-to-the-boundary rule of barrier
/// methods): the largest s ∈ [0, 1] such that along u0 + t (u1 − u0), t ∈ [0, s], every element e
/// keeps its volume ratio J_e ≥ j_c + keep (J_e(u0) − j_c), i.e. loses at most the share 1 − keep of
/// its distance to the collapsed ratio j_c. J_e along the step is the cubic det(D0 + t D1) / det(Dm)
/// of the element's edge matrices; its first crossing is bracketed between the roots of its
/// derivative (the cubic is monotone between them) and bisected to 1e-9. Elements that start at or below the bound (J_e(u0) ≤ j_c) do not limit s.
/// @param mesh        rest mesh (its nodes and tets)
/// @param u0, u1      displacements at the step's start and end, 3N [m]
/// @param j_collapsed j_c, the collapsed volume ratio [1], ≥ 0
/// @param keep        the share of the distance to j_c that every element keeps, in (0, 1)
/// @throws std::invalid_argument for sizes that do not match the mesh or parameters out of range.
double admissibleStepFraction(const TetMesh& mesh, const Eigen::VectorXd& u0, const Eigen::VectorXd& u1,
                              double j_collapsed, double keep);

/// The seed's loop around a DynamicSimulator:
///   save state → set moduli E_r = 1 + α s_VM → step → inverted elements (rest + u)?
///     yes: restore, increase α, repeat (external forces are not touched: a caller adds its forces
///          before step(), and the repeats inside step() reuse them, seed 2.6)
///     no:  decrease α, push the state to the undo history.
/// Constraints, gravity and external forces may go through this class (it forwards them and restarts
/// the settle count) or to the simulator directly: the settle criterion reads the simulator's own
/// constrained DOFs and external forces.
///
/// Release: the seed's loop settles the shape with α still high (the stiffer material's equilibrium,
/// up to 1.9× stiffer). So once speed and residual hold while an element is still stiffened by more
/// than SettleCriterion::max_modulus_excess, the driver releases: α halves after every accepted step,
/// past the controller's floor (alpha()), and a step that inverts elements is repeated with just
/// those elements stiffened, by a local α_e (E_r = 1 + max(α, α_e) s_VM; α_e = the α the release
/// started from, where they were valid, doubled on each further inversion) while the global α goes
/// on down: a folding rim does not stiffen the whole breast. The controller keeps its state for the
/// next search. Settled = speed and residual hold and every element without a local α has E_r − 1 ≤ δ.
/// The local α's (RunStats::locally_stiffened_elements) last until the α search restarts from the
/// initial α. A load or constraint change through this class or a restore ends the release, and so
/// does a solver failure during it (α back to the controller: the seed's loop, then a new release).
/// Without reversal (α fixed) there is no release and settled is the shape's criterion alone. A
/// release step still inverting after max_reversals_per_step local doublings ends the release for
/// this load: the local α's are dropped, the controller's α (valid where the shape settled) takes
/// over, and settled is the shape's criterion, with RunStats::max_modulus_excess saying how far the
/// state is from the base material's equilibrium.
///
/// Shortened steps: a formulation whose elements can lose their own volume while their nodes' stars
/// keep theirs (the average-nodal-pressure element, where an element's own volume change meets only
/// the shear modulus above its inversion barrier J_b) reports a collapsed volume ratio j_c > 0
/// (ElementFormulation::collapsedVolumeRatio: J_b / 3). The linearised step does not see the barrier
/// of an element that starts above J_b, so one step under a concentrated load (the first morphing
/// pulls at the rim) takes it from J ≈ 1 through zero, and keeping such steps valid by stiffening
/// the whole model takes an α ~30× the J − 1 tetrahedra's (docs/speed_accuracy.md, "ANP in the whole
/// pipeline"). So a step that leaves an element at or below j_c (inverted or not) is first shortened
/// to the fraction s = admissibleStepFraction(…, j_c, kStepKeep) of its increment: the state becomes
/// u0 + s (u1 − u0) with velocity s v1 (backward Euler's), and the step counts as accepted. From
/// J = 1 an element then stops near J_b (j_c + (1 − j_c)/4 = 0.325 at J_b 0.3), where the barrier's
/// stiffness is in the next step's matrix. Only a fraction below kMinStepFraction is reverted and
/// repeated stiffer as above. A shortened step does not count towards the settle criterion.
/// With j_c = 0 (the linear tetrahedra) every step is as the seed's.
///
/// Recovering elements: a state this class did not step to (one restored, or handed over from a
/// coarser model, whose interpolated displacement can invert a fine element) may start a step with
/// an invalid element. No α makes such a step valid by itself, since the element is invalid before
/// it moves: the step would be reverted until a stiffer one happened to lift the element above j_c
/// (on the fast phantom run's 48.8k-element ANP model: an element at J −0.14 after the hand-over,
/// four reverted 47 ms steps, α from 1e-7 to 1e-4 /Pa). So an element invalid at the start of the
/// step does not hold the step back while the step raises its volume ratio (StiffeningStepResult::
/// recovering_elements); one that loses volume does, as any other. Such a step does not count
/// towards the settle criterion.
class StiffeningSimulation {
 public:
  /// Shortened steps: the share of its distance to the collapsed ratio every element keeps.
  static constexpr double kStepKeep = 0.25;
  /// Shortened steps: a smaller fraction is not taken; the step is reverted and repeated stiffer.
  static constexpr double kMinStepFraction = 0.05;
  /// Tracking frames: a step still invalid after this many reversals (for an element inverting for
  /// the first time: the step as it was, then with the local α, then with twice it) is given up for
  /// the frame rather than running up to max_reversals_per_step solves:
  /// an element its stiffer neighbours still invert, or one at max_modulus_factor, is not fixed by
  /// more doublings within the frame, and the tracker has the next frame (the doublings go on there).
  static constexpr int kTrackingReversals = 3;

  /// One undo-history entry: restores the simulation exactly.
  struct HistoryEntry {
    SimulationState state;
    Eigen::VectorXd modulus_factors;
    AlphaController::State controller;
    Eigen::VectorXd element_alpha;  ///< the local α's [1/Pa] (elementAlpha())
  };

  /// @param sim   the simulator (not owned; must outlive this), built on `mesh`
  /// @param mesh  rest mesh (kept by reference; must outlive this)
  /// @throws std::invalid_argument for invalid parameters or a size mismatch.
  StiffeningSimulation(DynamicSimulator& sim, const TetMesh& mesh, const StiffeningParams& params = {});

  void fixNodes(const std::vector<int>& nodes);
  /// Sets gravity [m/s²]; a direction change beyond the tolerance restarts the α search.
  /// @return whether the search was restarted.
  bool setGravity(const Eigen::Vector3d& g_mps2);
  /// Restarts the α search from the initial α (any other boundary-condition change); ends a release
  /// and drops the local α's.
  void restartAlphaSearch();
  /// The same from a given α [1/Pa] (clamped to the controller's bounds), keeping the local α's: the
  /// boundary conditions changed, the load did not, and coming down from the initial α would soften
  /// the tissue again (sliding attached).
  void restartAlphaSearch(double alpha_per_pa);
  /// While held, accepted steps leave α as it is (reversals still increase it): the morphing stage
  /// holds α once the surface distance meets its tolerance (seed 2.6).
  void holdAlpha(bool hold) { hold_alpha_ = hold; }
  bool alphaHeld() const { return hold_alpha_; }
  /// Tracking frames: small moves about a settled state (a surface scan per frame).
  ///  - Local reversals: a reverted step stiffens only its invalid elements, by a local α (the
  ///    controller's initial α or twice the global α, whichever is higher, doubled on each further
  ///    reversal), and the global α stays (a solver failure still raises it). A global α would
  ///    stiffen the whole breast for one collapsing skin element and move the lesions under an
  ///    unchanged skin (measured on the phantom tracking its own skin with ANP: up to 3.3 mm within
  ///    a frame, docs/speed_accuracy.md, "Tracking with ANP"). The local α's stay until the α
  ///    search restarts from the initial α. At most kTrackingReversals reversals per step (a release
  ///    in progress when tracking began keeps max_reversals_per_step). Local α's never exceed the
  ///    controller's max_alpha_per_pa.
  ///  - A step's moduli come from the stress at the start of the step before (the element update
  ///    that step made anyway) instead of a second element update at its end, and the settle
  ///    criterion is not evaluated: one element update per step instead of two (2.8 ms of a 27 ms
  ///    tracking step at 48.8k ANP elements). With α held at its floor the moduli differ from the
  ///    seed's rule by parts in 10⁷.
  /// Switching it off brings the stress and forces up to the current state.
  void setTracking(bool on);
  bool tracking() const { return tracking_; }
  void addNodalForces(const std::vector<int>& nodes, const Points& forces_n);
  void clearExternalForces();

  /// The driver's state as an undo-history entry holds it (simulator state, modulus factors, α
  /// controller, local α's) into `e`, reusing its storage.
  void snapshot(HistoryEntry& e) const;
  /// Sets a snapshot's parts (local α's empty: none), then resync(): what a restored pipeline state
  /// and a repeated step go back to. @throws std::invalid_argument as checkElementAlpha, before any
  /// change.
  void restoreSnapshot(const SimulationState& state, const Eigen::VectorXd& modulus_factors,
                       const AlphaController::State& controller, const Eigen::VectorXd& local_alpha_per_pa);

  /// After the simulator's state, the moduli or the controller were set from outside (a restored
  /// snapshot): recomputes what this class keeps of the current state — the von Mises stress per
  /// unit modulus that the next step's moduli come from, the elastic forces, the inversion count —
  /// and starts the undo history at this state. Without it the next step would take its moduli from
  /// the state before the restore (at rest: E_r = 1 everywhere).
  void resync();

  /// One step with reversal (see the class comment). Never loops more than max_reversals_per_step
  /// times (in tracking frames, kTrackingReversals). A solver failure (non-finite solution, matrix not positive definite) counts as an
  /// inversion.
  StiffeningStepResult step();

  /// Undo history: number of stored states (≤ history_size); k = 0 is the newest.
  int historySize() const { return static_cast<int>(history_.size()); }
  const HistoryEntry& history(int k) const;
  /// Restores history entry k exactly (state, modulus factors, α controller, local α's); the entries newer
  /// than k are dropped. @throws std::out_of_range for k outside [0, historySize()).
  void revertTo(int k);

  /// The global α of the next step [1/Pa]: the controller's, or during the release the released one
  /// (which may fall below the controller's floor).
  double alpha() const { return releasing_ ? release_alpha_ : controller_.alpha(); }
  const AlphaController& controller() const { return controller_; }
  AlphaController& controller() { return controller_; }
  DynamicSimulator& simulator() { return sim_; }
  const StiffeningParams& params() const { return params_; }
  /// Local α per element [1/Pa], #T, 0 where none: the release's and the tracking frames' (class
  /// comment). Part of a snapshot (PipelineState): the moduli of later steps depend on them.
  const Eigen::VectorXd& elementAlpha() const { return element_alpha_; }
  /// Sets the local α's of a restored snapshot; an empty vector clears them.
  /// @throws std::invalid_argument as checkElementAlpha.
  void setElementAlpha(const Eigen::VectorXd& alpha_per_pa);
  /// Local α's fit a model of `elements` elements: none, or one per element, each finite and ≥ 0.
  /// @throws std::invalid_argument naming the count or the first bad value and its element.
  static void checkElementAlpha(const Eigen::VectorXd& alpha_per_pa, Eigen::Index elements);
  /// Base-material von Mises stress at the current state [Pa], #T.
  const Eigen::VectorXd& baseStress() const { return base_stress_; }
  /// The settle criterion holds (RunStats::settled), without computing the statistics: for the
  /// loops that ask after every step.
  bool settled() const { return settled_; }
  /// Statistics so far (wall_seconds: time spent inside step()); O(elements): volumes and moduli.
  RunStats stats() const;
  /// The per-node external forces of the simulator (3N [N]), used in the settle residual.
  const Eigen::VectorXd& externalForces() const { return sim_.externalForces(); }

 private:
  void refreshStress();  // elastic update at the current state: base stress, f_el
  void stressFromElements();  // base stress from the elements' last update (no update)
  void setModuli(const Eigen::VectorXd& stress);
  void pushHistory();
  void applySnapshot(const SimulationState& state, const Eigen::VectorXd& modulus_factors,
                     const AlphaController::State& controller, const Eigen::VectorXd& local_alpha_per_pa);
  void loadChanged();  // restarts the settle count and ends a release
  int countInverted();
  std::vector<int> invertedElements();
  // Inverted elements and, when the formulation says so (collapsedVolumeRatio), collapsed ones:
  // what a step from displacement u_start must not leave. Elements already invalid at u_start whose
  // volume ratio rose are left out and counted in `recovering` ("Recovering elements").
  std::vector<int> invalidElements(const Eigen::VectorXd& u_start, int& recovering);
  double modulusExcess() const;  // largest E_r − 1 over elements without a local α above the global one

  DynamicSimulator& sim_;
  const TetMesh& mesh_;
  StiffeningParams params_;
  AlphaController controller_;
  std::deque<HistoryEntry> history_;  // front = newest
  bool hold_alpha_ = false;
  bool tracking_ = false;
  std::vector<char> fixed_node_;  // per node: constrained in the simulator (refreshed per accepted step)
  Eigen::VectorXd base_stress_, trial_stress_, f_el_;
  Eigen::VectorXd loads_;  // step(): external and spring forces for the settle check (kept buffer)
  Eigen::VectorXd modulus_buffer_;  // setModuli(): the new factors before they are handed on (kept buffer)
  std::vector<char> invalid_flags_;  // invalidElements(): per element, invalid at the end of the trial (kept buffer)
  Points x_;
  Eigen::VectorXd rest_volume_;  // per element [m³], for the collapsed check
  long accepted_ = 0, reversed_ = 0, limit_hits_ = 0, shortened_steps_ = 0, steps_to_settle_ = -1;
  SimulationState shortened_;   // a shortened step's state (kept buffer)
  SimulationState step_start_;  // step(): the state a reverted trial goes back to (kept buffer)
  int settle_run_ = 0;
  bool settled_ = false;
  bool releasing_ = false;
  bool release_failed_ = false;  // the release hit the reversal limit under this load
  double release_alpha_ = 0.0, release_start_alpha_ = 0.0;  // [1/Pa]
  Eigen::VectorXd element_alpha_;  // local α per element [1/Pa], 0 = none (release, tracking)
  double excess_ = 0.0;
  double wall_ = 0.0;
  int last_inverted_ = 0;
};

}  // namespace breast_sim::core
