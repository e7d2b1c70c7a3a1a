// The smoothers of MultigridPreconditioner's V-cycle: the set-up of a level in every factorize()
// (fixed DOFs, inverse diagonal blocks, the float blocks of the sweeps, the damping by power
// iteration) and the sweeps themselves: damped block Jacobi, multicoloured block Gauss–Seidel and
// the Chebyshev polynomial [AB03].
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/solver/block_kernels.h"
#include "multigrid_detail.h"
#include "../util/ordered_sum.h"

namespace breast_sim::core {

void MultigridPreconditioner::scanLevel(int l) {
  Level& lv = *levels_[l];
  const SparseMatrix& M = *lv.A;
  const int* outer = M.outerIndexPtr();
  double* val = lv.owned ? lv.owned->valuePtr() : nullptr;
  const double* cval = M.valuePtr();
  // The coarsest level is solved directly: it only needs its empty rows fixed.
  const bool smoother = l + 1 < numLevels() || numLevels() == 1;
  int bad = -1;
#pragma omp parallel for schedule(static) if (lv.parallel())
  for (int i = 0; i < lv.nodes; ++i) {
    double d[9];
    for (int r = 0; r < 3; ++r) {
      const int row = 3 * i + r;
      const int d0 = outer[row] + 3 * lv.diag_block[i];
      bool coupled = false;
      for (int k = outer[row]; k < outer[row + 1] && !coupled; ++k) coupled = (k != d0 + r && cval[k] != 0.0);
      // A coarse DOF that only interpolates fixed fine DOFs has an empty row: make it decoupled.
      if (!coupled && val && cval[d0 + r] == 0.0) val[d0 + r] = 1.0;
      lv.free[row] = coupled ? 1.0 : 0.0;
      for (int c = 0; c < 3; ++c) d[3 * r + c] = cval[d0 + c];
    }
    if (l == 0 && rank_one_)
      for (int k = 0; k < 9; ++k) d[k] += rank_one_diag_[9 * static_cast<size_t>(i) + k];
    if (!smoother) continue;
    // Inverse by cofactors; Sylvester's criterion for positive definiteness.
    const double c00 = d[4] * d[8] - d[5] * d[7], c01 = d[2] * d[7] - d[1] * d[8], c02 = d[1] * d[5] - d[2] * d[4];
    const double c10 = d[5] * d[6] - d[3] * d[8], c11 = d[0] * d[8] - d[2] * d[6], c12 = d[2] * d[3] - d[0] * d[5];
    const double c20 = d[3] * d[7] - d[4] * d[6], c21 = d[1] * d[6] - d[0] * d[7], c22 = d[0] * d[4] - d[1] * d[3];
    const double det = d[0] * c00 + d[1] * c10 + d[2] * c20;
    if (!(d[0] > 0.0 && c22 > 0.0 && det > 0.0) || !std::isfinite(det)) {
#pragma omp critical(multigrid_bad_block)
      if (bad < 0 || i < bad) bad = i;
      continue;
    }
    const double inv = 1.0 / det;
    double* out = lv.dinv.data() + 9 * static_cast<size_t>(i);
    out[0] = c00 * inv, out[1] = c01 * inv, out[2] = c02 * inv;
    out[3] = c10 * inv, out[4] = c11 * inv, out[5] = c12 * inv;
    out[6] = c20 * inv, out[7] = c21 * inv, out[8] = c22 * inv;
  }
  if (bad >= 0) {
    std::ostringstream s;
    s << "multigrid: the matrix is not positive definite: the 3×3 diagonal block of node " << bad;
    if (l > 0) s << " of coarse level " << l;
    s << " is not positive definite (diagonal";
    for (int r = 0; r < 3; ++r) s << " " << cval[outer[3 * bad + r] + 3 * lv.diag_block[bad] + r];
    s << ")";
    throw std::runtime_error(s.str());
  }
}

void MultigridPreconditioner::estimateDamping(int l) {
  Level& lv = *levels_[l];
  const bool chebyshev = options_.smoother == MultigridOptions::Smoother::kChebyshev;
  if (!chebyshev && options_.jacobi_damping > 0.0) {
    lv.omega = options_.jacobi_damping;
    return;
  }
  if (l == 0 && options_.fine_eigenvalue_bound > 0.0) {
    lv.omega = std::min(1.0, 1.8 / options_.fine_eigenvalue_bound);
    lv.lambda_max = options_.fine_eigenvalue_bound;  // a bound: no safety factor
    return;
  }
  if (lv.block_val.empty()) return;  // a level solved directly (a hierarchy of one): no smoother
  // Power iteration on D⁻¹A: its largest eigenvalue bounds the damping (ω λ_max < 2).
  const int n = 3 * lv.nodes;
  int iterations = options_.power_iterations;
  if (lv.eigenvector.size() != n) {
    lv.eigenvector.resize(n);
    uint64_t state = 0x9e3779b97f4a7c15ULL;  // a fixed pseudo-random start: reproducible
    for (int i = 0; i < n; ++i) {
      state = state * 6364136223846793005ULL + 1442695040888963407ULL;
      lv.eigenvector[i] = static_cast<double>(state >> 11) / 9007199254740992.0 - 0.5;
    }
    // A cold start needs many more iterations: 3 × 4 = 12 once underestimated λ_max by a third on a
    // Galerkin level (ω λ_max = 2.05, a divergent smoother); 3 × 12 = 36 do not, measured over repeated runs.
    iterations *= 12;
  }
  double* v = lv.eigenvector.data();
  double* Av = lv.t.data();
  const double* dinv = lv.dinv.data();
  const double* fr = lv.free.data();
  // A v from the float blocks the smoother sweeps (toBlocks() ran first): the operator the damping
  // is for, at 2.7× fewer bytes than the CSR matrix. The products come out negated (0 − A v), which
  // the iteration does not see (y flips sign each time; λ is a ratio of norms).
  const float* bval = lv.block_val.data();
  const int* bcol = lv.block_col.data();
  const int* bstart = lv.block_start.data();
  static constexpr double kZero[3] = {0.0, 0.0, 0.0};
  double lambda = 0.0;
  for (int it = 0; it < iterations; ++it) {
#pragma omp parallel for schedule(static) if (lv.parallel())
    for (int i = 0; i < lv.nodes; ++i) blockRowResidual(bval, bcol, bstart[i], bstart[i + 1], kZero, v, Av + 3 * i);
    if (l == 0 && rank_one_) addRankOneProduct(R_, v, -1.0, Av, rank_one_work_.data());
    // The norms in a fixed order (util/ordered_sum.h): the same estimate on any thread count.
    const auto sums = util::orderedSums<2>(lv.nodes, lv.parallel(), [&](long i) {
      const double* d = dinv + 9 * i;
      const double* a = Av + 3 * i;
      double* y = v + 3 * i;
      const double vi = y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
      // Fixed DOFs (eigenvalue 1 of D⁻¹A) are left out of the iteration.
      const double y0 = fr[3 * i] * (d[0] * a[0] + d[1] * a[1] + d[2] * a[2]);
      const double y1 = fr[3 * i + 1] * (d[3] * a[0] + d[4] * a[1] + d[5] * a[2]);
      const double y2 = fr[3 * i + 2] * (d[6] * a[0] + d[7] * a[1] + d[8] * a[2]);
      y[0] = y0, y[1] = y1, y[2] = y2;
      return std::array<double, 2>{vi, y0 * y0 + y1 * y1 + y2 * y2};
    });
    const double vv = sums[0], yy = sums[1];
    if (!(yy > 0.0) || !(vv > 0.0)) break;
    lambda = std::sqrt(yy / vv);
    lv.eigenvector *= 1.0 / std::sqrt(yy);
  }
  // Power iteration approaches λ_max from below; ω = 1.2 / λ keeps ω λ_max < 1.9 as long as the
  // estimate is within 37 % of λ_max.
  lv.omega = lambda > 0.0 ? std::min(1.0, 1.2 / lambda) : 0.5;
  // Chebyshev: the polynomial stays below 1 in magnitude up to λ_max (1 + 1/ratio), so with the
  // safety factor 1.1 and ratio 10 an estimate within 21 % of the true λ_max suffices.
  lv.lambda_max = options_.chebyshev_eigenvalue_safety * (lambda > 0.0 ? lambda : 4.0);
}

void MultigridPreconditioner::toBlocks(int l) {
  Level& lv = *levels_[l];
  const SparseMatrix& M = *lv.A;
  const int* outer = M.outerIndexPtr();
  const double* val = M.valuePtr();
  float* out = lv.block_val.data();
#pragma omp parallel for schedule(static) if (lv.parallel())
  for (int i = 0; i < lv.nodes; ++i) {
    const int b0 = lv.block_start[i], nb = lv.block_start[i + 1] - b0;
    for (int r = 0; r < 3; ++r) {
      const double* v = val + outer[3 * i + r];
      float* o = out + 9 * static_cast<size_t>(b0) + 3 * r;
      for (int k = 0; k < nb; ++k)
        for (int c = 0; c < 3; ++c) o[9 * k + c] = static_cast<float>(v[3 * k + c]);
    }
  }
}

void MultigridPreconditioner::residual(int l, const double* b, const double* x, double* t) {
  const Level& lv = *levels_[l];
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  blockResidual(val, col, start, b, x, t, lv.nodes, options_.simd_kernels, lv.parallel());
  if (l == 0 && rank_one_) addRankOneProduct(R_, x, -1.0, t, rank_one_work_.data());
}

void MultigridPreconditioner::smooth(int l, const double* b, double* x, bool forward, bool from_zero) {
  Level& lv = *levels_[l];
  const double* dinv = lv.dinv.data();
  const int n = lv.nodes;
  if (options_.smoother == MultigridOptions::Smoother::kJacobi) {
    const double w = lv.omega;
    const double* t = b;
    if (!from_zero) {
      residual(l, b, x, lv.t.data());
      t = lv.t.data();
    }
#pragma omp parallel for schedule(static) if (lv.parallel())
    for (int i = 0; i < n; ++i) {
      const double* d = dinv + 9 * i;
      const double* s = t + 3 * i;
      double* xi = x + 3 * i;
      const double d0 = w * (d[0] * s[0] + d[1] * s[1] + d[2] * s[2]);
      const double d1 = w * (d[3] * s[0] + d[4] * s[1] + d[5] * s[2]);
      const double d2 = w * (d[6] * s[0] + d[7] * s[1] + d[8] * s[2]);
      if (from_zero) xi[0] = d0, xi[1] = d1, xi[2] = d2;
      else xi[0] += d0, xi[1] += d1, xi[2] += d2;
    }
    return;
  }
  if (from_zero) std::fill(x, x + 3 * n, 0.0);
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  auto relax = [&](int i) {
    double r[3];
    blockRowResidual(val, col, start[i], start[i + 1], b + 3 * i, x, r);
    const double* d = dinv + 9 * i;
    x[3 * i] += d[0] * r[0] + d[1] * r[1] + d[2] * r[2];
    x[3 * i + 1] += d[3] * r[0] + d[4] * r[1] + d[5] * r[2];
    x[3 * i + 2] += d[6] * r[0] + d[7] * r[1] + d[8] * r[2];
  };
  const int colours = static_cast<int>(lv.colour_start.size()) - 1;
#pragma omp parallel if (lv.parallel())
  for (int cc = 0; cc < colours; ++cc) {
    const int c = forward ? cc : colours - 1 - cc;
#pragma omp for schedule(static)
    for (int p = lv.colour_start[c]; p < lv.colour_start[c + 1]; ++p) relax(lv.colour_node[p]);
  }
}

// Chebyshev iteration for A x = b preconditioned by D [AB03; Saad, Iterative Methods, Alg. 12.1]:
// with θ = (λ_max + λ_min)/2, δ = (λ_max − λ_min)/2, σ = θ/δ and ρ₀ = 1/σ,
//   d₀ = D⁻¹ r₀ / θ,   d_k = ρ_k ρ_{k−1} d_{k−1} + (2 ρ_k / δ) D⁻¹ r_k,   ρ_k = 1/(2σ − ρ_{k−1}),
//   x_{k+1} = x_k + d_k,   r_k = b − A x_k,
// so the error after `degree` updates is T_k((θ − D⁻¹A)/δ) / T_k(σ) times the initial one.
void MultigridPreconditioner::chebyshev(int l, const double* b, double* x, int degree, bool from_zero) {
  Level& lv = *levels_[l];
  const double* dinv = lv.dinv.data();
  const int n = lv.nodes;
  const double upper = lv.lambda_max, lower = upper / options_.chebyshev_ratio;
  const double theta = 0.5 * (upper + lower), delta = 0.5 * (upper - lower), sigma = theta / delta;
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  double* d = lv.d.data();
  double rho = 1.0 / sigma;
  // Step k: d = alpha d + beta D⁻¹ (b − A x), then x += d (a second pass: the residuals read x).
  for (int k = 0; k < degree; ++k) {
    const double rho_new = k == 0 ? rho : 1.0 / (2.0 * sigma - rho);
    const double alpha = k == 0 ? 0.0 : rho_new * rho, beta = k == 0 ? 1.0 / theta : 2.0 * rho_new / delta;
    const bool zero = from_zero && k == 0;
    // The fine level of A = S + R: the rows below take S from the float blocks, b − R x from here.
    const double* bk = b;
    if (l == 0 && rank_one_ && !zero) {
      std::copy(b, b + 3 * n, rank_one_rhs_.data());
      addRankOneProduct(R_, x, -1.0, rank_one_rhs_.data(), rank_one_work_.data());
      bk = rank_one_rhs_.data();
    }
#pragma omp parallel if (lv.parallel())
    {
#pragma omp for schedule(static)
      for (int i = 0; i < n; ++i) {
        double r[3];
        if (zero) r[0] = b[3 * i], r[1] = b[3 * i + 1], r[2] = b[3 * i + 2];
        else blockRowResidual(val, col, start[i], start[i + 1], bk + 3 * i, x, r);
        const double* m = dinv + 9 * i;
        double* di = d + 3 * i;
        const double z0 = m[0] * r[0] + m[1] * r[1] + m[2] * r[2];
        const double z1 = m[3] * r[0] + m[4] * r[1] + m[5] * r[2];
        const double z2 = m[6] * r[0] + m[7] * r[1] + m[8] * r[2];
        if (k == 0) di[0] = beta * z0, di[1] = beta * z1, di[2] = beta * z2;
        else di[0] = alpha * di[0] + beta * z0, di[1] = alpha * di[1] + beta * z1, di[2] = alpha * di[2] + beta * z2;
      }
#pragma omp for schedule(static)
      for (int j = 0; j < 3 * n; ++j) x[j] = zero ? d[j] : x[j] + d[j];
    }
    rho = rho_new;
  }
}

void MultigridPreconditioner::smoothOnly(int level, const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (!factorized_) throw std::logic_error("multigrid: smoothOnly() without a successful factorize()");
  if (level < 0 || level + 1 >= numLevels())
    throw std::out_of_range("multigrid: level " + std::to_string(level) + " has no smoother (levels 0 to " +
                            std::to_string(numLevels() - 2) + " have)");
  const Level& lv = *levels_[level];
  if (b.size() != 3 * lv.nodes)
    throw std::invalid_argument("multigrid: smoothOnly() on level " + std::to_string(level) + " with " +
                                std::to_string(b.size()) + " values for " + std::to_string(3 * lv.nodes) + " DOFs");
  x.setZero(b.size());
  const int steps = options_.pre_smoothing_steps;
  if (options_.smoother == MultigridOptions::Smoother::kChebyshev) {
    if (steps > 0) chebyshev(level, b.data(), x.data(), steps, true);
    return;
  }
  for (int s = 0; s < steps; ++s) smooth(level, b.data(), x.data(), true, s == 0);
}

}  // namespace breast_sim::core
