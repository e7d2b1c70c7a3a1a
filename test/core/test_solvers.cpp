// Linear solvers of the time step: CHOLMOD, Jacobi-PCG and multigrid-PCG on the system of an
// implicit step of linear elasticity (A = M/dt² + K, Dirichlet on the chest wall) of the phantom
// (solver_fixture.h): agreement with a direct reference, fixed DOFs, errors, PCG's limits, reports and
// block products, the SIMD kernels. The multigrid itself is tested in test_multigrid.cpp.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/SparseCholesky>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/block_kernels.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "solver_fixture.h"

using namespace breast_sim::core;
using namespace breast_sim::core::test_fixtures;

namespace {

struct NamedSolver {
  std::string name;
  std::unique_ptr<LinearSolver> solver;
};

std::vector<NamedSolver> allSolvers(double tolerance) {
  PcgOptions pcg;
  pcg.relative_tolerance = tolerance;
  pcg.max_iterations = 20000;
  std::vector<NamedSolver> s;
  s.push_back({"cholmod", std::make_unique<CholmodSolver>()});
  s.push_back({"pcg-jacobi", std::make_unique<PcgSolver>(pcg)});
  s.push_back({"pcg-multigrid", std::make_unique<MultigridPcgSolver>(fixture().hierarchy, pcg)});
  MultigridOptions gauss_seidel;
  gauss_seidel.smoother = MultigridOptions::Smoother::kGaussSeidel;
  s.push_back({"pcg-multigrid", std::make_unique<MultigridPcgSolver>(fixture().hierarchy, pcg, gauss_seidel)});
  return s;
}

}  // namespace

TEST(Solvers, AllAgreeWithASparseLdltReferenceAtTightTolerance) {
  const Fixture& f = fixture();
  for (auto& [name, solver] : allSolvers(1e-12)) {
    SCOPED_TRACE(name);
    solver->analyzePattern(f.A);
    solver->factorize(f.A);
    Eigen::VectorXd x = Eigen::VectorXd::Zero(f.b.size());
    const SolveStats s = solver->solve(f.b, x);
    EXPECT_EQ(solver->name(), name);
    EXPECT_TRUE(s.converged) << s.iterations << " iterations, residual " << s.relative_residual;
    EXPECT_LE(relativeDifference(x, f.reference), 1e-6);
    EXPECT_LE((f.b - f.A * x).norm() / f.b.norm(), name == "cholmod" ? 1e-12 : 1.01e-12);
  }
}

TEST(Solvers, KeepFixedDofsExactlyAtTheirValue) {
  const Fixture& f = fixture();
  for (auto& [name, solver] : allSolvers(1e-6)) {
    SCOPED_TRACE(name);
    solver->analyzePattern(f.A);
    solver->factorize(f.A);
    Eigen::VectorXd x = Eigen::VectorXd::Constant(f.b.size(), 0.5);  // a poor guess, wrong on fixed DOFs too
    solver->solve(f.b, x);
    for (int v : f.fixed)
      for (int i = 0; i < 3; ++i) ASSERT_EQ(x[3 * v + i], f.b[3 * v + i]) << "node " << v << " axis " << i;
  }
}

TEST(PcgSolver, WarmStartFromTheSolutionReturnsAtOnce) {
  const Fixture& f = fixture();
  for (auto& [name, solver] : allSolvers(1e-8)) {
    if (name == "cholmod") continue;
    SCOPED_TRACE(name);
    solver->analyzePattern(f.A);
    solver->factorize(f.A);
    Eigen::VectorXd x = Eigen::VectorXd::Zero(f.b.size());
    ASSERT_TRUE(solver->solve(f.b, x).converged);
    const SolveStats again = solver->solve(f.b, x);
    EXPECT_LE(again.iterations, 1);
    EXPECT_TRUE(again.converged);
  }
}

