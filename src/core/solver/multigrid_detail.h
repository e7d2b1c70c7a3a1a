#pragma once
/// @file multigrid_detail.h
/// Internals of the geometric multigrid (private to multigrid*.cpp): the state of one level of
/// MultigridPreconditioner, the check of the 3×3-block layout, the size below which a level runs on
/// one thread, and the timer of MultigridPreconditioner::Timings.

#include <chrono>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/solver/multigrid.h"

namespace breast_sim::core {

namespace multigrid_detail {

using Clock = std::chrono::steady_clock;
inline double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Levels with fewer 3×3 blocks than this run on one thread. A block is one sweep's unit of work (9
// float multiply-adds). The team's threads spin between parallel regions (src/openmp_wait), so
// handing a region to the second thread costs microseconds: from 2,000 blocks (a level of about 150
// nodes) up two threads are faster. The 4.8k-element model's fine level has 15,700 blocks; its
// multigrid-PCG step takes 3.6–4.0 ms on two threads, 5.5–6.4 ms with the levels below 25,000
// blocks on one (bench_anp_split, docs/benchmarks.md, "Threads").
constexpr size_t kParallelMinBlocks = 2000;

// Checks the 3×3-block layout of fem/block_pattern.h and returns the neighbour lists
// (block columns) of every node: start (N + 1) and node indices.
void blockGraph(const SparseMatrix& A, const std::string& who, std::vector<int>& start, std::vector<int>& nbr,
                std::vector<int>* diag_block);

}  // namespace multigrid_detail

struct MultigridPreconditioner::Level {
  const SparseMatrix* A = nullptr;  // level 0: the caller's matrix; else the Galerkin operator
  SparseMatrix* owned = nullptr;    // coarse levels: writable (unit diagonals of empty rows)
  int nodes = 0;
  std::vector<int> diag_block;  // per node: block index of its diagonal block
  std::vector<double> dinv;     // per node: inverse of its 3×3 diagonal block, row-major
  std::vector<double> free;     // per DOF: 1 free, 0 decoupled (fixed)
  std::vector<int> colour_start, colour_node;
  // The operator in 3×3 blocks of floats for the V-cycle's sweeps (residuals and smoothing): one
  // column index per block instead of nine and 4-byte values move 2.7× fewer bytes than the CSR
  // matrix. Refreshed from A whenever A changes.
  std::vector<int> block_start, block_col;  // per node: its blocks; per block: its column node
  std::vector<float> block_val;             // per block: 9 values, row-major
  // Its sweeps, transfers and set-up on the team (multigrid_detail::kParallelMinBlocks).
  bool parallel() const { return block_col.size() >= multigrid_detail::kParallelMinBlocks; }
  // Transfer to the next coarser level: children (Pᵀ) of each coarse node.
  std::vector<int> child_start, child;
  std::vector<double> child_weight;
  Eigen::VectorXd b, x, t;
  Eigen::VectorXd d;           // Chebyshev: the last update direction
  double omega = 0.0;          // Jacobi damping
  double lambda_max = 0.0;     // Chebyshev: upper end of the interval
  Eigen::VectorXd eigenvector;  // last power-iteration vector (warm start)
};

}  // namespace breast_sim::core
