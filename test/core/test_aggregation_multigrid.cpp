// Smoothed-aggregation multigrid (solver/aggregation_multigrid.h) on the system of an implicit step
// of linear elasticity (A = M/dt² + K, Dirichlet on one face / the chest wall): the tentative
// prolongator reproduces the rigid modes, the Galerkin operators equal the naive triple product, the
// V-cycle is a symmetric positive definite operator that never moves fixed DOFs, and PCG with it
// reaches the CHOLMOD solution, also with prolongators kept from an earlier matrix.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/aggregation_multigrid.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "reference_step_matrix.h"

using namespace breast_sim::core;

namespace {

/// A box of nx × ny × nz cubes of edge h [m], six tetrahedra per cube (Kuhn subdivision), positively
/// oriented; node set "bottom" = the nodes at z = 0.
TetMesh boxMesh(int nx, int ny, int nz, double h) {
  auto id = [&](int i, int j, int k) { return i + (nx + 1) * (j + (ny + 1) * k); };
  Points x((nx + 1) * (ny + 1) * (nz + 1), 3);
  for (int k = 0; k <= nz; ++k)
    for (int j = 0; j <= ny; ++j)
      for (int i = 0; i <= nx; ++i) x.row(id(i, j, k)) << i * h, j * h * 1.1, k * h * 0.9;
  std::vector<Eigen::Vector4i> tets;
  const int perm[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i)
        for (const auto& p : perm) {
          int c[3] = {i, j, k};
          Eigen::Vector4i t;
          t[0] = id(c[0], c[1], c[2]);
          for (int s = 0; s < 3; ++s) {
            ++c[p[s]];
            t[s + 1] = id(c[0], c[1], c[2]);
          }
          Eigen::Matrix3d D;
          for (int s = 0; s < 3; ++s) D.col(s) = (x.row(t[s + 1]) - x.row(t[0])).transpose();
          if (D.determinant() < 0) std::swap(t[2], t[3]);
          tets.push_back(t);
        }
  Tets T(static_cast<Eigen::Index>(tets.size()), 4);
  for (size_t e = 0; e < tets.size(); ++e) T.row(static_cast<Eigen::Index>(e)) = tets[e].transpose();
  TetMesh mesh(x, T);
  std::vector<int> bottom;
  for (int j = 0; j <= ny; ++j)
    for (int i = 0; i <= nx; ++i) bottom.push_back(id(i, j, 0));
  mesh.setNodeSet("bottom", bottom);
  return mesh;
}

using breast_sim::test_support::stepMatrix;  // reference_step_matrix.h

SparseMatrix restMatrix(const TetMesh& mesh, const std::vector<int>& fixed) {
  return stepMatrix(mesh, fixed, [](int) { return Eigen::Matrix3d::Identity(); }, [](int) { return 1.0; });
}

/// The same mesh with element rotations up to 35° about x growing with height z, and moduli 1 … 4.
SparseMatrix rotatedMatrix(const TetMesh& mesh, const std::vector<int>& fixed) {
  const double zmax = mesh.nodes().col(2).maxCoeff();
  auto centroid = [&](int e) {
    Eigen::RowVector3d c = Eigen::RowVector3d::Zero();
    for (int a = 0; a < 4; ++a) c += mesh.nodes().row(mesh.tets()(e, a)) / 4.0;
    return c;
  };
  return stepMatrix(
      mesh, fixed,
      [&](int e) {
        return Eigen::AngleAxisd(0.6 * centroid(e).z() / zmax, Eigen::Vector3d::UnitX()).toRotationMatrix();
      },
      [&](int e) { return 1.0 + 3.0 * std::pow(std::sin(40.0 * centroid(e).x()), 2); });
}

/// A random load [N], zero on fixed DOFs.
Eigen::VectorXd randomLoad(Eigen::Index n, const std::vector<int>& fixed, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::VectorXd b(n);
  for (Eigen::Index i = 0; i < n; ++i) b[i] = 1e-3 * u(rng);
  for (int v : fixed) b.segment<3>(3 * v).setZero();
  return b;
}

struct Box {
  TetMesh mesh = boxMesh(12, 10, 8, 0.005);
  std::vector<int> fixed = mesh.nodeSet("bottom");
  SparseMatrix A = restMatrix(mesh, fixed);
};
const Box& box() {
  static const Box b;
  return b;
}

/// Options that give three levels on the box.
AggregationMultigridOptions threeLevels() {
  AggregationMultigridOptions o;
  o.max_coarsest_dofs = 100;
  return o;
}

Eigen::VectorXd cholmodSolve(const SparseMatrix& A, const Eigen::VectorXd& b) {
  CholmodSolver direct;
  direct.analyzePattern(A);
  direct.factorize(A);
  Eigen::VectorXd x;
  direct.solve(b, x);
  return x;
}

}  // namespace

