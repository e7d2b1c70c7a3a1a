#pragma once
/// @file dynamic_simulator.h
/// Dynamic FEM, M ü + C u̇ + K u = f, with implicit (backward) Euler steps [GW08].

#include <memory>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/fem/element_formulation.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::core {

/// Time integration settings.
struct DynamicsParams {
  double time_step_s = 0.033;                ///< dt [s], the seed paper's 0.033 s
  double mass_damping_per_s = 1.0;           ///< Rayleigh α_M [1/s]: C = α_M M + α_K K
  double stiffness_damping_s = 0.02;         ///< Rayleigh α_K [s]
  Eigen::Vector3d gravity_mps2 = Eigen::Vector3d::Zero();  ///< g [m/s²]; may change between steps
  /// @throws std::invalid_argument naming the field and the accepted range.
  void validate() const;
};

/// Everything that defines where the simulation is: cheap to copy, so a round-robin history of
/// states can be kept for time-step reversal.
struct SimulationState {
  Eigen::VectorXd displacement_m;  ///< u at t, 3N [m]
  Eigen::VectorXd velocity_mps;    ///< u̇ at t, 3N [m/s] (backward Euler: (u_t − u_{t−1}) / dt)
  double time_s = 0.0;
  long step = 0;
};

/// What one step did.
struct StepStats {
  SolveStats solve;
  double assembly_seconds = 0.0;  ///< rotations, forces and matrix [s]
  double setup_seconds = 0.0;     ///< solver factorize() [s]
  double total_seconds = 0.0;
  /// The step solved with the matrix and solver set-up of an earlier step (setMatrixReuse).
  bool matrix_reused = false;
};

/// What all step() calls of a simulator did, summed (a profile of a run: where its time went).
struct StepTotals {
  long steps = 0;                 ///< step() calls (accepted and reverted trials alike)
  long iterations = 0;            ///< Krylov iterations
  double assembly_seconds = 0.0;  ///< rotations, forces and matrix [s]
  double setup_seconds = 0.0;     ///< solver factorize() [s]
  double solve_seconds = 0.0;     ///< solver solve() [s]
  double total_seconds = 0.0;     ///< whole step() calls [s]
  long reused_matrix = 0;         ///< steps solved with an earlier step's matrix (setMatrixReuse)
  long resolved_assembled = 0;    ///< reusing solves discarded for a move that more than doubled
};

/// Backward Euler in velocity form, linearised at the start of the step (co-rotated stiffness):
///   (M(1 + dt α_M) + dt(dt + α_K) K) v_{t+1} = M v_t + dt (f_ext + f_el(x_t)),  u_{t+1} = u_t + dt v_{t+1}
/// with f_el the elastic forces on the nodes. Fixed nodes keep their displacement; target nodes
/// reach their prescribed displacement at the end of the next step. Both are imposed by eliminating
/// their DOFs (unit rows and columns), which keeps the matrix SPD with a fixed pattern.
class DynamicSimulator {
 public:
  /// @param mesh      rest mesh
  /// @param elements  element formulation built on `mesh`
  /// @param solver    linear solver; analyzePattern() is called here
  DynamicSimulator(const TetMesh& mesh, std::unique_ptr<ElementFormulation> elements,
                   const ElasticMaterial& material, const DynamicsParams& params,
                   std::unique_ptr<LinearSolver> solver);

  int numNodes() const { return num_nodes_; }
  const DynamicsParams& params() const { return params_; }
  void setGravity(const Eigen::Vector3d& g_mps2) { params_.gravity_mps2 = g_mps2; }
  /// Replaces the time step, damping and gravity (e.g. a long quasi-static step for settling).
  /// @throws std::invalid_argument as DynamicsParams::validate; the old parameters stay then.
  void setParams(const DynamicsParams& p) {
    p.validate();
    params_ = p;
  }

  /// Dirichlet: these nodes keep their current displacement. @throws on an index out of range.
  void fixNodes(const std::vector<int>& nodes);
  /// Frees every fixed and target node.
  void clearConstraints();
  /// Moving displacement constraints: node nodes[i] reaches displacement targets_m.row(i) [m] at
  /// the end of the next step (used by sliding). Replaces earlier targets of those nodes.
  void setNodeTargets(const std::vector<int>& nodes, const Points& targets_m);

