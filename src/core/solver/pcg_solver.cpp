#include "breast_sim/core/solver/pcg_solver.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include <Eigen/Eigenvalues>

#include "breast_sim/core/solver/block_kernels.h"
#include "../util/ordered_sum.h"

namespace breast_sim::core {

namespace {

// Matrix rows: products and scans of fewer rows than this run on one thread.
constexpr Eigen::Index kParallelMin = 1024;
// Vector operations (x += αp, r −= αq with rᵀr; rᵀz; p = z + βp) of fewer entries than this run on
// one thread. The team's threads spin between parallel regions (src/openmp_wait): handing a region
// to the second thread costs a few microseconds, as long as three streams of about 1,000 entries
// (docs/benchmarks.md, "Threads").
constexpr Eigen::Index kParallelMinVector = 2048;
// Up to this many iterations the recursive residual is reported at the iteration limit.
constexpr int kRecursiveResidualMaxIterations = 8;

std::string dofName(Eigen::Index k) {
  std::ostringstream s;
  s << k << " (node " << k / 3 << ", " << "xyz"[k % 3] << ")";
  return s.str();
}

// r = b − A x; returns rᵀr (in a fixed order: util/ordered_sum.h).
double residual(const SparseMatrix& A, const Eigen::VectorXd& b, const Eigen::VectorXd& x, Eigen::VectorXd& r) {
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  const double* xp = x.data();
  return util::orderedSum(n, n > kParallelMin, [&](long i) {
    double s = b[i];
    for (int k = outer[i]; k < outer[i + 1]; ++k) s -= val[k] * xp[inner[k]];
    r[i] = s;
    return s * s;
  });
}

// q = A p; returns pᵀq.
double multiplyDot(const SparseMatrix& A, const Eigen::VectorXd& p, Eigen::VectorXd& q) {
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  const double* pp = p.data();
  return util::orderedSum(n, n > kParallelMin, [&](long i) {
    double s = 0.0;
    for (int k = outer[i]; k < outer[i + 1]; ++k) s += val[k] * pp[inner[k]];
    q[i] = s;
    return pp[i] * s;
  });
}

// x += α p, r −= α q; returns rᵀr.
double update(double alpha, const Eigen::VectorXd& p, const Eigen::VectorXd& q, Eigen::VectorXd& x,
              Eigen::VectorXd& r) {
  const Eigen::Index n = x.size();
  return util::orderedSum(n, n > kParallelMinVector, [&](long i) {
    x[i] += alpha * p[i];
    const double ri = r[i] - alpha * q[i];
    r[i] = ri;
    return ri * ri;
  });
}

double dot(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  return util::orderedSum(a.size(), a.size() > kParallelMinVector, [&](long i) { return a[i] * b[i]; });
}

// p = z + β p
void updateDirection(double beta, const Eigen::VectorXd& z, Eigen::VectorXd& p) {
  const Eigen::Index n = p.size();
#pragma omp parallel for schedule(static) if (n > kParallelMinVector)
  for (Eigen::Index i = 0; i < n; ++i) p[i] = z[i] + beta * p[i];
}

void copy(const Eigen::VectorXd& from, Eigen::VectorXd& to) {
  const Eigen::Index n = from.size();
#pragma omp parallel for schedule(static) if (n > kParallelMinVector)
  for (Eigen::Index i = 0; i < n; ++i) to[i] = from[i];
}

// Node columns of every 3×3 block when A has the block layout (rows 3I, 3I+1, 3I+2 hold the same
// columns, three per neighbour J: 3J, 3J+1, 3J+2); false (and nothing set) otherwise.
bool blockColumns(const SparseMatrix& A, std::vector<int>& block_start, std::vector<int>& block_col) {
  const Eigen::Index n = A.rows();
  if (n % 3 != 0 || !A.isCompressed()) return false;
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const int nodes = static_cast<int>(n / 3);
  std::vector<int> start(static_cast<size_t>(nodes) + 1, 0), col;
  col.reserve(static_cast<size_t>(A.nonZeros() / 9));
  for (int i = 0; i < nodes; ++i) {
    const int len = outer[3 * i + 1] - outer[3 * i];
    if (len % 3 != 0) return false;
    for (int r = 1; r < 3; ++r)
      if (outer[3 * i + r + 1] - outer[3 * i + r] != len ||
          !std::equal(inner + outer[3 * i], inner + outer[3 * i + 1], inner + outer[3 * i + r]))
        return false;
    for (int m = 0; m < len; m += 3) {
      const int c = inner[outer[3 * i] + m];
      if (c % 3 != 0 || inner[outer[3 * i] + m + 1] != c + 1 || inner[outer[3 * i] + m + 2] != c + 2) return false;
      col.push_back(c / 3);
    }
    start[i + 1] = static_cast<int>(col.size());
  }
  block_start = std::move(start);
  block_col = std::move(col);
  return true;
}

}  // namespace

std::vector<int> diagonalPositions(const SparseMatrix& A, const std::string& who) {
  if (A.rows() != A.cols()) {
    std::ostringstream s;
    s << who << ": the matrix must be square, got " << A.rows() << "×" << A.cols();
    throw std::invalid_argument(s.str());
  }
  if (!A.isCompressed()) throw std::invalid_argument(who + ": the matrix must be compressed (call makeCompressed())");
  std::vector<int> pos(static_cast<size_t>(A.rows()), -1);
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  for (Eigen::Index i = 0; i < A.rows(); ++i) {
    for (int k = outer[i]; k < outer[i + 1]; ++k)
      if (inner[k] == i) pos[i] = k;
    if (pos[i] < 0)
      throw std::invalid_argument(who + ": row " + dofName(i) +
                                  " has no stored diagonal entry; store the diagonal of every row (a fixed DOF "
                                  "keeps a unit diagonal)");
  }
  return pos;
}

void parallelMultiply(const SparseMatrix& A, const Eigen::VectorXd& x, Eigen::VectorXd& y) {
  y.resize(A.rows());
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  const double* xp = x.data();
#pragma omp parallel for schedule(static) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) {
    double s = 0.0;
    const int end = A.isCompressed() ? outer[i + 1] : outer[i] + A.innerNonZeroPtr()[i];
    for (int k = outer[i]; k < end; ++k) s += val[k] * xp[inner[k]];
    y[i] = s;
  }
}