TEST(Aggregation, CoversEveryFreeNodeOnceAndLeavesFixedNodesOut) {
  const Box& b = box();
  int count = 0;
  const std::vector<int> agg = aggregateNodes(b.A, 3, 0.08, &count);
  ASSERT_EQ(static_cast<int>(agg.size()), b.mesh.numNodes());
  std::vector<bool> fixed(static_cast<size_t>(b.mesh.numNodes()), false);
  for (int v : b.fixed) fixed[v] = true;
  std::vector<int> size(static_cast<size_t>(count), 0);
  for (int i = 0; i < b.mesh.numNodes(); ++i) {
    if (fixed[i]) {
      EXPECT_EQ(agg[i], -1) << "fixed node " << i;
      continue;
    }
    ASSERT_GE(agg[i], 0) << "free node " << i;
    ASSERT_LT(agg[i], count);
    ++size[agg[i]];
  }
  const int free_nodes = b.mesh.numNodes() - static_cast<int>(b.fixed.size());
  // Real coarsening: aggregates of several nodes on average, none empty.
  EXPECT_LT(count, free_nodes / 5);
  for (int a = 0; a < count; ++a) EXPECT_GT(size[a], 0) << "aggregate " << a;
}

TEST(TentativeProlongator, ReproducesTheRigidModesExactlyOnEachAggregate) {
  const Box& b = box();
  int count = 0;
  const std::vector<int> agg = aggregateNodes(b.A, 3, 0.08, &count);
  Eigen::MatrixXd B = rigidBodyModes(b.mesh.nodes());
  for (int v : b.fixed) B.middleRows(3 * v, 3).setZero();
  Eigen::MatrixXd Bc;
  const BlockProlongator T = tentativeProlongator(agg, count, 3, B, &Bc);
  const SparseMatrix P = T.toSparse();
  ASSERT_EQ(P.rows(), B.rows());
  ASSERT_EQ(P.cols(), 6 * count);
  const Eigen::MatrixXd PB = P * Bc;
  EXPECT_LT((PB - B).cwiseAbs().maxCoeff(), 1e-12 * B.cwiseAbs().maxCoeff());
  // Orthonormal columns within each aggregate: PᵀP is the identity on the kept modes.
  const Eigen::MatrixXd PtP = Eigen::MatrixXd(SparseMatrix(P.transpose()) * P);
  for (int c = 0; c < PtP.rows(); ++c)
    for (int d = 0; d < PtP.cols(); ++d) {
      const double expect = (c == d && PtP(c, c) > 0.5) ? 1.0 : 0.0;
      ASSERT_NEAR(PtP(c, d), expect, 1e-12) << "coarse DOFs " << c << ", " << d;
    }
  // The coarse near-null space, aggregated once more on a coarse matrix's graph, is reproduced too.
  AggregationMultigridPreconditioner M(b.mesh.nodes(), threeLevels());
  M.analyzePattern(b.A);
  M.factorize(b.A);
  ASSERT_GE(M.numLevels(), 3);
  int count2 = 0;
  const std::vector<int> agg2 = aggregateNodes(M.levelMatrix(1), 6, 0.04, &count2);
  // M aggregated the same matrix with the same θ: its level 1 has one node per aggregate above.
  ASSERT_EQ(M.levelMatrix(1).rows(), Bc.rows());
  Eigen::MatrixXd Bc2;
  const BlockProlongator T2 = tentativeProlongator(agg2, count2, 6, Bc, &Bc2);
  const Eigen::MatrixXd PB2 = T2.toSparse() * Bc2;
  Eigen::MatrixXd expect = Bc;
  for (size_t i = 0; i < agg2.size(); ++i)
    if (agg2[i] < 0) expect.middleRows(6 * static_cast<Eigen::Index>(i), 6).setZero();
  EXPECT_LT((PB2 - expect).cwiseAbs().maxCoeff(), 1e-12 * Bc.cwiseAbs().maxCoeff());
}

