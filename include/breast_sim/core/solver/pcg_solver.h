#pragma once
/// @file pcg_solver.h
/// Preconditioned conjugate gradients (parallel, warm-started) and the preconditioner interface.

#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/solver/linear_solver.h"
#include "breast_sim/core/solver/rank_one_sum.h"

namespace breast_sim::core {

/// z = M⁻¹ r for a symmetric positive definite approximation M of A.
/// \note M⁻¹ must be a fixed linear, symmetric, positive definite map between factorize() calls
/// (CG's convergence theory needs it): no tolerance-driven inner iterations.
class Preconditioner {
 public:
  virtual ~Preconditioner() = default;
  /// Symbolic set-up for A's sparsity pattern.
  virtual void analyzePattern(const SparseMatrix& A) = 0;
  /// Numeric set-up for A's values. May keep a pointer to A: A must stay alive and unchanged until
  /// the last apply() before the next factorize().
  /// @throws std::runtime_error naming the preconditioner when A is evidently not positive definite.
  virtual void factorize(const SparseMatrix& A) = 0;
  /// z = M⁻¹ r. z has A's size on entry (no allocation); r and z do not alias.
  virtual void apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) = 0;
  /// Short name: "jacobi", "multigrid".
  virtual std::string name() const = 0;
  /// Told by PCG after each solve that iterated: `iterations` reduced the residual by
  /// `residual_reduction` = ‖r_k‖ / ‖r_0‖, r_0 the residual of the initial guess with the decoupled
  /// rows solved (at an iteration limit of at most 8, r_k is the recursive residual). A
  /// preconditioner may renew parts of itself when convergence degrades; the default ignores it.
  virtual void reportConvergence(int iterations, double residual_reduction) {
    (void)iterations;
    (void)residual_reduction;
  }
  /// Sets up again, from the matrix of the last factorize(), every part that an earlier matrix left
  /// in place (the multigrid's coarse operators and smoother dampings between its renewals), for PCG
  /// to call when M⁻¹ turned out not positive definite for this matrix. Returns false when nothing
  /// was kept from an earlier matrix, so that a renewal would change nothing (the default).
  /// @throws as factorize().
  virtual bool renew() { return false; }
  /// Whether it approximates A = S + R with R a rank-one sum (solver/rank_one_sum.h); the
  /// default does not.
  virtual bool acceptsRankOneSum() const { return false; }
  /// analyzePattern() and factorize() for A = S + R (LinearSolver::analyzeWithRankOne and
  /// factorizeWithRankOne say what may change between calls). The default throws std::logic_error.
  virtual void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R);
  virtual void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R);

  /// The matrix of the last factorize() (S of a rank-one sum) rounded to float, in 3×3 blocks (node
  /// rows: blocks start[i] .. start[i+1] − 1, column node col[k], nine row-major values val[9k ..]),
  /// when the preconditioner keeps such a copy; val is null otherwise (and after a factorize that
  /// failed). Valid until the next analyzePattern(), factorize() or their rank-one forms.
  struct FloatBlocks {
    const float* val = nullptr;
    const int* col = nullptr;
    const int* start = nullptr;
    int nodes = 0;
  };
  virtual FloatBlocks floatBlocks() const { return {}; }
};

/// Point Jacobi: M = diag(A).
class JacobiPreconditioner : public Preconditioner {
 public:
  void analyzePattern(const SparseMatrix& A) override;
  /// @throws std::runtime_error "pcg-jacobi: … diagonal entry … ≤ 0" naming the DOF.
  void factorize(const SparseMatrix& A) override;
  void apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) override;
  std::string name() const override { return "jacobi"; }
  /// M = diag(S + R).
  bool acceptsRankOneSum() const override { return true; }
  void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;
  void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;

 private:
  std::vector<int> diagonal_position_;  // per row: index of (i, i) in A's value array
  Eigen::VectorXd inverse_diagonal_;
  std::vector<double> rank_one_diagonal_;  // 9 per node: the diagonal blocks of R
};