// ---------------------------------------------------------------------------------------------------

void Preconditioner::analyzeWithRankOne(const SparseMatrix&, const RankOneSum&) {
  throw std::logic_error(name() + ": takes no rank-one sum beside the matrix");
}

void Preconditioner::factorizeWithRankOne(const SparseMatrix&, const RankOneSum&) {
  throw std::logic_error(name() + ": takes no rank-one sum beside the matrix");
}

// ---------------------------------------------------------------------------------------------------

void JacobiPreconditioner::analyzePattern(const SparseMatrix& A) {
  diagonal_position_ = diagonalPositions(A, "pcg-jacobi");
  inverse_diagonal_.resize(A.rows());
}

void JacobiPreconditioner::factorize(const SparseMatrix& A) {
  if (static_cast<Eigen::Index>(diagonal_position_.size()) != A.rows())
    throw std::logic_error("pcg-jacobi: factorize() called before analyzePattern() or with another size");
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  for (Eigen::Index i = 0; i < n; ++i) {
    const double d = val[diagonal_position_[i]];
    if (!(d > 0.0)) {
      std::ostringstream s;
      s << "pcg-jacobi: the matrix is not positive definite: diagonal entry of row " << dofName(i) << " is " << d;
      throw std::runtime_error(s.str());
    }
    inverse_diagonal_[i] = 1.0 / d;
  }
}

void JacobiPreconditioner::analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  analyzePattern(S);
  rank_one_diagonal_.assign(9 * static_cast<size_t>(R.nodes), 0.0);
}