namespace {

// b with its free rows changed by a smooth and a random part (the fixed rows keep their values).
Eigen::VectorXd perturbedLoad(const Fixture& f, double scale, unsigned seed) {
  std::vector<char> fixed_row(static_cast<size_t>(f.b.size()), 0);
  for (int v : f.fixed)
    for (int i = 0; i < 3; ++i) fixed_row[static_cast<size_t>(3 * v + i)] = 1;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::VectorXd b = f.b;
  const double size = f.b.cwiseAbs().maxCoeff();
  for (Eigen::Index i = 0; i < b.size(); ++i)
    if (!fixed_row[static_cast<size_t>(i)]) b[i] = scale * b[i] + 0.3 * size * u(rng);
  return b;
}

// The slow reference of the projected guess: x_fixed + W c with (WᵀAW) c = Wᵀb, W the spanning
// vectors with their fixed rows zeroed (dense, from the matrix itself).
Eigen::VectorXd galerkinGuess(const Fixture& f, const std::vector<Eigen::VectorXd>& span, const Eigen::VectorXd& b) {
  Eigen::MatrixXd W(b.size(), static_cast<Eigen::Index>(span.size()));
  for (size_t j = 0; j < span.size(); ++j) W.col(static_cast<Eigen::Index>(j)) = span[j];
  Eigen::VectorXd x = Eigen::VectorXd::Zero(b.size());
  for (int v : f.fixed)
    for (int i = 0; i < 3; ++i) {
      W.row(3 * v + i).setZero();
      x[3 * v + i] = b[3 * v + i] / f.A.coeff(3 * v + i, 3 * v + i);
    }
  const Eigen::MatrixXd AW = f.A * W;
  const Eigen::VectorXd c = (W.transpose() * AW).ldlt().solve(W.transpose() * b);
  return x + W * c;
}

double energyNormError(const SparseMatrix& A, const Eigen::VectorXd& x, const Eigen::VectorXd& exact) {
  const Eigen::VectorXd e = x - exact;
  return std::sqrt(e.dot(A * e));
}

}  // namespace

// PcgOptions::projection_vectors: the solve starts from the combination of the caller's guess and
// the kept solutions that is nearest the solution in the A-norm. Held to a dense Galerkin projection
// built from the matrix, on the phantom's step matrix with its fixed chest-wall rows.
TEST(PcgSolver, StartsFromTheANormBestCombinationOfItsGuessAndItsLastSolutions) {
  const Fixture& f = fixture();
  PcgOptions o;
  o.relative_tolerance = 1e-11;
  o.max_iterations = 20000;
  o.projection_vectors = 3;
  PcgSolver pcg(o);
  pcg.analyzePattern(f.A);
  pcg.factorize(f.A);
  Eigen::VectorXd x1 = Eigen::VectorXd::Zero(f.b.size());
  ASSERT_TRUE(pcg.solve(f.b, x1).converged);
  Eigen::VectorXd x2 = x1;
  const Eigen::VectorXd b2 = perturbedLoad(f, 1.3, 2);
  ASSERT_TRUE(pcg.solve(b2, x2).converged);
  ASSERT_EQ(pcg.keptSolutions(), 2);

  const Eigen::VectorXd b3 = perturbedLoad(f, 1.5, 3);
  const Eigen::VectorXd exact = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>{Eigen::SparseMatrix<double>(f.A)}.solve(b3);
  PcgOptions guess_only = o;
  guess_only.max_iterations = 0;  // returns the initial guess
  struct Case {
    const char* what;
    Eigen::VectorXd guess;
    std::vector<Eigen::VectorXd> span;  // what the guess is projected onto
  };
  // A time step's guess is the newest solution itself: it is not counted twice. A zero guess adds
  // nothing to the span.
  const std::vector<Case> cases = {{"guess = newest solution", x2, {x2, x1}},
                                   {"zero guess", Eigen::VectorXd::Zero(f.b.size()), {x2, x1}},
                                   {"another guess", 0.5 * x1, {0.5 * x1, x2, x1}}};
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    PcgSolver p(o);
    p.analyzePattern(f.A);
    p.factorize(f.A);
    Eigen::VectorXd y1 = Eigen::VectorXd::Zero(f.b.size());
    p.solve(f.b, y1);
    Eigen::VectorXd y2 = y1;
    p.solve(b2, y2);
    ASSERT_EQ(y2, x2);
    p.setOptions(guess_only);
    Eigen::VectorXd x = c.guess;
    const SolveStats st = p.solve(b3, x);
    EXPECT_EQ(st.iterations, 0);
    const Eigen::VectorXd ref = galerkinGuess(f, c.span, b3);
    EXPECT_LE((x - ref).norm(), 1e-9 * ref.norm());
    for (int v : f.fixed)
      for (int i = 0; i < 3; ++i) ASSERT_EQ(x[3 * v + i], b3[3 * v + i] / f.A.coeff(3 * v + i, 3 * v + i));
    // Never farther from the solution in the A-norm than the caller's guess, fixed rows solved.
    Eigen::VectorXd plain = c.guess;
    for (int v : f.fixed)
      for (int i = 0; i < 3; ++i) plain[3 * v + i] = b3[3 * v + i] / f.A.coeff(3 * v + i, 3 * v + i);
    EXPECT_LT(energyNormError(f.A, x, exact), energyNormError(f.A, plain, exact));
    // The residual the solve reported is that of the projected guess.
    EXPECT_NEAR(st.relative_residual, (b3 - f.A * x).norm() / b3.norm(), 1e-9 * st.relative_residual);
  }
}

