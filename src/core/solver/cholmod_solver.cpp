#include "breast_sim/core/solver/cholmod_solver.h"

#include <chrono>
#include <sstream>
#include <stdexcept>

#include <cholmod.h>
#include <dlfcn.h>

namespace breast_sim::core {

namespace {

// Sets OpenBLAS's thread count for a scope when OpenBLAS is the BLAS in this process (looked up at
// run time: CHOLMOD links whatever libblas the system provides).
class BlasThreadScope {
 public:
  explicit BlasThreadScope(int threads) {
    if (threads <= 0 || !api().set || !api().get) return;
    previous_ = api().get();
    if (previous_ != threads) api().set(threads);
    else previous_ = 0;
  }
  ~BlasThreadScope() {
    if (previous_ > 0) api().set(previous_);
  }
  BlasThreadScope(const BlasThreadScope&) = delete;
  BlasThreadScope& operator=(const BlasThreadScope&) = delete;

 private:
  struct Api {
    void (*set)(int) = reinterpret_cast<void (*)(int)>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
    int (*get)() = reinterpret_cast<int (*)()>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"));
  };
  static const Api& api() {
    static const Api a;
    return a;
  }
  int previous_ = 0;
};

}  // namespace

struct CholmodSolver::Impl {
  cholmod_common common{};
  cholmod_factor* factor = nullptr;
  cholmod_dense* x = nullptr;  // solve2 workspaces, reused between solves
  cholmod_dense* y = nullptr;
  cholmod_dense* e = nullptr;
  Eigen::Index n = -1;
  Eigen::Index nnz = -1;
  bool factorized = false;
  SparseMatrix compressed;  // only for uncompressed input
  CholmodOptions options;

  Impl() {
    cholmod_start(&common);
    common.supernodal = CHOLMOD_SUPERNODAL;
    // Failures become exceptions with our own message; CHOLMOD's printing would only duplicate it.
    common.print = 0;
    common.error_handler = nullptr;
  }
  ~Impl() {
    freeFactor();
    cholmod_finish(&common);
  }
  void freeFactor() {
    if (factor) cholmod_free_factor(&factor, &common);
    if (x) cholmod_free_dense(&x, &common);
    if (y) cholmod_free_dense(&y, &common);
    if (e) cholmod_free_dense(&e, &common);
    factorized = false;
  }

