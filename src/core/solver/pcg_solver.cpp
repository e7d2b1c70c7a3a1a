#include "breast_sim/core/solver/pcg_solver.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include <omp.h>

#include "team.h"

namespace breast_sim::core {

namespace {

// Vectors of a few thousand entries are not worth waking a second thread for.
constexpr Eigen::Index kParallelMin = 4096;

std::string dofName(Eigen::Index k) {
  std::ostringstream s;
  s << k << " (node " << k / 3 << ", " << "xyz"[k % 3] << ")";
  return s.str();
}

// r = b − A x; returns rᵀr.
double residual(const SparseMatrix& A, const Eigen::VectorXd& b, const Eigen::VectorXd& x, Eigen::VectorXd& r) {
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  const double* xp = x.data();
  double rr = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : rr) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) {
    double s = b[i];
    for (int k = outer[i]; k < outer[i + 1]; ++k) s -= val[k] * xp[inner[k]];
    r[i] = s;
    rr += s * s;
  }
  return rr;
}

// q = A p; returns pᵀq.
double multiplyDot(const SparseMatrix& A, const Eigen::VectorXd& p, Eigen::VectorXd& q) {
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const Eigen::Index n = A.rows();
  const double* pp = p.data();
  double pq = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : pq) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) {
    double s = 0.0;
    for (int k = outer[i]; k < outer[i + 1]; ++k) s += val[k] * pp[inner[k]];
    q[i] = s;
    pq += pp[i] * s;
  }
  return pq;
}

// x += α p, r −= α q; returns rᵀr.
double update(double alpha, const Eigen::VectorXd& p, const Eigen::VectorXd& q, Eigen::VectorXd& x,
              Eigen::VectorXd& r) {
  const Eigen::Index n = x.size();
  double rr = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : rr) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) {
    x[i] += alpha * p[i];
    const double ri = r[i] - alpha * q[i];
    r[i] = ri;
    rr += ri * ri;
  }
  return rr;
}

double dot(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  const Eigen::Index n = a.size();
  double s = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : s) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) s += a[i] * b[i];
  return s;
}

// p = z + β p
void updateDirection(double beta, const Eigen::VectorXd& z, Eigen::VectorXd& p) {
  const Eigen::Index n = p.size();
#pragma omp parallel for schedule(static) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) p[i] = z[i] + beta * p[i];
}

void copy(const Eigen::VectorXd& from, Eigen::VectorXd& to) {
  const Eigen::Index n = from.size();
#pragma omp parallel for schedule(static) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) to[i] = from[i];
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

void JacobiPreconditioner::apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) {
  const Eigen::Index n = r.size();
#pragma omp parallel for schedule(static) if (n > kParallelMin)
  for (Eigen::Index i = 0; i < n; ++i) z[i] = inverse_diagonal_[i] * r[i];
}

bool JacobiPreconditioner::applyInTeam(const Eigen::VectorXd& r, Eigen::VectorXd& z, double* rz_partial) {
  Eigen::Index i0, i1;
  team::split<Eigen::Index>(r.size(), omp_get_thread_num(), omp_get_num_threads(), 1, i0, i1);
  double rz = 0.0;
  for (Eigen::Index i = i0; i < i1; ++i) {
    z[i] = inverse_diagonal_[i] * r[i];
    rz += r[i] * z[i];
  }
  *rz_partial = rz;
#pragma omp barrier
  return true;
}

// ---------------------------------------------------------------------------------------------------

PcgSolver::PcgSolver(PcgOptions options, std::unique_ptr<Preconditioner> preconditioner)
    : options_(options), preconditioner_(std::move(preconditioner)) {
  if (!preconditioner_) preconditioner_ = std::make_unique<JacobiPreconditioner>();
}

void PcgSolver::analyzePattern(const SparseMatrix& A) {
  n_ = -1;
  diagonal_position_ = diagonalPositions(A, name());
  preconditioner_->analyzePattern(A);
  const Eigen::Index n = A.rows();
  decoupled_flag_.assign(static_cast<size_t>(n), 0);
  decoupled_.clear();
  decoupled_.reserve(static_cast<size_t>(n));
  for (Eigen::VectorXd* v : {&r_, &z_, &p_, &q_, &p_next_}) v->setZero(n);
  partial_.assign(static_cast<size_t>(std::max(1, omp_get_max_threads())) * team::kStride, 0.0);
  n_ = n;
  nnz_ = A.nonZeros();
  A_ = nullptr;
}