TEST(PcgSolver, ASolutionInTheSpanOfItsLastSolutionsReturnsAtOnce) {
  const Fixture& f = fixture();
  PcgOptions o;
  o.relative_tolerance = 1e-9;
  o.max_iterations = 20000;
  PcgSolver pcg(o);
  ASSERT_EQ(o.projection_vectors, 2);  // the default
  pcg.analyzePattern(f.A);
  pcg.factorize(f.A);
  Eigen::VectorXd x = Eigen::VectorXd::Zero(f.b.size());
  const SolveStats first = pcg.solve(f.b, x);
  ASSERT_TRUE(first.converged);
  ASSERT_GT(first.iterations, 10);
  // Twice the load on the free rows, the fixed rows kept: 2 x on the free rows, from a zero guess.
  Eigen::VectorXd b = 2.0 * f.b;
  for (int v : f.fixed)
    for (int i = 0; i < 3; ++i) b[3 * v + i] = f.b[3 * v + i];
  Eigen::VectorXd y = Eigen::VectorXd::Zero(f.b.size());
  const SolveStats s = pcg.solve(b, y);
  EXPECT_TRUE(s.converged);
  EXPECT_EQ(s.iterations, 0);
  // Without the kept solutions it iterates as the first solve did.
  pcg.forgetSolutions();
  EXPECT_EQ(pcg.keptSolutions(), 0);
  Eigen::VectorXd z = Eigen::VectorXd::Zero(f.b.size());
  EXPECT_GT(pcg.solve(b, z).iterations, 10);
  // A new analysis drops them too.
  EXPECT_EQ(pcg.keptSolutions(), 1);
  pcg.analyzePattern(f.A);
  EXPECT_EQ(pcg.keptSolutions(), 0);
}

TEST(PcgSolver, ProjectionVectorsOutsideTheirRangeAreRefusedByName) {
  for (int k : {0, -1, kMaxProjectionVectors + 1}) {
    PcgOptions o;
    o.projection_vectors = k;
    try {
      PcgSolver pcg(o);
      ADD_FAILURE() << k << " accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("projection_vectors " + std::to_string(k)), std::string::npos) << e.what();
    }
    PcgSolver pcg;
    EXPECT_THROW(pcg.setOptions(o), std::invalid_argument);
    EXPECT_EQ(pcg.options().projection_vectors, PcgOptions{}.projection_vectors);
  }
}

TEST(PcgSolver, ZeroRightHandSideGivesZeroAtOnce) {
  const Fixture& f = fixture();
  PcgSolver pcg;
  pcg.analyzePattern(f.A);
  pcg.factorize(f.A);
  Eigen::VectorXd x = Eigen::VectorXd::Ones(f.b.size());
  const SolveStats s = pcg.solve(Eigen::VectorXd::Zero(f.b.size()), x);
  EXPECT_EQ(s.iterations, 0);
  EXPECT_TRUE(s.converged);
  EXPECT_EQ(x.cwiseAbs().maxCoeff(), 0.0);
}

