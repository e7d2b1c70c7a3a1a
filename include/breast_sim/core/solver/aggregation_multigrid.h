#pragma once
/// @file aggregation_multigrid.h
/// Smoothed-aggregation algebraic multigrid [VMB96] as a PCG preconditioner for the 3×3-block
/// symmetric positive definite system of an implicit step of 3-D elasticity, and PCG with it (the
/// LinearSolver "pcg-sa-multigrid").
///
/// What it is: a symmetric V-cycle, damped block Jacobi V(ν,ν) on every level and CHOLMOD on the
/// coarsest, over coarse spaces built from the matrix and the fine nodes' coordinates alone. The
/// spaces are nested and contain the six rigid-body modes exactly, so the V-cycle is a fixed SPD
/// operator and its coarse correction an A-orthogonal projection.
///
/// When to use it: where no coarse meshes are at hand. It needs no MeshHierarchy, so no label image to
/// mesh coarser levels from (the geometric multigrid of multigrid.h needs both), and works on any
/// tetrahedral mesh, e.g. one read from a file. Where a hierarchy can be built, the geometric multigrid
/// is faster (the two are compared in docs/benchmarks.md).
///
/// Units and shapes: N nodes, 3 DOFs each in the order x0 y0 z0 x1 …; the matrix is 3N × 3N in the
/// block layout of fem/block_pattern.h (a step system A = M/dt² + K in N/m), the coordinates N × 3 [m],
/// apply() maps a residual of 3N values to a correction of 3N in the units of the solution. Coarse
/// levels have 6 DOFs per aggregate (6×6 blocks). Fixed DOFs are decoupled rows (the LinearSolver
/// contract); they are masked out of the near-null space and of the prolongators (zero rows), so a
/// coarse correction never moves them, and a coarse DOF with an empty row (a rigid mode an aggregate
/// cannot carry, e.g. a rotation about the line through a two-node aggregate) gets a unit diagonal.
///
/// Errors: std::invalid_argument for options out of range, coordinates of another node count, or a
/// matrix of the wrong size or not in block layout; std::logic_error for factorize() before
/// analyzePattern() or with another pattern, apply() before a successful factorize();
/// std::runtime_error "sa-multigrid: …" when a diagonal block is not positive definite or CHOLMOD
/// fails on the coarsest level.
///
/// The method. Elasticity's operator annihilates the rigid-body motions apart from the mass term
/// M/dt² and the Dirichlet rows, so locally rigid errors are smooth for a block smoother and must be
/// removed by the coarse space. Per level: (1) nodes are aggregated on the strong block graph,
/// ‖A_ij‖_F > θ √(‖A_ii‖_F ‖A_jj‖_F); (2) per aggregate the rigid modes (from the coordinates on the
/// fine level, from the previous level's coarse basis below) are orthonormalised, B_agg = Q R, Q
/// giving the tentative prolongator P̂ and R the coarse near-null space, so P̂ B_c = B exactly;
/// (3) one damped block-Jacobi step, P = (I − ω_P D⁻¹A) P̂ with ω_P λ_max(D⁻¹A) = prolongator_damping
/// (4/3), lowers the energy of the coarse basis; (4) A_c = Pᵀ A P, recursively until a level is
/// small enough for CHOLMOD (max_coarsest_dofs). factorize() does all of this every time, or with
/// AggregationMultigridOptions::reuse_prolongators keeps the aggregates and P of the first call and
/// redoes only the Galerkin products, the smoothers and the coarsest factorization.
///
/// [VMB96] P. Vaněk, J. Mandel, M. Brezina: Algebraic multigrid by smoothed aggregation for second
///         and fourth order elliptic problems. Computing 56 (1996) 179–196.

#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/linear_solver.h"
#include "breast_sim/core/solver/pcg_solver.h"

