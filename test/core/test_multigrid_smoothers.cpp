// Smoothers of the multigrid V-cycle (solver/multigrid.h), in particular the Chebyshev polynomial
// smoother [AB03]: its error propagator is the scaled Chebyshev polynomial of D⁻¹A (checked against
// a slow reference built from the three-term recurrence of T_k), it damps the interval it is set up
// for as theory says, its interval covers the spectrum on every level, and the V-cycle with it is a
// symmetric positive definite preconditioner that PCG converges with.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/SparseCholesky>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "reference_step_matrix.h"

using namespace breast_sim::core;

namespace {

/// The phantom at ~8000 elements, three levels, the rest step system (ν = 0.48) and its load.
struct Fixture {
  ModelCase model_case;
  SimulationModel model;
  MeshHierarchy hierarchy;
  std::vector<int> fixed;
  SparseMatrix A;
  Eigen::VectorXd b;
};

const Fixture& fixture() {
  static const Fixture f = [] {
    Fixture f;
    f.model_case = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
    f.model_case.meshing.target_elements = 8000;
    f.model = buildSimulationModel(f.model_case);
    CoarseningOptions coarsening;
    coarsening.max_coarsest_elements = 600;  // three levels: two smoothed ones
    f.hierarchy = buildMeshHierarchy(f.model_case, f.model, coarsening);
    f.fixed = f.model.mesh.nodeSet(node_sets::kChestWall);
    f.A = breast_sim::test_support::restStepMatrix(f.model.mesh, f.fixed);
    std::mt19937 rng(11);
    std::normal_distribution<double> g;
    f.b.resize(f.A.rows());
    for (Eigen::Index i = 0; i < f.b.size(); ++i) f.b[i] = g(rng);
    for (int v : f.fixed) f.b.segment<3>(3 * v).setZero();
    return f;
  }();
  return f;
}

MultigridOptions chebyshevOptions(int degree, double ratio = 10.0) {
  MultigridOptions o;
  o.smoother = MultigridOptions::Smoother::kChebyshev;
  o.pre_smoothing_steps = o.post_smoothing_steps = degree;
  o.chebyshev_ratio = ratio;
  return o;
}

/// y = D⁻¹ A x with D the 3×3 block diagonal of A, in double (slow reference).
struct BlockJacobiOperator {
  const SparseMatrix& A;
  std::vector<Eigen::Matrix3d> Dinv;
  explicit BlockJacobiOperator(const SparseMatrix& M) : A(M) {
    const int n = static_cast<int>(A.rows() / 3);
    Dinv.resize(static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) Dinv[i] = Eigen::Matrix3d(Eigen::MatrixXd(A.block(3 * i, 3 * i, 3, 3))).inverse();
  }
  Eigen::VectorXd operator()(const Eigen::VectorXd& x) const {
    Eigen::VectorXd y = A * x;
    for (size_t i = 0; i < Dinv.size(); ++i) y.segment<3>(3 * i) = Dinv[i] * y.segment<3>(3 * i);
    return y;
  }
  /// λ_max by a long power iteration and its eigenvector.
  double largestEigenvalue(Eigen::VectorXd* vector = nullptr, int iterations = 400) const {
    Eigen::VectorXd x = Eigen::VectorXd::Ones(A.rows()), y;
    for (Eigen::Index i = 0; i < x.size(); ++i) x[i] += 0.3 * std::sin(static_cast<double>(7 * i));
    double lambda = 0.0;
    for (int it = 0; it < iterations; ++it) {
      y = (*this)(x);
      lambda = y.norm() / x.norm();
      x = y / y.norm();
    }
    if (vector) *vector = x;
    return lambda;
  }
};

/// p(D⁻¹A) e with p(t) = T_k((θ − t)/δ) / T_k(θ/δ), T_k by its three-term recurrence
/// T_{j+1}(y) = 2y T_j(y) − T_{j−1}(y) on vectors and on the scalar σ = θ/δ: an independent evaluation
/// of the polynomial that the smoother's two-term update recurrence applies.
Eigen::VectorXd chebyshevErrorPropagator(const BlockJacobiOperator& op, const Eigen::VectorXd& e, int k, double lower,
                                         double upper) {
  const double theta = 0.5 * (upper + lower), delta = 0.5 * (upper - lower), sigma = theta / delta;
  auto Y = [&](const Eigen::VectorXd& v) -> Eigen::VectorXd { return (theta * v - op(v)) / delta; };
  Eigen::VectorXd t_prev = e, t = Y(e);
  double s_prev = 1.0, s = sigma;
  if (k == 0) return e;
  for (int j = 1; j < k; ++j) {
    Eigen::VectorXd t_next = 2.0 * Y(t) - t_prev;
    const double s_next = 2.0 * sigma * s - s_prev;
    t_prev = std::move(t), t = std::move(t_next);
    s_prev = s, s = s_next;
  }
  return t / s;
}

double chebyshevT(int k, double y) { return std::cosh(k * std::acosh(y)); }  // y ≥ 1

double energyNorm(const SparseMatrix& A, const Eigen::VectorXd& e) { return std::sqrt(e.dot(A * e)); }

}  // namespace