void PcgSolver::factorize(const SparseMatrix& A) {
  if (n_ < 0) throw std::logic_error(name() + ": factorize() called before analyzePattern()");
  if (A.rows() != n_ || A.cols() != n_ || A.nonZeros() != nnz_ || !A.isCompressed()) {
    std::ostringstream s;
    s << name() << ": the matrix changed from " << n_ << "×" << n_ << " with " << nnz_ << " nonzeros to "
      << A.rows() << "×" << A.cols() << " with " << A.nonZeros()
      << (A.isCompressed() ? "" : " (uncompressed)") << "; call analyzePattern() when the pattern changes";
    throw std::logic_error(s.str());
  }
  A_ = nullptr;
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
  preconditioner_->factorize(A);
  A_ = &A;
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
  const int threads = omp_get_max_threads();
  if (team_solve_ && threads > 1 && n_ > kParallelMin && preconditioner_->supportsTeam())
    return solveInTeam(b, x, threads);
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
  double rr = residual(A, b, x, r_);
  if (std::sqrt(rr) <= tol) {
    stats.converged = true;
    return finish(rr, bnorm);
  }

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
    if (!(rz > 0.0)) {
      std::ostringstream s;
      s << name() << ": the preconditioner is not positive definite (rᵀM⁻¹r = " << rz << " at iteration " << it
        << ")";
      throw std::runtime_error(s.str());
    }
    const double pq = multiplyDot(A, p_, q_);
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
      // The recursive residual drifts from b − A x; confirm with the true one.
      rr = residual(A, b, x, r_);
      if (std::sqrt(rr) <= tol) {
        stats.converged = true;
        break;
      }
      restart = true;
      continue;
    }
    preconditioner_->apply(r_, z_);
    const double rz_new = dot(r_, z_);
    updateDirection(rz_new / rz, z_, p_);
    rz = rz_new;
  }
  stats.iterations = it;
  if (!stats.converged) rr = residual(A, b, x, r_);
  return finish(rr, bnorm);
}

