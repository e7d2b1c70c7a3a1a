// The check of the 3×3-block layout that the Galerkin product and the V-cycle rely on, and the
// Galerkin product [GW10] itself.
#include <algorithm>
#include <sstream>
#include <stdexcept>

#include <omp.h>

#include "multigrid_detail.h"

namespace breast_sim::core {

namespace multigrid_detail {

// Checks the 3×3-block layout of fem/block_pattern.h and returns the neighbour lists
// (block columns) of every node: start (N + 1) and node indices.
void blockGraph(const SparseMatrix& A, const std::string& who, std::vector<int>& start, std::vector<int>& nbr,
                std::vector<int>* diag_block) {
  auto fail = [&](const std::string& what) {
    throw std::invalid_argument(who + ": the matrix is not in 3×3-block layout (fem/block_pattern.h): " + what);
  };
  if (A.rows() != A.cols() || A.rows() % 3 != 0) fail("size " + std::to_string(A.rows()) + "×" + std::to_string(A.cols()));
  if (!A.isCompressed()) fail("it is not compressed (call makeCompressed())");
  const int n = static_cast<int>(A.rows() / 3);
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  start.assign(static_cast<size_t>(n) + 1, 0);
  nbr.clear();
  nbr.reserve(static_cast<size_t>(A.nonZeros() / 9));
  if (diag_block) diag_block->assign(static_cast<size_t>(n), -1);
  for (int i = 0; i < n; ++i) {
    const int len = outer[3 * i + 1] - outer[3 * i];
    if (len % 3 != 0 || outer[3 * i + 2] - outer[3 * i + 1] != len || outer[3 * i + 3] - outer[3 * i + 2] != len)
      fail("rows of node " + std::to_string(i) + " differ in length or are not whole blocks");
    int last = -1;
    for (int k = 0; k < len / 3; ++k) {
      const int c0 = inner[outer[3 * i] + 3 * k];
      if (c0 % 3 != 0 || c0 / 3 <= last) fail("block " + std::to_string(k) + " of node " + std::to_string(i));
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          if (inner[outer[3 * i + r] + 3 * k + c] != c0 + c)
            fail("block " + std::to_string(k) + " of node " + std::to_string(i) + ", row " + std::to_string(r));
      last = c0 / 3;
      if (last == i && diag_block) (*diag_block)[i] = k;
      nbr.push_back(last);
    }
    if (diag_block && (*diag_block)[i] < 0) fail("node " + std::to_string(i) + " has no diagonal block");
    start[i + 1] = static_cast<int>(nbr.size());
  }
}

}  // namespace multigrid_detail

using multigrid_detail::blockGraph;

namespace {
// Galerkin products over fewer fine nodes than this run on one thread. Each fine block meets every
// pair of its nodes' coarse parents (about 16 products of 3×3 blocks), so the product pays for the
// team's wake-up at far smaller levels than a sweep does (multigrid_detail::kParallelMinBlocks).
constexpr int kGalerkinParallelMinNodes = 400;
}  // namespace

// ---------------------------------------------------------------------------------------------------
// Galerkin product [GW10]: A_c row I = Σ_{i child of I} w_iI · (row i of A) · P. Each coarse row is
// one task: the rows of A of its children are summed into a small dense buffer over the fine nodes
// they touch (C = Pᵀ A restricted to row I), which is then multiplied by P into A_c's row I. No
// intermediate matrix is stored and no two tasks write the same memory.

void GalerkinProduct::analyze(const SparseMatrix& A, const NodeProlongation& P, const std::vector<int>* extra_start,
                              const std::vector<int>* extra_nodes) {
  const std::string who = "GalerkinProduct";
  if (A.rows() != 3 * P.rows()) {
    std::ostringstream s;
    s << who << ": the matrix has " << A.rows() << " rows, the prolongation " << P.rows() << " fine nodes (×3 = "
      << 3 * P.rows() << ")";
    throw std::invalid_argument(s.str());
  }
  std::vector<int> nbr_start, nbr;
  blockGraph(A, who, nbr_start, nbr, nullptr);
  if (extra_start && (!extra_nodes || static_cast<Eigen::Index>(extra_start->size()) != P.cols() + 1))
    throw std::invalid_argument(who + ": the extra coarse pattern has " +
                                std::to_string(extra_start ? extra_start->size() : 0) + " row starts for " +
                                std::to_string(P.cols()) + " coarse nodes (+1)");
  P_ = P;
  P_.makeCompressed();
  const int nf = static_cast<int>(P_.rows()), nc = static_cast<int>(P_.cols());
  const int* pout = P_.outerIndexPtr();
  const int* pin = P_.innerIndexPtr();
  const double* pval = P_.valuePtr();

  // Pᵀ: children of every coarse node.
  child_start_.assign(static_cast<size_t>(nc) + 1, 0);
  for (int k = 0; k < P_.nonZeros(); ++k) ++child_start_[pin[k] + 1];
  for (int I = 0; I < nc; ++I) child_start_[I + 1] += child_start_[I];
  child_.resize(static_cast<size_t>(P_.nonZeros()));
  child_weight_.resize(child_.size());
  {
    std::vector<int> fill(child_start_.begin(), child_start_.end() - 1);
    for (int i = 0; i < nf; ++i)
      for (int k = pout[i]; k < pout[i + 1]; ++k) {
        child_[fill[pin[k]]] = i;
        child_weight_[fill[pin[k]]++] = pval[k];
      }
  }

  fine_start_.assign(1, 0);
  fine_.clear();
  c_start_.assign(1, 0);
  c_slot_.clear();
  g_count_.clear();
  g_start_.assign(1, 0);
  g_weight_.clear();
  g_slot_.clear();
  diag_k_.assign(static_cast<size_t>(nc), 0);
  std::vector<int> fine_stamp(static_cast<size_t>(nf), -1), fine_local(static_cast<size_t>(nf), 0);
  std::vector<int> coarse_stamp(static_cast<size_t>(nc), -1), coarse_local(static_cast<size_t>(nc), 0);
  std::vector<int> cols, G;
  std::vector<int> coarse_start(1, 0), coarse_cols;  // block pattern of A_c
  max_fine_ = 0;
  for (int I = 0; I < nc; ++I) {
    // F(I): the fine nodes coupled to I's children, ascending.
    cols.clear();
    for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch)
      for (int k = nbr_start[child_[ch]]; k < nbr_start[child_[ch] + 1]; ++k)
        if (fine_stamp[nbr[k]] != I) {
          fine_stamp[nbr[k]] = I;
          cols.push_back(nbr[k]);
        }
    std::sort(cols.begin(), cols.end());
    for (size_t s = 0; s < cols.size(); ++s) fine_local[cols[s]] = static_cast<int>(s);
    fine_.insert(fine_.end(), cols.begin(), cols.end());
    fine_start_.push_back(static_cast<int>(fine_.size()));
    max_fine_ = std::max(max_fine_, static_cast<int>(cols.size()));
    for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch)
      for (int k = nbr_start[child_[ch]]; k < nbr_start[child_[ch] + 1]; ++k) c_slot_.push_back(fine_local[nbr[k]]);
    c_start_.push_back(static_cast<int>(c_slot_.size()));
    // G(I): the coarse parents of F(I), ascending = the block columns of A_c's row I.
    G.clear();
    for (int f : cols)
      for (int k = pout[f]; k < pout[f + 1]; ++k)
        if (coarse_stamp[pin[k]] != I) {
          coarse_stamp[pin[k]] = I;
          G.push_back(pin[k]);
        }
    if (coarse_stamp[I] != I) {  // keep a diagonal block even for a node without children
      coarse_stamp[I] = I;
      G.push_back(I);
    }
    if (extra_start)
      for (int k = (*extra_start)[I]; k < (*extra_start)[I + 1]; ++k)
        if (coarse_stamp[(*extra_nodes)[k]] != I) {
          coarse_stamp[(*extra_nodes)[k]] = I;
          G.push_back((*extra_nodes)[k]);
        }
    std::sort(G.begin(), G.end());
    for (size_t s = 0; s < G.size(); ++s) coarse_local[G[s]] = static_cast<int>(s);
    diag_k_[I] = coarse_local[I];
    for (int f : cols) {
      int count = 0;
      for (int k = pout[f]; k < pout[f + 1]; ++k)
        if (pin[k] >= I) {
          g_weight_.push_back(k);
          g_slot_.push_back(coarse_local[pin[k]]);
          ++count;
        }
      g_count_.push_back(static_cast<unsigned char>(count));
    }
    g_start_.push_back(static_cast<int>(g_slot_.size()));
    coarse_cols.insert(coarse_cols.end(), G.begin(), G.end());
    coarse_start.push_back(static_cast<int>(coarse_cols.size()));
  }

  // A_c in block layout: rows 3I + r hold columns 3J + c for J in G(I).
  coarse_ = SparseMatrix(3 * nc, 3 * nc);
  coarse_.resizeNonZeros(9 * static_cast<Eigen::Index>(coarse_cols.size()));
  int* cout = coarse_.outerIndexPtr();
  int* cin = coarse_.innerIndexPtr();
  cout[0] = 0;
  for (int I = 0; I < nc; ++I) {
    const int len = 3 * (coarse_start[I + 1] - coarse_start[I]);
    for (int r = 0; r < 3; ++r) {
      int* row = cin + cout[3 * I + r];
      for (int k = coarse_start[I]; k < coarse_start[I + 1]; ++k)
        for (int c = 0; c < 3; ++c) *row++ = 3 * coarse_cols[k] + c;
      cout[3 * I + r + 1] = cout[3 * I + r] + len;
    }
  }
  std::fill(coarse_.valuePtr(), coarse_.valuePtr() + coarse_.nonZeros(), 0.0);
  // Lower blocks (I, J < I) are copies of the transposed upper blocks (J, I).
  mirror_start_.assign(1, 0);
  mirror_dst_.clear();
  mirror_node_.clear();
  mirror_k_.clear();
  for (int I = 0; I < nc; ++I) {
    for (int k = coarse_start[I]; k < coarse_start[I] + diag_k_[I]; ++k) {
      const int J = coarse_cols[k];
      const auto first = coarse_cols.begin() + coarse_start[J], last = coarse_cols.begin() + coarse_start[J + 1];
      mirror_dst_.push_back(k - coarse_start[I]);
      mirror_node_.push_back(J);
      mirror_k_.push_back(static_cast<int>(std::lower_bound(first, last, I) - first));
    }
    mirror_start_.push_back(static_cast<int>(mirror_dst_.size()));
  }

  buffers_.clear();  // compute() sizes them for this pattern and the thread count it runs on
  fine_rows_ = A.rows();
  fine_nnz_ = A.nonZeros();
}

