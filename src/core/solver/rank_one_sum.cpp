// Rank-one sums: the product and diagonal the solvers use in place of an assembled matrix, the
// assembled matrix as their slow reference, and the Galerkin image a coarse level is built from.
#include "breast_sim/core/solver/rank_one_sum.h"

#include <algorithm>
#include <stdexcept>
#include <string>

#include <omp.h>

namespace breast_sim::core {

namespace {

// Sums of fewer terms than this run on one thread: handing a region to the second thread costs more
// than it saves (the limit of kParallelMinBlocks in multigrid_detail.h for a term per node).
constexpr int kParallelMinTerms = 200;

inline double mask(const double* free, int dof) { return free ? free[dof] : 1.0; }

}  // namespace

RankOneSum withMaskApplied(const RankOneSum& R, std::vector<double>& storage) {
  RankOneSum M = R;
  const int entries = R.entries();
  storage.resize(6 * static_cast<size_t>(entries));
  double* by_term = storage.data();
  double* by_node = storage.data() + 3 * static_cast<size_t>(entries);
  const double* free = R.free;
#pragma omp parallel for schedule(static) if (R.terms > kParallelMinTerms)
  for (int k = 0; k < entries; ++k) {
    const int a = 3 * R.entry_node[k];
    for (int c = 0; c < 3; ++c) by_term[3 * static_cast<size_t>(k) + c] = mask(free, a + c) * R.entry_vector[3 * static_cast<size_t>(k) + c];
  }
#pragma omp parallel for schedule(static) if (R.terms > kParallelMinTerms)
  for (int a = 0; a < R.nodes; ++a)
    for (int j = R.node_start[a]; j < R.node_start[a + 1]; ++j)
      for (int c = 0; c < 3; ++c) by_node[3 * static_cast<size_t>(j) + c] = by_term[3 * static_cast<size_t>(R.node_entry[j]) + c];
  M.entry_vector = by_term;
  M.node_vector = by_node;
  M.free = nullptr;
  return M;
}

double addRankOneProduct(const RankOneSum& R, const double* x, double alpha, double* y, double* workspace) {
  if (R.empty()) return 0.0;
  const double* free = R.free;
  const double s = R.scale;
  double* t = workspace;
  // Pass 1: t_r = s w_r b_rᵀ D x.
#pragma omp parallel for schedule(static) if (R.terms > kParallelMinTerms)
  for (int r = 0; r < R.terms; ++r) {
    double dotp = 0.0;
    const int k1 = R.term_start[r + 1];
    if (free) {
      for (int k = R.term_start[r]; k < k1; ++k) {
        const int a = 3 * R.entry_node[k];
        const double* b = R.entry_vector + 3 * static_cast<size_t>(k);
        dotp += free[a] * b[0] * x[a] + free[a + 1] * b[1] * x[a + 1] + free[a + 2] * b[2] * x[a + 2];
      }
    } else {
      for (int k = R.term_start[r]; k < k1; ++k) {
        const int a = 3 * R.entry_node[k];
        const double* b = R.entry_vector + 3 * static_cast<size_t>(k);
        dotp += b[0] * x[a] + b[1] * x[a + 1] + b[2] * x[a + 2];
      }
    }
    t[r] = s * R.weight[r] * dotp;
  }
  // xᵀ R x = Σ_r t_r b_rᵀ D x = Σ_r s w_r (b_rᵀ D x)², summed in term order.
  double quadratic = 0.0;
  for (int r = 0; r < R.terms; ++r) {
    const double w = s * R.weight[r];
    if (w > 0.0) quadratic += t[r] * t[r] / w;
  }
  // Pass 2: y_a += alpha D_a Σ_r t_r b_r[a], gathered per node.
#pragma omp parallel for schedule(static) if (R.terms > kParallelMinTerms)
  for (int a = 0; a < R.nodes; ++a) {
    double y0 = 0.0, y1 = 0.0, y2 = 0.0;
    if (R.node_vector) {
      for (int j = R.node_start[a]; j < R.node_start[a + 1]; ++j) {
        const double tr = t[R.node_term[j]];
        const double* b = R.node_vector + 3 * static_cast<size_t>(j);
        y0 += tr * b[0], y1 += tr * b[1], y2 += tr * b[2];
      }
    } else {
      for (int j = R.node_start[a]; j < R.node_start[a + 1]; ++j) {
        const double tr = t[R.node_term[j]];
        const double* b = R.entry_vector + 3 * static_cast<size_t>(R.node_entry[j]);
        y0 += tr * b[0], y1 += tr * b[1], y2 += tr * b[2];
      }
    }
    if (free) y0 *= free[3 * a], y1 *= free[3 * a + 1], y2 *= free[3 * a + 2];
    y[3 * a] += alpha * y0;
    y[3 * a + 1] += alpha * y1;
    y[3 * a + 2] += alpha * y2;
  }
  return alpha * quadratic;
}

void addRankOneDiagonal(const RankOneSum& R, double* blocks) {
  if (R.empty()) return;
  const double* free = R.free;
#pragma omp parallel for schedule(static) if (R.terms > kParallelMinTerms)
  for (int a = 0; a < R.nodes; ++a) {
    double d[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int j = R.node_start[a]; j < R.node_start[a + 1]; ++j) {
      const double w = R.scale * R.weight[R.node_term[j]];
      const double* b = R.entry_vector + 3 * static_cast<size_t>(R.node_entry[j]);
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) d[3 * r + c] += w * b[r] * b[c];
    }
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) blocks[9 * static_cast<size_t>(a) + 3 * r + c] += mask(free, 3 * a + r) * mask(free, 3 * a + c) * d[3 * r + c];
  }
}