// One parallel region for the whole solve (see the class comment). Every thread runs the same
// control flow: scalars come from team::sum over the partials, which gives the same bits on every
// thread. A partial slot is written again only after a later barrier, so no thread can overwrite a
// partial another thread is still adding up: slot 0 ‖b‖², 1 true residual, 2 pᵀAp, 3 recursive
// residual, 4 rᵀz.
SolveStats PcgSolver::solveInTeam(const Eigen::VectorXd& b, Eigen::VectorXd& x, int threads) {
  const auto t0 = std::chrono::steady_clock::now();
  const size_t need = static_cast<size_t>(threads) * team::kStride;
  if (partial_.size() < need) partial_.assign(need, 0.0);  // OMP_NUM_THREADS raised since analyzePattern()
  const SparseMatrix& A = *A_;
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  const double* val = A.valuePtr();
  const double* bp = b.data();
  double* xp = x.data();
  double* rp = r_.data();
  double* zp = z_.data();
  double* qp = q_.data();
  const unsigned char* decoupled = decoupled_flag_.data();
  const int* diag = diagonal_position_.data();
  double* partial = partial_.data();
  const Eigen::Index n = n_;
  const int unit = n % 3 == 0 ? 3 : 1;

  // Results, written by thread 0 (every thread has the same values).
  int iterations = 0;
  bool converged = false;
  double final_rr = 0.0, final_bnorm = 0.0;
  enum class Failure { kNone, kMatrix, kPreconditioner, kPreconditionerError } failure = Failure::kNone;
  double failure_value = 0.0;

#pragma omp parallel num_threads(threads)
  {
    const int tid = omp_get_thread_num();
    const int T = omp_get_num_threads();
    double* mine = partial + static_cast<size_t>(tid) * team::kStride;
    Eigen::Index i0, i1;
    team::split<Eigen::Index>(n, tid, T, unit, i0, i1);
    // The direction p alternates between two buffers: the product pass reads the old one (any row)
    // while it writes the new one (own rows).
    double* p_old = p_.data();
    double* p_new = p_next_.data();

    // r = b − A x over own rows; returns its share of rᵀr.
    auto residual_share = [&]() {
      double rr = 0.0;
      for (Eigen::Index i = i0; i < i1; ++i) {
        double v = bp[i];
        for (int k = outer[i]; k < outer[i + 1]; ++k) v -= val[k] * xp[inner[k]];
        rp[i] = v;
        rr += v * v;
      }
      return rr;
    };

    double bb = 0.0;
    for (Eigen::Index i = i0; i < i1; ++i) {
      bb += bp[i] * bp[i];
      if (decoupled[i]) xp[i] = bp[i] / val[diag[i]];
    }
    mine[0] = bb;
#pragma omp barrier
    const double bnorm = std::sqrt(team::sum(partial, T, 0));
    bool done = false;
    double rr = 0.0;
    int it = 0;
    Failure fail = Failure::kNone;
    double fail_value = 0.0;
    if (bnorm == 0.0) {
      for (Eigen::Index i = i0; i < i1; ++i) xp[i] = 0.0;
      done = true;
    } else {
      mine[1] = residual_share();
#pragma omp barrier
      rr = team::sum(partial, T, 1);
    }
    const double tol = options_.relative_tolerance * bnorm;
    if (!done && std::sqrt(rr) <= tol) done = true;
    bool conv = done;

    bool restart = true;
    double rz = 0.0, beta = 0.0;
    while (!done && it < options_.max_iterations) {
      if (restart) {
        if (!preconditioner_->applyInTeam(r_, z_, mine + 4)) {
          fail = Failure::kPreconditionerError;
          break;
        }
        rz = team::sum(partial, T, 4);
        beta = 0.0;
        restart = false;
      }
      if (!(rz > 0.0)) {
        fail = Failure::kPreconditioner, fail_value = rz;
        break;
      }
      // p ← z + β p and q = A p in one pass: A (z + β p_old) needs no finished p.
      double pq = 0.0;
      if (beta == 0.0) {
        for (Eigen::Index i = i0; i < i1; ++i) {
          double v = 0.0;
          for (int k = outer[i]; k < outer[i + 1]; ++k) v += val[k] * zp[inner[k]];
          qp[i] = v;
          p_new[i] = zp[i];
          pq += zp[i] * v;
        }
      } else {
        for (Eigen::Index i = i0; i < i1; ++i) {
          double v = 0.0;
          for (int k = outer[i]; k < outer[i + 1]; ++k) {
            const int j = inner[k];
            v += val[k] * (zp[j] + beta * p_old[j]);
          }
          qp[i] = v;
          const double pi = zp[i] + beta * p_old[i];
          p_new[i] = pi;
          pq += pi * v;
        }
      }
      mine[2] = pq;
#pragma omp barrier
      pq = team::sum(partial, T, 2);
      std::swap(p_old, p_new);  // p_old is now the current direction
      if (!(pq > 0.0)) {
        fail = Failure::kMatrix, fail_value = pq;
        break;
      }
      const double alpha = rz / pq;
      double rr_share = 0.0;
      for (Eigen::Index i = i0; i < i1; ++i) {
        xp[i] += alpha * p_old[i];
        const double ri = rp[i] - alpha * qp[i];
        rp[i] = ri;
        rr_share += ri * ri;
      }
      mine[3] = rr_share;
#pragma omp barrier
      rr = team::sum(partial, T, 3);
      ++it;
      if (std::sqrt(rr) <= tol) {
        // The recursive residual drifts from b − A x; confirm with the true one.
        mine[1] = residual_share();
#pragma omp barrier
        rr = team::sum(partial, T, 1);
        if (std::sqrt(rr) <= tol) {
          conv = true;
          break;
        }
        restart = true;
        continue;
      }
      if (!preconditioner_->applyInTeam(r_, z_, mine + 4)) {
        fail = Failure::kPreconditionerError;
        break;
      }
      const double rz_new = team::sum(partial, T, 4);
      beta = rz_new / rz;
      rz = rz_new;
    }
    if (fail == Failure::kNone && !conv && bnorm > 0.0) {
      // Iteration limit: report the true residual.
      mine[1] = residual_share();
#pragma omp barrier
      rr = team::sum(partial, T, 1);
    }
    if (tid == 0) {
      iterations = it, converged = conv && fail == Failure::kNone, final_rr = rr, final_bnorm = bnorm;
      failure = fail, failure_value = fail_value;
    }
  }

  if (failure == Failure::kPreconditionerError) {
    std::exception_ptr e = preconditioner_->takeTeamError();
    if (e) std::rethrow_exception(e);
    throw std::runtime_error(name() + ": the preconditioner failed without saying why");
  }
  if (failure == Failure::kPreconditioner) {
    std::ostringstream s;
    s << name() << ": the preconditioner is not positive definite (rᵀM⁻¹r = " << failure_value << " at iteration "
      << iterations << ")";
    throw std::runtime_error(s.str());
  }
  if (failure == Failure::kMatrix) {
    std::ostringstream s;
    s << name() << ": the matrix is not positive definite (pᵀAp = " << failure_value << " at iteration " << iterations
      << "); check the stiffness for inverted elements or negative moduli";
    throw std::runtime_error(s.str());
  }
  SolveStats stats;
  stats.iterations = iterations;
  stats.converged = converged;
  if (final_bnorm == 0.0) stats.converged = true;
  stats.relative_residual = final_bnorm > 0 ? std::sqrt(final_rr) / final_bnorm : 0.0;
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return stats;
}

}  // namespace breast_sim::core