void JacobiPreconditioner::factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  if (static_cast<Eigen::Index>(rank_one_diagonal_.size()) != 3 * S.rows() || R.nodes * 3 != S.rows())
    throw std::logic_error("pcg-jacobi: factorizeWithRankOne() called before analyzeWithRankOne() or with another size");
  std::fill(rank_one_diagonal_.begin(), rank_one_diagonal_.end(), 0.0);
  addRankOneDiagonal(R, rank_one_diagonal_.data());
  factorize(S);
  for (Eigen::Index i = 0; i < S.rows(); ++i) {
    const double d = 1.0 / inverse_diagonal_[i] + rank_one_diagonal_[9 * (i / 3) + 4 * (i % 3)];
    inverse_diagonal_[i] = 1.0 / d;
  }
}

void JacobiPreconditioner::apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) {
  const Eigen::Index n = r.size();
#pragma omp parallel for schedule(static) if (n > kParallelMinVector)
  for (Eigen::Index i = 0; i < n; ++i) z[i] = inverse_diagonal_[i] * r[i];
}

// ---------------------------------------------------------------------------------------------------

PcgSolver::PcgSolver(PcgOptions options, std::unique_ptr<Preconditioner> preconditioner)
    : preconditioner_(std::move(preconditioner)) {
  if (!preconditioner_) preconditioner_ = std::make_unique<JacobiPreconditioner>();
  setOptions(options);
}

void PcgSolver::setOptions(const PcgOptions& options) {
  if (options.projection_vectors < 1 || options.projection_vectors > kMaxProjectionVectors) {
    std::ostringstream s;
    s << name() << ": projection_vectors " << options.projection_vectors << " is not in 1 .. "
      << kMaxProjectionVectors << "; 1 starts every solve from the caller's guess alone";
    throw std::invalid_argument(s.str());
  }
  options_ = options;
  if (kept_solutions_ > options_.projection_vectors) kept_solutions_ = options_.projection_vectors;
}

void PcgSolver::setRelativeTolerance(double tolerance) {
  if (!(tolerance > 0.0 && tolerance < 1.0)) {
    std::ostringstream s;
    s << name() << ": relative tolerance " << tolerance << " is not in (0, 1); e.g. 1e-2 per time step";
    throw std::invalid_argument(s.str());
  }
  options_.relative_tolerance = tolerance;
}

void PcgSolver::analyzePattern(const SparseMatrix& A) {
  rank_one_ = false;
  n_ = -1;
  diagonal_position_ = diagonalPositions(A, name());
  preconditioner_->analyzePattern(A);
  analyzeCommon(A);
}

void PcgSolver::analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  if (!acceptsRankOneSum())
    throw std::logic_error(name() + ": the preconditioner '" + preconditioner_->name() +
                           "' does not take a rank-one sum; assemble the whole matrix");
  if (3 * static_cast<Eigen::Index>(R.nodes) != S.rows()) {
    std::ostringstream s;
    s << name() << ": the rank-one sum has " << R.nodes << " nodes, the matrix " << S.rows() << " rows";
    throw std::invalid_argument(s.str());
  }
  rank_one_ = false;
  n_ = -1;
  diagonal_position_ = diagonalPositions(S, name());
  preconditioner_->analyzeWithRankOne(S, R);
  analyzeCommon(S);
  rank_one_ = true;
  rank_one_terms_ = R.terms;
  rank_one_entries_ = R.entries();
  rank_one_work_.assign(static_cast<size_t>(std::max(R.terms, 1)), 0.0);
}

void PcgSolver::analyzeCommon(const SparseMatrix& A) {
  const Eigen::Index n = A.rows();
  kept_solutions_ = 0;
  decoupled_flag_.assign(static_cast<size_t>(n), 0);
  decoupled_.clear();
  decoupled_.reserve(static_cast<size_t>(n));
  for (Eigen::VectorXd* v : {&r_, &z_, &p_, &q_}) v->setZero(n);
  block_start_.clear();
  block_col_.clear();
  blockColumns(A, block_start_, block_col_);
  analysed_outer_.assign(A.outerIndexPtr(), A.outerIndexPtr() + n + 1);
  n_ = n;
  nnz_ = A.nonZeros();
  A_ = nullptr;
  float_blocks_ = {};
}