TEST(ChebyshevSmoother, ErrorPropagatorIsTheScaledChebyshevPolynomialOnEverySmoothedLevel) {
  const Fixture& f = fixture();
  for (const int degree : {1, 2, 3, 4}) {
    MultigridPreconditioner mg(f.hierarchy, chebyshevOptions(degree, 7.0));
    mg.analyzePattern(f.A);
    mg.factorize(f.A);
    ASSERT_GE(mg.numLevels(), 3);
    for (int l = 0; l + 1 < mg.numLevels(); ++l) {
      SCOPED_TRACE("degree " + std::to_string(degree) + ", level " + std::to_string(l));
      const SparseMatrix& A = mg.levelMatrix(l);
      const BlockJacobiOperator op(A);
      const double upper = mg.chebyshevEigenvalueBound(l);
      if (l == 0) {
        EXPECT_EQ(upper, MultigridOptions{}.fine_eigenvalue_bound);
      }
      ASSERT_GT(upper, 0.0);
      // A smooth and a rough exact solution; smoothing from x = 0 leaves the error p(D⁻¹A) x*.
      std::mt19937 rng(5 + l);
      std::normal_distribution<double> g;
      Eigen::VectorXd x_star(A.rows());
      for (Eigen::Index i = 0; i < x_star.size(); ++i) x_star[i] = g(rng) + std::sin(0.01 * static_cast<double>(i));
      const Eigen::VectorXd rhs = A * x_star;
      Eigen::VectorXd x;
      mg.smoothOnly(l, rhs, x);
      const Eigen::VectorXd error = x_star - x;
      const Eigen::VectorXd expected = chebyshevErrorPropagator(op, x_star, degree, upper / 7.0, upper);
      // The smoother multiplies by a float copy of A: agreement to float precision.
      EXPECT_LT((error - expected).norm() / expected.norm(), 1e-5)
          << "|error| " << error.norm() << ", |expected| " << expected.norm();
      // |p| ≤ 1 on the spectrum: the energy norm of the error never grows.
      EXPECT_LT(energyNorm(A, error), energyNorm(A, x_star));
    }
  }
}

