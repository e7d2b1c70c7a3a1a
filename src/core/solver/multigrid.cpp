// MultigridPreconditioner: the levels and their transfers (analyzePattern), the numeric update with
// the coarse renewal policy and the coarsest factorization (factorize, reportConvergence), and the
// V-cycle (apply). The smoothers are in multigrid_smoothers.cpp, the Galerkin product in
// multigrid_galerkin.cpp, the mesh hierarchy and its prolongations in multigrid_hierarchy.cpp.
#include "breast_sim/core/solver/multigrid.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "multigrid_detail.h"

namespace breast_sim::core {

using multigrid_detail::blockGraph;
using multigrid_detail::Clock;
using multigrid_detail::since;

// ---------------------------------------------------------------------------------------------------
// Levels and transfers

MultigridPreconditioner::MultigridPreconditioner(std::vector<NodeProlongation> prolongations,
                                                 MultigridOptions options)
    : options_(options), prolongations_(std::move(prolongations)) {
  for (auto& P : prolongations_) P.makeCompressed();
  for (size_t l = 0; l + 1 < prolongations_.size(); ++l)
    if (prolongations_[l].cols() != prolongations_[l + 1].rows())
      throw std::invalid_argument("multigrid: prolongation " + std::to_string(l) + " has " +
                                  std::to_string(prolongations_[l].cols()) + " coarse nodes, prolongation " +
                                  std::to_string(l + 1) + " " + std::to_string(prolongations_[l + 1].rows()) +
                                  " fine nodes");
  if (options_.pre_smoothing_steps < 0 || options_.post_smoothing_steps < 0 ||
      !(options_.jacobi_damping >= 0 && options_.jacobi_damping <= 1) || !(options_.coarsest_diagonal_shift >= 0) ||
      !(options_.fine_eigenvalue_bound >= 0) ||
      options_.coarse_update_interval < 1 || options_.power_iterations < 1 || options_.dense_coarsest_max_dofs < 0)
    throw std::invalid_argument(
        "multigrid: smoothing steps must be ≥ 0, the Jacobi damping in [0, 1], the coarsest shift and the "
        "eigenvalue bound ≥ 0, the coarse update interval and the power iterations ≥ 1, the dense coarsest size ≥ 0");
  if (!(options_.coarse_update_cost_iterations > 0.0) || !std::isfinite(options_.coarse_update_cost_iterations))
    throw std::invalid_argument("multigrid: coarse_update_cost_iterations = " +
                                std::to_string(options_.coarse_update_cost_iterations) +
                                " must be a finite number of PCG iterations > 0 (e.g. 5)");
  if (!(options_.chebyshev_ratio > 1.0) || !std::isfinite(options_.chebyshev_ratio) ||
      !(options_.chebyshev_eigenvalue_safety >= 1.0) || !std::isfinite(options_.chebyshev_eigenvalue_safety))
    throw std::invalid_argument("multigrid: chebyshev_ratio = " + std::to_string(options_.chebyshev_ratio) +
                                " must be > 1 (e.g. 10) and chebyshev_eigenvalue_safety = " +
                                std::to_string(options_.chebyshev_eigenvalue_safety) + " ≥ 1 (e.g. 1.1)");
}

MultigridPreconditioner::MultigridPreconditioner(const MeshHierarchy& hierarchy, MultigridOptions options)
    : MultigridPreconditioner(hierarchy.prolongations(), options) {}

MultigridPreconditioner::~MultigridPreconditioner() = default;

const SparseMatrix& MultigridPreconditioner::levelMatrix(int level) const {
  if (level < 0 || level >= numLevels() || !levels_[level]->A)
    throw std::out_of_range("multigrid: no matrix for level " + std::to_string(level) + " (factorize first)");
  return *levels_[level]->A;
}

double MultigridPreconditioner::jacobiDamping(int level) const { return levels_.at(level)->omega; }

double MultigridPreconditioner::chebyshevEigenvalueBound(int level) const {
  return options_.smoother == MultigridOptions::Smoother::kChebyshev ? levels_.at(level)->lambda_max : 0.0;
}

int MultigridPreconditioner::numColours(int level) const {
  return static_cast<int>(levels_.at(level)->colour_start.size()) - 1;
}

void MultigridPreconditioner::analyzePattern(const SparseMatrix& A) {
  rank_one_ = false;
  analyzeLevels(A, nullptr, nullptr);
}

bool MultigridPreconditioner::acceptsRankOneSum() const {
  return !prolongations_.empty() && options_.smoother != MultigridOptions::Smoother::kGaussSeidel;
}

void MultigridPreconditioner::analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  if (!acceptsRankOneSum())
    throw std::logic_error(prolongations_.empty()
                               ? "multigrid: a hierarchy of one level solves the assembled matrix directly; it takes no rank-one sum"
                               : "multigrid: the Gauss–Seidel smoother takes no rank-one sum (use jacobi or chebyshev)");
  if (3 * static_cast<Eigen::Index>(R.nodes) != S.rows())
    throw std::invalid_argument("multigrid: the rank-one sum has " + std::to_string(R.nodes) + " nodes, the matrix " +
                                std::to_string(S.rows()) + " rows");
  rank_one_ = false;
  rank_one_galerkin_.analyze(R, prolongations_[0]);
  analyzeLevels(S, &rank_one_galerkin_.patternStart(), &rank_one_galerkin_.patternNodes());
  rank_one_ = true;
  rank_one_terms_ = R.terms;
  rank_one_entries_ = R.entries();
  rank_one_diag_.assign(9 * static_cast<size_t>(R.nodes), 0.0);
  rank_one_work_.assign(static_cast<size_t>(std::max(R.terms, 1)), 0.0);
  rank_one_rhs_.setZero(S.rows());
}