TEST(Solvers, NonPositiveDefiniteMatrixIsAClearError) {
  const Fixture& f = fixture();
  // A free DOF with a negative diagonal: indefinite, with the same pattern.
  std::vector<bool> is_fixed(static_cast<size_t>(f.A.rows() / 3), false);
  for (int v : f.fixed) is_fixed[v] = true;
  int node = 0;
  while (is_fixed[node]) ++node;
  const int dof = 3 * node + 1;
  SparseMatrix bad = f.A;
  bad.coeffRef(dof, dof) = -bad.coeff(dof, dof);
  for (auto& [name, solver] : allSolvers(1e-8)) {
    SCOPED_TRACE(name);
    solver->analyzePattern(bad);
    try {
      solver->factorize(bad);
      FAIL() << "expected an error";
    } catch (const std::runtime_error& e) {
      const std::string what = e.what();
      EXPECT_NE(what.find(name == "cholmod" ? "cholmod" : name == "pcg-jacobi" ? "pcg-jacobi" : "multigrid"),
                std::string::npos)
          << what;
      EXPECT_NE(what.find("not positive definite"), std::string::npos) << what;
      EXPECT_NE(what.find(std::to_string(name == "cholmod" || name == "pcg-jacobi" ? dof : node)), std::string::npos)
          << what;
    }
  }
}

TEST(PcgSolver, IndefiniteMatrixWithPositiveDiagonalIsReportedDuringTheSolve) {
  // [1 2; 2 1] has eigenvalues 3 and −1; b = (1, −1) points at the negative one.
  SparseMatrix A(2, 2);
  A.insert(0, 0) = 1, A.insert(0, 1) = 2, A.insert(1, 0) = 2, A.insert(1, 1) = 1;
  A.makeCompressed();
  PcgSolver pcg;
  pcg.analyzePattern(A);
  pcg.factorize(A);
  Eigen::VectorXd x;
  try {
    pcg.solve(Eigen::Vector2d(1, -1), x);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("pcg-jacobi: the matrix is not positive definite"), std::string::npos)
        << e.what();
  }
}

TEST(Solvers, ValuesChangeWithoutANewAnalysis) {
  // A stiffer material on the same pattern: factorize again, solve again, still right.
  const Fixture& f = fixture();
  const SparseMatrix A2 = implicitStepMatrix(f.model.mesh, f.fixed, 6000.0, 0.45);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(A2)};
  const Eigen::VectorXd reference = ldlt.solve(f.b);
  for (auto& [name, solver] : allSolvers(1e-10)) {
    SCOPED_TRACE(name);
    solver->analyzePattern(f.A);
    solver->factorize(f.A);
    solver->factorize(A2);
    Eigen::VectorXd x;
    solver->solve(f.b, x);
    EXPECT_LE(relativeDifference(x, reference), 1e-6);
  }
}

TEST(PcgSolver, StopsAtTheIterationLimitAndSaysSo) {
  const Fixture& f = fixture();
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-12;
  pcg.max_iterations = 3;
  PcgSolver solver(pcg);
  solver.analyzePattern(f.A);
  solver.factorize(f.A);
  Eigen::VectorXd x;
  const SolveStats s = solver.solve(f.b, x);
  EXPECT_FALSE(s.converged);
  EXPECT_EQ(s.iterations, 3);
  EXPECT_NEAR(s.relative_residual, (f.b - f.A * x).norm() / f.b.norm(), 1e-12);
  EXPECT_GT(s.relative_residual, 1e-12);
}

// The block-by-block products (fast path) against the row-wise ones (slow reference): the same
// system with two DOFs swapped (x of node 0, y of node 1) is no longer in block layout, and Jacobi-PCG
// is equivariant under the permutation, so ten iterations on both give the same iterate up to
// round-off — with the limit reached, the reported residual is the recursive one on both.
TEST(PcgSolver, BlockProductsEqualTheRowWiseOnes) {
  const Fixture& f = fixture();
  const Eigen::Index n = f.A.rows();
  Eigen::VectorXi perm = Eigen::VectorXi::LinSpaced(static_cast<int>(n), 0, static_cast<int>(n) - 1);
  std::swap(perm[0], perm[4]);
  const Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> P(perm);
  SparseMatrix Ap = P * f.A * P.transpose();
  Ap.makeCompressed();
  const Eigen::VectorXd bp = P * f.b;
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-14;
  pcg.max_iterations = 10;
  PcgSolver blocks(pcg), rows(pcg);
  blocks.analyzePattern(f.A);
  rows.analyzePattern(Ap);
  EXPECT_TRUE(blocks.blockLayout());
  EXPECT_FALSE(rows.blockLayout());
  blocks.factorize(f.A);
  rows.factorize(Ap);
  Eigen::VectorXd x, y;
  const SolveStats sb = blocks.solve(f.b, x);
  const SolveStats sr = rows.solve(bp, y);
  EXPECT_EQ(sb.iterations, 10);
  EXPECT_EQ(sr.iterations, 10);
  EXPECT_LE((x - P.transpose() * y).norm(), 1e-10 * x.norm());
  EXPECT_NEAR(sb.relative_residual, sr.relative_residual, 1e-10 * sr.relative_residual);
  EXPECT_NEAR(sb.relative_residual, (f.b - f.A * x).norm() / f.b.norm(), 1e-6 * sb.relative_residual);
}