SparseMatrix rankOneMatrix(const RankOneSum& R) {
  std::vector<Eigen::Triplet<double>> triplets;
  for (int r = 0; r < R.terms; ++r) {
    const double w = R.scale * R.weight[r];
    for (int k1 = R.term_start[r]; k1 < R.term_start[r + 1]; ++k1)
      for (int k2 = R.term_start[r]; k2 < R.term_start[r + 1]; ++k2)
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) {
            const int row = 3 * R.entry_node[k1] + i, col = 3 * R.entry_node[k2] + j;
            triplets.emplace_back(row, col, w * mask(R.free, row) * R.entry_vector[3 * k1 + i] *
                                                mask(R.free, col) * R.entry_vector[3 * k2 + j]);
          }
  }
  SparseMatrix M(3 * R.nodes, 3 * R.nodes);
  M.setFromTriplets(triplets.begin(), triplets.end());
  M.makeCompressed();
  return M;
}

// ---------------------------------------------------------------------------------------------------

void RankOneGalerkin::analyze(const RankOneSum& R, const RankOneProlongation& P) {
  if (P.rows() != R.nodes)
    throw std::invalid_argument("RankOneGalerkin: the prolongation has " + std::to_string(P.rows()) +
                                " fine nodes, the rank-one sum " + std::to_string(R.nodes));
  P_ = P;
  P_.makeCompressed();
  terms_ = R.terms;
  entries_ = R.entries();
  coarse_nodes_ = static_cast<int>(P_.cols());
  const int* pout = P_.outerIndexPtr();
  const int* pin = P_.innerIndexPtr();

  // Supports S(r) and where each prolongation entry of each term entry lands in S(r).
  supp_start_.assign(1, 0);
  supp_node_.clear();
  map_start_.assign(1, 0);
  map_p_.clear();
  map_local_.clear();
  std::vector<int> stamp(static_cast<size_t>(coarse_nodes_), -1), local(static_cast<size_t>(coarse_nodes_), 0), S;
  for (int r = 0; r < terms_; ++r) {
    S.clear();
    for (int k = R.term_start[r]; k < R.term_start[r + 1]; ++k) {
      const int a = R.entry_node[k];
      for (int p = pout[a]; p < pout[a + 1]; ++p)
        if (stamp[pin[p]] != r) {
          stamp[pin[p]] = r;
          S.push_back(pin[p]);
        }
    }
    std::sort(S.begin(), S.end());
    for (size_t q = 0; q < S.size(); ++q) local[S[q]] = static_cast<int>(q);
    for (int k = R.term_start[r]; k < R.term_start[r + 1]; ++k) {
      const int a = R.entry_node[k];
      for (int p = pout[a]; p < pout[a + 1]; ++p) {
        map_p_.push_back(p);
        map_local_.push_back(local[pin[p]]);
      }
      map_start_.push_back(static_cast<int>(map_p_.size()));
    }
    supp_node_.insert(supp_node_.end(), S.begin(), S.end());
    supp_start_.push_back(static_cast<int>(supp_node_.size()));
  }

  // Per coarse node: the terms holding it, in term order.
  coarse_start_.assign(static_cast<size_t>(coarse_nodes_) + 1, 0);
  for (int I : supp_node_) ++coarse_start_[I + 1];
  for (int I = 0; I < coarse_nodes_; ++I) coarse_start_[I + 1] += coarse_start_[I];
  coarse_term_.resize(supp_node_.size());
  coarse_local_.resize(supp_node_.size());
  {
    std::vector<int> fill(coarse_start_.begin(), coarse_start_.end() - 1);
    for (int r = 0; r < terms_; ++r)
      for (int q = supp_start_[r]; q < supp_start_[r + 1]; ++q) {
        const int I = supp_node_[q];
        coarse_term_[fill[I]] = r;
        coarse_local_[fill[I]++] = q - supp_start_[r];
      }
  }

  // The image's block pattern: I couples to every node of every support holding I.
  pattern_start_.assign(1, 0);
  pattern_nodes_.clear();
  std::fill(stamp.begin(), stamp.end(), -1);
  std::vector<int> row;
  for (int I = 0; I < coarse_nodes_; ++I) {
    row.clear();
    stamp[I] = I;
    row.push_back(I);
    for (int m = coarse_start_[I]; m < coarse_start_[I + 1]; ++m) {
      const int r = coarse_term_[m];
      for (int q = supp_start_[r]; q < supp_start_[r + 1]; ++q)
        if (stamp[supp_node_[q]] != I) {
          stamp[supp_node_[q]] = I;
          row.push_back(supp_node_[q]);
        }
    }
    std::sort(row.begin(), row.end());
    pattern_nodes_.insert(pattern_nodes_.end(), row.begin(), row.end());
    pattern_start_.push_back(static_cast<int>(pattern_nodes_.size()));
  }
  c_.assign(3 * supp_node_.size(), 0.0);
  slot_maps_.clear();  // add() makes them for this pattern and the thread count it runs on
}

