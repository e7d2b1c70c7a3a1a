// The geometric multigrid of solver/multigrid.h on the phantom's step system (solver_fixture.h): the
// mesh hierarchy and its prolongations, the Galerkin product, the V-cycle as a preconditioner (fixed
// DOFs, symmetry, the coarsest solve, the damping, stale coarse operators and their adaptive renewal)
// and PCG with it.
#include <gtest/gtest.h>

#include <algorithm>
#include <numeric>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include <omp.h>

#include <Eigen/Dense>
#include <Eigen/SparseCholesky>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "solver_fixture.h"

using namespace breast_sim::core;
using namespace breast_sim::core::test_fixtures;

namespace {

std::vector<double> freeMask(const SparseMatrix& A, const std::vector<int>& fixed_nodes) {
  std::vector<double> free(static_cast<size_t>(A.rows()), 1.0);
  for (int v : fixed_nodes)
    for (int i = 0; i < 3; ++i) free[3 * v + i] = 0.0;
  return free;
}

}  // namespace

TEST(MeshHierarchy, CoarseMeshesOfThePhantomShrinkDownToTheRequestedSize) {
  const Fixture& f = fixture();
  ASSERT_GE(f.hierarchy.numLevels(), 3);
  for (int l = 0; l + 1 < f.hierarchy.numLevels(); ++l) {
    SCOPED_TRACE("level " + std::to_string(l));
    EXPECT_LT(f.hierarchy.mesh(l + 1).numTets(), 0.8 * f.hierarchy.mesh(l).numTets());
    EXPECT_NEAR(f.hierarchy.mesh(l + 1).volume() / f.hierarchy.mesh(l).volume(), 1.0, 0.05);
    EXPECT_EQ(f.hierarchy.prolongation(l).rows(), f.hierarchy.mesh(l).numNodes());
    EXPECT_EQ(f.hierarchy.prolongation(l).cols(), f.hierarchy.mesh(l + 1).numNodes());
  }
  EXPECT_LE(f.hierarchy.mesh(f.hierarchy.numLevels() - 1).numTets(), 600);
}

TEST(Prolongation, RowsArePartitionsOfUnityAndReproduceLinearFieldsInsideTheCoarseMesh) {
  const Fixture& f = fixture();
  Eigen::Matrix3d G;  // an affine displacement u(x) = G x + c [m]
  G << 0.1, -0.2, 0.05, 0.3, 0.0, -0.1, 0.02, 0.04, -0.3;
  const Eigen::RowVector3d c(0.001, -0.002, 0.003);
  for (int l = 0; l + 1 < f.hierarchy.numLevels(); ++l) {
    SCOPED_TRACE("level " + std::to_string(l));
    const TetMesh& fine = f.hierarchy.mesh(l);
    const TetMesh& coarse = f.hierarchy.mesh(l + 1);
    const NodeProlongation& P = f.hierarchy.prolongation(l);
    const double coarse_edge = std::cbrt(6 * std::sqrt(2.0) * coarse.volume() / coarse.numTets());  // [m]
    Eigen::VectorXd uc(3 * coarse.numNodes());
    for (int J = 0; J < coarse.numNodes(); ++J) uc.segment<3>(3 * J) = (coarse.nodes().row(J) * G.transpose() + c).transpose();
    const Eigen::VectorXd uf = expandToDofs(P) * uc;
    const Eigen::VectorXd row_sums = P * Eigen::VectorXd::Ones(P.cols());
    int inside = 0;
    for (int i = 0; i < fine.numNodes(); ++i) {
      EXPECT_NEAR(row_sums[i], 1.0, 1e-12) << "fine node " << i;
      // Nodes outside the coarse mesh (mostly on the skin) are snapped onto it: close, not exact.
      EXPECT_LE(f.hierarchy.outsideDistance(l)[i], 2 * coarse_edge) << "fine node " << i;
      if (f.hierarchy.outsideDistance(l)[i] > 0.0) continue;
      ++inside;
      const Eigen::RowVector3d expected = fine.nodes().row(i) * G.transpose() + c;
      // Exact up to the round-off of the barycentric solve (the field is ~1e-2 m here).
      EXPECT_LT((uf.segment<3>(3 * i).transpose() - expected).norm(), 1e-11) << "fine node " << i;
    }
    // Most nodes of a coarse level lie on its surface, so only the fine level has many inside.
    EXPECT_GT(inside, l == 0 ? fine.numNodes() / 4 : 0);
  }
}