void MultigridPreconditioner::analyzeLevels(const SparseMatrix& A, const std::vector<int>* extra_start,
                                            const std::vector<int>* extra_nodes) {
  const int L = static_cast<int>(prolongations_.size()) + 1;
  const Eigen::Index n0 = prolongations_.empty() ? A.rows() / 3 : prolongations_[0].rows();
  if (A.rows() != 3 * n0 || A.cols() != 3 * n0) {
    std::ostringstream s;
    s << "multigrid: the matrix is " << A.rows() << "×" << A.cols() << ", the hierarchy's fine level has " << n0
      << " nodes (" << 3 * n0 << " DOFs)";
    throw std::invalid_argument(s.str());
  }
  levels_.clear();
  factorized_ = false;
  galerkin_.assign(static_cast<size_t>(L - 1), GalerkinProduct());
  fine_nnz_ = -1;
  for (int l = 0; l < L; ++l) {
    auto lv = std::make_unique<Level>();
    if (l == 0) {
      lv->A = &A;
    } else {
      if (l == 1) galerkin_[0].analyze(*levels_[0]->A, prolongations_[0], extra_start, extra_nodes);
      else galerkin_[l - 1].analyze(*levels_[l - 1]->A, prolongations_[l - 1]);
      lv->owned = &galerkin_[l - 1].coarse();
      lv->A = lv->owned;
    }
    const SparseMatrix& M = *lv->A;
    std::vector<int> start, nbr;
    blockGraph(M, "multigrid level " + std::to_string(l), start, nbr, &lv->diag_block);
    const int n = static_cast<int>(M.rows() / 3);
    lv->nodes = n;
    lv->dinv.assign(9 * static_cast<size_t>(n), 0.0);
    lv->free.assign(3 * static_cast<size_t>(n), 1.0);
    lv->b.setZero(3 * n);
    lv->x.setZero(3 * n);
    lv->t.setZero(3 * n);
    if (options_.smoother == MultigridOptions::Smoother::kChebyshev && l + 1 < L) lv->d.setZero(3 * n);
    // Greedy colouring of the node graph: nodes of one colour share no block, so a Gauss–Seidel
    // sweep over one colour is a parallel Jacobi step over independent nodes.
    std::vector<int> colour(static_cast<size_t>(n), -1), seen;
    int colours = 0;
    for (int i = 0; i < n; ++i) {
      seen.assign(static_cast<size_t>(colours) + 1, 0);
      for (int k = start[i]; k < start[i + 1]; ++k)
        if (colour[nbr[k]] >= 0) seen[colour[nbr[k]]] = 1;
      int c = 0;
      while (seen[c]) ++c;
      colour[i] = c;
      colours = std::max(colours, c + 1);
    }
    lv->colour_start.assign(static_cast<size_t>(colours) + 1, 0);
    for (int i = 0; i < n; ++i) ++lv->colour_start[colour[i] + 1];
    for (int c = 0; c < colours; ++c) lv->colour_start[c + 1] += lv->colour_start[c];
    lv->colour_node.resize(static_cast<size_t>(n));
    std::vector<int> fill(lv->colour_start.begin(), lv->colour_start.end() - 1);
    for (int i = 0; i < n; ++i) lv->colour_node[fill[colour[i]]++] = i;
    lv->block_start = std::move(start);
    lv->block_col = std::move(nbr);
    if (l + 1 < L) {  // a smoothed level (the coarsest is solved directly as it is)
      lv->block_val.assign(9 * lv->block_col.size(), 0.0f);
      const NodeProlongation& P = prolongations_[l];
      const int nc = static_cast<int>(P.cols());
      lv->child_start.assign(static_cast<size_t>(nc) + 1, 0);
      for (int k = 0; k < P.nonZeros(); ++k) ++lv->child_start[P.innerIndexPtr()[k] + 1];
      for (int I = 0; I < nc; ++I) lv->child_start[I + 1] += lv->child_start[I];
      lv->child.resize(static_cast<size_t>(P.nonZeros()));
      lv->child_weight.resize(lv->child.size());
      std::vector<int> f(lv->child_start.begin(), lv->child_start.end() - 1);
      for (int i = 0; i < P.rows(); ++i)
        for (int k = P.outerIndexPtr()[i]; k < P.outerIndexPtr()[i + 1]; ++k) {
          const int I = P.innerIndexPtr()[k];
          lv->child[f[I]] = i;
          lv->child_weight[f[I]++] = P.valuePtr()[k];
        }
    }
    levels_.push_back(std::move(lv));
  }
  const Eigen::Index coarsest_dofs = levels_.back()->A->rows();
  dense_coarsest_ = L > 1 && coarsest_dofs <= options_.dense_coarsest_max_dofs;
  if (dense_coarsest_) {
    coarsest_dense_.setZero(coarsest_dofs, coarsest_dofs);
    coarsest_llt_ = Eigen::LLT<Eigen::MatrixXd>(coarsest_dofs);
  } else {
    coarsest_dense_.resize(0, 0);
    coarsest_.analyzePattern(*levels_.back()->A);
  }
  fine_nnz_ = A.nonZeros();
  fine_outer_.assign(A.outerIndexPtr(), A.outerIndexPtr() + A.rows() + 1);
  fine_only_ = 0;
  renew_requested_ = true;  // the first factorize() makes the coarse operators
  rate_count_ = 0;
  lost_iterations_ = 0.0;
  factorized_ = false;
}