void PcgSolver::factorize(const SparseMatrix& A) {
  if (rank_one_)
    throw std::logic_error(name() + ": analysed with a rank-one sum: call factorizeWithRankOne()");
  checkAndScan(A);
  preconditioner_->factorize(A);
  A_ = &A;
  takeFloatBlocks();
}

void PcgSolver::factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) {
  if (!rank_one_)
    throw std::logic_error(name() + ": factorizeWithRankOne() called without analyzeWithRankOne()");
  if (R.terms != rank_one_terms_ || R.entries() != rank_one_entries_ || 3 * static_cast<Eigen::Index>(R.nodes) != n_)
    throw std::logic_error(name() + ": the rank-one sum's structure changed since analyzeWithRankOne()");
  checkAndScan(S);
  // Decoupled rows are solved alone (x_i = b_i / S_ii): R must not reach them.
  for (int i : decoupled_)
    if (!R.free || R.free[i] != 0.0)
      throw std::logic_error(name() + ": row " + dofName(i) +
                             " of the matrix is decoupled (fixed) but the rank-one sum does not mask it");
  // The mask folded into a copy of the vectors: the many products of the iterations read none.
  R_ = withMaskApplied(R, rank_one_masked_);
  preconditioner_->factorizeWithRankOne(S, R_);
  A_ = &S;
  takeFloatBlocks();
}

void PcgSolver::takeFloatBlocks() {
  const Preconditioner::FloatBlocks f = preconditioner_->floatBlocks();
  if (f.val && 3 * static_cast<Eigen::Index>(f.nodes) != n_) {
    A_ = nullptr;  // not factorized: solve() refuses until a factorize() succeeds
    std::ostringstream s;
    s << name() << ": the preconditioner's float copy of the matrix has " << f.nodes << " node rows, the matrix "
      << n_ << " rows";
    throw std::logic_error(s.str());
  }
  float_blocks_ = f;
}

void PcgSolver::checkAndScan(const SparseMatrix& A) {
  if (n_ < 0) throw std::logic_error(name() + ": factorize() called before analyzePattern()");
  if (A.rows() != n_ || A.cols() != n_ || A.nonZeros() != nnz_ || !A.isCompressed()) {
    std::ostringstream s;
    s << name() << ": the matrix changed from " << n_ << "×" << n_ << " with " << nnz_ << " nonzeros to "
      << A.rows() << "×" << A.cols() << " with " << A.nonZeros()
      << (A.isCompressed() ? "" : " (uncompressed)") << "; call analyzePattern() when the pattern changes";
    throw std::logic_error(s.str());
  }
  // The block products walk the analysed block lists over A's rows: the row starts must be the
  // analysed ones (the same count of entries in other rows would read past the values).
  if (!std::equal(analysed_outer_.begin(), analysed_outer_.end(), A.outerIndexPtr()))
    throw std::logic_error(name() + ": the matrix's row lengths changed since analyzePattern(); call it again");
  A_ = nullptr;
  float_blocks_ = {};
  const int* outer = A.outerIndexPtr();
  const double* val = A.valuePtr();
  Eigen::Index bad = -1;
#pragma omp parallel for schedule(static) if (n_ > kParallelMin)
  for (Eigen::Index i = 0; i < n_; ++i) {
    const int dk = diagonal_position_[i];
    if (!(val[dk] > 0.0)) {
#pragma omp critical(pcg_bad_diagonal)
      if (bad < 0 || i < bad) bad = i;
    }
    bool off = false;
    for (int k = outer[i]; k < outer[i + 1] && !off; ++k) off = (k != dk && val[k] != 0.0);
    decoupled_flag_[i] = off ? 0 : 1;
  }
  if (bad >= 0) {
    std::ostringstream s;
    s << name() << ": the matrix is not positive definite: diagonal entry of row " << dofName(bad) << " is "
      << val[diagonal_position_[bad]];
    throw std::runtime_error(s.str());
  }
  decoupled_.clear();
  for (Eigen::Index i = 0; i < n_; ++i)
    if (decoupled_flag_[i]) decoupled_.push_back(static_cast<int>(i));
}