/// Stopping rule and limits of PCG.
struct PcgOptions {
  /// Converged when ‖b − A x‖₂ ≤ relative_tolerance · ‖b‖₂ (the true residual is checked before
  /// convergence is declared, so round-off in the recursive residual cannot fake it).
  double relative_tolerance = 1e-8;
  int max_iterations = 2000;  ///< returns with converged = false after this many iterations
  /// Products with a block-layout matrix by the AVX2/FMA kernel when the processor has it
  /// (solver/block_kernels.h); false = the portable scalar kernel.
  bool simd_kernels = true;
  /// Initial guess from the solver's own past: the combination of the caller's guess and the last
  /// solutions closest to the solution in the A-norm (a Galerkin projection onto their span
  /// [Fischer, Comput. Methods Appl. Mech. Engrg. 163 (1998) 193]), at one product with A per
  /// vector. It is never farther from the solution in the A-norm than the caller's guess. The count
  /// of vectors spanning it, the caller's guess included, in 1 .. kMaxProjectionVectors; 1 = the
  /// caller's guess alone. With 2 a time step starts from the best multiple of its last velocity
  /// and of that velocity's last change: 48.8k elements, 25 dynamic steps to 1e-2, 15.4 PCG
  /// iterations per step fall to 7.2 (4 vectors: 6.0); the main job's solves at 20.8k take 12.2
  /// instead of 15.9 (4 vectors: 14.0), its sliding stage gains nothing (docs/benchmarks.md, "The
  /// initial guess").
  int projection_vectors = 2;
};

/// Largest PcgOptions::projection_vectors.
inline constexpr int kMaxProjectionVectors = 8;

/// The tightest relative tolerance at which PCG's iteration products use the preconditioner's float
/// copy of A (Preconditioner::floatBlocks). Below it the float operator's rounding (about 1e-7 of
/// each entry) would hold the residual up: at 48.8k elements, 1e-4 takes 18.4 iterations either
/// way, 1e-5 27.4 instead of 23.9 (docs/benchmarks.md, "The iteration's product").
inline constexpr double kFloatProductMinTolerance = 1e-4;

/// Conjugate gradients with a preconditioner, for symmetric positive definite A [Saad, Iterative
/// Methods for Sparse Linear Systems, alg. 9.1]. All vector work and the sparse matrix–vector
/// product run in parallel over rows (OpenMP); solve() does not allocate once x has A's size.
///
/// Decoupled rows (no nonzero off the diagonal: the Dirichlet rows of the LinearSolver contract)
/// are solved exactly before iterating (x_i = b_i / A_ii) and stay at that value: every
/// preconditioner keeps them decoupled.
///
/// A matrix in the 3×3-block layout of fem/block_pattern.h (found in analyzePattern()) is multiplied
/// block by block: one column index per block instead of nine, and each x_J read once for three
/// rows. At the iteration limit the preconditioner is not applied for the iteration that would
/// follow, and after at most 8 iterations the reported residual is the recursive one
/// (SolveStats::relative_residual; beyond that the true one is recomputed).
///
/// When the preconditioner keeps A rounded to float blocks (the multigrid's fine level) and the
/// tolerance is at least kFloatProductMinTolerance, the iteration's products (and the projected
/// guess's) read those: half the bytes of the double matrix, the arithmetic in double. Convergence
/// is still declared on the double matrix's true residual; a confirmation that fails, or a pᵀAp ≤ 0
/// of the copy, switches the rest of the solve to the double products. A copy whose size differs
/// from A's is a std::logic_error of factorize().
/// \note factorize() keeps a pointer to A: A must stay alive and unchanged until the last solve()
/// before the next factorize(). A must be compressed CSR with sorted columns (Eigen's default).
/// \note Indefiniteness is only detected when met: factorize() throws on a diagonal entry ≤ 0,
/// solve() throws std::runtime_error when pᵀAp ≤ 0 (both name the solver).
class PcgSolver : public LinearSolver {
 public:
  /// @param preconditioner  owned; nullptr = JacobiPreconditioner
  explicit PcgSolver(PcgOptions options = {}, std::unique_ptr<Preconditioner> preconditioner = nullptr);

  void analyzePattern(const SparseMatrix& A) override;
  /// @throws std::logic_error before analyzePattern or when A's size, nonzero count or row lengths changed;
  ///         std::runtime_error when a diagonal entry is ≤ 0 or the preconditioner throws.
  void factorize(const SparseMatrix& A) override;
  /// Iterates from the initial guess x (warm start; an x of the wrong size starts from zero).
  /// Returns at once (0 iterations) when x already meets the tolerance; b = 0 gives x = 0.
  /// @throws std::logic_error before factorize or for a b of the wrong size;
  ///         std::runtime_error when pᵀAp ≤ 0 (A not positive definite) or rᵀM⁻¹r ≤ 0 (bad
  ///         preconditioner).
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override;
  /// "pcg-" + the preconditioner's name.
  std::string name() const override { return "pcg-" + preconditioner_->name(); }
  double relativeTolerance() const override { return options_.relative_tolerance; }
  void setRelativeTolerance(double tolerance) override;