// ---------------------------------------------------------------------------------------------------
// Numeric update and coarse renewal

void MultigridPreconditioner::factorize(const SparseMatrix& A) {
  if (rank_one_) throw std::logic_error("multigrid: analysed with a rank-one sum: call factorizeWithRankOne()");
  factorizeLevels(A);
}

bool MultigridPreconditioner::renew() {
  if (!factorized_ || numLevels() == 1 || fine_only_ == 0) return false;
  for (auto& lv : levels_) lv->eigenvector.resize(0);  // estimateDamping() starts cold
  renew_requested_ = true;
  factorizeLevels(*levels_[0]->A);
  return true;
}

void MultigridPreconditioner::factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  if (!rank_one_) throw std::logic_error("multigrid: factorizeWithRankOne() called without analyzeWithRankOne()");
  if (R.terms != rank_one_terms_ || R.entries() != rank_one_entries_ || 3 * static_cast<Eigen::Index>(R.nodes) != S.rows())
    throw std::logic_error("multigrid: the rank-one sum's structure changed since analyzeWithRankOne()");
  R_ = R;
  std::fill(rank_one_diag_.begin(), rank_one_diag_.end(), 0.0);
  addRankOneDiagonal(R_, rank_one_diag_.data());
  factorizeLevels(S);
}