TEST(ChebyshevSmoother, DampsItsIntervalAsTheoryPredictsAndNeverAmplifies) {
  // The top eigenvector of D⁻¹A (λ in [λ_max/ratio, λ_max]) is damped by |p(λ)| ≤ 1/T_k(σ) (not
  // monotonically in k: p oscillates on the interval), and a random error's energy norm shrinks.
  const Fixture& f = fixture();
  const BlockJacobiOperator op(f.A);
  Eigen::VectorXd top;
  const double lambda = op.largestEigenvalue(&top);
  ASSERT_GT(lambda, 1.0);
  ASSERT_LT(lambda, MultigridOptions{}.fine_eigenvalue_bound);  // the bound holds
  std::mt19937 rng(9);
  std::normal_distribution<double> g;
  Eigen::VectorXd rough(f.A.rows());
  for (Eigen::Index i = 0; i < rough.size(); ++i) rough[i] = g(rng);
  for (int v : f.fixed) rough.segment<3>(3 * v).setZero(), top.segment<3>(3 * v).setZero();
  for (const int degree : {1, 2, 3, 5}) {
    SCOPED_TRACE("degree " + std::to_string(degree));
    const double ratio = 10.0;
    MultigridPreconditioner mg(f.hierarchy, chebyshevOptions(degree, ratio));
    mg.analyzePattern(f.A);
    mg.factorize(f.A);
    const double upper = mg.chebyshevEigenvalueBound(0), lower = upper / ratio;
    const double theta = 0.5 * (upper + lower), delta = 0.5 * (upper - lower);
    const double bound = 1.0 / chebyshevT(degree, theta / delta);
    const double predicted = std::abs(std::cos(degree * std::acos((theta - lambda) / delta))) * bound;
    Eigen::VectorXd x;
    mg.smoothOnly(0, f.A * top, x);
    const double top_factor = (top - x).norm() / top.norm();
    EXPECT_NEAR(top_factor, predicted, 0.02 * bound + 1e-4) << "lambda " << lambda;
    EXPECT_LE(top_factor, bound * 1.02);
    mg.smoothOnly(0, f.A * rough, x);
    const double rough_factor = energyNorm(f.A, rough - x) / energyNorm(f.A, rough);
    EXPECT_LT(rough_factor, 1.0);
    EXPECT_GT(rough_factor, 0.0);
  }
}

TEST(ChebyshevSmoother, IntervalCoversTheSpectrumOfEveryLevel) {
  // |p| < 1 on the spectrum of D⁻¹A as long as λ_max(D⁻¹A) < λ_max (1 + 1/ratio): the fine bound and
  // the safety factor on the coarse levels' power-iteration estimates must give that.
  const Fixture& f = fixture();
  const MultigridOptions o = chebyshevOptions(2);
  MultigridPreconditioner mg(f.hierarchy, o);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  for (int l = 0; l + 1 < mg.numLevels(); ++l) {
    SCOPED_TRACE("level " + std::to_string(l));
    const double lambda = BlockJacobiOperator(mg.levelMatrix(l)).largestEigenvalue();
    const double upper = mg.chebyshevEigenvalueBound(l);
    EXPECT_LT(lambda, upper * (1.0 + 1.0 / o.chebyshev_ratio)) << "upper end " << upper;
    if (l > 0) {
      EXPECT_GT(upper, 0.9 * lambda);  // an estimate, not a blind bound
    }
  }
}

TEST(ChebyshevSmoother, VCycleIsSymmetricPositiveDefinite) {
  const Fixture& f = fixture();
  std::mt19937 rng(3);
  std::normal_distribution<double> g;
  Eigen::VectorXd u(f.b.size()), v(f.b.size());
  for (Eigen::Index i = 0; i < u.size(); ++i) u[i] = g(rng), v[i] = g(rng);
  for (const int degree : {1, 2, 3}) {
    SCOPED_TRACE("degree " + std::to_string(degree));
    MultigridPreconditioner mg(f.hierarchy, chebyshevOptions(degree));
    mg.analyzePattern(f.A);
    mg.factorize(f.A);
    Eigen::VectorXd Mu(u.size()), Mv(v.size()), Mb(v.size());
    mg.apply(u, Mu);
    mg.apply(v, Mv);
    EXPECT_NEAR(u.dot(Mv) / v.dot(Mu), 1.0, 1e-10);
    EXPECT_GT(u.dot(Mu), 0.0);
    EXPECT_GT(v.dot(Mv), 0.0);
    // Positive definite also on the smoothest and the roughest modes: the load and A times it.
    mg.apply(f.b, Mb);
    EXPECT_GT(f.b.dot(Mb), 0.0);
    const Eigen::VectorXd Ab = f.A * f.b;
    mg.apply(Ab, Mb);
    EXPECT_GT(Ab.dot(Mb), 0.0);
  }
}

