// The coarse space of smoothed aggregation: the block layout check and the fixed DOFs it starts from,
// the aggregates of the strong block graph, the rigid-body modes and the tentative prolongator that
// reproduces them on every aggregate.
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include <Eigen/Dense>

#include "aggregation_detail.h"

namespace breast_sim::core {

namespace aggregation_detail {

// Checks the b×b block layout (rows b·i … b·i+b−1 hold the same columns, b per neighbour, ascending,
// the diagonal block included) and returns the block graph: per node its blocks (start, N + 1), per
// block its column node, per node the index of its diagonal block.
void blockGraph(const SparseMatrix& A, int bs, const std::string& who, std::vector<int>& start, std::vector<int>& nbr,
                std::vector<int>& diag_block) {
  auto fail = [&](const std::string& what) {
    throw std::invalid_argument(who + ": the matrix is not in " + std::to_string(bs) + "×" + std::to_string(bs) +
                                "-block layout (fem/block_pattern.h): " + what);
  };
  if (bs < 1) throw std::invalid_argument(who + ": block size " + std::to_string(bs) + " must be ≥ 1");
  if (A.rows() != A.cols() || A.rows() % bs != 0)
    fail("size " + std::to_string(A.rows()) + "×" + std::to_string(A.cols()));
  if (!A.isCompressed()) fail("it is not compressed (call makeCompressed())");
  const int n = static_cast<int>(A.rows() / bs);
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  start.assign(static_cast<size_t>(n) + 1, 0);
  nbr.clear();
  nbr.reserve(static_cast<size_t>(A.nonZeros() / (bs * bs)));
  diag_block.assign(static_cast<size_t>(n), -1);
  for (int i = 0; i < n; ++i) {
    const int len = outer[bs * i + 1] - outer[bs * i];
    if (len % bs != 0) fail("the rows of node " + std::to_string(i) + " are not whole blocks");
    for (int r = 1; r < bs; ++r)
      if (outer[bs * i + r + 1] - outer[bs * i + r] != len) fail("the rows of node " + std::to_string(i) + " differ in length");
    int last = -1;
    for (int k = 0; k < len / bs; ++k) {
      const int c0 = inner[outer[bs * i] + bs * k];
      if (c0 % bs != 0 || c0 / bs <= last) fail("block " + std::to_string(k) + " of node " + std::to_string(i));
      for (int r = 0; r < bs; ++r)
        for (int c = 0; c < bs; ++c)
          if (inner[outer[bs * i + r] + bs * k + c] != c0 + c)
            fail("block " + std::to_string(k) + " of node " + std::to_string(i) + ", row " + std::to_string(r));
      last = c0 / bs;
      if (last == i) diag_block[i] = k;
      nbr.push_back(last);
    }
    if (diag_block[i] < 0) fail("node " + std::to_string(i) + " has no diagonal block");
    start[i + 1] = static_cast<int>(nbr.size());
  }
}

// Per DOF: 1 when its row has a nonzero off the diagonal, else 0 (decoupled, i.e. fixed).
void coupledRows(const SparseMatrix& A, std::vector<double>& free) {
  const int n = static_cast<int>(A.rows());
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  free.resize(static_cast<size_t>(n));
#pragma omp parallel for schedule(static) if (n > 3 * kParallelMinNodes)
  for (int r = 0; r < n; ++r) {
    bool coupled = false;
    for (int k = outer[r]; k < outer[r + 1] && !coupled; ++k) coupled = inner[k] != r && val[k] != 0.0;
    free[r] = coupled ? 1.0 : 0.0;
  }
}

}  // namespace aggregation_detail

using aggregation_detail::blockGraph;
using aggregation_detail::coupledRows;
using aggregation_detail::kC;

SparseMatrix BlockProlongator::toSparse() const {
  std::vector<Eigen::Triplet<double, int>> t;
  for (int i = 0; i < fine_nodes; ++i)
    for (int q = start[i]; q < start[i + 1]; ++q)
      for (int r = 0; r < fine_block; ++r)
        for (int m = 0; m < kC; ++m) {
          const double v = val[static_cast<size_t>(q) * fine_block * kC + r * kC + m];
          if (v != 0.0) t.emplace_back(fine_block * i + r, kC * col[q] + m, v);
        }
  SparseMatrix P(static_cast<Eigen::Index>(fine_block) * fine_nodes, static_cast<Eigen::Index>(kC) * coarse_nodes);
  P.setFromTriplets(t.begin(), t.end());
  return P;
}

std::vector<int> aggregateNodes(const SparseMatrix& A, int block_size, double theta, int* count) {
  std::vector<int> start, nbr, diag;
  blockGraph(A, block_size, "aggregateNodes", start, nbr, diag);
  const int bs = block_size;
  const int n = static_cast<int>(start.size()) - 1;
  const int* outer = A.outerIndexPtr();
  const double* val = A.valuePtr();
  std::vector<double> norm(nbr.size(), 0.0);
  for (int i = 0; i < n; ++i)
    for (int k = start[i]; k < start[i + 1]; ++k) {
      double s = 0.0;
      for (int r = 0; r < bs; ++r)
        for (int c = 0; c < bs; ++c) {
          const double v = val[outer[bs * i + r] + bs * (k - start[i]) + c];
          s += v * v;
        }
      norm[k] = std::sqrt(s);
    }
  std::vector<double> free;
  coupledRows(A, free);
  std::vector<char> fixed(static_cast<size_t>(n), 1);
  for (int i = 0; i < n; ++i)
    for (int r = 0; r < bs; ++r)
      if (free[bs * i + r] != 0.0) fixed[i] = 0;
  auto strong = [&](int i, int k) {
    const int j = nbr[k];
    return j != i && !fixed[j] && norm[k] > 0.0 && norm[k] > theta * std::sqrt(norm[diag[i] + start[i]] * norm[diag[j] + start[j]]);
  };
  std::vector<int> agg(static_cast<size_t>(n), -1);
  int c = 0;
  // Phase 1: a node whose strong neighbourhood is untouched roots an aggregate of it.
  for (int i = 0; i < n; ++i) {
    if (fixed[i] || agg[i] >= 0) continue;
    bool any = false, clear = true;
    for (int k = start[i]; k < start[i + 1] && clear; ++k)
      if (strong(i, k)) any = true, clear = agg[nbr[k]] < 0;
    if (!any || !clear) continue;
    agg[i] = c;
    for (int k = start[i]; k < start[i + 1]; ++k)
      if (strong(i, k)) agg[nbr[k]] = c;
    ++c;
  }
  // Phase 2: left-over nodes join the phase-1 aggregate they are most strongly connected to.
  const std::vector<int> first = agg;
  for (int i = 0; i < n; ++i) {
    if (fixed[i] || agg[i] >= 0) continue;
    double best = 0.0;
    for (int k = start[i]; k < start[i + 1]; ++k)
      if (strong(i, k) && first[nbr[k]] >= 0 && norm[k] > best) best = norm[k], agg[i] = first[nbr[k]];
  }
  // Phase 3: what is left forms aggregates with its still free strong neighbours.
  for (int i = 0; i < n; ++i) {
    if (fixed[i] || agg[i] >= 0) continue;
    agg[i] = c;
    for (int k = start[i]; k < start[i + 1]; ++k)
      if (strong(i, k) && agg[nbr[k]] < 0) agg[nbr[k]] = c;
    ++c;
  }
  if (count) *count = c;
  return agg;
}

Eigen::MatrixXd rigidBodyModes(const Points& x) {
  const Eigen::Index n = x.rows();
  Eigen::MatrixXd B = Eigen::MatrixXd::Zero(3 * n, kC);
  if (n == 0) return B;
  const Eigen::RowVector3d centre = x.colwise().mean();
  double rms = std::sqrt((x.rowwise() - centre).rowwise().squaredNorm().mean());
  if (!(rms > 0.0)) rms = 1.0;
  for (Eigen::Index i = 0; i < n; ++i) {
    const Eigen::RowVector3d p = (x.row(i) - centre) / rms;
    for (int a = 0; a < 3; ++a) B(3 * i + a, a) = 1.0;
    // ω × p for ω = e_x, e_y, e_z
    B(3 * i + 1, 3) = -p.z(), B(3 * i + 2, 3) = p.y();
    B(3 * i + 0, 4) = p.z(), B(3 * i + 2, 4) = -p.x();
    B(3 * i + 0, 5) = -p.y(), B(3 * i + 1, 5) = p.x();
  }
  return B;
}

BlockProlongator tentativeProlongator(const std::vector<int>& aggregate, int num_aggregates, int block_size,
                                      const Eigen::MatrixXd& B, Eigen::MatrixXd* B_coarse) {
  const int n = static_cast<int>(aggregate.size()), bs = block_size;
  if (bs < 1 || B.rows() != static_cast<Eigen::Index>(bs) * n || B.cols() != kC || num_aggregates < 0)
    throw std::invalid_argument("tentativeProlongator: B is " + std::to_string(B.rows()) + "×" +
                                std::to_string(B.cols()) + ", expected " + std::to_string(bs * n) + "×6 (block size " +
                                std::to_string(bs) + ", " + std::to_string(n) + " nodes)");
  std::vector<int> first(static_cast<size_t>(num_aggregates) + 1, 0), members(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) {
    if (aggregate[i] >= num_aggregates || aggregate[i] < -1)
      throw std::invalid_argument("tentativeProlongator: node " + std::to_string(i) + " has aggregate " +
                                  std::to_string(aggregate[i]) + ", expected −1 … " + std::to_string(num_aggregates - 1));
    if (aggregate[i] >= 0) ++first[aggregate[i] + 1];
  }
  for (int a = 0; a < num_aggregates; ++a) first[a + 1] += first[a];
  {
    std::vector<int> fill(first.begin(), first.end() - 1);
    for (int i = 0; i < n; ++i)
      if (aggregate[i] >= 0) members[fill[aggregate[i]]++] = i;
  }
  BlockProlongator P;
  P.fine_nodes = n, P.coarse_nodes = num_aggregates, P.fine_block = bs;
  P.start.assign(static_cast<size_t>(n) + 1, 0);
  for (int i = 0; i < n; ++i) P.start[i + 1] = P.start[i] + (aggregate[i] >= 0 ? 1 : 0);
  P.col.resize(static_cast<size_t>(P.start[n]));
  P.val.assign(static_cast<size_t>(P.start[n]) * bs * kC, 0.0);
  for (int i = 0; i < n; ++i)
    if (aggregate[i] >= 0) P.col[P.start[i]] = aggregate[i];
  Eigen::MatrixXd Bc = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(kC) * num_aggregates, kC);
#pragma omp parallel if (num_aggregates > 64)
  {
    Eigen::MatrixXd Q;
#pragma omp for schedule(dynamic, 16)
    for (int a = 0; a < num_aggregates; ++a) {
      const int m = bs * (first[a + 1] - first[a]);
      Q.resize(m, kC);
      for (int p = first[a]; p < first[a + 1]; ++p)
        Q.middleRows(static_cast<Eigen::Index>(bs) * (p - first[a]), bs) = B.middleRows(static_cast<Eigen::Index>(bs) * members[p], bs);
      Eigen::Matrix<double, kC, kC> R = Eigen::Matrix<double, kC, kC>::Zero();
      // Modified Gram–Schmidt, twice ("twice is enough"), dropping numerically dependent modes.
      for (int j = 0; j < kC; ++j) {
        const double norm0 = Q.col(j).norm();
        for (int pass = 0; pass < 2; ++pass)
          for (int k = 0; k < j; ++k) {
            if (R(k, k) == 0.0) continue;
            const double r = Q.col(k).dot(Q.col(j));
            Q.col(j) -= r * Q.col(k);
            R(k, j) += r;
          }
        const double nj = Q.col(j).norm();
        if (norm0 > 0.0 && nj > 1e-10 * norm0) {
          Q.col(j) /= nj;
          R(j, j) = nj;
        } else {
          Q.col(j).setZero();
          R(j, j) = 0.0;
        }
      }
      for (int p = first[a]; p < first[a + 1]; ++p) {
        double* out = P.val.data() + static_cast<size_t>(P.start[members[p]]) * bs * kC;
        for (int r = 0; r < bs; ++r)
          for (int c = 0; c < kC; ++c) out[r * kC + c] = Q(static_cast<Eigen::Index>(bs) * (p - first[a]) + r, c);
      }
      Bc.middleRows(static_cast<Eigen::Index>(kC) * a, kC) = R;
    }
  }
  if (B_coarse) *B_coarse = std::move(Bc);
  return P;
}

}  // namespace breast_sim::core