namespace breast_sim::core {

/// Coarse DOFs per aggregate: the six rigid-body modes.
constexpr int kRigidModes = 6;

/// Options of the smoothed-aggregation hierarchy and its V-cycle.
struct AggregationMultigridOptions {
  /// θ of the strength of connection on the fine level (0 = every block is strong).
  double strength_threshold = 0.08;
  /// θ is multiplied by this on each coarser level (Vaněk et al.: 1/2).
  double strength_decay = 0.5;
  /// One damped-Jacobi step on the tentative prolongator (false = plain aggregation, P = P̂).
  bool smooth_prolongator = true;
  /// ω_P λ_max(D⁻¹A) of the prolongator smoothing (4/3 is the classical choice).
  double prolongator_damping = 4.0 / 3.0;
  /// Block-Jacobi sweeps before and after the coarse correction (the same number: symmetric).
  int smoothing_steps = 1;
  /// ω λ_max(D⁻¹A) of the damped block-Jacobi smoother, λ_max estimated per level by power
  /// iteration; must stay below 2 for a convergent smoother (a positive definite V-cycle).
  double smoother_damping = 4.0 / 3.0;
  /// Coarsen until a level has at most this many DOFs (6 per aggregate); that level goes to CHOLMOD.
  int max_coarsest_dofs = 300;
  int max_levels = 8;  ///< never more levels than this (fine included)
  /// Power iterations per level and factorize() for λ_max(D⁻¹A), warm-started from the last
  /// vector; the first estimate on a level takes ten times as many.
  int power_iterations = 3;
  /// Keep the aggregates and prolongators of the first factorize() after analyzePattern(); later
  /// calls recompute only the Galerkin operators, the smoothers and the coarsest factorization.
  bool reuse_prolongators = false;
};

/// A block-sparse prolongator from coarse nodes (6 DOFs each) to fine nodes (`fine_block` DOFs each):
/// row block i holds blocks start[i] … start[i+1]−1, block k couples coarse node col[k] and stores
/// fine_block × 6 values row-major at val[k·fine_block·6].
struct BlockProlongator {
  int fine_nodes = 0;
  int coarse_nodes = 0;
  int fine_block = 3;
  std::vector<int> start, col;
  std::vector<double> val;
  /// The same operator as a DOF-level sparse matrix (fine_block·fine_nodes × 6·coarse_nodes), for
  /// tests and references.
  SparseMatrix toSparse() const;
};

/// Aggregates of the nodes of a matrix in `block_size`×`block_size` block layout (fem/block_pattern.h
/// generalised: rows b·i … b·i+b−1 hold the same columns, b per neighbour): node i is in aggregate
/// result[i] (−1 for a node all of whose DOFs are decoupled, i.e. fixed). Strong connection:
/// ‖A_ij‖_F > θ √(‖A_ii‖_F ‖A_jj‖_F). Phase 1 makes an aggregate of every node whose strong
/// neighbours are all still free, together with them; phase 2 attaches each left-over node to the
/// aggregate it is most strongly connected to; phase 3 groups what is left with its free strong
/// neighbours (possibly alone).
/// @param count  set to the number of aggregates
/// @throws std::invalid_argument when A is not in block layout or block_size < 1.
std::vector<int> aggregateNodes(const SparseMatrix& A, int block_size, double theta, int* count);

/// The six rigid-body modes at the given coordinates, 3N × 6 (DOF order x0 y0 z0 x1 …): three unit
/// translations and the rotations about x, y, z through the centroid, their lever arms divided by
/// the RMS distance to the centroid (so all six columns have comparable norms).
Eigen::MatrixXd rigidBodyModes(const Points& coordinates_m);

/// Tentative prolongator P̂ of smoothed aggregation: for each aggregate a, the rows of B of its nodes
/// (block_size per node) are orthonormalised by modified Gram–Schmidt (twice), B_a = Q_a R_a; Q_a is
/// P̂'s block column of aggregate a and R_a (6 × 6) the aggregate's rows of B_coarse, so that
/// P̂ · B_coarse = B on every aggregated node. A mode that is numerically dependent within an
/// aggregate (column norm after orthogonalisation below 1e-10 of its norm before) gives a zero
/// column of Q_a and a zero row of R_a. Nodes with aggregate −1 get an empty row.
/// @param B  (block_size · #nodes) × 6, already masked (zero rows on fixed DOFs)
/// @throws std::invalid_argument when sizes do not fit or an aggregate index is out of range.
BlockProlongator tentativeProlongator(const std::vector<int>& aggregate, int num_aggregates, int block_size,
                                      const Eigen::MatrixXd& B, Eigen::MatrixXd* B_coarse);

/// Smoothed-aggregation V-cycle as a PCG preconditioner: damped block-Jacobi V(ν,ν) with the
/// operator in float blocks for the sweeps (arithmetic in double, as in multigrid.h), CHOLMOD on the
/// coarsest level. apply() does not allocate.
/// \note factorize() keeps a pointer to the fine matrix (see Preconditioner). Not thread-safe.
class AggregationMultigridPreconditioner : public Preconditioner {
 public:
  /// @param coordinates_m  #N × 3 node positions [m] of the fine level (the rigid modes); use the
  ///        current positions of a deformed body (its co-rotated operator annihilates rotations
  ///        about them), see setCoordinates()
  /// @throws std::invalid_argument for bad options.
  explicit AggregationMultigridPreconditioner(Points coordinates_m, AggregationMultigridOptions options = {});
  ~AggregationMultigridPreconditioner() override;