// A matrix with the analysed size and entry count but other row lengths is refused by both PCG and
// the multigrid (their block lists are laid out over the analysed rows), not read out of bounds.
TEST(Solvers, OtherRowLengthsWithTheSameEntryCountAreRefused) {
  const Fixture& f = fixture();
  std::vector<Eigen::Triplet<double>> t;
  for (int r = 0; r < f.A.rows(); ++r)
    for (SparseMatrix::InnerIterator it(f.A, r); it; ++it) t.emplace_back(r, static_cast<int>(it.col()), it.value());
  // Move one off-diagonal entry of the last row into the first row's unused columns.
  const int last = static_cast<int>(f.A.rows()) - 1;
  auto moved = std::find_if(t.begin(), t.end(), [&](const auto& e) { return e.row() == last && e.col() != last; });
  ASSERT_NE(moved, t.end());
  int free_col = 0;
  while (f.A.coeff(0, free_col) != 0.0 || free_col == 0) ++free_col;
  *moved = Eigen::Triplet<double>(0, free_col, 0.0);
  SparseMatrix B(f.A.rows(), f.A.cols());
  B.setFromTriplets(t.begin(), t.end());
  B.makeCompressed();
  ASSERT_EQ(B.nonZeros(), f.A.nonZeros());
  for (auto& [name, solver] : allSolvers(1e-8)) {
    if (name == "cholmod") continue;  // CHOLMOD analyses its own copy
    SCOPED_TRACE(name);
    solver->analyzePattern(f.A);
    EXPECT_THROW(solver->factorize(B), std::logic_error);
  }
  MultigridPreconditioner mg(f.hierarchy);  // on its own, without PCG's check in front
  mg.analyzePattern(f.A);
  EXPECT_THROW(mg.factorize(B), std::logic_error);
  mg.factorize(f.A);  // the analysed pattern still works
}