TEST(ChebyshevSmoother, PcgConvergesToTheDirectSolutionWithFewerIterationsThanJacobiOfTheSameCost) {
  // Degree k costs what k Jacobi sweeps cost; the polynomial must not need more iterations.
  const Fixture& f = fixture();
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(f.A)};
  const Eigen::VectorXd reference = ldlt.solve(f.b);
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-10;
  pcg.max_iterations = 500;
  for (const int degree : {1, 2, 3}) {
    SCOPED_TRACE("degree " + std::to_string(degree));
    MultigridOptions jacobi;
    jacobi.pre_smoothing_steps = jacobi.post_smoothing_steps = degree;
    MultigridPcgSolver with_jacobi(f.hierarchy, pcg, jacobi), with_chebyshev(f.hierarchy, pcg, chebyshevOptions(degree));
    with_jacobi.analyzePattern(f.A);
    with_jacobi.factorize(f.A);
    with_chebyshev.analyzePattern(f.A);
    with_chebyshev.factorize(f.A);
    Eigen::VectorXd xj = Eigen::VectorXd::Zero(f.b.size()), xc = xj;
    const SolveStats sj = with_jacobi.solve(f.b, xj);
    const SolveStats sc = with_chebyshev.solve(f.b, xc);
    ASSERT_TRUE(sc.converged);
    EXPECT_LT((xc - reference).norm() / reference.norm(), 1e-6);
    EXPECT_LE(sc.iterations, sj.iterations) << "jacobi " << sj.iterations << ", chebyshev " << sc.iterations;
  }
}

TEST(ChebyshevSmoother, RejectsAnEmptyIntervalAndSmoothingWithoutFactorization) {
  const Fixture& f = fixture();
  for (const double ratio : {1.0, 0.5, -2.0, std::nan("")}) {
    MultigridOptions o = chebyshevOptions(2, ratio);
    EXPECT_THROW(MultigridPreconditioner(f.hierarchy, o), std::invalid_argument) << "ratio " << ratio;
  }
  MultigridOptions o = chebyshevOptions(2);
  o.chebyshev_eigenvalue_safety = 0.9;
  EXPECT_THROW(MultigridPreconditioner(f.hierarchy, o), std::invalid_argument);
  MultigridPreconditioner mg(f.hierarchy, chebyshevOptions(2));
  Eigen::VectorXd x;
  EXPECT_THROW(mg.smoothOnly(0, f.b, x), std::logic_error);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  EXPECT_THROW(mg.smoothOnly(mg.numLevels() - 1, f.b, x), std::out_of_range);
  EXPECT_THROW(mg.smoothOnly(0, f.b.head(9), x), std::invalid_argument);
}

TEST(JacobiSmoother, SmoothOnlyIsDampedBlockJacobiFromZero) {
  // The existing smoother through the same test entry: one sweep from zero is x = ω D⁻¹ b.
  const Fixture& f = fixture();
  MultigridPreconditioner mg(f.hierarchy);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  const BlockJacobiOperator op(f.A);
  Eigen::VectorXd x, expected(f.b.size());
  mg.smoothOnly(0, f.b, x);
  for (size_t i = 0; i < op.Dinv.size(); ++i) expected.segment<3>(3 * i) = mg.jacobiDamping(0) * op.Dinv[i] * f.b.segment<3>(3 * i);
  EXPECT_LT((x - expected).norm() / expected.norm(), 1e-12);
  EXPECT_EQ(mg.chebyshevEigenvalueBound(0), 0.0);
}