TEST(GalerkinProduct, EqualsTheNaiveTripleProductWithFixedDofsMaskedOut) {
  const Fixture& f = fixture();
  const NodeProlongation& P = f.hierarchy.prolongation(0);
  const std::vector<double> free = freeMask(f.A, f.fixed);
  const SparseMatrix Pd = expandToDofs(P);
  Eigen::VectorXd d(free.size());
  for (size_t i = 0; i < free.size(); ++i) d[static_cast<Eigen::Index>(i)] = free[i];
  for (const bool masked : {true, false}) {
    SCOPED_TRACE(masked ? "fixed DOFs masked" : "no mask");
    const SparseMatrix DP = masked ? SparseMatrix(d.asDiagonal() * Pd) : Pd;
    // slow reference: the naive product in Eigen
    const Eigen::MatrixXd reference = Eigen::MatrixXd(SparseMatrix(DP.transpose()) * f.A * DP);
    GalerkinProduct g;
    g.analyze(f.A, P);
    g.compute(f.A, masked ? free.data() : nullptr);
    const Eigen::MatrixXd fast = Eigen::MatrixXd(g.coarse());
    const double scale = reference.cwiseAbs().maxCoeff();
    EXPECT_LT((fast - reference).cwiseAbs().maxCoeff(), 1e-13 * scale);
    EXPECT_LT((fast - fast.transpose()).cwiseAbs().maxCoeff(), 1e-13 * scale);
    // Computing twice gives the same values (no accumulation across calls).
    g.compute(f.A, masked ? free.data() : nullptr);
    EXPECT_EQ((Eigen::MatrixXd(g.coarse()) - fast).cwiseAbs().maxCoeff(), 0.0);
  }
}

// The per-thread buffers follow the thread count compute() runs on, which may differ from the one
// analyze() ran on (the simulator chooses each step's thread count): same bits either way.
TEST(GalerkinProduct, AnalysedOnOneThreadComputesOnTwoWithTheSameBits) {
  const Fixture& f = fixture();
  const NodeProlongation& P = f.hierarchy.prolongation(0);
  ASSERT_GT(P.rows(), 400);  // above the product's one-thread threshold
  const std::vector<double> free = freeMask(f.A, f.fixed);
  const int threads = omp_get_max_threads();
  Eigen::MatrixXd coarse[2];
  for (int analysed_on = 1; analysed_on <= 2; ++analysed_on) {
    omp_set_num_threads(analysed_on);
    GalerkinProduct g;
    g.analyze(f.A, P);
    omp_set_num_threads(2);
    g.compute(f.A, free.data());
    coarse[analysed_on - 1] = Eigen::MatrixXd(g.coarse());
  }
  omp_set_num_threads(threads);
  ASSERT_GT(coarse[1].norm(), 0.0);
  EXPECT_TRUE((coarse[0].array() == coarse[1].array()).all());
}

TEST(MultigridPcg, NeedsFarFewerIterationsThanJacobiPcg) {
  const Fixture& f = fixture();
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-8;
  pcg.max_iterations = 5000;
  PcgSolver jacobi(pcg);
  MultigridPcgSolver multigrid(f.hierarchy, pcg);
  int iterations[2];
  LinearSolver* solvers[2] = {&jacobi, &multigrid};
  for (int k = 0; k < 2; ++k) {
    solvers[k]->analyzePattern(f.A);
    solvers[k]->factorize(f.A);
    Eigen::VectorXd x = Eigen::VectorXd::Zero(f.b.size());
    const SolveStats s = solvers[k]->solve(f.b, x);
    ASSERT_TRUE(s.converged) << solvers[k]->name();
    iterations[k] = s.iterations;
  }
  EXPECT_LE(4 * iterations[1], iterations[0]) << "jacobi " << iterations[0] << ", multigrid " << iterations[1];
}

TEST(MultigridPreconditioner, CoarseCorrectionNeverMovesFixedDofs) {
  const Fixture& f = fixture();
  MultigridPreconditioner mg(f.hierarchy);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  Eigen::VectorXd r = f.b, z = Eigen::VectorXd::Zero(f.b.size());
  for (int v : f.fixed) r.segment<3>(3 * v).setZero();
  mg.apply(r, z);
  for (int v : f.fixed) EXPECT_EQ(z.segment<3>(3 * v).cwiseAbs().maxCoeff(), 0.0) << "node " << v;
}