double PcgSolver::applyMatrix(const Eigen::VectorXd* b, const Eigen::VectorXd& x, Eigen::VectorXd& y) {
  const SparseMatrix& A = *A_;
  if (!b && float_products_) {
    const Preconditioner::FloatBlocks& f = float_blocks_;
    const double s = floatBlockProduct(f.val, f.col, f.start, x.data(), y.data(), f.nodes, options_.simd_kernels,
                                       A.rows() > kParallelMin);
    return rank_one_ ? s + addRankOneProduct(R_, x.data(), 1.0, y.data(), rank_one_work_.data()) : s;
  }
  // Block layout: the products block by block (solver/block_kernels.h): one column index per block
  // instead of nine, x_J read once for three rows, the nine multiply-adds of a block independent.
  const double s = !block_start_.empty()
                       ? blockProduct(A.outerIndexPtr(), A.valuePtr(), block_start_.data(), block_col_.data(),
                                      b ? b->data() : nullptr, x.data(), y.data(),
                                      static_cast<int>(block_start_.size()) - 1, b != nullptr, options_.simd_kernels,
                                      A.rows() > kParallelMin)
                   : (b ? residual(A, *b, x, y) : multiplyDot(A, x, y));
  if (!rank_one_) return s;
  if (!b) return s + addRankOneProduct(R_, x.data(), 1.0, y.data(), rank_one_work_.data());
  addRankOneProduct(R_, x.data(), -1.0, y.data(), rank_one_work_.data());
  return dot(y, y);
}

