#pragma once
/// @file cholmod_solver.h
/// Direct solver: supernodal Cholesky factorization A = L Lᵀ by CHOLMOD (SuiteSparse).

#include <memory>
#include <string>

#include <Eigen/Core>

#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::core {

/// Options of the direct solver.
struct CholmodOptions {
  /// BLAS threads while this solver factorizes and solves: 0 = as configured (OPENBLAS_NUM_THREADS),
  /// n > 0 = n for the duration of the call (OpenBLAS only; other BLAS are left alone). 1 suits small
  /// matrices (a multigrid's coarsest level): there thread wake-ups cost more than they save, and
  /// threads that spin after a call steal the cores from OpenMP.
  int blas_threads = 0;
};

/// Sparse Cholesky through CHOLMOD: fill-reducing ordering and symbolic analysis once per pattern
/// (analyzePattern), supernodal numeric factorization per step (factorize), two triangular solves
/// (solve).
///
/// The matrix is handed to CHOLMOD as a view, not a copy: the CSR arrays of a symmetric matrix are
/// the CSC arrays of its transpose, i.e. of the matrix itself, and CHOLMOD reads one triangle.
/// \note Both triangles must be stored (as assembly writes them); only the lower triangle of the CSR
/// matrix is read, so an unsymmetric input is not detected.
/// \note A must be compressed (Eigen's default after setFromTriplets or makeCompressed()); an
/// uncompressed matrix is copied once per call.
/// \note Not thread-safe: one instance per thread. CHOLMOD's BLAS may itself use several threads.
class CholmodSolver : public LinearSolver {
 public:
  explicit CholmodSolver(CholmodOptions options = {});
  ~CholmodSolver() override;
  CholmodSolver(const CholmodSolver&) = delete;
  CholmodSolver& operator=(const CholmodSolver&) = delete;

  /// Orders (CHOLMOD's default: AMD, METIS when AMD fills badly) and analyses A's pattern.
  /// @param A  3N×3N (or any n×n) symmetric, compressed CSR
  /// @throws std::invalid_argument if A is not square; std::runtime_error if CHOLMOD fails.
  void analyzePattern(const SparseMatrix& A) override;
  /// Numeric factorization of A (same pattern as the last analyzePattern).
  /// @throws std::logic_error before analyzePattern or when A's size or nonzero count changed;
  ///         std::runtime_error "cholmod: … not positive definite … column k (node k/3, axis)" when
  ///         A is not positive definite, k being the column of A (original order) where it failed.
  void factorize(const SparseMatrix& A) override;
  /// x = A⁻¹ b with the last factorization; the initial x is ignored. Allocation-free after the
  /// first call when x already has A's size. Stats: 0 iterations, converged; the residual is not
  /// measured (reported as 0: the factorization is backward stable and A is not kept).
  /// @throws std::logic_error before a successful factorize or when b has the wrong size.
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override;
  std::string name() const override { return "cholmod"; }

  /// Nonzeros of the factor L (after factorize; 0 before) — fill-in diagnostics.
  long factorNonzeros() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace breast_sim::core
