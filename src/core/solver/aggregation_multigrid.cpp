#include "breast_sim/core/solver/aggregation_multigrid.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <stdexcept>

#include <omp.h>

#include <Eigen/Dense>

namespace breast_sim::core {

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Levels below this many nodes run on one thread: waking the second costs more than it saves.
constexpr int kParallelMinNodes = 400;
constexpr int kC = kRigidModes;  // coarse DOFs per aggregate

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

// ---------------------------------------------------------------------------------------------------
// Building blocks

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

// ---------------------------------------------------------------------------------------------------
// The hierarchy

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
    double vv = 0.0, yy = 0.0;
#pragma omp parallel if (lv.nodes > kParallelMinNodes)
    {
#pragma omp for schedule(static)
      for (int r = 0; r < n; ++r) {
        double s = 0.0;
        for (int k = outer[r]; k < outer[r + 1]; ++k) s += val[k] * v[inner[k]];
        Av[r] = s;
      }
#pragma omp for schedule(static) reduction(+ : vv, yy)
      for (int i = 0; i < lv.nodes; ++i) {
        const double* d = dinv + static_cast<size_t>(i) * bs * bs;
        double y[kC];
        for (int a = 0; a < bs; ++a) {
          double s = 0.0;
          for (int c = 0; c < bs; ++c) s += d[a * bs + c] * Av[bs * i + c];
          y[a] = fr[bs * i + a] * s;  // decoupled DOFs (eigenvalue 1) are left out
        }
        for (int a = 0; a < bs; ++a) {
          vv += v[bs * i + a] * v[bs * i + a];
          v[bs * i + a] = y[a];
          yy += y[a] * y[a];
        }
      }
    }
    if (!(yy > 0.0) || !(vv > 0.0)) break;
    lambda = std::sqrt(yy / vv);
    lv.eigenvector *= 1.0 / std::sqrt(yy);
  }
  lv.lambda = lambda > 0.0 ? lambda : 1.0;
  lv.omega = std::min(1.0, options_.smoother_damping / lv.lambda);
}

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