TEST(TentativeProlongator, DropsAModeATwoNodeAggregateCannotCarry) {
  // Two nodes on the x axis: the rotation about x moves neither, so one of six modes is dependent.
  Points x(2, 3);
  x << 0, 0, 0, 1, 0, 0;
  // Rotation modes through the centroid (0.5, 0, 0): the one about x is zero on both nodes.
  Eigen::MatrixXd B = rigidBodyModes(x);
  Eigen::MatrixXd Bc;
  const BlockProlongator T = tentativeProlongator({0, 0}, 1, 3, B, &Bc);
  const Eigen::MatrixXd Q = Eigen::MatrixXd(T.toSparse());
  int kept = 0;
  for (int c = 0; c < 6; ++c) kept += Q.col(c).norm() > 0.5 ? 1 : 0;
  EXPECT_EQ(kept, 5);
  EXPECT_LT((Q * Bc - B).cwiseAbs().maxCoeff(), 1e-14);
}

TEST(AggregationMultigrid, GalerkinOperatorsEqualTheNaiveTripleProduct) {
  const Box& b = box();
  const SparseMatrix A = rotatedMatrix(b.mesh, b.fixed);
  AggregationMultigridPreconditioner M(b.mesh.nodes(), threeLevels());
  M.analyzePattern(A);
  M.factorize(A);
  ASSERT_GE(M.numLevels(), 3);
  for (int l = 0; l + 1 < M.numLevels(); ++l) {
    const SparseMatrix& Al = M.levelMatrix(l);
    SparseMatrix P = M.prolongator(l).toSparse();
    // Mask the rows of decoupled DOFs of level l.
    for (int r = 0; r < P.outerSize(); ++r) {
      bool coupled = false;
      for (SparseMatrix::InnerIterator it(Al, r); it; ++it) coupled |= it.col() != r && it.value() != 0.0;
      if (!coupled)
        for (SparseMatrix::InnerIterator it(P, r); it; ++it) it.valueRef() = 0.0;
    }
    Eigen::MatrixXd naive = Eigen::MatrixXd(SparseMatrix(P.transpose()) * Al * P);
    Eigen::MatrixXd fast = Eigen::MatrixXd(M.levelMatrix(l + 1));
    // The fast operator has unit diagonals on empty rows (modes an aggregate cannot carry).
    for (Eigen::Index r = 0; r < naive.rows(); ++r)
      if (naive.row(r).cwiseAbs().maxCoeff() == 0.0) naive(r, r) = 1.0;
    EXPECT_LT((naive - fast).cwiseAbs().maxCoeff(), 1e-10 * naive.cwiseAbs().maxCoeff()) << "level " << l + 1;
    EXPECT_LT((fast - fast.transpose()).cwiseAbs().maxCoeff(), 1e-14 * fast.cwiseAbs().maxCoeff());
  }
}

TEST(AggregationMultigrid, VCycleIsSymmetricPositiveDefiniteAndKeepsFixedDofs) {
  const Box& b = box();
  for (const bool smooth : {true, false}) {
    AggregationMultigridOptions o = threeLevels();
    o.smooth_prolongator = smooth;
    AggregationMultigridPreconditioner M(b.mesh.nodes(), o);
    M.analyzePattern(b.A);
    M.factorize(b.A);
    ASSERT_GE(M.numLevels(), 3);
    const Eigen::Index n = b.A.rows();
    std::mt19937 rng(3);
    std::normal_distribution<double> g;
    Eigen::VectorXd x(n), y(n), Mx(n), My(n);
    for (int trial = 0; trial < 5; ++trial) {
      for (Eigen::Index i = 0; i < n; ++i) x[i] = g(rng), y[i] = g(rng);
      for (int v : b.fixed) x.segment<3>(3 * v).setZero(), y.segment<3>(3 * v).setZero();
      M.apply(x, Mx);
      M.apply(y, My);
      const double xMy = x.dot(My), yMx = y.dot(Mx);
      EXPECT_NEAR(xMy, yMx, 1e-10 * std::sqrt(x.dot(Mx) * y.dot(My))) << "smooth " << smooth;
      EXPECT_GT(x.dot(Mx), 0.0);
      for (int v : b.fixed) EXPECT_EQ(Mx.segment<3>(3 * v).cwiseAbs().maxCoeff(), 0.0) << "fixed node " << v;
    }
  }
}

