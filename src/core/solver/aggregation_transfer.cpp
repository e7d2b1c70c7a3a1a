// The transfers of smoothed aggregation: the smoothed prolongator P = (I − ω_P D⁻¹A) P̂ with the
// pattern of the next level, and the Galerkin products A·P and Pᵀ(A P) in every factorize().
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "aggregation_detail.h"

namespace breast_sim::core {

using aggregation_detail::kC;
using aggregation_detail::kParallelMinNodes;

namespace {

// Pattern of A·P on the block level: per fine node i, the coarse nodes reached through its
// neighbours' prolongator rows (each once).
void productPattern(int nc, const std::vector<int>& a_start, const std::vector<int>& a_col, const BlockProlongator& P,
                    std::vector<int>& ap_start, std::vector<int>& ap_col) {
  const int n = static_cast<int>(a_start.size()) - 1;
  std::vector<int> marker(static_cast<size_t>(nc), -1);
  ap_start.assign(static_cast<size_t>(n) + 1, 0);
  ap_col.clear();
  for (int i = 0; i < n; ++i) {
    for (int k = a_start[i]; k < a_start[i + 1]; ++k) {
      const int j = a_col[k];
      for (int q = P.start[j]; q < P.start[j + 1]; ++q)
        if (marker[P.col[q]] != i) {
          marker[P.col[q]] = i;
          ap_col.push_back(P.col[q]);
        }
    }
    std::sort(ap_col.begin() + ap_start[i], ap_col.end());
    ap_start[i + 1] = static_cast<int>(ap_col.size());
  }
}

// Values of A·P (BS × 6 per entry, row-major) in the pattern of productPattern. A in BS×BS block
// layout (CSR), p_val the prolongator's values (BS × 6 per block).
template <int BS>
void productValues(const SparseMatrix& A, const std::vector<int>& a_start, const std::vector<int>& a_col, int nc,
                   const BlockProlongator& P, const double* p_val, const std::vector<int>& ap_start,
                   const std::vector<int>& ap_col, double* ap_val) {
  const int n = static_cast<int>(a_start.size()) - 1;
  const int* outer = A.outerIndexPtr();
  const double* aval = A.valuePtr();
#pragma omp parallel if (n > kParallelMinNodes)
  {
    std::vector<int> marker(static_cast<size_t>(nc), -1);
#pragma omp for schedule(static)
    for (int i = 0; i < n; ++i) {
      const int e0 = ap_start[i], e1 = ap_start[i + 1];
      for (int e = e0; e < e1; ++e) marker[ap_col[e]] = e;
      std::fill(ap_val + static_cast<size_t>(e0) * BS * kC, ap_val + static_cast<size_t>(e1) * BS * kC, 0.0);
      const double* row[BS];
      for (int r = 0; r < BS; ++r) row[r] = aval + outer[BS * i + r];
      for (int k = a_start[i]; k < a_start[i + 1]; ++k) {
        const int j = a_col[k], off = BS * (k - a_start[i]);
        double a[BS][BS];
        for (int r = 0; r < BS; ++r)
          for (int c = 0; c < BS; ++c) a[r][c] = row[r][off + c];
        for (int q = P.start[j]; q < P.start[j + 1]; ++q) {
          const double* p = p_val + static_cast<size_t>(q) * BS * kC;
          double* out = ap_val + static_cast<size_t>(marker[P.col[q]]) * BS * kC;
          for (int r = 0; r < BS; ++r)
            for (int c = 0; c < BS; ++c) {
              const double arc = a[r][c];
              const double* pc = p + c * kC;
              double* o = out + r * kC;
              for (int m = 0; m < kC; ++m) o[m] += arc * pc[m];
            }
        }
      }
    }
  }
}

void productValues(int bs, const SparseMatrix& A, const std::vector<int>& a_start, const std::vector<int>& a_col,
                   int nc, const BlockProlongator& P, const double* p_val, const std::vector<int>& ap_start,
                   const std::vector<int>& ap_col, double* ap_val) {
  if (bs == 3) productValues<3>(A, a_start, a_col, nc, P, p_val, ap_start, ap_col, ap_val);
  else if (bs == kC) productValues<kC>(A, a_start, a_col, nc, P, p_val, ap_start, ap_col, ap_val);
  else throw std::logic_error("sa-multigrid: block size " + std::to_string(bs) + " is not 3 or 6");
}

}  // namespace

void AggregationMultigridPreconditioner::buildTransfer(int l, const Eigen::MatrixXd& B, Eigen::MatrixXd* B_coarse) {
  Level& lv = *levels_[l];
  const int bs = lv.bs;
  // Aggregates and the tentative prolongator from the masked near-null space.
  const double theta = options_.strength_threshold * std::pow(options_.strength_decay, l);
  int nc = 0;
  const std::vector<int> agg = aggregateNodes(*lv.A, bs, theta, &nc);
  Eigen::MatrixXd Bm = B;
  for (Eigen::Index r = 0; r < Bm.rows(); ++r)
    if (lv.free[r] == 0.0) Bm.row(r).setZero();
  BlockProlongator T = tentativeProlongator(agg, nc, bs, Bm, B_coarse);
  if (options_.smooth_prolongator) {
    // P = (I − ω_P D⁻¹ A) P̂: the pattern of A P̂ (it contains P̂'s own block).
    std::vector<int> s, c;
    productPattern(nc, lv.block_start, lv.block_col, T, s, c);
    std::vector<double> v(c.size() * static_cast<size_t>(bs) * kC);
    productValues(bs, *lv.A, lv.block_start, lv.block_col, nc, T, T.val.data(), s, c, v.data());
    const double w = options_.prolongator_damping / lv.lambda;
    BlockProlongator P;
    P.fine_nodes = T.fine_nodes, P.coarse_nodes = nc, P.fine_block = bs;
    P.start = std::move(s), P.col = std::move(c);
    P.val.assign(v.size(), 0.0);
    const int n = lv.nodes;
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
    for (int i = 0; i < n; ++i) {
      const double* d = lv.dinv.data() + static_cast<size_t>(i) * bs * bs;
      for (int e = P.start[i]; e < P.start[i + 1]; ++e) {
        const double* ap = v.data() + static_cast<size_t>(e) * bs * kC;
        double* out = P.val.data() + static_cast<size_t>(e) * bs * kC;
        for (int r = 0; r < bs; ++r)
          for (int m = 0; m < kC; ++m) {
            double s2 = 0.0;
            for (int k = 0; k < bs; ++k) s2 += d[r * bs + k] * ap[k * kC + m];
            out[r * kC + m] = -w * s2;
          }
        if (T.start[i + 1] > T.start[i] && T.col[T.start[i]] == P.col[e]) {
          const double* t = T.val.data() + static_cast<size_t>(T.start[i]) * bs * kC;
          for (int k = 0; k < bs * kC; ++k) out[k] += t[k];
        }
      }
    }
    lv.P = std::move(P);
  } else {
    lv.P = std::move(T);
  }
  // Pᵀ lists, the pattern of A·P, and the next level's pattern (the block union over children).
  const BlockProlongator& P = lv.P;
  lv.child_start.assign(static_cast<size_t>(nc) + 1, 0);
  for (int q = 0; q < static_cast<int>(P.col.size()); ++q) ++lv.child_start[P.col[q] + 1];
  for (int I = 0; I < nc; ++I) lv.child_start[I + 1] += lv.child_start[I];
  lv.child_node.resize(P.col.size());
  lv.child_block.resize(P.col.size());
  {
    std::vector<int> fill(lv.child_start.begin(), lv.child_start.end() - 1);
    for (int i = 0; i < lv.nodes; ++i)
      for (int q = P.start[i]; q < P.start[i + 1]; ++q) {
        const int k = fill[P.col[q]]++;
        lv.child_node[k] = i;
        lv.child_block[k] = q;
      }
  }
  productPattern(nc, lv.block_start, lv.block_col, P, lv.ap_start, lv.ap_col);
  lv.ap_val.resize(lv.ap_col.size() * static_cast<size_t>(bs) * kC);
  lv.pm.resize(P.val.size());

  auto next = std::make_unique<Level>();
  next->bs = kC;
  next->nodes = nc;
  std::vector<int> marker(static_cast<size_t>(nc), -1);
  next->block_start.assign(static_cast<size_t>(nc) + 1, 0);
  next->diag_block.assign(static_cast<size_t>(nc), -1);
  for (int J = 0; J < nc; ++J) {
    const size_t s0 = next->block_col.size();
    for (int k = lv.child_start[J]; k < lv.child_start[J + 1]; ++k) {
      const int i = lv.child_node[k];
      for (int e = lv.ap_start[i]; e < lv.ap_start[i + 1]; ++e)
        if (marker[lv.ap_col[e]] != J) {
          marker[lv.ap_col[e]] = J;
          next->block_col.push_back(lv.ap_col[e]);
        }
    }
    if (marker[J] != J) next->block_col.push_back(J);  // an aggregate with no free DOF still gets its diagonal
    std::sort(next->block_col.begin() + static_cast<std::ptrdiff_t>(s0), next->block_col.end());
    next->block_start[J + 1] = static_cast<int>(next->block_col.size());
    for (int s = next->block_start[J]; s < next->block_start[J + 1]; ++s)
      if (next->block_col[s] == J) next->diag_block[J] = s - next->block_start[J];
  }
  // The CSR matrix in 6×6 block layout.
  const int nb = static_cast<int>(next->block_col.size());
  SparseMatrix& C = next->owned;
  C.resize(static_cast<Eigen::Index>(kC) * nc, static_cast<Eigen::Index>(kC) * nc);
  C.resizeNonZeros(static_cast<Eigen::Index>(nb) * kC * kC);
  int* outer = C.outerIndexPtr();
  int* inner = C.innerIndexPtr();
  outer[0] = 0;
  for (int J = 0; J < nc; ++J) {
    const int len = kC * (next->block_start[J + 1] - next->block_start[J]);
    for (int a = 0; a < kC; ++a) {
      const int row = kC * J + a;
      outer[row + 1] = outer[row] + len;
      for (int s = next->block_start[J]; s < next->block_start[J + 1]; ++s)
        for (int b = 0; b < kC; ++b) inner[outer[row] + kC * (s - next->block_start[J]) + b] = kC * next->block_col[s] + b;
    }
  }
  std::fill(C.valuePtr(), C.valuePtr() + C.nonZeros(), 0.0);
  next->A = &next->owned;
  // Transposed block of every block (the pattern is symmetric).
  lv.mirror.assign(static_cast<size_t>(nb), -1);
  for (int J = 0; J < nc; ++J)
    for (int s = next->block_start[J]; s < next->block_start[J + 1]; ++s) {
      const int K = next->block_col[s];
      const auto b = next->block_col.begin();
      const auto it = std::lower_bound(b + next->block_start[K], b + next->block_start[K + 1], J);
      if (it == b + next->block_start[K + 1] || *it != J)
        throw std::logic_error("sa-multigrid: the Galerkin pattern is not symmetric");
      lv.mirror[s] = static_cast<int>(it - b) - next->block_start[K];
    }
  levels_.push_back(std::move(next));
}

void AggregationMultigridPreconditioner::galerkin(int l) {
  Level& lv = *levels_[l];
  Level& nx = *levels_[l + 1];
  const int bs = lv.bs, nc = nx.nodes;
  // Masked prolongator D P (decoupled fine DOFs never move), then A (D P) and (D P)ᵀ A (D P).
  const BlockProlongator& P = lv.P;
#pragma omp parallel for schedule(static) if (lv.nodes > kParallelMinNodes)
  for (int i = 0; i < lv.nodes; ++i)
    for (int q = P.start[i]; q < P.start[i + 1]; ++q)
      for (int r = 0; r < bs; ++r) {
        const double f = lv.free[bs * i + r];
        const size_t o = static_cast<size_t>(q) * bs * kC + r * kC;
        for (int m = 0; m < kC; ++m) lv.pm[o + m] = f * P.val[o + m];
      }
  productValues(bs, *lv.A, lv.block_start, lv.block_col, nc, P, lv.pm.data(), lv.ap_start, lv.ap_col,
                lv.ap_val.data());
  SparseMatrix& C = nx.owned;
  const int* cout = C.outerIndexPtr();
  double* cval = C.valuePtr();
#pragma omp parallel if (nc > kParallelMinNodes / 8)
  {
    std::vector<int> marker(static_cast<size_t>(nc), -1);
#pragma omp for schedule(dynamic, 8)
    for (int J = 0; J < nc; ++J) {
      for (int s = nx.block_start[J]; s < nx.block_start[J + 1]; ++s) marker[nx.block_col[s]] = s - nx.block_start[J];
      const int len = cout[kC * J + 1] - cout[kC * J];
      double* row[kC];
      for (int a = 0; a < kC; ++a) {
        row[a] = cval + cout[kC * J + a];
        std::fill(row[a], row[a] + len, 0.0);
      }
      for (int k = lv.child_start[J]; k < lv.child_start[J + 1]; ++k) {
        const int i = lv.child_node[k];
        const double* p = lv.pm.data() + static_cast<size_t>(lv.child_block[k]) * bs * kC;
        for (int e = lv.ap_start[i]; e < lv.ap_start[i + 1]; ++e) {
          const int K = lv.ap_col[e];
          if (K < J) continue;  // upper blocks only; the lower ones are mirrored
          const double* ap = lv.ap_val.data() + static_cast<size_t>(e) * bs * kC;
          const int o = kC * marker[K];
          double blk[kC][kC] = {};
          for (int r = 0; r < bs; ++r)
            for (int a = 0; a < kC; ++a) {
              const double pa = p[r * kC + a];
              if (pa == 0.0) continue;
              for (int b = 0; b < kC; ++b) blk[a][b] += pa * ap[r * kC + b];
            }
          for (int a = 0; a < kC; ++a)
            for (int b = 0; b < kC; ++b) row[a][o + b] += blk[a][b];
        }
      }
    }
#pragma omp for schedule(static)
    for (int J = 0; J < nc; ++J)
      for (int s = nx.block_start[J]; s < nx.block_start[J + 1]; ++s) {
        const int K = nx.block_col[s];
        if (K >= J) continue;
        const int o = kC * (s - nx.block_start[J]), ok = kC * lv.mirror[s];
        for (int a = 0; a < kC; ++a)
          for (int b = 0; b < kC; ++b) cval[cout[kC * J + a] + o + b] = cval[cout[kC * K + b] + ok + a];
      }
  }
}

}  // namespace breast_sim::core