TEST(MultigridPreconditioner, IsASymmetricPositiveDefiniteOperatorWithEitherSmoother) {
  const Fixture& f = fixture();
  std::mt19937 rng(3);
  std::normal_distribution<double> g;
  Eigen::VectorXd u(f.b.size()), v(f.b.size());
  for (Eigen::Index i = 0; i < u.size(); ++i) u[i] = g(rng), v[i] = g(rng);
  for (const auto smoother : {MultigridOptions::Smoother::kGaussSeidel, MultigridOptions::Smoother::kJacobi}) {
    SCOPED_TRACE(smoother == MultigridOptions::Smoother::kJacobi ? "jacobi" : "gauss-seidel");
    MultigridOptions o;
    o.smoother = smoother;
    o.pre_smoothing_steps = o.post_smoothing_steps = 2;
    MultigridPreconditioner mg(f.hierarchy, o);
    mg.analyzePattern(f.A);
    mg.factorize(f.A);
    Eigen::VectorXd Mu(u.size()), Mv(v.size());
    mg.apply(u, Mu);
    mg.apply(v, Mv);
    EXPECT_NEAR(u.dot(Mv) / v.dot(Mu), 1.0, 1e-10);
    EXPECT_GT(u.dot(Mu), 0.0);
    EXPECT_GT(v.dot(Mv), 0.0);
  }
}

// The coarsest level by dense Cholesky (fast path) and by CHOLMOD (reference): the same V-cycle up
// to round-off, on the fixture's three levels.
TEST(MultigridPreconditioner, DenseCoarsestSolveEqualsCholmods) {
  const Fixture& f = fixture();
  std::mt19937 rng(5);
  std::normal_distribution<double> g;
  Eigen::VectorXd u(f.b.size());
  for (Eigen::Index i = 0; i < u.size(); ++i) u[i] = g(rng);
  MultigridOptions dense, sparse;
  dense.dense_coarsest_max_dofs = 100000;
  sparse.dense_coarsest_max_dofs = 0;
  MultigridPreconditioner a(f.hierarchy, dense), b(f.hierarchy, sparse);
  a.analyzePattern(f.A);
  b.analyzePattern(f.A);
  for (int step = 0; step < 2; ++step) {  // a second factorize() reuses the dense storage
    a.factorize(f.A);
    b.factorize(f.A);
    Eigen::VectorXd za(u.size()), zb(u.size());
    a.apply(u, za);
    b.apply(u, zb);
    EXPECT_LE((za - zb).norm(), 1e-10 * zb.norm());
    EXPECT_GT((za - zb).norm(), 0.0);  // two different factorizations: not one path taken twice
  }
  MultigridOptions bad = dense;
  bad.dense_coarsest_max_dofs = -1;
  EXPECT_THROW(MultigridPreconditioner(f.hierarchy, bad), std::invalid_argument);
}

// The float copy of the fine matrix PCG iterates with (Preconditioner::floatBlocks): the caller's
// matrix entry by entry, rounded to float, after every factorize() (also one that keeps the coarse
// operators), and none with a single level or before factorize().
TEST(MultigridPreconditioner, OffersTheFineMatrixRoundedToFloatBlocks) {
  const Fixture& f = fixture();
  MultigridOptions keep_coarse;
  keep_coarse.coarse_update_interval = 5;
  MultigridPreconditioner mg(f.hierarchy, keep_coarse);
  mg.analyzePattern(f.A);
  EXPECT_EQ(mg.floatBlocks().val, nullptr);
  SparseMatrix A2 = f.A;
  A2 *= 1.5;
  for (const SparseMatrix* A : {&f.A, static_cast<const SparseMatrix*>(&A2)}) {
    const long renewals = mg.coarseRenewals();
    mg.factorize(*A);
    EXPECT_EQ(mg.coarseRenewals(), A == &f.A ? renewals + 1 : renewals);
    const Preconditioner::FloatBlocks b = mg.floatBlocks();
    ASSERT_NE(b.val, nullptr);
    ASSERT_EQ(3 * static_cast<Eigen::Index>(b.nodes), A->rows());
    long entries = 0;
    for (int i = 0; i < b.nodes; ++i)
      for (int k = b.start[i]; k < b.start[i + 1]; ++k)
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c, ++entries)
            ASSERT_EQ(b.val[9 * k + 3 * r + c], static_cast<float>(A->coeff(3 * i + r, 3 * b.col[k] + c)))
                << "node " << i << " block " << k;
    EXPECT_EQ(entries, A->nonZeros());
  }
  MultigridPreconditioner single(std::vector<NodeProlongation>{});
  single.analyzePattern(f.A);
  single.factorize(f.A);
  EXPECT_EQ(single.floatBlocks().val, nullptr);
}