double PcgSolver::projectInitialGuess(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  constexpr int K = kMaxProjectionVectors;
  if (options_.projection_vectors < 2 || kept_solutions_ == 0) return -1.0;
  const Eigen::Index n = n_;
  // What spans it: the caller's guess, then the kept solutions newest first, without a first one
  // equal to the guess (a time step starts from its last solution).
  std::array<const Eigen::VectorXd*, K> list{};
  int m = 0;
  list[m++] = &x;
  const int first = solutions_[0] == x ? 1 : 0;
  for (int k = first; k < kept_solutions_ && m < options_.projection_vectors; ++k) list[m++] = &solutions_[k];
  if (m < 2) return -1.0;
  if (static_cast<int>(basis_.size()) < m) {
    basis_.resize(static_cast<size_t>(m));
    basis_products_.resize(static_cast<size_t>(m));
  }
  // The basis: the guess and the differences of neighbours in the list (the same span; successive
  // solutions are nearly parallel, their differences are not), zero on the decoupled rows, whose
  // values are known. Its Gram matrix G = WᵀAW and g = Wᵀb (Wᵀ A x_decoupled = 0).
  Eigen::Matrix<double, K, K> G = Eigen::Matrix<double, K, K>::Zero();
  Eigen::Matrix<double, K, 1> g = Eigen::Matrix<double, K, 1>::Zero();
  const bool parallel = n > kParallelMinVector;
  const unsigned char* fixed = decoupled_flag_.data();
  for (int j = 0; j < m; ++j) {
    Eigen::VectorXd& w = basis_[static_cast<size_t>(j)];
    Eigen::VectorXd& q = basis_products_[static_cast<size_t>(j)];
    w.resize(n);
    q.resize(n);
    const double* a = list[j]->data();
    const double* before = j > 0 ? list[j - 1]->data() : nullptr;
#pragma omp parallel for schedule(static) if (parallel)
    for (Eigen::Index i = 0; i < n; ++i) w[i] = fixed[i] ? 0.0 : (before ? before[i] - a[i] : a[i]);
    applyMatrix(nullptr, w, q);
    const std::array<double, K + 1> sums = util::orderedSums<K + 1>(n, parallel, [&](long i) {
      std::array<double, K + 1> t{};
      for (int l = 0; l <= j; ++l) t[l] = basis_[static_cast<size_t>(l)][i] * q[i];
      t[K] = w[i] * b[i];
      return t;
    });
    for (int l = 0; l <= j; ++l) G(l, j) = G(j, l) = sums[l];
    g[j] = sums[K];
  }
  // c = G⁺ g on the directions G resolves: scaled to a unit diagonal, eigenvalues below 1e-12 of
  // the largest dropped (a zero or repeated basis vector). Sizes up to K on the stack: no allocation.
  using SmallMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, K, K>;
  using SmallVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, K, 1>;
  SmallVector scale(m);
  for (int j = 0; j < m; ++j) scale[j] = G(j, j) > 0.0 ? 1.0 / std::sqrt(G(j, j)) : 0.0;
  const SmallMatrix Gs = scale.asDiagonal() * G.topLeftCorner(m, m) * scale.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<SmallMatrix> eig(Gs);
  if (eig.info() != Eigen::Success) return -1.0;
  const double largest = eig.eigenvalues().maxCoeff();
  if (!(largest > 0.0)) return -1.0;
  const SmallVector gs = scale.cwiseProduct(g.head(m));
  SmallVector c = SmallVector::Zero(m);
  for (int e = 0; e < m; ++e) {
    const double lambda = eig.eigenvalues()[e];
    if (lambda > 1e-12 * largest) c += eig.eigenvectors().col(e) * (eig.eigenvectors().col(e).dot(gs) / lambda);
  }
  c = scale.cwiseProduct(c);
  if (!c.allFinite()) return -1.0;
  // x = x_decoupled + W c and r = b − A x = b − (AW) c (zero on the decoupled rows).
  return util::orderedSum(n, parallel, [&](long i) {
    if (fixed[i]) {
      r_[i] = 0.0;
      return 0.0;
    }
    double xi = 0.0, ri = b[i];
    for (int l = 0; l < m; ++l) {
      xi += c[l] * basis_[static_cast<size_t>(l)][i];
      ri -= c[l] * basis_products_[static_cast<size_t>(l)][i];
    }
    x[i] = xi;
    r_[i] = ri;
    return ri * ri;
  });
}

void PcgSolver::keepSolution(const Eigen::VectorXd& x) {
  const int keep = options_.projection_vectors;
  if (keep < 2) {
    kept_solutions_ = 0;
    return;
  }
  if (static_cast<int>(solutions_.size()) < keep) solutions_.resize(static_cast<size_t>(keep));
  // The oldest slot becomes the newest (its storage reused).
  std::rotate(solutions_.begin(), solutions_.begin() + (keep - 1), solutions_.begin() + keep);
  solutions_[0].resize(x.size());
  copy(x, solutions_[0]);
  kept_solutions_ = std::min(kept_solutions_ + 1, keep);
}