  // CSR arrays of the symmetric A read as CSC: column j is row j of A. stype = 1 reads the entries
  // with row index ≤ column index of that view, i.e. the lower triangle of the CSR matrix.
  cholmod_sparse view(const SparseMatrix& A) {
    const SparseMatrix* m = &A;
    if (!A.isCompressed()) {
      compressed = A;
      compressed.makeCompressed();
      m = &compressed;
    }
    cholmod_sparse s{};
    s.nrow = s.ncol = static_cast<size_t>(m->rows());
    s.nzmax = static_cast<size_t>(m->nonZeros());
    s.p = const_cast<int*>(m->outerIndexPtr());
    s.i = const_cast<int*>(m->innerIndexPtr());
    s.x = const_cast<double*>(m->valuePtr());
    s.stype = 1;
    s.itype = CHOLMOD_INT;
    s.xtype = CHOLMOD_REAL;
    s.dtype = CHOLMOD_DOUBLE;
    s.sorted = 1;  // Eigen keeps inner indices sorted
    s.packed = 1;
    return s;
  }
};

CholmodSolver::CholmodSolver(CholmodOptions options) : impl_(std::make_unique<Impl>()) { impl_->options = options; }
CholmodSolver::~CholmodSolver() = default;

void CholmodSolver::analyzePattern(const SparseMatrix& A) {
  if (A.rows() != A.cols()) {
    std::ostringstream s;
    s << "cholmod: the matrix must be square, got " << A.rows() << "×" << A.cols();
    throw std::invalid_argument(s.str());
  }
  impl_->freeFactor();
  cholmod_sparse a = impl_->view(A);
  impl_->factor = cholmod_analyze(&a, &impl_->common);
  if (!impl_->factor || impl_->common.status < CHOLMOD_OK) {
    std::ostringstream s;
    s << "cholmod: symbolic analysis of a " << A.rows() << "×" << A.cols() << " matrix with " << A.nonZeros()
      << " nonzeros failed (CHOLMOD status " << impl_->common.status << ")";
    impl_->n = -1;
    throw std::runtime_error(s.str());
  }
  impl_->n = A.rows();
  impl_->nnz = A.nonZeros();
}

void CholmodSolver::factorize(const SparseMatrix& A) {
  if (impl_->n < 0) throw std::logic_error("cholmod: factorize() called before analyzePattern()");
  if (A.rows() != impl_->n || A.cols() != impl_->n || A.nonZeros() != impl_->nnz) {
    std::ostringstream s;
    s << "cholmod: the matrix changed from " << impl_->n << "×" << impl_->n << " with " << impl_->nnz
      << " nonzeros to " << A.rows() << "×" << A.cols() << " with " << A.nonZeros()
      << "; call analyzePattern() when the pattern changes";
    throw std::logic_error(s.str());
  }
  impl_->factorized = false;
  cholmod_sparse a = impl_->view(A);
  const BlasThreadScope blas(impl_->options.blas_threads);
  const int ok = cholmod_factorize(&a, impl_->factor, &impl_->common);
  cholmod_factor* L = impl_->factor;
  if (impl_->common.status == CHOLMOD_NOT_POSDEF || (ok && L->minor < L->n)) {
    // L->minor is a column of the permuted matrix; report the caller's column.
    const size_t k = L->minor;
    const int col = (L->Perm && k < L->n) ? static_cast<const int*>(L->Perm)[k] : static_cast<int>(k);
    std::ostringstream s;
    s << "cholmod: the matrix is not positive definite: the factorization failed at column " << col
      << " (node " << col / 3 << ", " << "xyz"[col % 3] << "; pivot " << k << " of " << L->n
      << " in the fill-reducing order); check the stiffness (inverted elements, negative moduli) and "
         "that every DOF is either free with mass or fixed with a unit diagonal";
    throw std::runtime_error(s.str());
  }
  if (!ok || impl_->common.status < CHOLMOD_OK) {
    std::ostringstream s;
    s << "cholmod: numeric factorization failed (CHOLMOD status " << impl_->common.status
      << (impl_->common.status == CHOLMOD_OUT_OF_MEMORY ? ": out of memory" : "") << ")";
    throw std::runtime_error(s.str());
  }
  impl_->factorized = true;
}

SolveStats CholmodSolver::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  const auto t0 = std::chrono::steady_clock::now();
  if (!impl_->factorized) throw std::logic_error("cholmod: solve() called without a successful factorize()");
  if (b.size() != impl_->n) {
    std::ostringstream s;
    s << "cholmod: right-hand side has " << b.size() << " entries, the matrix " << impl_->n << " rows";
    throw std::logic_error(s.str());
  }
  cholmod_dense B{};
  B.nrow = static_cast<size_t>(impl_->n);
  B.ncol = 1;
  B.nzmax = B.nrow;
  B.d = B.nrow;
  B.x = const_cast<double*>(b.data());
  B.xtype = CHOLMOD_REAL;
  B.dtype = CHOLMOD_DOUBLE;
  const BlasThreadScope blas(impl_->options.blas_threads);
  if (!cholmod_solve2(CHOLMOD_A, impl_->factor, &B, nullptr, &impl_->x, nullptr, &impl_->y, &impl_->e,
                      &impl_->common)) {
    std::ostringstream s;
    s << "cholmod: solve failed (CHOLMOD status " << impl_->common.status << ")";
    throw std::runtime_error(s.str());
  }
  x.resize(impl_->n);
  const double* xs = static_cast<const double*>(impl_->x->x);
  std::copy(xs, xs + impl_->n, x.data());
  SolveStats stats;
  stats.converged = true;
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return stats;
}

long CholmodSolver::factorNonzeros() const {
  return impl_->factorized ? static_cast<long>(impl_->common.lnz) : 0;
}

}  // namespace breast_sim::core