TEST(MultigridPreconditioner, RejectsAMatrixNotInBlockLayout) {
  const Fixture& f = fixture();
  SparseMatrix A(f.A.rows(), f.A.cols());
  A.setIdentity();
  MultigridPreconditioner mg(f.hierarchy);
  try {
    mg.analyzePattern(A);
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("3×3-block layout"), std::string::npos) << e.what();
  }
}

TEST(MultigridPreconditioner, StaysSymmetricPositiveDefiniteWithStaleCoarseOperators) {
  // Coarse operators from the softer matrix, fine level from a stiffer one: still a valid
  // preconditioner, and PCG still converges to the right answer.
  const Fixture& f = fixture();
  const SparseMatrix A2 = implicitStepMatrix(f.model.mesh, f.fixed, 5000.0, 0.45);
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-10;
  MultigridOptions o;
  o.coarse_update_interval = 2;
  MultigridPcgSolver solver(f.hierarchy, pcg, o);
  solver.analyzePattern(f.A);
  solver.factorize(f.A);
  const Eigen::MatrixXd coarse_before = Eigen::MatrixXd(solver.multigrid().levelMatrix(1));
  solver.factorize(A2);  // the second of the interval: fine level only
  EXPECT_EQ((Eigen::MatrixXd(solver.multigrid().levelMatrix(1)) - coarse_before).cwiseAbs().maxCoeff(), 0.0);
  std::mt19937 rng(5);
  std::normal_distribution<double> g;
  Eigen::VectorXd u(f.b.size()), v(f.b.size()), Mu(f.b.size()), Mv(f.b.size());
  for (Eigen::Index i = 0; i < u.size(); ++i) u[i] = g(rng), v[i] = g(rng);
  solver.multigrid().apply(u, Mu);
  solver.multigrid().apply(v, Mv);
  EXPECT_NEAR(u.dot(Mv) / v.dot(Mu), 1.0, 1e-10);
  EXPECT_GT(u.dot(Mu), 0.0);
  Eigen::VectorXd x;
  ASSERT_TRUE(solver.solve(f.b, x).converged);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(A2)};
  EXPECT_LE(relativeDifference(x, ldlt.solve(f.b)), 1e-6);
  solver.factorize(A2);  // the next interval: coarse operators follow
  EXPECT_GT((Eigen::MatrixXd(solver.multigrid().levelMatrix(1)) - coarse_before).cwiseAbs().maxCoeff(), 0.0);
}