TEST(AggregationMultigrid, PcgReachesTheCholmodSolutionOnTheBoxAlsoWithKeptProlongators) {
  const Box& b = box();
  const SparseMatrix A2 = rotatedMatrix(b.mesh, b.fixed);
  const Eigen::VectorXd rhs = randomLoad(b.A.rows(), b.fixed, 5);
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-10;
  pcg.max_iterations = 500;
  for (const bool reuse : {false, true}) {
    AggregationMultigridOptions o = threeLevels();
    o.reuse_prolongators = reuse;
    AggregationMultigridPcgSolver solver(b.mesh.nodes(), pcg, o);
    solver.analyzePattern(b.A);
    solver.factorize(b.A);  // the first step: aggregates and prolongators from the rest matrix
    for (const SparseMatrix* A : {&b.A, &A2}) {
      solver.factorize(*A);
      Eigen::VectorXd x = Eigen::VectorXd::Zero(A->rows());
      const SolveStats s = solver.solve(rhs, x);
      EXPECT_TRUE(s.converged) << "reuse " << reuse;
      const Eigen::VectorXd ref = cholmodSolve(*A, rhs);
      EXPECT_LT((x - ref).norm() / ref.norm(), 1e-8) << "reuse " << reuse;
      EXPECT_LT(s.iterations, 100) << "reuse " << reuse;  // ~65 at ν = 0.48 (Jacobi-PCG: > 400)
    }
  }
}

TEST(AggregationMultigrid, PcgOnThePhantomReachesCholmodInFarFewerIterationsThanJacobi) {
  ModelCase c = loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  c.meshing.target_elements = 6000;
  const SimulationModel model = buildSimulationModel(c);
  const std::vector<int>& fixed = model.mesh.nodeSet(node_sets::kChestWall);
  const SparseMatrix A = restMatrix(model.mesh, fixed);
  const Eigen::VectorXd rhs = randomLoad(A.rows(), fixed, 9);
  const Eigen::VectorXd ref = cholmodSolve(A, rhs);
  PcgOptions pcg;
  pcg.relative_tolerance = 1e-8;
  pcg.max_iterations = 5000;
  AggregationMultigridPcgSolver sa(model.mesh.nodes(), pcg);
  sa.analyzePattern(A);
  sa.factorize(A);
  Eigen::VectorXd x = Eigen::VectorXd::Zero(A.rows());
  const SolveStats s = sa.solve(rhs, x);
  ASSERT_TRUE(s.converged);
  EXPECT_LT((x - ref).norm() / ref.norm(), 1e-6);
  EXPECT_LT((A * x - rhs).norm() / rhs.norm(), 1e-8);
  PcgSolver jacobi(pcg);
  jacobi.analyzePattern(A);
  jacobi.factorize(A);
  Eigen::VectorXd xj = Eigen::VectorXd::Zero(A.rows());
  const SolveStats sj = jacobi.solve(rhs, xj);
  EXPECT_LT(5 * s.iterations, sj.iterations) << "sa " << s.iterations << ", jacobi " << sj.iterations;
}

TEST(AggregationMultigrid, BadInputIsAClearError) {
  const Box& b = box();
  EXPECT_THROW(AggregationMultigridPreconditioner(b.mesh.nodes(), [] {
                 AggregationMultigridOptions o;
                 o.smoother_damping = 2.5;
                 return o;
               }()),
               std::invalid_argument);
  AggregationMultigridPreconditioner M(b.mesh.nodes().topRows(10));
  EXPECT_THROW(M.analyzePattern(b.A), std::invalid_argument);
  AggregationMultigridPreconditioner N(b.mesh.nodes());
  EXPECT_THROW(N.factorize(b.A), std::logic_error);
  Eigen::VectorXd z(b.A.rows());
  EXPECT_THROW(N.apply(Eigen::VectorXd::Zero(b.A.rows()), z), std::logic_error);
}
