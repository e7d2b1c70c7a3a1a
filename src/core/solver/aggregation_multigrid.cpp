// AggregationMultigridPreconditioner: the levels (analyzePattern), their set-up in every factorize()
// (fixed DOFs, block inverses, damping, the transfers of aggregation_transfer.cpp, the coarsest
// factorization) and the V-cycle (apply). The coarse space is built in aggregation_coarse_space.cpp.
#include "breast_sim/core/solver/aggregation_multigrid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <stdexcept>

#include <Eigen/Dense>

#include "aggregation_detail.h"
#include "../util/ordered_sum.h"

namespace breast_sim::core {

using aggregation_detail::blockGraph;
using aggregation_detail::Clock;
using aggregation_detail::coupledRows;
using aggregation_detail::kC;
using aggregation_detail::kParallelMinNodes;
using aggregation_detail::since;

namespace {

// b − A x over the blocks [k0, k1) of node i's rows, float blocks (BS×BS row-major), into r.
template <int BS>
inline void blockResidual(const float* val, const int* col, int k0, int k1, const double* b, const double* x,
                          double* r) {
  double s[BS];
  for (int a = 0; a < BS; ++a) s[a] = b[a];
  for (int k = k0; k < k1; ++k) {
    const float* v = val + static_cast<size_t>(k) * BS * BS;
    const double* xj = x + static_cast<size_t>(BS) * col[k];
    for (int a = 0; a < BS; ++a) {
      double t = 0.0;
      for (int c = 0; c < BS; ++c) t += v[a * BS + c] * xj[c];
      s[a] -= t;
    }
  }
  for (int a = 0; a < BS; ++a) r[a] = s[a];
}

}  // namespace

AggregationMultigridPreconditioner::AggregationMultigridPreconditioner(Points coordinates_m,
                                                                       AggregationMultigridOptions options)
    : options_(options), coordinates_(std::move(coordinates_m)) {
  const auto& o = options_;
  if (!(o.strength_threshold >= 0) || !(o.strength_decay > 0) || !(o.prolongator_damping > 0) ||
      o.smoothing_steps < 1 || !(o.smoother_damping > 0 && o.smoother_damping < 2) || o.max_coarsest_dofs < 6 ||
      o.max_levels < 1 || o.power_iterations < 1)
    throw std::invalid_argument(
        "sa-multigrid: options out of range (strength threshold ≥ 0, decay > 0, prolongator damping > 0, smoothing "
        "steps ≥ 1, smoother damping in (0, 2), max coarsest DOFs ≥ 6, max levels ≥ 1, power iterations ≥ 1)");
}

AggregationMultigridPreconditioner::~AggregationMultigridPreconditioner() = default;

void AggregationMultigridPreconditioner::setCoordinates(Points coordinates_m) {
  if (coordinates_m.rows() != coordinates_.rows())
    throw std::invalid_argument("sa-multigrid: setCoordinates with " + std::to_string(coordinates_m.rows()) +
                                " nodes, the solver has " + std::to_string(coordinates_.rows()));
  coordinates_ = std::move(coordinates_m);
}

const SparseMatrix& AggregationMultigridPreconditioner::levelMatrix(int level) const {
  if (level < 0 || level >= numLevels() || !levels_[level]->A)
    throw std::out_of_range("sa-multigrid: no matrix for level " + std::to_string(level) + " (factorize first)");
  return *levels_[level]->A;
}

const BlockProlongator& AggregationMultigridPreconditioner::prolongator(int level) const {
  if (level < 0 || level + 1 >= numLevels())
    throw std::out_of_range("sa-multigrid: no prolongator below level " + std::to_string(level));
  return levels_[level]->P;
}

double AggregationMultigridPreconditioner::smootherDamping(int level) const { return levels_.at(level)->omega; }

void AggregationMultigridPreconditioner::analyzePattern(const SparseMatrix& A) {
  if (A.rows() != 3 * coordinates_.rows() || A.cols() != A.rows()) {
    std::ostringstream s;
    s << "sa-multigrid: the matrix is " << A.rows() << "×" << A.cols() << ", the coordinates have "
      << coordinates_.rows() << " nodes (" << 3 * coordinates_.rows() << " DOFs)";
    throw std::invalid_argument(s.str());
  }
  levels_.clear();
  auto lv = std::make_unique<Level>();
  lv->A = &A;
  lv->bs = 3;
  blockGraph(A, 3, "sa-multigrid", lv->block_start, lv->block_col, lv->diag_block);
  lv->nodes = static_cast<int>(A.rows() / 3);
  levels_.push_back(std::move(lv));
  fine_nnz_ = A.nonZeros();
  built_ = factorized_ = false;
}

void AggregationMultigridPreconditioner::scanLevel(int l, bool coarsest) {
  Level& lv = *levels_[l];
  const SparseMatrix& M = *lv.A;
  const int bs = lv.bs, n = lv.nodes;
  coupledRows(M, lv.free);
  const int* outer = M.outerIndexPtr();
  double* val = l > 0 ? lv.owned.valuePtr() : nullptr;
  const double* cval = M.valuePtr();
  lv.dinv.resize(static_cast<size_t>(n) * bs * bs);
  int bad = -1;
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
  for (int i = 0; i < n; ++i) {
    Eigen::Matrix<double, kC, kC> d;
    for (int r = 0; r < bs; ++r) {
      const int d0 = outer[bs * i + r] + bs * lv.diag_block[i];
      // A coarse DOF whose row is empty (a mode its aggregate cannot carry): unit diagonal, decoupled.
      if (val && lv.free[bs * i + r] == 0.0 && cval[d0 + r] == 0.0) val[d0 + r] = 1.0;
      for (int c = 0; c < bs; ++c) d(r, c) = cval[d0 + c];
    }
    if (coarsest) continue;
    double* out = lv.dinv.data() + static_cast<size_t>(i) * bs * bs;
    bool ok = true;
    if (bs == 3) {
      Eigen::LLT<Eigen::Matrix3d> llt(d.topLeftCorner<3, 3>());
      ok = llt.info() == Eigen::Success;
      Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>> inv(out);
      inv = llt.solve(Eigen::Matrix3d::Identity());
    } else {
      Eigen::LLT<Eigen::Matrix<double, kC, kC>> llt(d);
      ok = llt.info() == Eigen::Success;
      Eigen::Map<Eigen::Matrix<double, kC, kC, Eigen::RowMajor>> inv(out);
      inv = llt.solve(Eigen::Matrix<double, kC, kC>::Identity());
    }
    if (!ok || !std::isfinite(out[0])) {
#pragma omp critical(sa_multigrid_bad_block)
      if (bad < 0 || i < bad) bad = i;
    }
  }
  if (bad >= 0) {
    std::ostringstream s;
    s << "sa-multigrid: the matrix is not positive definite: the diagonal block of node " << bad;
    if (l > 0) s << " of coarse level " << l;
    s << " is not positive definite";
    throw std::runtime_error(s.str());
  }
  if (coarsest) return;
  // Float copy of the operator for the sweeps.
  const int bb = bs * bs;
  lv.block_val.resize(lv.block_col.size() * static_cast<size_t>(bb));
  float* fv = lv.block_val.data();
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
  for (int i = 0; i < n; ++i) {
    const int b0 = lv.block_start[i], nb = lv.block_start[i + 1] - b0;
    for (int r = 0; r < bs; ++r) {
      const double* v = cval + outer[bs * i + r];
      float* o = fv + static_cast<size_t>(b0) * bb + bs * r;
      for (int k = 0; k < nb; ++k)
        for (int c = 0; c < bs; ++c) o[static_cast<size_t>(bb) * k + c] = static_cast<float>(v[bs * k + c]);
    }
  }
}

void AggregationMultigridPreconditioner::estimateDamping(int l) {
  Level& lv = *levels_[l];
  const int bs = lv.bs, n = bs * lv.nodes;
  int iterations = options_.power_iterations;
  if (lv.eigenvector.size() != n) {
    lv.eigenvector.resize(n);
    uint64_t state = 0x9e3779b97f4a7c15ULL;  // fixed pseudo-random start: reproducible
    for (int i = 0; i < n; ++i) {
      state = state * 6364136223846793005ULL + 1442695040888963407ULL;
      lv.eigenvector[i] = static_cast<double>(state >> 11) / 9007199254740992.0 - 0.5;
    }
    iterations *= 10;
  }
  lv.t.resize(n);
  double* v = lv.eigenvector.data();
  double* Av = lv.t.data();
  const SparseMatrix& M = *lv.A;
  const int* outer = M.outerIndexPtr();
  const int* inner = M.innerIndexPtr();
  const double* val = M.valuePtr();
  const double* dinv = lv.dinv.data();
  const double* fr = lv.free.data();
  double lambda = 0.0;
  for (int it = 0; it < iterations; ++it) {
#pragma omp parallel for schedule(static) if (lv.nodes > kParallelMinNodes)
    for (int r = 0; r < n; ++r) {
      double s = 0.0;
      for (int k = outer[r]; k < outer[r + 1]; ++k) s += val[k] * v[inner[k]];
      Av[r] = s;
    }
    // The norms in a fixed order (util/ordered_sum.h): the same estimate on any thread count.
    const auto sums = util::orderedSums<2>(lv.nodes, lv.nodes > kParallelMinNodes, [&](long i) {
      const double* d = dinv + static_cast<size_t>(i) * bs * bs;
      double y[kC];
      for (int a = 0; a < bs; ++a) {
        double s = 0.0;
        for (int c = 0; c < bs; ++c) s += d[a * bs + c] * Av[bs * i + c];
        y[a] = fr[bs * i + a] * s;  // decoupled DOFs (eigenvalue 1) are left out
      }
      std::array<double, 2> t{0.0, 0.0};
      for (int a = 0; a < bs; ++a) {
        t[0] += v[bs * i + a] * v[bs * i + a];
        v[bs * i + a] = y[a];
        t[1] += y[a] * y[a];
      }
      return t;
    });
    const double vv = sums[0], yy = sums[1];
    if (!(yy > 0.0) || !(vv > 0.0)) break;
    lambda = std::sqrt(yy / vv);
    lv.eigenvector *= 1.0 / std::sqrt(yy);
  }
  lv.lambda = lambda > 0.0 ? lambda : 1.0;
  lv.omega = std::min(1.0, options_.smoother_damping / lv.lambda);
}

void AggregationMultigridPreconditioner::factorizeCoarsest() {
  const auto t0 = Clock::now();
  try {
    coarsest_->factorize(*levels_.back()->A);
  } catch (const std::runtime_error& e) {
    throw std::runtime_error("sa-multigrid: coarsest level " + std::to_string(numLevels() - 1) + ": " + e.what());
  }
  timings_.coarse_factorize_s += since(t0);
}

void AggregationMultigridPreconditioner::buildHierarchy() {
  // Keep the power-iteration vectors of levels whose size stays (warm start across set-ups).
  std::vector<Eigen::VectorXd> saved;
  for (auto& lv : levels_) saved.push_back(std::move(lv->eigenvector));
  levels_.resize(1);
  Eigen::MatrixXd B = rigidBodyModes(coordinates_);
  for (int l = 0;; ++l) {
    Level& lv = *levels_[l];
    if (l < static_cast<int>(saved.size()) && saved[l].size() == lv.bs * lv.nodes) lv.eigenvector = std::move(saved[l]);
    const bool coarsest = lv.bs * lv.nodes <= options_.max_coarsest_dofs || l + 1 >= options_.max_levels;
    auto t0 = Clock::now();
    scanLevel(l, coarsest);
    timings_.scan_s += since(t0);
    if (coarsest) break;
    t0 = Clock::now();
    estimateDamping(l);
    timings_.damping_s += since(t0);
    t0 = Clock::now();
    Eigen::MatrixXd Bc;
    buildTransfer(l, B, &Bc);
    timings_.hierarchy_s += since(t0);
    B = std::move(Bc);
    // No real coarsening (aggregates of one or two nodes carry more DOFs than they replace): level l
    // is the coarsest.
    if (kC * levels_[l + 1]->nodes > 0.5 * lv.bs * lv.nodes) {
      levels_.pop_back();
      break;
    }
    t0 = Clock::now();
    galerkin(l);
    timings_.galerkin_s += since(t0);
  }
  for (auto& lv : levels_) {
    lv->b.setZero(lv->bs * lv->nodes);
    lv->x.setZero(lv->bs * lv->nodes);
    lv->t.setZero(lv->bs * lv->nodes);
  }
  coarsest_ = std::make_unique<CholmodSolver>(CholmodOptions{1});
  auto t0 = Clock::now();
  coarsest_->analyzePattern(*levels_.back()->A);
  timings_.hierarchy_s += since(t0);
  factorizeCoarsest();
  timings_.level_s.assign(levels_.size(), 0.0);
  built_ = true;
}

void AggregationMultigridPreconditioner::numericLevels() {
  const int L = numLevels();
  for (int l = 0; l < L; ++l) {
    auto t0 = Clock::now();
    scanLevel(l, l + 1 == L);
    timings_.scan_s += since(t0);
    if (l + 1 == L) break;
    t0 = Clock::now();
    estimateDamping(l);
    timings_.damping_s += since(t0);
    t0 = Clock::now();
    galerkin(l);
    timings_.galerkin_s += since(t0);
  }
  factorizeCoarsest();
}

void AggregationMultigridPreconditioner::factorize(const SparseMatrix& A) {
  if (fine_nnz_ < 0) throw std::logic_error("sa-multigrid: factorize() called before analyzePattern()");
  if (A.rows() != 3 * coordinates_.rows() || A.nonZeros() != fine_nnz_)
    throw std::logic_error("sa-multigrid: the matrix pattern changed since analyzePattern()");
  factorized_ = false;
  timings_ = Timings{};
  levels_[0]->A = &A;
  if (!built_ || !options_.reuse_prolongators) buildHierarchy();
  else numericLevels();
  timings_.level_s.assign(levels_.size(), 0.0);
  factorized_ = true;
}

void AggregationMultigridPreconditioner::smooth(int l, bool from_zero) {
  Level& lv = *levels_[l];
  const int n = lv.nodes, bs = lv.bs;
  const double w = lv.omega;
  const double* b = lv.b.data();
  double* x = lv.x.data();
  double* t = lv.t.data();
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  const double* dinv = lv.dinv.data();
  if (!from_zero) {
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
    for (int i = 0; i < n; ++i) {
      if (bs == 3) blockResidual<3>(val, col, start[i], start[i + 1], b + 3 * i, x, t + 3 * i);
      else blockResidual<kC>(val, col, start[i], start[i + 1], b + kC * i, x, t + kC * i);
    }
  }
  const double* s = from_zero ? b : t;
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
  for (int i = 0; i < n; ++i) {
    const double* d = dinv + static_cast<size_t>(i) * bs * bs;
    for (int a = 0; a < bs; ++a) {
      double u = 0.0;
      for (int c = 0; c < bs; ++c) u += d[a * bs + c] * s[bs * i + c];
      if (from_zero) x[bs * i + a] = w * u;
      else x[bs * i + a] += w * u;
    }
  }
}

void AggregationMultigridPreconditioner::vcycle(int l) {
  Level& lv = *levels_[l];
  if (l + 1 == numLevels()) {
    const auto t0 = Clock::now();
    coarsest_->solve(lv.b, lv.x);
    timings_.level_s[l] += since(t0);
    return;
  }
  auto t0 = Clock::now();
  Level& nx = *levels_[l + 1];
  const int n = lv.nodes, bs = lv.bs, nc = nx.nodes;
  for (int s = 0; s < options_.smoothing_steps; ++s) smooth(l, s == 0);
  // Residual t = b − A x and restriction b_c = (D P)ᵀ t.
  {
    const float* val = lv.block_val.data();
    const int* col = lv.block_col.data();
    const int* start = lv.block_start.data();
    const double* b = lv.b.data();
    const double* x = lv.x.data();
    double* t = lv.t.data();
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
    for (int i = 0; i < n; ++i) {
      if (bs == 3) blockResidual<3>(val, col, start[i], start[i + 1], b + 3 * i, x, t + 3 * i);
      else blockResidual<kC>(val, col, start[i], start[i + 1], b + kC * i, x, t + kC * i);
    }
    double* bc = nx.b.data();
#pragma omp parallel for schedule(static) if (nc > kParallelMinNodes / 8)
    for (int J = 0; J < nc; ++J) {
      double s[kC] = {};
      for (int k = lv.child_start[J]; k < lv.child_start[J + 1]; ++k) {
        const double* p = lv.pm.data() + static_cast<size_t>(lv.child_block[k]) * bs * kC;
        const double* ti = t + static_cast<size_t>(bs) * lv.child_node[k];
        for (int r = 0; r < bs; ++r)
          for (int m = 0; m < kC; ++m) s[m] += p[r * kC + m] * ti[r];
      }
      for (int m = 0; m < kC; ++m) bc[kC * J + m] = s[m];
    }
  }
  timings_.level_s[l] += since(t0);
  vcycle(l + 1);
  t0 = Clock::now();
  // Prolongation x += (D P) x_c.
  {
    const double* xc = nx.x.data();
    double* x = lv.x.data();
    const BlockProlongator& P = lv.P;
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
    for (int i = 0; i < n; ++i)
      for (int q = P.start[i]; q < P.start[i + 1]; ++q) {
        const double* p = lv.pm.data() + static_cast<size_t>(q) * bs * kC;
        const double* xk = xc + static_cast<size_t>(kC) * P.col[q];
        for (int r = 0; r < bs; ++r) {
          double s = 0.0;
          for (int m = 0; m < kC; ++m) s += p[r * kC + m] * xk[m];
          x[bs * i + r] += s;
        }
      }
  }
  for (int s = 0; s < options_.smoothing_steps; ++s) smooth(l, false);
  timings_.level_s[l] += since(t0);
}

void AggregationMultigridPreconditioner::apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) {
  if (!factorized_) throw std::logic_error("sa-multigrid: apply() without a successful factorize()");
  ++timings_.applications;
  Level& lv = *levels_[0];
  lv.b = r;  // same size: no allocation
  vcycle(0);
  z = lv.x;
}

AggregationMultigridPcgSolver::AggregationMultigridPcgSolver(Points coordinates_m, PcgOptions pcg_options,
                                                             AggregationMultigridOptions options)
    : PcgSolver(pcg_options,
                std::make_unique<AggregationMultigridPreconditioner>(std::move(coordinates_m), options)) {}

}  // namespace breast_sim::core