  /// Linear node springs (used by implicit sliding: a stiff spring along the wall normal keeps a node
  /// on the wall, softer tangential ones model friction and tethering): node nodes[i] feels
  ///   f_i = −K_i (x_i − a_i),  K_i = stiffness_n_per_m[i] (symmetric positive semi-definite 3×3 [N/m]),
  ///   a_i = anchors_m.row(i) (a position [m], not a displacement),
  /// plus, if given, a constant force forces_n.row(i) [N] on the node (e.g. kinetic friction),
  /// taken implicitly: the step adds dt² K_i to its matrix (one diagonal 3×3 block per node, inside
  /// the fixed pattern), so a stiff spring costs no stability. Replaces all earlier springs; a node
  /// may appear once. Springs are not part of the state (like constraints).
  /// @throws std::invalid_argument for mismatched sizes, a node out of range or repeated, or a
  ///         non-finite or non-symmetric block (names the node).
  void setNodeSprings(const std::vector<int>& nodes, const std::vector<Eigen::Matrix3d>& stiffness_n_per_m,
                      const Points& anchors_m, const Points& forces_n = Points());
  void clearNodeSprings();
  const std::vector<int>& springNodes() const { return spring_nodes_; }
  /// Spring forces at the state the last step() started from [N], 3N (0 without springs).
  const Eigen::VectorXd& springForces() const { return spring_force_; }
  /// Spring forces at the current state [N], 3N (computed now).
  Eigen::VectorXd currentSpringForces() const;
  /// The same added to `f` (3N [N]), without a vector of its own (for loops that ask every step).
  /// @throws std::invalid_argument when f does not have 3N entries.
  void addCurrentSpringForces(Eigen::VectorXd& f) const;

  /// Adds to the per-node external forces [N]; they accumulate until clearExternalForces() (used by
  /// surface morphing). Gravity is separate (params().gravity_mps2).
  void addNodalForces(const std::vector<int>& nodes, const Points& forces_n);
  void clearExternalForces() { external_force_.setZero(); }

  /// One implicit time step. @throws std::runtime_error if the solver fails.
  StepStats step();
  /// Matrix reuse: the step matrix assembled at one step, with the solver's set-up for it, serves
  /// up to `steps` − 1 following steps as well; their right-hand sides (elastic forces at x_t,
  /// springs, constraints) are computed as always. Such a step solves with the linearisation of a
  /// nearby earlier state (its rotations and modulus factors), as an inexact solve does, and the
  /// following steps correct it. A spring's stiffness block may lag in the same way while the
  /// change, times dt², is within 5 % of its node's smallest diagonal entry without the spring (a
  /// wall spring turning with the wall; more than that acts as an explicit spring and diverges).
  /// Anything else that enters the matrix makes the next step assemble: the time step or damping,
  /// the constrained DOFs, the spring nodes, a spring block changed by more than that, and restore().
  /// A lagged linearisation can still let a mode grow (in tracking frames at 6k elements, a skin
  /// node's move grew 0.18 → 14.7 mm over three reusing steps): a reusing step whose largest node
  /// move more than doubles the last step's is solved again with an assembled matrix.
  /// Why: a tracking frame moves the model by a fraction of a millimetre, and at 48.8k elements
  /// the matrix gather and the solver's set-up are about a fifth of the frame's step
  /// (docs/tracking.md, "Latency"). 1 (the default): every step assembles. A split stiffness
  /// (splitStiffness()) assembles every step: its rank-one part lives in the element formulation's
  /// arrays, which every element update rewrites, and its one-ring part holds the inversion
  /// barrier's stiffness, which changes steeply (reused with a current rank-one part, one node of a
  /// barrier element moved 3–14 mm in a tracking frame; docs/tracking.md, "Latency"). The first step
  /// after a change of `steps` assembles; with 1 nothing of this is recorded or checked.
  /// @throws std::invalid_argument for steps < 1 (names the value).
  void setMatrixReuse(int steps);
  int matrixReuse() const { return matrix_reuse_; }
  /// Whether the step's matrix is the formulation's compact part with its rank-one part applied
  /// by the solver (ElementFormulation::compactPattern and LinearSolver::acceptsRankOneSum), rather
  /// than the whole assembled stiffness.
  bool splitStiffness() const { return split_; }