SolveStats PcgSolver::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  const auto t0 = std::chrono::steady_clock::now();
  if (!A_) throw std::logic_error(name() + ": solve() called without a successful factorize()");
  if (b.size() != n_) {
    std::ostringstream s;
    s << name() << ": right-hand side has " << b.size() << " entries, the matrix " << n_ << " rows";
    throw std::logic_error(s.str());
  }
  if (x.size() != n_) x.setZero(n_);
  const SparseMatrix& A = *A_;
  SolveStats stats;
  auto finish = [&](double rr, double bnorm) {
    stats.relative_residual = bnorm > 0 ? std::sqrt(rr) / bnorm : 0.0;
    stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return stats;
  };

  const double bnorm = std::sqrt(dot(b, b));
  if (bnorm == 0.0) {
    x.setZero();
    stats.converged = true;
    return finish(0.0, 0.0);
  }
  const double* val = A.valuePtr();
  for (int i : decoupled_) x[i] = b[i] / val[diagonal_position_[i]];
  const double tol = options_.relative_tolerance * bnorm;
  float_products_ = float_blocks_.val != nullptr && options_.relative_tolerance >= kFloatProductMinTolerance;
  auto trueResidual = [&]() { return applyMatrix(&b, x, r_); };
  double rr = projectInitialGuess(b, x);
  const bool projected = rr >= 0.0;
  if (!projected) rr = trueResidual();
  if (std::sqrt(rr) <= tol) {
    // A projected guess is confirmed with the true residual (its residual was formed from products).
    if (projected) rr = trueResidual();
    if (std::sqrt(rr) <= tol) {
      stats.converged = true;
      keepSolution(x);
      return finish(rr, bnorm);
    }
    float_products_ = false;
  }
  double rr_initial = rr;  // of the reported solve: from the start, or from a renewal of M
  int it_initial = 0;

  bool restart = true;
  double rz = 0.0;
  int it = 0;
  while (it < options_.max_iterations) {
    if (restart) {
      preconditioner_->apply(r_, z_);
      rz = dot(r_, z_);
      copy(z_, p_);
      restart = false;
    }
    if (!(rz > 0.0) && !stats.preconditioner_renewed) {
      // Parts of M kept from an earlier matrix can leave it indefinite for this one
      // (Preconditioner::renew): set them up from this matrix, once, and go on from x.
      if (preconditioner_->renew()) {
        stats.preconditioner_renewed = true;
        takeFloatBlocks();
        float_products_ = float_products_ && float_blocks_.val != nullptr;
        rr = trueResidual();
        // The renewed M's convergence is what the preconditioner hears (its reference rate).
        rr_initial = rr;
        it_initial = it;
        restart = true;
        continue;
      }
    }
    if (!(rz > 0.0)) {
      std::ostringstream s;
      s << name() << ": the preconditioner is not positive definite (rᵀM⁻¹r = " << rz << " at iteration " << it
        << ")";
      throw std::runtime_error(s.str());
    }
    const double pq = applyMatrix(nullptr, p_, q_);
    if (!(pq > 0.0) && float_products_) {
      // The float copy's rounding can leave a badly conditioned A indefinite: go on in double.
      float_products_ = false;
      rr = trueResidual();
      restart = true;
      continue;
    }
    if (!(pq > 0.0)) {
      std::ostringstream s;
      s << name() << ": the matrix is not positive definite (pᵀAp = " << pq << " at iteration " << it
        << "); check the stiffness for inverted elements or negative moduli";
      throw std::runtime_error(s.str());
    }
    const double alpha = rz / pq;
    rr = update(alpha, p_, q_, x, r_);
    ++it;
    if (std::sqrt(rr) <= tol) {
      // The recursive residual drifts from b − A x (and is the float operator's while
      // float_products_); confirm with the true one, and go on from it in double.
      rr = trueResidual();
      if (std::sqrt(rr) <= tol) {
        stats.converged = true;
        break;
      }
      float_products_ = false;
      restart = true;
      continue;
    }
    if (it == options_.max_iterations) break;  // no preconditioning for an iteration that will not come
    preconditioner_->apply(r_, z_);
    const double rz_new = dot(r_, z_);
    updateDirection(rz_new / rz, z_, p_);
    rz = rz_new;
  }
  stats.iterations = it;
  // At the iteration limit rr is the recursive residual: within round-off of ‖b − A x‖² after the
  // few iterations of a capped time step (a whole product cheaper than recomputing it), within the
  // float copy's rounding with float products (about 1e-5 of it at 48.8k elements). Over many
  // iterations it can drift below the true one, which is then recomputed.
  if (!stats.converged && it > kRecursiveResidualMaxIterations) rr = trueResidual();
  if (it > it_initial) preconditioner_->reportConvergence(it - it_initial, std::sqrt(rr / rr_initial));
  keepSolution(x);
  return finish(rr, bnorm);
}

}  // namespace breast_sim::core