// The AVX2/FMA kernels (fast path) against the portable scalar ones (reference) on the fixture's
// matrix: the float-block residual of the V-cycle and PCG's block products. One accumulator per
// block entry in both (the AVX2 residual two sets), so they differ in the last bits only.
TEST(BlockKernels, SimdEqualsScalar) {
  if (!blockKernelsHaveSimd()) GTEST_SKIP() << "this processor has no AVX2/FMA";
  const Fixture& f = fixture();
  const int* outer = f.A.outerIndexPtr();
  const int* inner = f.A.innerIndexPtr();
  const double* val = f.A.valuePtr();
  const int nodes = static_cast<int>(f.A.rows() / 3);
  std::vector<int> start(1, 0), col;
  std::vector<float> blocks;
  for (int i = 0; i < nodes; ++i) {
    const int len = outer[3 * i + 1] - outer[3 * i];
    for (int m = 0; m < len; m += 3) {
      col.push_back(inner[outer[3 * i] + m] / 3);
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) blocks.push_back(static_cast<float>(val[outer[3 * i + r] + m + c]));
    }
    start.push_back(static_cast<int>(col.size()));
  }
  std::mt19937 rng(11);
  std::normal_distribution<double> g;
  Eigen::VectorXd x(f.A.rows()), b(f.A.rows());
  for (Eigen::Index i = 0; i < x.size(); ++i) x[i] = g(rng), b[i] = g(rng);
  // A range that starts and ends inside the matrix, and the whole of it.
  for (const auto& [i0, i1] : {std::pair<int, int>{0, nodes}, std::pair<int, int>{nodes / 3, nodes - 7}}) {
    Eigen::VectorXd ts = Eigen::VectorXd::Zero(x.size()), tv = ts;
    blockResidualRows(blocks.data(), col.data(), start.data(), b.data(), x.data(), ts.data(), i0, i1, false);
    blockResidualRows(blocks.data(), col.data(), start.data(), b.data(), x.data(), tv.data(), i0, i1, true);
    EXPECT_LE((ts - tv).norm(), 1e-12 * ts.norm());
    EXPECT_GT(ts.segment(3 * i0, 3 * (i1 - i0)).norm(), 0.0);
    // The AVX-512F residual (where the processor has it, as here) does the AVX2 one's arithmetic.
    Eigen::VectorXd t2 = Eigen::VectorXd::Zero(x.size());
    blockResidualRowsAvx2(blocks.data(), col.data(), start.data(), b.data(), x.data(), t2.data(), i0, i1);
    for (Eigen::Index r = 0; r < x.size(); ++r) ASSERT_EQ(t2[r], tv[r]) << "row " << r;
    for (const Eigen::VectorXd* t : {&ts, &tv})  // nothing written outside the range
      EXPECT_EQ(t->head(3 * i0).norm() + t->tail(x.size() - 3 * i1).norm(), 0.0);
    for (const bool residual : {false, true}) {
      Eigen::VectorXd ys = Eigen::VectorXd::Zero(x.size()), yv = ys;
      const double ss = blockProductRows(outer, val, start.data(), col.data(), b.data(), x.data(), ys.data(), i0, i1,
                                         residual, false);
      const double sv = blockProductRows(outer, val, start.data(), col.data(), b.data(), x.data(), yv.data(), i0, i1,
                                         residual, true);
      EXPECT_LE((ys - yv).norm(), 1e-12 * ys.norm());
      EXPECT_NEAR(ss, sv, 1e-12 * std::abs(ss));
    }
  }
  // PCG's product with the float blocks: the residual kernel's sums (y = −(0 − A x), bit for bit,
  // on each instruction set) and, against a double product of the rounded values, to round-off.
  SparseMatrix Af = f.A;
  for (Eigen::Index k = 0; k < Af.nonZeros(); ++k)
    Af.valuePtr()[k] = static_cast<double>(static_cast<float>(Af.valuePtr()[k]));
  const Eigen::VectorXd Afx = Af * x;
  const Eigen::VectorXd zero = Eigen::VectorXd::Zero(x.size());
  for (const bool simd : {false, true}) {
    Eigen::VectorXd yf(x.size()), t(x.size());
    const double xAfx = floatBlockProductRows(blocks.data(), col.data(), start.data(), x.data(), yf.data(), 0, nodes, simd);
    blockResidualRows(blocks.data(), col.data(), start.data(), zero.data(), x.data(), t.data(), 0, nodes, simd);
    for (Eigen::Index r = 0; r < x.size(); ++r) ASSERT_EQ(yf[r], -t[r]) << "row " << r << (simd ? " simd" : " scalar");
    EXPECT_LE((yf - Afx).norm(), 1e-12 * Afx.norm());
    EXPECT_NEAR(xAfx, x.dot(Afx), 1e-10 * std::abs(x.dot(Afx)));
    // The whole product over chunks, on the team: the same sum as one range.
    Eigen::VectorXd yp(x.size());
    EXPECT_EQ(floatBlockProduct(blocks.data(), col.data(), start.data(), x.data(), yp.data(), nodes, simd, true),
              floatBlockProduct(blocks.data(), col.data(), start.data(), x.data(), yf.data(), nodes, simd, false));
    EXPECT_EQ((yp - yf).norm(), 0.0);
  }

  // The double product against Eigen's (slow reference), over all rows.
  Eigen::VectorXd y(x.size());
  const double xAx = blockProductRows(outer, val, start.data(), col.data(), nullptr, x.data(), y.data(), 0, nodes, false, true);
  const Eigen::VectorXd Ax = f.A * x;
  EXPECT_LE((y - Ax).norm(), 1e-12 * Ax.norm());
  EXPECT_NEAR(xAx, x.dot(Ax), 1e-10 * std::abs(x.dot(Ax)));
}