void MultigridPreconditioner::factorizeLevels(const SparseMatrix& A) {
  if (fine_nnz_ < 0) throw std::logic_error("multigrid: factorize() called before analyzePattern()");
  // Same size, entry count and row lengths: the float blocks and the Galerkin index lists are laid
  // out over the analysed rows.
  if (A.rows() != levels_[0]->A->rows() || A.nonZeros() != fine_nnz_ ||
      !std::equal(fine_outer_.begin(), fine_outer_.end(), A.outerIndexPtr()))
    throw std::logic_error("multigrid: the matrix pattern changed since analyzePattern()");
  factorized_ = false;
  timings_.scan_s = timings_.damping_s = timings_.galerkin_s = timings_.coarse_factorize_s = 0.0;
  timings_.applications = 0;
  timings_.level_s.resize(levels_.size());  // allocates once
  std::fill(timings_.level_s.begin(), timings_.level_s.end(), 0.0);
  levels_[0]->A = &A;
  // Coarse renewal: at the first factorization (and after one that failed), after
  // coarse_update_interval − 1 fine-only ones, or early when the adaptive rule asked for it
  // (reportConvergence).
  const bool coarse = numLevels() == 1 || renew_requested_ || fine_only_ + 1 >= options_.coarse_update_interval;
  const int L = coarse ? numLevels() : 1;
  for (int l = 0; l < L; ++l) {
    auto t0 = Clock::now();
    if (l > 0) {
      galerkin_[l - 1].compute(*levels_[l - 1]->A, levels_[l - 1]->free.data());
      if (l == 1 && rank_one_) rank_one_galerkin_.add(R_, galerkin_[0].coarse());
      timings_.galerkin_s += since(t0);
      t0 = Clock::now();
    }
    // The coarsest level needs no smoother, only the unit diagonals of empty rows.
    scanLevel(l);
    if (l + 1 < numLevels()) toBlocks(l);
    timings_.scan_s += since(t0);
    if (coarse && options_.smoother != MultigridOptions::Smoother::kGaussSeidel && (l + 1 < numLevels() || l == 0)) {
      t0 = Clock::now();
      estimateDamping(l);
      timings_.damping_s += since(t0);
    }
  }
  if (!coarse) {
    ++fine_only_;
    factorized_ = true;
    return;
  }
  const auto t0 = Clock::now();
  Level& last = *levels_.back();
  if (last.owned && options_.coarsest_diagonal_shift > 0.0) {
    const int* outer = last.owned->outerIndexPtr();
    double* val = last.owned->valuePtr();
    for (int i = 0; i < last.nodes; ++i)
      for (int r = 0; r < 3; ++r) val[outer[3 * i + r] + 3 * last.diag_block[i] + r] *= 1.0 + options_.coarsest_diagonal_shift;
  }
  if (dense_coarsest_) {
    const SparseMatrix& C = *last.A;
    coarsest_dense_.setZero();
    for (Eigen::Index r = 0; r < C.rows(); ++r)
      for (int k = C.outerIndexPtr()[r]; k < C.outerIndexPtr()[r + 1]; ++k)
        coarsest_dense_(r, C.innerIndexPtr()[k]) = C.valuePtr()[k];
    coarsest_llt_.compute(coarsest_dense_);
    if (coarsest_llt_.info() != Eigen::Success)
      throw std::runtime_error("multigrid: coarsest level " + std::to_string(L - 1) + ": the " +
                               std::to_string(C.rows()) +
                               "-DOF Galerkin operator is not positive definite (dense Cholesky failed); check the "
                               "stiffness (inverted elements, negative moduli)");
  } else {
    try {
      coarsest_.factorize(*last.A);
    } catch (const std::runtime_error& e) {
      throw std::runtime_error("multigrid: coarsest level " + std::to_string(L - 1) + ": " + e.what());
    }
  }
  timings_.coarse_factorize_s = since(t0);
  ++coarse_renewals_;
  fine_only_ = 0;
  renew_requested_ = false;
  rate_count_ = 0;
  lost_iterations_ = 0.0;
  factorized_ = true;
}

Preconditioner::FloatBlocks MultigridPreconditioner::floatBlocks() const {
  if (!factorized_ || numLevels() < 2) return {};
  const Level& lv = *levels_[0];
  return {lv.block_val.data(), lv.block_col.data(), lv.block_start.data(), lv.nodes};
}

void MultigridPreconditioner::reportConvergence(int iterations, double residual_reduction) {
  if (!options_.coarse_update_adaptive || iterations < 1 || numLevels() == 1) return;
  if (!std::isfinite(residual_reduction)) {  // a broken solve: start afresh
    renew_requested_ = true;
    return;
  }
  if (residual_reduction == 0.0) return;  // solved exactly: nothing to measure
  const double cost = options_.coarse_update_cost_iterations;
  if (residual_reduction >= 1.0) {
    // CG's residual norm need not fall in every iteration: a capped solve of a few iterations can
    // end above its start with sound coarse operators. Its iterations count as lost.
    if (rate_count_ > 0) lost_iterations_ += iterations;
  } else {
    const double log_rate = std::log(residual_reduction) / iterations;  // < 0: log of the mean reduction per iteration
    if (rate_count_++ == 0) {
      first_log_rate_ = log_rate;  // the reference: fresh coarse operators
      lost_iterations_ = 0.0;
      return;
    }
    // At the reference rate the same reduction takes iterations · ρ/ρ_0 iterations: the rest was
    // lost. Faster solves give iterations back, at most one renewal's worth in all: a reference
    // taken at an unusually slow solve cannot bank credit that holds the renewal off for good.
    lost_iterations_ = std::max(-cost, lost_iterations_ + iterations * (1.0 - log_rate / first_log_rate_));
  }
  if (lost_iterations_ >= cost) renew_requested_ = true;
}

