// Linear solvers of the time step: CHOLMOD, Jacobi-PCG and multigrid-PCG on the system of an
// implicit step of linear elasticity (A = M/dt² + K, Dirichlet on the chest wall) of the phantom.
#include <gtest/gtest.h>

#include <algorithm>
#include <numeric>
#include <cmath>
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
#include "reference_step_matrix.h"

using namespace breast_sim::core;

namespace {

// ---------------------------------------------------------------------------------------------------
// Test-local assembly (the project's FEM lives in fem/; this one only has to be SPD and realistic).

/// A = M/dt² + K of linear tetrahedra at rest [N/m] (reference_step_matrix.h).
SparseMatrix implicitStepMatrix(const TetMesh& mesh, const std::vector<int>& fixed_nodes, double E_pa = 2000.0,
                                double nu = 0.48, double density = 1000.0, double dt = 0.033) {
  return breast_sim::test_support::restStepMatrix(mesh, fixed_nodes, E_pa, nu, density, dt);
}

/// Gravity on the lumped masses plus a random load [N]; fixed DOFs get `fixed_value` [m].
Eigen::VectorXd load(const SparseMatrix& A, const TetMesh& mesh, const std::vector<int>& fixed_nodes,
                     double fixed_value = 0.0, unsigned seed = 7) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::VectorXd b(A.rows());
  const Eigen::VectorXd V = mesh.tetVolumes();
  b.setZero();
  for (int e = 0; e < mesh.numTets(); ++e)
    for (int a = 0; a < 4; ++a) b[3 * mesh.tets()(e, a) + 2] -= 1000.0 * V[e] / 4 * 9.81;
  const double scale = b.cwiseAbs().maxCoeff();
  for (Eigen::Index i = 0; i < b.size(); ++i) b[i] += 0.5 * scale * u(rng);
  for (int v : fixed_nodes)
    for (int i = 0; i < 3; ++i) b[3 * v + i] = fixed_value * (1 + i);
  return b;
}

std::vector<double> freeMask(const SparseMatrix& A, const std::vector<int>& fixed_nodes) {
  std::vector<double> free(static_cast<size_t>(A.rows()), 1.0);
  for (int v : fixed_nodes)
    for (int i = 0; i < 3; ++i) free[3 * v + i] = 0.0;
  return free;
}

double relativeDifference(const Eigen::VectorXd& a, const Eigen::VectorXd& b) { return (a - b).norm() / b.norm(); }

/// The phantom at ~8000 elements, its hierarchy (three levels) and the step system; built once.
struct Fixture {
  ModelCase model_case;
  SimulationModel model;
  MeshHierarchy hierarchy;
  std::vector<int> fixed;
  SparseMatrix A;
  Eigen::VectorXd b;
  Eigen::VectorXd reference;  // Eigen SimplicialLDLT
};

const Fixture& fixture() {
  static const Fixture f = [] {
    Fixture f;
    f.model_case = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
    f.model_case.meshing.target_elements = 8000;
    f.model = buildSimulationModel(f.model_case);
    CoarseningOptions coarsening;
    coarsening.max_coarsest_elements = 600;  // three levels, to test the recursion
    f.hierarchy = buildMeshHierarchy(f.model_case, f.model, coarsening);
    f.fixed = f.model.mesh.nodeSet(node_sets::kChestWall);
    f.A = implicitStepMatrix(f.model.mesh, f.fixed);
    f.b = load(f.A, f.model.mesh, f.fixed, 1e-3);
    const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt{Eigen::SparseMatrix<double>(f.A)};
    f.reference = ldlt.solve(f.b);
    return f;
  }();
  return f;
}

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
  // The double product against Eigen's (slow reference), over all rows.
  Eigen::VectorXd y(x.size());
  const double xAx = blockProductRows(outer, val, start.data(), col.data(), nullptr, x.data(), y.data(), 0, nodes, false, true);
  const Eigen::VectorXd Ax = f.A * x;
  EXPECT_LE((y - Ax).norm(), 1e-12 * Ax.norm());
  EXPECT_NEAR(xAx, x.dot(Ax), 1e-10 * std::abs(x.dot(Ax)));
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