namespace {
// Jacobi that also offers PCG a float copy of the matrix, made from its values times `scale` (1 =
// the matrix rounded, as the multigrid keeps it); NaN values for a copy that must not be read; a
// node count off by `extra_nodes` for a copy of the wrong size.
class FloatCopyJacobi : public JacobiPreconditioner {
 public:
  explicit FloatCopyJacobi(double scale, int extra_nodes = 0) : scale_(scale), extra_nodes_(extra_nodes) {}
  void factorize(const SparseMatrix& A) override {
    JacobiPreconditioner::factorize(A);
    const int* outer = A.outerIndexPtr();
    const int* inner = A.innerIndexPtr();
    const double* val = A.valuePtr();
    nodes_ = static_cast<int>(A.rows() / 3);
    start_.assign(1, 0);
    col_.clear();
    val_.clear();
    for (int i = 0; i < nodes_; ++i) {
      const int len = outer[3 * i + 1] - outer[3 * i];
      for (int m = 0; m < len; m += 3) {
        col_.push_back(inner[outer[3 * i] + m] / 3);
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) val_.push_back(static_cast<float>(scale_ * val[outer[3 * i + r] + m + c]));
      }
      start_.push_back(static_cast<int>(col_.size()));
    }
  }
  FloatBlocks floatBlocks() const override { return {val_.data(), col_.data(), start_.data(), nodes_ + extra_nodes_}; }

 private:
  double scale_;
  int extra_nodes_;
  int nodes_ = 0;
  std::vector<int> start_, col_;
  std::vector<float> val_;
};

struct FloatCopySolve {
  SolveStats stats;
  Eigen::VectorXd x;
};

FloatCopySolve solveWithFloatCopy(const Fixture& f, double tolerance, std::unique_ptr<Preconditioner> pre) {
  PcgOptions o;
  o.relative_tolerance = tolerance;
  PcgSolver pcg(o, std::move(pre));
  pcg.analyzePattern(f.A);
  pcg.factorize(f.A);
  FloatCopySolve s;
  s.x = Eigen::VectorXd::Zero(f.b.size());
  s.stats = pcg.solve(f.b, s.x);
  return s;
}
}  // namespace

// PCG iterates with the preconditioner's float copy of A at tolerances of at least
// kFloatProductMinTolerance, and declares convergence on the double matrix's residual alone: the
// rounded copy follows the double iteration (the slow reference); a wrong copy (100× too stiff, or
// negative definite) still ends within the tolerance of the double matrix, because a refused
// confirmation or a pᵀAp ≤ 0 of the copy switches to the double products; below that tolerance the
// copy is not read; a copy of the wrong size is refused by factorize().
TEST(PcgSolver, IteratesWithTheFloatCopyAndConvergesOnTheDoubleMatrix) {
  const Fixture& f = fixture();
  const double tol = 1e-3;
  ASSERT_GE(tol, kFloatProductMinTolerance);
  const FloatCopySolve exact = solveWithFloatCopy(f, tol, std::make_unique<JacobiPreconditioner>());
  const FloatCopySolve rounded = solveWithFloatCopy(f, tol, std::make_unique<FloatCopyJacobi>(1.0));
  const FloatCopySolve wrong = solveWithFloatCopy(f, tol, std::make_unique<FloatCopyJacobi>(100.0));
  const FloatCopySolve negative = solveWithFloatCopy(f, tol, std::make_unique<FloatCopyJacobi>(-1.0));
  for (const FloatCopySolve* s : {&exact, &rounded, &wrong, &negative}) {
    ASSERT_TRUE(s->stats.converged);
    const double true_residual = (f.b - f.A * s->x).norm() / f.b.norm();
    EXPECT_LE(true_residual, tol);
    EXPECT_NEAR(s->stats.relative_residual, true_residual, 1e-9 * true_residual);
  }
  EXPECT_EQ(rounded.stats.iterations, exact.stats.iterations);
  EXPECT_LE((rounded.x - exact.x).norm(), 1e-4 * exact.x.norm());
  // The wrong copy's iterate was read: it converged to (100 A)⁻¹ b first, which the double residual
  // refused, and the solve went on from there with the double matrix (iterating with the copy again
  // would take each restart only 1 % nearer).
  EXPECT_GT(wrong.stats.iterations, exact.stats.iterations);
  EXPECT_LE(wrong.stats.iterations, 3 * exact.stats.iterations);
  EXPECT_LE(negative.stats.iterations, exact.stats.iterations + 1);

  PcgSolver sized(PcgOptions{}, std::make_unique<FloatCopyJacobi>(1.0, 1));
  sized.analyzePattern(f.A);
  EXPECT_THROW(sized.factorize(f.A), std::logic_error);
  Eigen::VectorXd x;
  EXPECT_THROW(sized.solve(f.b, x), std::logic_error);

  const double nan = std::numeric_limits<double>::quiet_NaN();
  const FloatCopySolve tight = solveWithFloatCopy(f, kFloatProductMinTolerance / 10, std::make_unique<FloatCopyJacobi>(nan));
  EXPECT_TRUE(tight.stats.converged);
  EXPECT_TRUE(tight.x.allFinite());
}