// The fine level's damping estimated (fine_eigenvalue_bound 0, as for the average-nodal-pressure
// element) on a matrix whose diagonal blocks dominate (λ_max(D⁻¹A) near 1: ω = 1) and kept, with
// the coarse operators, for the step matrix itself (λ_max near 3): ω λ_max > 2, the smoother
// diverges and the V-cycle is indefinite. PCG renews the preconditioner from the new matrix once
// (Preconditioner::renew) and converges to the direct solution; right after a renewal there is
// nothing to renew.
TEST(MultigridPreconditioner, RenewsItselfInTheSolveWhenWhatItKeptLeavesItIndefinite) {
  const Fixture& f = fixture();
  const SparseMatrix& stiff = f.A;
  SparseMatrix soft = stiff;  // the same pattern, diagonal blocks × 100
  for (int c = 0; c < soft.outerSize(); ++c)
    for (SparseMatrix::InnerIterator it(soft, c); it; ++it)
      if (it.row() / 3 == it.col() / 3) it.valueRef() *= 100.0;
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-8;
  MultigridOptions o;
  o.fine_eigenvalue_bound = 0.0;
  o.coarse_update_interval = 100;
  MultigridPcgSolver solver(f.hierarchy, pcg, o);
  solver.analyzePattern(soft);
  solver.factorize(soft);
  const double omega_soft = solver.multigrid().jacobiDamping(0);
  EXPECT_GT(omega_soft, 0.9);
  solver.factorize(stiff);  // fine level only: ω and the coarse operators are the soft matrix's
  EXPECT_EQ(solver.multigrid().jacobiDamping(0), omega_soft);
  std::mt19937 rng(11);
  std::normal_distribution<double> g;
  Eigen::VectorXd u(f.b.size()), Mu(f.b.size());
  double smallest = 1.0;
  for (int k = 0; k < 20; ++k) {
    for (Eigen::Index i = 0; i < u.size(); ++i) u[i] = g(rng);
    solver.multigrid().apply(u, Mu);
    smallest = std::min(smallest, u.dot(Mu) / u.squaredNorm());
  }
  const long renewals = solver.multigrid().coarseRenewals();
  Eigen::VectorXd x;
  const SolveStats st = solver.solve(f.b, x);
  std::printf("[ measure  ] omega %.3f kept from the soft matrix: smallest u^T M^-1 u / u^T u of 20 random u %.3g; "
              "the solve renewed: %d, omega then %.3f, %d iterations\n",
              omega_soft, smallest, st.preconditioner_renewed, solver.multigrid().jacobiDamping(0), st.iterations);
  EXPECT_TRUE(st.preconditioner_renewed);
  EXPECT_EQ(solver.multigrid().coarseRenewals(), renewals + 1);
  EXPECT_LT(solver.multigrid().jacobiDamping(0), 0.6 * omega_soft);
  ASSERT_TRUE(st.converged);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(stiff)};
  EXPECT_LE(relativeDifference(x, ldlt.solve(f.b)), 1e-6);
  EXPECT_FALSE(solver.multigrid().renew());  // just renewed: nothing kept from an earlier matrix
  x.setZero();
  solver.forgetSolutions();  // no projected initial guess: the solve iterates
  const SolveStats again = solver.solve(f.b, x);
  EXPECT_GT(again.iterations, 0);
  EXPECT_FALSE(again.preconditioner_renewed);
}

TEST(MultigridPreconditioner, AutomaticJacobiDampingKeepsEverySmootherConvergent) {
  // ω λ_max(D⁻¹A) < 2 on every smoothed level, λ_max from a long power iteration (slow reference).
  const Fixture& f = fixture();
  MultigridPreconditioner mg(f.hierarchy);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  for (int l = 0; l + 1 < mg.numLevels(); ++l) {
    SCOPED_TRACE("level " + std::to_string(l));
    const SparseMatrix& A = mg.levelMatrix(l);
    const int n = static_cast<int>(A.rows() / 3);
    std::vector<Eigen::Matrix3d> Dinv(static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) Dinv[i] = Eigen::Matrix3d(Eigen::MatrixXd(A.block(3 * i, 3 * i, 3, 3))).inverse();
    Eigen::VectorXd x = Eigen::VectorXd::Ones(A.rows()), y;
    for (Eigen::Index i = 0; i < x.size(); ++i) x[i] += 0.1 * std::sin(static_cast<double>(i));
    double lambda = 0.0;
    for (int it = 0; it < 300; ++it) {
      y = A * x;
      for (int i = 0; i < n; ++i) y.segment<3>(3 * i) = Dinv[i] * y.segment<3>(3 * i);
      lambda = y.norm() / x.norm();
      x = y / y.norm();
    }
    const double omega = mg.jacobiDamping(l);
    EXPECT_GT(omega, 0.0);
    EXPECT_LT(omega * lambda, 1.9) << "omega " << omega << ", lambda_max " << lambda;
  }
}