// ---------------------------------------------------------------------------------------------------
// V-cycle

void MultigridPreconditioner::vcycle(int l, const double* b, double* x) {
  auto t0 = Clock::now();
  Level& lv = *levels_[l];
  Level& next = *levels_[l + 1];
  const int pre = options_.pre_smoothing_steps, post = options_.post_smoothing_steps;
  const bool chebyshev_smoother = options_.smoother == MultigridOptions::Smoother::kChebyshev;
  if (pre == 0) std::fill(x, x + 3 * lv.nodes, 0.0);
  if (chebyshev_smoother && pre > 0) chebyshev(l, b, x, pre, true);
  else
    for (int s = 0; s < pre; ++s) smooth(l, b, x, true, s == 0);
  residual(l, b, x, lv.t.data());

  // Restriction b_c = (D P)ᵀ t.
  const double* t = lv.t.data();
  const double* fr = lv.free.data();
  double* bc = next.b.data();
  const int nc = next.nodes;
#pragma omp parallel for schedule(static) if (lv.parallel())
  for (int I = 0; I < nc; ++I) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    for (int k = lv.child_start[I]; k < lv.child_start[I + 1]; ++k) {
      const int i = 3 * lv.child[k];
      const double w = lv.child_weight[k];
      s0 += w * fr[i] * t[i];
      s1 += w * fr[i + 1] * t[i + 1];
      s2 += w * fr[i + 2] * t[i + 2];
    }
    bc[3 * I] = s0, bc[3 * I + 1] = s1, bc[3 * I + 2] = s2;
  }

  timings_.level_s[l] += since(t0);
  if (l + 2 == numLevels()) {
    t0 = Clock::now();
    if (dense_coarsest_) next.x = coarsest_llt_.solve(next.b);  // into next.x's storage, no allocation
    else coarsest_.solve(next.b, next.x);
    timings_.level_s[l + 1] += since(t0);
  } else {
    vcycle(l + 1, next.b.data(), next.x.data());
  }
  t0 = Clock::now();

  // Prolongation x += (D P) x_c.
  const NodeProlongation& P = prolongations_[l];
  const int* pout = P.outerIndexPtr();
  const int* pin = P.innerIndexPtr();
  const double* pval = P.valuePtr();
  const double* xc = next.x.data();
#pragma omp parallel for schedule(static) if (lv.parallel())
  for (int i = 0; i < lv.nodes; ++i) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    for (int k = pout[i]; k < pout[i + 1]; ++k) {
      const int J = 3 * pin[k];
      s0 += pval[k] * xc[J];
      s1 += pval[k] * xc[J + 1];
      s2 += pval[k] * xc[J + 2];
    }
    x[3 * i] += fr[3 * i] * s0;
    x[3 * i + 1] += fr[3 * i + 1] * s1;
    x[3 * i + 2] += fr[3 * i + 2] * s2;
  }
  if (chebyshev_smoother && post > 0) chebyshev(l, b, x, post, false);
  else
    for (int s = 0; s < post; ++s) smooth(l, b, x, false, false);
  timings_.level_s[l] += since(t0);
}

void MultigridPreconditioner::apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) {
  if (!factorized_) throw std::logic_error("multigrid: apply() without a successful factorize()");
  ++timings_.applications;
  if (numLevels() == 1) {
    const auto t0 = Clock::now();
    coarsest_.solve(r, z);
    timings_.level_s[0] += since(t0);
    return;
  }
  vcycle(0, r.data(), z.data());
}

MultigridPcgSolver::MultigridPcgSolver(const MeshHierarchy& hierarchy, PcgOptions pcg_options,
                                       MultigridOptions multigrid_options)
    : PcgSolver(pcg_options, std::make_unique<MultigridPreconditioner>(hierarchy, multigrid_options)) {}

MultigridPcgSolver::MultigridPcgSolver(std::vector<NodeProlongation> prolongations, PcgOptions pcg_options,
                                       MultigridOptions multigrid_options)
    : PcgSolver(pcg_options,
                std::make_unique<MultigridPreconditioner>(std::move(prolongations), multigrid_options)) {}

}  // namespace breast_sim::core