  const SimulationState& state() const { return state_; }
  /// Every step() since construction, summed; restore() does not undo it.
  const StepTotals& totals() const { return totals_; }
  /// Restores a saved state exactly (constraints and external forces are not part of it). The
  /// solver forgets its past solutions (LinearSolver::forgetSolutions), so the steps that follow
  /// depend on the state, not on what ran before.
  /// @throws std::invalid_argument if its size does not match the mesh.
  void restore(const SimulationState& s);
  /// #N×3 displacement [m].
  Points displacement() const;
  /// Lumped nodal masses [kg], #N.
  const Eigen::VectorXd& lumpedMass() const { return mass_; }
  ElementFormulation& elements() { return *elements_; }
  const ElementFormulation& elements() const { return *elements_; }
  LinearSolver& solver() { return *solver_; }
  /// Elastic forces at the current state [N], 3N (updates the element linearisation).
  const Eigen::VectorXd& elasticForces();
  /// The elastic forces last computed [N], 3N, no recomputation: after step() those at the state
  /// the step started from, f_el(x_t) (elasticForces() overwrites them with the current state's).
  const Eigen::VectorXd& lastElasticForces() const { return f_el_; }
  /// Reaction of the constraints in the last step() [N], 3N: at each constrained DOF the force the
  /// constraint applied to the node, (A_r v_{t+1} − b_r) / dt of the full (uneliminated) row r —
  /// inertia, damping, elastic, external and gravity forces included; 0 at free DOFs. Sliding
  /// moves its constraints along the tangential part of −reaction (the load on the wall).
  const Eigen::VectorXd& constraintForces() const { return constraint_force_; }
  /// Per-node external forces accumulated by addNodalForces() [N], 3N.
  const Eigen::VectorXd& externalForces() const { return external_force_; }
  /// Per DOF: 1 if fixed or a target (constrained), else 0.
  const std::vector<char>& constrainedDofs() const { return constrained_; }
  /// Per node: 1 where any of its DOFs is constrained, into `fixed` (resized to #N; no allocation
  /// once it has that size).
  void constrainedNodes(std::vector<char>& fixed) const;

 private:
  const Points rest_;
  const int num_nodes_;
  std::unique_ptr<ElementFormulation> elements_;
  DynamicsParams params_;
  std::unique_ptr<LinearSolver> solver_;
  Eigen::VectorXd mass_;            // per node [kg]
  Eigen::VectorXd external_force_;  // 3N [N]
  std::vector<char> constrained_;   // per DOF
  Eigen::VectorXd constraint_velocity_;  // per DOF, for constrained DOFs [m/s] (targets) or 0
  std::vector<char> is_target_;     // per DOF: target (1) or fixed (0) when constrained
  Eigen::VectorXd target_displacement_;  // per DOF [m]
  SimulationState state_;
  StepTotals totals_;
  SparseMatrix A_;
  Eigen::VectorXd f_el_, rhs_, v_next_;
  Eigen::VectorXd constraint_force_;       // 3N, reactions of the last step [N]
  std::vector<int> spring_nodes_;
  std::vector<Eigen::Matrix3d> spring_k_;  // [N/m]
  Points spring_anchor_;                   // [m]
  Points spring_constant_;                 // [N], one row per spring node (zero when none given)
  Eigen::VectorXd spring_force_;           // 3N [N]
  std::vector<int> saved_start_;           // per constrained row: offset into saved_values_ (+1)
  std::vector<double> saved_values_, saved_rhs_;  // constrained rows before elimination
  Points x_;
  // Per-step assembly data (the pattern of A_ is fixed): position of each row's diagonal in
  // A_'s value array, and the elimination lists for the constraint set `elim_for_` they were built
  // for (rebuilt in step() when constrained_ differs): constrained rows, and per free row that has
  // constrained columns the value positions of those columns (CSR: elim_row_, elim_start_, elim_pos_).
  std::vector<int> diag_pos_;
  std::vector<char> elim_for_;
  std::vector<int> constrained_rows_;
  std::vector<int> elim_row_, elim_start_, elim_pos_;
  // The stiffness split as A_ (compact) + a rank-one sum the solver applies (ElementFormulation::
  // compactPattern, LinearSolver::acceptsRankOneSum): its DOF mask (1 free, 0 constrained), the
  // per-term workspace of its products and one product (right-hand side, reactions).
  bool split_ = false;
  std::vector<double> free_mask_;
  std::vector<double> rank_one_work_;
  Eigen::VectorXd rank_one_product_;
  // Matrix reuse (setMatrixReuse): steps per assembly; steps since the last one (0: none to reuse,
  // e.g. after restore()); while reuse is on, the dynamics and springs it was assembled with; the
  // values of the eliminated constrained columns (elim_pos_ order) that the right-hand side needs.
  int matrix_reuse_ = 1;
  int matrix_age_ = 0;
  DynamicsParams assembled_params_;
  std::vector<int> assembled_spring_nodes_;
  std::vector<Eigen::Matrix3d> assembled_spring_k_;
  std::vector<double> assembled_spring_scale_;  // per spring: its node's smallest diagonal entry without it
  std::vector<double> elim_values_;
  double last_largest_move_ = 0.0;  // the last step's largest node move [m]
  bool springsAsAssembled() const;  // the springs match the reused matrix's (setMatrixReuse)
};

}  // namespace breast_sim::core