TEST(MortonOrder, RenumbersNodesWithoutChangingTheMesh) {
  const Fixture& f = fixture();
  const TetMesh& mesh = f.hierarchy.mesh(1);
  std::vector<int> new_index;
  const TetMesh m = mortonOrdered(mesh, &new_index);
  ASSERT_EQ(m.numNodes(), mesh.numNodes());
  ASSERT_EQ(m.numTets(), mesh.numTets());
  EXPECT_NEAR(m.volume(), mesh.volume(), 1e-12 * mesh.volume());
  for (int v = 0; v < mesh.numNodes(); ++v) EXPECT_EQ(m.nodes().row(new_index[v]), mesh.nodes().row(v));
  for (const auto& [name, set] : mesh.nodeSets()) {
    SCOPED_TRACE(name);
    ASSERT_EQ(m.nodeSet(name).size(), set.size());
    for (int v : set) EXPECT_TRUE(std::binary_search(m.nodeSet(name).begin(), m.nodeSet(name).end(), new_index[v]));
  }
  // Neighbours get nearby numbers: the mean index distance along element edges drops.
  auto spread = [](const TetMesh& t) {
    double sum = 0.0;
    for (int e = 0; e < t.numTets(); ++e)
      for (int a = 0; a < 4; ++a)
        for (int b = a + 1; b < 4; ++b) sum += std::abs(t.tets()(e, a) - t.tets()(e, b));
    return sum / (6.0 * t.numTets());
  };
  // The mesher's output is Morton-ordered already (ordering again changes nothing); a shuffled copy
  // of it, like CGAL's refinement order, spreads at least twice as far.
  const TetMesh& fine = f.model.mesh;
  std::vector<int> again;
  mortonOrdered(fine, &again);
  for (int v = 0; v < fine.numNodes(); ++v) ASSERT_EQ(again[v], v);
  std::vector<int> shuffle(static_cast<size_t>(fine.numNodes()));
  for (int v = 0; v < fine.numNodes(); ++v) shuffle[v] = static_cast<int>((7919LL * v) % fine.numNodes());
  ASSERT_EQ(std::gcd(7919, fine.numNodes()), 1);
  Points x(fine.numNodes(), 3);
  for (int v = 0; v < fine.numNodes(); ++v) x.row(shuffle[v]) = fine.nodes().row(v);
  Tets t = fine.tets();
  for (Eigen::Index e = 0; e < t.rows(); ++e)
    for (int a = 0; a < 4; ++a) t(e, a) = shuffle[t(e, a)];
  const TetMesh shuffled(x, t, fine.regionLabels());
  EXPECT_LT(spread(fine), 0.5 * spread(shuffled));
  EXPECT_EQ(spread(mortonOrdered(shuffled)), spread(fine));
}

TEST(MultigridPcg, WithoutCoarseLevelsIsCholeskyPreconditionedCg) {
  const Fixture& f = fixture();
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-10;
  MultigridPcgSolver solver(std::vector<NodeProlongation>{}, pcg);
  solver.analyzePattern(f.A);
  solver.factorize(f.A);
  Eigen::VectorXd x;
  const SolveStats s = solver.solve(f.b, x);
  EXPECT_TRUE(s.converged);
  EXPECT_LE(s.iterations, 2);
  EXPECT_LE(relativeDifference(x, f.reference), 1e-8);
}