// The tolerance can be changed between solves (the node loosens it for tracking frames): a looser
// one stops earlier, at a residual within it; direct solvers report 0 and ignore it; nonsense is
// refused and leaves the old tolerance.
TEST(LinearSolver, RelativeToleranceCanBeChangedBetweenSolves) {
  const Fixture& f = fixture();
  MultigridPcgSolver pcg(f.hierarchy);
  pcg.analyzePattern(f.A);
  pcg.factorize(f.A);
  LinearSolver& solver = pcg;
  EXPECT_EQ(solver.relativeTolerance(), 1e-8);
  Eigen::VectorXd tight, loose;
  const int tight_iterations = solver.solve(f.b, tight).iterations;
  solver.setRelativeTolerance(1e-2);
  EXPECT_EQ(solver.relativeTolerance(), 1e-2);
  const SolveStats s = solver.solve(f.b, loose);
  EXPECT_TRUE(s.converged);
  EXPECT_LE(s.relative_residual, 1e-2);
  EXPECT_LT(s.iterations, tight_iterations / 2);
  for (double bad : {0.0, 1.0, -1e-3, std::nan("")}) EXPECT_THROW(solver.setRelativeTolerance(bad), std::invalid_argument);
  EXPECT_EQ(solver.relativeTolerance(), 1e-2);

  CholmodSolver cholmod;
  LinearSolver& direct = cholmod;
  EXPECT_EQ(direct.relativeTolerance(), 0.0);
  EXPECT_NO_THROW(direct.setRelativeTolerance(0.1));
  EXPECT_EQ(direct.relativeTolerance(), 0.0);
}

namespace {
/// Jacobi, and what PCG reports to the preconditioner after each solve.
class ReportRecorder : public JacobiPreconditioner {
 public:
  void reportConvergence(int iterations, double residual_reduction) override {
    reports.emplace_back(iterations, residual_reduction);
  }
  std::vector<std::pair<int, double>> reports;
};
}  // namespace

TEST(PcgSolver, ReportsItsResidualReductionToThePreconditioner) {
  const Fixture& f = fixture();
  for (int cap : {5, 1000}) {
    SCOPED_TRACE("iteration limit " + std::to_string(cap));
    PcgOptions o;
    o.relative_tolerance = 1e-6;
    o.max_iterations = cap;
    auto recorder = std::make_unique<ReportRecorder>();
    ReportRecorder* rec = recorder.get();
    PcgSolver pcg(o, std::move(recorder));
    pcg.analyzePattern(f.A);
    pcg.factorize(f.A);
    Eigen::VectorXd x0 = Eigen::VectorXd::Constant(f.b.size(), 1e-4), x = x0;
    const SolveStats st = pcg.solve(f.b, x);
    ASSERT_EQ(rec->reports.size(), 1u);
    EXPECT_EQ(rec->reports[0].first, st.iterations);
    // r_0 is the residual after PCG solved the decoupled (fixed) rows exactly.
    for (int i : pcg.decoupledRows()) x0[i] = f.b[i] / f.A.coeff(i, i);
    const double reduction = (f.b - f.A * x).norm() / (f.b - f.A * x0).norm();
    EXPECT_NEAR(rec->reports[0].second, reduction, 1e-6 * reduction);
    // A warm start at the answer does not iterate and reports nothing.
    pcg.solve(f.b, x);
    if (st.converged) EXPECT_EQ(rec->reports.size(), 1u);
  }
}
