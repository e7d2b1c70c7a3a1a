#pragma once
/// @file linear_solver.h
/// The interface every linear solver of the time step implements: CHOLMOD (direct) and PCG with a
/// geometric multigrid preconditioner [GW08].

#include <string>

#include <Eigen/Core>
#include <Eigen/SparseCore>

namespace breast_sim::core {

struct RankOneSum;  // solver/rank_one_sum.h

/// Compressed sparse row matrix, the format assembly writes into (3 DOFs per node: x0 y0 z0 x1 …).
using SparseMatrix = Eigen::SparseMatrix<double, Eigen::RowMajor, int>;

/// What one solve did.
struct SolveStats {
  int iterations = 0;             ///< Krylov iterations (0 for a direct solve)
  /// ‖b − A x‖ / ‖b‖ at return (PCG stopped by its iteration limit after at most 8 iterations: the
  /// recursive residual, equal to it up to round-off that far, or up to the float copy's rounding
  /// when PCG multiplied by it, about 1e-5 of it)
  double relative_residual = 0.0;
  bool converged = false;
  double seconds = 0.0;           ///< wall time of solve() [s]
  /// PCG: the preconditioner was set up again from this matrix during the solve (Preconditioner::renew)
  bool preconditioner_renewed = false;
};

/// Solves A x = b for symmetric positive definite A whose sparsity pattern stays fixed over many
/// time steps while its values change every step.
/// \note Dirichlet conditions are applied by the caller before factorize(): the rows and columns of
/// fixed DOFs are zeroed with a unit diagonal, so A stays SPD and its pattern does not change.
class LinearSolver {
 public:
  virtual ~LinearSolver() = default;
  /// Symbolic set-up for A's sparsity pattern (ordering, hierarchy structure). Call when it changes.
  virtual void analyzePattern(const SparseMatrix& A) = 0;
  /// Numeric set-up for A's values (factorization, coarse operators). Call once per step.
  /// @throws std::runtime_error when A is not positive definite (names the solver and the column).
  virtual void factorize(const SparseMatrix& A) = 0;
  /// Solves A x = b with the last factorized A. On entry x is the initial guess (warm start;
  /// iterative solvers use it, direct solvers ignore it).
  virtual SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) = 0;
  /// Short name for tables: "cholmod", "pcg-jacobi", "pcg-multigrid".
  virtual std::string name() const = 0;
  /// Relative residual at which an iterative solve stops (‖b − A x‖ ≤ tol ‖b‖); 0 for a direct
  /// solver (solved to round-off).
  virtual double relativeTolerance() const { return 0.0; }
  /// Sets that tolerance for the next solves, e.g. a looser one for a tracking frame than for a
  /// precomputation; a direct solver ignores it.
  /// @throws std::invalid_argument unless 0 < tolerance < 1 (iterative solvers).
  virtual void setRelativeTolerance(double tolerance) { (void)tolerance; }
  /// Drops what the solver kept from earlier solves for its initial guesses (PcgSolver: the last
  /// solutions), so that the next solves depend only on their own inputs, e.g. after the caller's
  /// state was replaced. Nothing to drop by default.
  virtual void forgetSolutions() {}

  /// Whether the solver takes A = S + R with R a rank-one sum applied without a matrix
  /// (solver/rank_one_sum.h): PCG with its Jacobi or multigrid preconditioner (Jacobi or Chebyshev
  /// smoother, at least two levels). Direct and aggregation solvers need the assembled matrix.
  virtual bool acceptsRankOneSum() const { return false; }
  /// analyzePattern() for A = S + R: S's pattern and R's structure (terms, entries, nodes), both
  /// fixed until the next call; the Dirichlet rows of S (the contract above) must be masked in R
  /// (RankOneSum::free). @throws std::logic_error when !acceptsRankOneSum().
  virtual void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R);
  /// factorize() for A = S + R; R's vectors, weights, scale and mask may change from call to call.
  /// The solver keeps the view: R's arrays must stay alive and unchanged until the last solve()
  /// before the next factorize. @throws as factorize(); std::logic_error when !acceptsRankOneSum().
  virtual void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R);
};

}  // namespace breast_sim::core
