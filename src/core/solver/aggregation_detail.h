#pragma once
/// @file aggregation_detail.h
/// Internals of the smoothed-aggregation multigrid (private to aggregation_*.cpp): the state of one
/// level of AggregationMultigridPreconditioner, the check of the b×b block layout, the detection of
/// fixed DOFs, the size below which a level runs on one thread, and the timer of its Timings.

#include <chrono>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/solver/aggregation_multigrid.h"

namespace breast_sim::core {

namespace aggregation_detail {

using Clock = std::chrono::steady_clock;
inline double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Levels below this many nodes run on one thread: waking the second costs more than it saves.
constexpr int kParallelMinNodes = 400;
constexpr int kC = kRigidModes;  // coarse DOFs per aggregate

// Checks the b×b block layout (rows b·i … b·i+b−1 hold the same columns, b per neighbour, ascending,
// the diagonal block included) and returns the block graph: per node its blocks (start, N + 1), per
// block its column node, per node the index of its diagonal block.
void blockGraph(const SparseMatrix& A, int bs, const std::string& who, std::vector<int>& start, std::vector<int>& nbr,
                std::vector<int>& diag_block);

// Per DOF: 1 when its row has a nonzero off the diagonal, else 0 (decoupled, i.e. fixed).
void coupledRows(const SparseMatrix& A, std::vector<double>& free);

}  // namespace aggregation_detail

struct AggregationMultigridPreconditioner::Level {
  const SparseMatrix* A = nullptr;  // level 0: the caller's matrix; else `owned`
  SparseMatrix owned;               // Galerkin operator (6×6 blocks)
  int nodes = 0, bs = 3;
  std::vector<int> block_start, block_col, diag_block;
  std::vector<float> block_val;  // the operator in float blocks for the sweeps
  std::vector<double> dinv;      // per node: inverse of its diagonal block, row-major
  std::vector<double> free;      // per DOF: 1 free, 0 decoupled
  double omega = 0.0, lambda = 0.0;
  Eigen::VectorXd eigenvector, b, x, t;
  // Transfer to level + 1 (not on the coarsest level).
  BlockProlongator P;
  std::vector<double> pm;  // P's values with the rows of decoupled DOFs zeroed
  std::vector<int> child_start, child_node, child_block;  // Pᵀ: per coarse node its (fine node, block)
  std::vector<int> ap_start, ap_col;                       // pattern of A·P
  std::vector<double> ap_val;
  std::vector<int> mirror;  // per block of level + 1: index (in its column node's row) of the transposed block
};

}  // namespace breast_sim::core