  /// Coordinates for the next full set-up (every factorize() without reuse_prolongators).
  /// @throws std::invalid_argument when the node count differs.
  void setCoordinates(Points coordinates_m);

  /// @throws std::invalid_argument when A is not 3#N square in 3×3-block layout.
  void analyzePattern(const SparseMatrix& A) override;
  /// @throws std::logic_error before analyzePattern or when A's pattern changed;
  ///         std::runtime_error "sa-multigrid: …" when a diagonal block is not positive definite or
  ///         CHOLMOD fails on the coarsest level.
  void factorize(const SparseMatrix& A) override;
  void apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) override;
  std::string name() const override { return "sa-multigrid"; }

  int numLevels() const { return static_cast<int>(levels_.size()); }
  /// Operator of a level after factorize() (0: the caller's matrix; ≥ 1: Galerkin, 6×6 blocks).
  const SparseMatrix& levelMatrix(int level) const;
  /// Prolongator from level+1 to level (raw values, fixed rows not yet masked).
  const BlockProlongator& prolongator(int level) const;
  /// Block-Jacobi damping ω of a level (0 for the coarsest).
  double smootherDamping(int level) const;
  const AggregationMultigridOptions& options() const { return options_; }

  /// Where the time goes [s]: the parts of the last factorize() and of the apply() calls since.
  struct Timings {
    double hierarchy_s = 0.0;         ///< aggregation, tentative and smoothed prolongators, symbolic products
    double galerkin_s = 0.0;          ///< numeric A·P and Pᵀ(A P), all levels
    double scan_s = 0.0;              ///< fixed DOFs, block inverses, float copies, all levels
    double damping_s = 0.0;           ///< power iterations
    double coarse_factorize_s = 0.0;  ///< CHOLMOD on the coarsest level
    int applications = 0;             ///< apply() calls since that factorize()
    std::vector<double> level_s;      ///< per level, summed over those calls, without the levels below
  };
  const Timings& lastFactorizeTimings() const { return timings_; }

 private:
  struct Level;
  void buildHierarchy();
  void numericLevels();
  void scanLevel(int level, bool coarsest);
  void estimateDamping(int level);
  void buildTransfer(int level, const Eigen::MatrixXd& B, Eigen::MatrixXd* B_coarse);
  void galerkin(int level);
  void factorizeCoarsest();
  void vcycle(int level);
  void smooth(int level, bool from_zero);

  AggregationMultigridOptions options_;
  Points coordinates_;
  std::vector<std::unique_ptr<Level>> levels_;
  std::unique_ptr<CholmodSolver> coarsest_;
  const SparseMatrix* fine_ = nullptr;
  Eigen::Index fine_nnz_ = -1;
  bool built_ = false;
  bool factorized_ = false;
  Timings timings_;
};

/// PCG with the smoothed-aggregation V-cycle: the LinearSolver "pcg-sa-multigrid".
class AggregationMultigridPcgSolver : public PcgSolver {
 public:
  AggregationMultigridPcgSolver(Points coordinates_m, PcgOptions pcg_options = {},
                                AggregationMultigridOptions options = {});
  AggregationMultigridPreconditioner& multigrid() {
    return static_cast<AggregationMultigridPreconditioner&>(preconditioner());
  }
  const AggregationMultigridPreconditioner& multigrid() const {
    return static_cast<const AggregationMultigridPreconditioner&>(preconditioner());
  }
};

}  // namespace breast_sim::core