void RankOneGalerkin::add(const RankOneSum& R, SparseMatrix& coarse) {
  if (supp_start_.empty()) throw std::logic_error("RankOneGalerkin: add() before analyze()");
  if (R.terms != terms_ || R.entries() != entries_ || coarse.rows() != 3 * coarse_nodes_)
    throw std::logic_error("RankOneGalerkin: add() with a rank-one sum or coarse matrix other than the analysed one");
  if (R.empty()) return;
  const double* pval = P_.valuePtr();
  const double* free = R.free;
  // c_r = Pᵀ D b_r on S(r).
#pragma omp parallel for schedule(static) if (terms_ > kParallelMinTerms)
  for (int r = 0; r < terms_; ++r) {
    double* c = c_.data() + 3 * static_cast<size_t>(supp_start_[r]);
    std::fill(c, c + 3 * (supp_start_[r + 1] - supp_start_[r]), 0.0);
    for (int k = R.term_start[r]; k < R.term_start[r + 1]; ++k) {
      const int a = 3 * R.entry_node[k];
      const double* b = R.entry_vector + 3 * static_cast<size_t>(k);
      const double b0 = mask(free, a) * b[0], b1 = mask(free, a + 1) * b[1], b2 = mask(free, a + 2) * b[2];
      for (int m = map_start_[k]; m < map_start_[k + 1]; ++m) {
        const double w = pval[map_p_[m]];
        double* cq = c + 3 * map_local_[m];
        cq[0] += w * b0, cq[1] += w * b1, cq[2] += w * b2;
      }
    }
  }
  // Row I of the image: Σ_{r ∋ I} s w_r c_r[I] c_rᵀ, one task per row.
  const int* cout = coarse.outerIndexPtr();
  const int* cin = coarse.innerIndexPtr();
  double* cval = coarse.valuePtr();
  int missing = -1;
  // One slot map per thread of the caller's current count (the first call after analyze() makes them).
  const int threads = std::max(1, omp_get_max_threads());
  if (slot_maps_.size() < static_cast<size_t>(threads))
    slot_maps_.resize(static_cast<size_t>(threads), std::vector<int>(static_cast<size_t>(coarse_nodes_), -1));
#pragma omp parallel num_threads(threads) if (terms_ > kParallelMinTerms)
  {
    std::vector<int>& slot = slot_maps_[omp_get_thread_num()];
#pragma omp for schedule(dynamic, 32)
    for (int I = 0; I < coarse_nodes_; ++I) {
      const int len = cout[3 * I + 1] - cout[3 * I];
      for (int q = 0; q < len / 3; ++q) slot[cin[cout[3 * I] + 3 * q] / 3] = q;
      double* r0 = cval + cout[3 * I];
      double* r1 = cval + cout[3 * I + 1];
      double* r2 = cval + cout[3 * I + 2];
      for (int m = coarse_start_[I]; m < coarse_start_[I + 1]; ++m) {
        const int r = coarse_term_[m];
        const double w = R.scale * R.weight[r];
        const double* c = c_.data() + 3 * static_cast<size_t>(supp_start_[r]);
        const double* ci = c + 3 * coarse_local_[m];
        const double u0 = w * ci[0], u1 = w * ci[1], u2 = w * ci[2];
        for (int q = supp_start_[r]; q < supp_start_[r + 1]; ++q) {
          const int s = slot[supp_node_[q]];
          if (s < 0) {
#pragma omp critical(rank_one_galerkin_missing)
            missing = I;
            continue;
          }
          const double* cj = c + 3 * (q - supp_start_[r]);
          const int o = 3 * s;
          r0[o] += u0 * cj[0], r0[o + 1] += u0 * cj[1], r0[o + 2] += u0 * cj[2];
          r1[o] += u1 * cj[0], r1[o + 1] += u1 * cj[1], r1[o + 2] += u1 * cj[2];
          r2[o] += u2 * cj[0], r2[o + 1] += u2 * cj[1], r2[o + 2] += u2 * cj[2];
        }
      }
      for (int q = 0; q < len / 3; ++q) slot[cin[cout[3 * I] + 3 * q] / 3] = -1;
    }
  }
  if (missing >= 0)
    throw std::invalid_argument("RankOneGalerkin: the coarse matrix has no block for the image's coupling of coarse node " +
                                std::to_string(missing) + "; analyse the coarse pattern with patternStart()/patternNodes()");
}


// ---------------------------------------------------------------------------------------------------
// The solver interfaces' defaults: solvers that need the assembled matrix.

void LinearSolver::analyzeWithRankOne(const SparseMatrix&, const RankOneSum&) {
  throw std::logic_error(name() + ": takes no rank-one sum beside the matrix; assemble the whole matrix");
}

void LinearSolver::factorizeWithRankOne(const SparseMatrix&, const RankOneSum&) {
  throw std::logic_error(name() + ": takes no rank-one sum beside the matrix; assemble the whole matrix");
}

}  // namespace breast_sim::core