void GalerkinProduct::compute(const SparseMatrix& A, const double* free) {
  if (A.rows() != fine_rows_ || A.nonZeros() != fine_nnz_)
    throw std::logic_error("GalerkinProduct: compute() with a matrix of another pattern than analyze()");
  const int nc = static_cast<int>(P_.cols());
  const int* aout = A.outerIndexPtr();
  const double* aval = A.valuePtr();
  const double* pval = P_.valuePtr();
  const int* cout = coarse_.outerIndexPtr();
  double* cval = coarse_.valuePtr();
  // One buffer per thread of the caller's current count (the first call after analyze() makes them).
  const int threads = std::max(1, omp_get_max_threads());
  if (buffers_.size() < static_cast<size_t>(threads))
    buffers_.resize(static_cast<size_t>(threads), std::vector<double>(9 * static_cast<size_t>(std::max(max_fine_, 1))));
#pragma omp parallel num_threads(threads) if (P_.rows() > kGalerkinParallelMinNodes)
  {
    double* C = buffers_[omp_get_thread_num()].data();
#pragma omp for schedule(dynamic, 32)
    for (int I = 0; I < nc; ++I) {
      // C = row I of (D P)ᵀ A over the fine nodes F(I).
      const int nF = fine_start_[I + 1] - fine_start_[I];
      std::fill(C, C + 9 * nF, 0.0);
      int idx = c_start_[I];
      for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch) {
        const int i = child_[ch];
        const double w = child_weight_[ch];
        if (ch + 1 < child_start_[I + 1]) {
          // Children are scattered over A: fetch the next one's rows while this one is summed.
          const int next = 3 * child_[ch + 1];
          for (int r = 0; r < 3; ++r) {
            const double* row = aval + aout[next + r];
            __builtin_prefetch(row);
            __builtin_prefetch(row + 8);
            __builtin_prefetch(row + 16);
            __builtin_prefetch(row + 24);
            __builtin_prefetch(row + 32);
          }
        }
        const double m0 = free ? w * free[3 * i] : w;
        const double m1 = free ? w * free[3 * i + 1] : w;
        const double m2 = free ? w * free[3 * i + 2] : w;
        const double* a0 = aval + aout[3 * i];
        const double* a1 = aval + aout[3 * i + 1];
        const double* a2 = aval + aout[3 * i + 2];
        const int nb = (aout[3 * i + 1] - aout[3 * i]) / 3;
        if (m0 == 0.0 && m1 == 0.0 && m2 == 0.0) {  // a fixed node contributes nothing
          idx += nb;
          continue;
        }
        for (int k = 0; k < nb; ++k) {
          double* c = C + 9 * c_slot_[idx++];
          const int o = 3 * k;
          c[0] += m0 * a0[o], c[1] += m0 * a0[o + 1], c[2] += m0 * a0[o + 2];
          c[3] += m1 * a1[o], c[4] += m1 * a1[o + 1], c[5] += m1 * a1[o + 2];
          c[6] += m2 * a2[o], c[7] += m2 * a2[o + 1], c[8] += m2 * a2[o + 2];
        }
      }
      // Upper blocks of A_c row I = C · P.
      const int up = 3 * diag_k_[I];
      double* r0 = cval + cout[3 * I];
      double* r1 = cval + cout[3 * I + 1];
      double* r2 = cval + cout[3 * I + 2];
      const int len = cout[3 * I + 1] - cout[3 * I];
      std::fill(r0 + up, r0 + len, 0.0);
      std::fill(r1 + up, r1 + len, 0.0);
      std::fill(r2 + up, r2 + len, 0.0);
      int g = g_start_[I];
      const unsigned char* count = g_count_.data() + fine_start_[I];
      for (int s = 0; s < nF; ++s) {
        const double* c = C + 9 * s;
        for (int e = 0; e < count[s]; ++e, ++g) {
          const double w = pval[g_weight_[g]];
          const int o = 3 * g_slot_[g];
          r0[o] += w * c[0], r0[o + 1] += w * c[1], r0[o + 2] += w * c[2];
          r1[o] += w * c[3], r1[o + 1] += w * c[4], r1[o + 2] += w * c[5];
          r2[o] += w * c[6], r2[o + 1] += w * c[7], r2[o + 2] += w * c[8];
        }
      }
    }
    // Lower blocks: A_c(I, J) = A_c(J, I)ᵀ, after every upper block is done (the barrier above).
#pragma omp for schedule(static)
    for (int I = 0; I < nc; ++I)
      for (int m = mirror_start_[I]; m < mirror_start_[I + 1]; ++m) {
        const int o = 3 * mirror_dst_[m], J = mirror_node_[m], oj = 3 * mirror_k_[m];
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) cval[cout[3 * I + r] + o + c] = cval[cout[3 * J + c] + oj + r];
      }
  }
}

}  // namespace breast_sim::core