TEST(MultigridPreconditioner, RenewsTheCoarseOperatorsOnceTheIterationsTheirAgeLostAreWorthARenewal) {
  const Fixture& f = fixture();
  MultigridOptions o;
  o.coarse_update_interval = 100;
  o.coarse_update_adaptive = true;
  o.coarse_update_cost_iterations = 6.0;
  MultigridPreconditioner mg(f.hierarchy, o);
  mg.analyzePattern(f.A);
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 1);
  // The first solve after a renewal is the reference: 10 iterations to 1e-3 (log rate −0.69).
  mg.reportConvergence(10, 1e-3);
  EXPECT_EQ(mg.lostIterationsSinceRenewal(), 0.0);
  mg.factorize(f.A);
  // As fast again: nothing lost.
  mg.reportConvergence(10, 1e-3);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), 0.0, 1e-12);
  mg.factorize(f.A);
  // 1e-2 in 10 iterations: at the reference rate 10·2/3 would have done; 10/3 lost.
  mg.reportConvergence(10, 1e-2);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), 10.0 / 3.0, 1e-12);
  mg.factorize(f.A);
  // A faster solve gives iterations back: 1e-4 in 3 would have taken 40/3 at the reference; the sum
  // 10/3 + 3 − 40/3 = −7 stops at one renewal's worth of credit, −6.
  mg.reportConvergence(3, 1e-4);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), -6.0, 1e-12);
  mg.factorize(f.A);
  mg.reportConvergence(10, 1e-2);  // 10/3 more: −8/3
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), -8.0 / 3.0, 1e-12);
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 1);
  mg.reportConvergence(15, 1e-1);  // 15 − 10/3 more: 9 ≥ 6, renewed at the next factorize()
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), 9.0, 1e-12);
  EXPECT_EQ(mg.coarseRenewals(), 1);
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 2);
  // A new reference after the renewal: the slow rate is now the norm.
  mg.reportConvergence(6, 1e-1);
  mg.reportConvergence(6, 1e-1);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), 0.0, 1e-12);
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 2);
  // Credit for fast solves is capped at one renewal's worth.
  mg.reportConvergence(10, 1e-30);
  EXPECT_EQ(mg.lostIterationsSinceRenewal(), -6.0);
  mg.reportConvergence(10, 1e-1);  // 10 iterations where 6 would have done: 4 lost
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), -2.0, 1e-12);
  // A residual that vanished teaches nothing; one that did not fall lost all its iterations (CG's
  // residual need not fall in a capped solve of a few); a non-finite one renews at once.
  mg.reportConvergence(3, 0.0);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), -2.0, 1e-12);
  for (int k = 0; k < 2; ++k) mg.reportConvergence(4, 1.5);
  EXPECT_NEAR(mg.lostIterationsSinceRenewal(), 6.0, 1e-12);
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 3);
  EXPECT_EQ(mg.lostIterationsSinceRenewal(), 0.0);
  mg.reportConvergence(3, std::nan(""));
  mg.factorize(f.A);
  EXPECT_EQ(mg.coarseRenewals(), 4);

  // An early renewal restarts the interval: interval 3, renewed at factorizations 0, 2 (early), 5.
  MultigridOptions short_interval = o;
  short_interval.coarse_update_interval = 3;
  MultigridPreconditioner mg3(f.hierarchy, short_interval);
  mg3.analyzePattern(f.A);
  std::vector<long> renewals;
  for (int k = 0; k < 6; ++k) {
    if (k == 2) mg3.reportConvergence(3, std::nan(""));
    mg3.factorize(f.A);
    renewals.push_back(mg3.coarseRenewals());
  }
  EXPECT_EQ(renewals, (std::vector<long>{1, 1, 2, 2, 2, 3}));

  // Off (the default): only the interval renews.
  MultigridOptions fixed = o;
  fixed.coarse_update_adaptive = false;
  fixed.coarse_update_interval = 3;
  MultigridPreconditioner mg2(f.hierarchy, fixed);
  mg2.analyzePattern(f.A);
  for (int k = 0; k < 7; ++k) {
    mg2.factorize(f.A);
    mg2.reportConvergence(10, k == 0 ? 1e-3 : 0.9);
  }
  EXPECT_EQ(mg2.coarseRenewals(), 3);  // factorizations 0, 3 and 6

  // In PCG: a solve reports its reduction (ReportsItsResidualReductionToThePreconditioner); with a
  // stiffer matrix on stale coarse operators the solver still converges to the answer.
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-10;
  MultigridPcgSolver solver(f.hierarchy, pcg, o);
  solver.analyzePattern(f.A);
  solver.factorize(f.A);
  Eigen::VectorXd x;
  ASSERT_TRUE(solver.solve(f.b, x).converged);
  const SparseMatrix A2 = implicitStepMatrix(f.model.mesh, f.fixed, 5000.0, 0.45);
  solver.factorize(A2);
  x.setZero();
  ASSERT_TRUE(solver.solve(f.b, x).converged);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(A2)};
  EXPECT_LE(relativeDifference(x, ldlt.solve(f.b)), 1e-6);
  EXPECT_EQ(solver.multigrid().coarseRenewals(), 1);
  EXPECT_NE(solver.multigrid().lostIterationsSinceRenewal(), 0.0);  // the second solve was measured against the first
}

TEST(MultigridPreconditioner, RejectsACoarseUpdateCostThatIsNotPositive) {
  const Fixture& f = fixture();
  for (double c : {0.0, -1.0, std::nan("")}) {
    MultigridOptions o;
    o.coarse_update_cost_iterations = c;
    try {
      MultigridPreconditioner mg(f.hierarchy, o);
      FAIL() << "expected an error for " << c;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("coarse_update_cost_iterations"), std::string::npos) << e.what();
    }
  }
}