  const PcgOptions& options() const { return options_; }
  /// @throws std::invalid_argument naming projection_vectors when it is not in 1 .. kMaxProjectionVectors.
  void setOptions(const PcgOptions& options);
  Preconditioner& preconditioner() { return *preconditioner_; }
  const Preconditioner& preconditioner() const { return *preconditioner_; }
  /// Whether analyzePattern() found A in 3×3-block layout (and multiplies it block by block).
  bool blockLayout() const { return !block_start_.empty(); }
  /// Rows found decoupled (fixed) by the last factorize(), ascending.
  const std::vector<int>& decoupledRows() const { return decoupled_; }
  /// Drops the kept solutions (PcgOptions::projection_vectors): the next solve starts from the
  /// caller's guess alone. analyzePattern() drops them as well.
  void forgetSolutions() override { kept_solutions_ = 0; }
  /// How many past solutions are kept for the next initial guess.
  int keptSolutions() const { return kept_solutions_; }

  /// A = S + R: every product of the iteration adds R's (solver/rank_one_sum.h), the
  /// preconditioner approximates S + R. Taken when the preconditioner takes it.
  bool acceptsRankOneSum() const override { return preconditioner_->acceptsRankOneSum(); }
  void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;
  void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;

 private:
  void analyzeCommon(const SparseMatrix& A);  // analyzePattern() after the preconditioner's
  void checkAndScan(const SparseMatrix& A);   // factorize() without the preconditioner's
  void takeFloatBlocks();                     // after the preconditioner's factorize()
  // The projected initial guess (PcgOptions::projection_vectors) into x and its residual into r_;
  // returns rᵀr, or −1 (x unchanged) when there is nothing to project.
  double projectInitialGuess(const Eigen::VectorXd& b, Eigen::VectorXd& x);
  void keepSolution(const Eigen::VectorXd& x);
  // A = S + R when analysed with R. b null: y = A x, returns xᵀy, from the float blocks while
  // float_products_; else y = b − A x from the double matrix, returns yᵀy.
  double applyMatrix(const Eigen::VectorXd* b, const Eigen::VectorXd& x, Eigen::VectorXd& y);
  PcgOptions options_;
  std::unique_ptr<Preconditioner> preconditioner_;
  const SparseMatrix* A_ = nullptr;
  Eigen::Index n_ = -1;
  Eigen::Index nnz_ = -1;
  std::vector<int> diagonal_position_;
  std::vector<unsigned char> decoupled_flag_;
  std::vector<int> decoupled_;
  std::vector<int> block_start_, block_col_;  // node columns of A's 3×3 blocks (empty: no block layout)
  std::vector<int> analysed_outer_;           // A's row starts at analyzePattern()
  Preconditioner::FloatBlocks float_blocks_;  // of the last factorize (val null: none)
  bool float_products_ = false;               // this solve's products from float_blocks_
  Eigen::VectorXd r_, z_, p_, q_;
  // A = S + R when analysed with a rank-one sum: the view of the last factorize, its structure
  // from analyzeWithRankOne (terms, entries), and the per-term workspace of its products.
  bool rank_one_ = false;
  RankOneSum R_;
  int rank_one_terms_ = 0, rank_one_entries_ = 0;
  std::vector<double> rank_one_work_;
  std::vector<double> rank_one_masked_;  // R's vectors with its mask applied (withMaskApplied)
  // Past solutions, newest first (the first kept_solutions_ hold them), and the projection's basis
  // and its products with A.
  std::vector<Eigen::VectorXd> solutions_, basis_, basis_products_;
  int kept_solutions_ = 0;
};

/// y = A x, in parallel over rows (OpenMP). y is resized if needed; x and y must not alias.
void parallelMultiply(const SparseMatrix& A, const Eigen::VectorXd& x, Eigen::VectorXd& y);

/// Index of the diagonal entry of each row in A's value array.
/// @throws std::invalid_argument naming the row when a row has no stored diagonal entry, or A is
///         not square or not compressed.
std::vector<int> diagonalPositions(const SparseMatrix& A, const std::string& who);

}  // namespace breast_sim::core
