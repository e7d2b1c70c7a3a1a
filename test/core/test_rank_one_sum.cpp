// Rank-one sums (solver/rank_one_sum.h) and the split stiffness of the average-nodal-pressure
// element: the compact part plus the sum is the two-ring matrix, the masked product, diagonal and
// Galerkin image equal their assembled slow references, the products are the same bits on one and
// two threads, PCG with the Jacobi and multigrid preconditioners solves S + R as CHOLMOD solves the
// assembled matrix, and a simulator that splits the stiffness steps, settles and reports reactions
// as one that assembles it.
#include <gtest/gtest.h>

#include <random>
#include <string>
#include <tuple>
#include <memory>

#include <omp.h>

#include <Eigen/Dense>

#include "breast_sim/core/fem/anp_tet_fem.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "breast_sim/core/solver/rank_one_sum.h"

using namespace breast_sim::core;

namespace {

ElasticMaterial tissue() {
  ElasticMaterial m;
  m.youngs_modulus_pa = 2000.0;
  m.poisson_ratio = 0.48;
  return m;
}

Points deformed(const TetMesh& m, double sigma_m, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> d(0, sigma_m);
  Points x = m.nodes();
  Eigen::Matrix3d G;
  G << 0.06, 0.04, -0.02, 0.0, -0.05, 0.03, 0.02, 0.0, 0.08;
  x += m.nodes() * G.transpose();
  for (int i = 0; i < x.size(); ++i) x.data()[i] += d(rng);
  return x;
}

/// An ANP element with the barrier and per-element moduli, updated at a deformed pose.
struct UpdatedAnp {
  TetMesh mesh;
  std::unique_ptr<AnpTetFem> fem;
  explicit UpdatedAnp(const Eigen::Vector3i& cells, unsigned seed = 3) : mesh(makeBoxMesh(cells, {0.04, 0.03, 0.03})) {
    fem = std::make_unique<AnpTetFem>(mesh, tissue());
    fem->setInversionBarrier(0.3);
    Eigen::VectorXd factors = Eigen::VectorXd::Ones(mesh.numTets());
    for (int e = 0; e < mesh.numTets(); e += 7) factors[e] = 1.7;
    fem->setModulusFactors(factors);
    Eigen::VectorXd f(3 * mesh.numNodes());
    fem->update(deformed(mesh, 5e-4, seed), f);
  }
};

Eigen::VectorXd randomVector(Eigen::Index n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::VectorXd v(n);
  for (Eigen::Index i = 0; i < n; ++i) v[i] = u(rng);
  return v;
}

/// 1 for every DOF of a node kept free, 0 for the nodes of the x_min face.
std::vector<double> freeMask(const TetMesh& m) {
  std::vector<double> free(3 * static_cast<size_t>(m.numNodes()), 1.0);
  for (int n : m.nodeSet("x_min"))
    for (int c = 0; c < 3; ++c) free[3 * n + c] = 0.0;
  return free;
}

Eigen::MatrixXd dense(const SparseMatrix& A) { return Eigen::MatrixXd(A); }

}  // namespace

TEST(RankOneSum, AnpCompactPartPlusTheSumIsTheTwoRingStiffness) {
  const UpdatedAnp a({4, 3, 3});
  ASSERT_NE(a.fem->compactPattern(), nullptr);
  SparseMatrix full = a.fem->pattern().matrix(), compact = a.fem->compactPattern()->matrix();
  a.fem->assignStiffness(0.7, full);
  a.fem->assignCompactStiffness(0.7, compact);
  EXPECT_LT(compact.nonZeros() * 2, full.nonZeros());  // the one-ring pattern is the narrower one
  RankOneSum R = a.fem->rankOneStiffness();
  R.scale = 0.7;
  const Eigen::MatrixXd K = dense(full);
  EXPECT_LT((dense(compact) + dense(rankOneMatrix(R)) - K).norm(), 1e-12 * K.norm());
  // The product: K x = K_c x + R x, and the returned xᵀ R x.
  const Eigen::VectorXd x = randomVector(full.rows(), 11);
  Eigen::VectorXd y = compact * x;
  std::vector<double> work(R.terms);
  const double quadratic = addRankOneProduct(R, x.data(), 1.0, y.data(), work.data());
  EXPECT_LT((y - K * x).norm(), 1e-12 * (K * x).norm());
  EXPECT_NEAR(quadratic, x.dot(rankOneMatrix(R) * x), 1e-12 * std::abs(quadratic));
  // A second sum adds; alpha scales.
  Eigen::VectorXd z = Eigen::VectorXd::Zero(x.size());
  addRankOneProduct(R, x.data(), -2.0, z.data(), work.data());
  EXPECT_LT((z + 2.0 * (rankOneMatrix(R) * x)).norm(), 1e-12 * z.norm());
}

TEST(RankOneSum, MaskedProductDiagonalAndMatrixAgree) {
  const UpdatedAnp a({4, 3, 3});
  const std::vector<double> free = freeMask(a.mesh);
  RankOneSum R = a.fem->rankOneStiffness();
  RankOneSum Rm = R;
  Rm.free = free.data();
  Rm.scale = 3.0;
  R.scale = 3.0;
  const Eigen::VectorXd d = Eigen::Map<const Eigen::VectorXd>(free.data(), static_cast<Eigen::Index>(free.size()));
  const Eigen::MatrixXd M = dense(rankOneMatrix(R));
  const Eigen::MatrixXd Mm = dense(rankOneMatrix(Rm));
  EXPECT_LT((Mm - d.asDiagonal() * M * d.asDiagonal()).norm(), 1e-12 * M.norm());
  const Eigen::VectorXd x = randomVector(M.rows(), 5);
  Eigen::VectorXd y = Eigen::VectorXd::Zero(x.size());
  std::vector<double> work(R.terms);
  addRankOneProduct(Rm, x.data(), 1.0, y.data(), work.data());
  EXPECT_LT((y - Mm * x).norm(), 1e-12 * (Mm * x).norm());
  std::vector<double> blocks(9 * static_cast<size_t>(R.nodes), 0.0);
  addRankOneDiagonal(Rm, blocks.data());
  double err = 0.0;
  for (int n = 0; n < R.nodes; ++n)
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) err = std::max(err, std::abs(blocks[9 * n + 3 * r + c] - Mm(3 * n + r, 3 * n + c)));
  EXPECT_LT(err, 1e-12 * Mm.diagonal().maxCoeff());
}

TEST(RankOneSum, ProductIsTheSameBitsOnOneAndTwoThreads) {
  const UpdatedAnp a({16, 12, 12});  // more terms than the product's one-thread threshold
  RankOneSum R = a.fem->rankOneStiffness();
  const std::vector<double> free = freeMask(a.mesh);
  R.free = free.data();
  const Eigen::VectorXd x = randomVector(3 * R.nodes, 9);
  std::vector<double> work(R.terms);
  Eigen::VectorXd y[2];
  double q[2];
  const int threads = omp_get_max_threads();
  for (int t = 0; t < 2; ++t) {
    omp_set_num_threads(t + 1);
    y[t] = Eigen::VectorXd::Zero(x.size());
    q[t] = addRankOneProduct(R, x.data(), 1.0, y[t].data(), work.data());
  }
  omp_set_num_threads(threads);
  EXPECT_EQ(q[0], q[1]);
  EXPECT_TRUE((y[0].array() == y[1].array()).all());
}

namespace {

/// A zero coarse matrix with exactly the image's pattern, in block layout (every 3×3 block stored).
SparseMatrix zeroImagePattern(const RankOneGalerkin& g, int coarse_nodes) {
  std::vector<Eigen::Triplet<double>> t;
  for (int I = 0; I < coarse_nodes; ++I)
    for (int k = g.patternStart()[I]; k < g.patternStart()[I + 1]; ++k)
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) t.emplace_back(3 * I + r, 3 * g.patternNodes()[k] + c, 1.0);
  SparseMatrix C(3 * coarse_nodes, 3 * coarse_nodes);
  C.setFromTriplets(t.begin(), t.end());
  C.makeCompressed();
  std::fill(C.valuePtr(), C.valuePtr() + C.nonZeros(), 0.0);
  return C;
}

}  // namespace

// The image's per-thread slot maps follow the thread count add() runs on, which may differ from the
// one analyze() ran on (the simulator chooses each step's thread count): same bits either way.
TEST(RankOneGalerkin, AnalysedOnOneThreadAddsOnTwoWithTheSameBits) {
  const UpdatedAnp a({16, 12, 12});
  const TetMesh coarse = makeBoxMesh({6, 4, 4}, {0.04, 0.03, 0.03});
  const NodeProlongation P = barycentricProlongation(a.mesh, coarse, 1e-6);
  RankOneSum R = a.fem->rankOneStiffness();
  ASSERT_GT(R.terms, 2000);  // more terms than the image's one-thread threshold (kParallelMinTerms)
  const std::vector<double> free = freeMask(a.mesh);
  R.free = free.data();
  const int threads = omp_get_max_threads();
  Eigen::MatrixXd image[2];
  for (int analysed_on = 1; analysed_on <= 2; ++analysed_on) {
    omp_set_num_threads(analysed_on);
    RankOneGalerkin g;
    g.analyze(R, P);
    SparseMatrix C = zeroImagePattern(g, coarse.numNodes());
    omp_set_num_threads(2);
    g.add(R, C);
    image[analysed_on - 1] = dense(C);
  }
  omp_set_num_threads(threads);
  ASSERT_GT(image[1].norm(), 0.0);
  EXPECT_TRUE((image[0].array() == image[1].array()).all());
}

TEST(RankOneGalerkin, ImageIsTheTripleProductOfTheAssembledSum) {
  const UpdatedAnp a({6, 4, 4});
  const TetMesh coarse = makeBoxMesh({3, 2, 2}, {0.04, 0.03, 0.03});
  const NodeProlongation P = barycentricProlongation(a.mesh, coarse, 1e-6);
  RankOneSum R = a.fem->rankOneStiffness();
  const std::vector<double> free = freeMask(a.mesh);
  R.free = free.data();
  R.scale = 0.5;
  RankOneGalerkin g;
  g.analyze(R, P);
  const int nc = coarse.numNodes();
  SparseMatrix C = zeroImagePattern(g, nc);
  g.add(R, C);
  const SparseMatrix Pd = expandToDofs(P);
  const Eigen::MatrixXd ref = dense(SparseMatrix(Pd.transpose() * rankOneMatrix(R) * Pd));
  EXPECT_LT((dense(C) - ref).norm(), 1e-12 * ref.norm());
  EXPECT_LT((dense(C) - dense(C).transpose()).norm(), 1e-12 * ref.norm());
  // A coarse pattern without the image's couplings is refused, naming a coarse node.
  SparseMatrix diagonal(3 * nc, 3 * nc);
  std::vector<Eigen::Triplet<double>> td;
  for (int I = 0; I < nc; ++I)
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) td.emplace_back(3 * I + r, 3 * I + c, 0.0);
  diagonal.setFromTriplets(td.begin(), td.end());
  diagonal.makeCompressed();
  try {
    g.add(R, diagonal);
    FAIL() << "a coarse pattern without the image's blocks was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("no block for the image's coupling of coarse node"), std::string::npos) << e.what();
  }
}

namespace {

/// The implicit step's matrices of an updated ANP element on a box with the x_min face fixed:
/// the assembled A = M/dt² + K and the split S = M/dt² + K_c with R, both with the fixed DOFs
/// decoupled (unit rows and columns), and a load.
struct StepSystem {
  UpdatedAnp anp;
  std::vector<double> free;
  SparseMatrix A, S;
  RankOneSum R;
  Eigen::VectorXd b;
  explicit StepSystem(const Eigen::Vector3i& cells) : anp(cells), free(freeMask(anp.mesh)) {
    A = anp.fem->pattern().matrix();
    S = anp.fem->compactPattern()->matrix();
    anp.fem->assignStiffness(1.0, A);
    anp.fem->assignCompactStiffness(1.0, S);
    const Eigen::VectorXd V = anp.mesh.tetVolumes();
    Eigen::VectorXd mass = Eigen::VectorXd::Zero(anp.mesh.numNodes());
    for (int e = 0; e < anp.mesh.numTets(); ++e)
      for (int i = 0; i < 4; ++i) mass[anp.mesh.tets()(e, i)] += 1000.0 * V[e] / 4;
    for (SparseMatrix* M : {&A, &S}) {
      for (int row = 0; row < M->rows(); ++row)
        for (SparseMatrix::InnerIterator it(*M, row); it; ++it) {
          if (free[row] == 0.0 || free[it.col()] == 0.0) it.valueRef() = row == it.col() ? 1.0 : 0.0;
          else if (row == it.col()) it.valueRef() += mass[row / 3] / (0.033 * 0.033);
        }
    }
    R = anp.fem->rankOneStiffness();
    R.free = free.data();
    b = randomVector(A.rows(), 21);
    for (Eigen::Index i = 0; i < b.size(); ++i)
      if (free[i] == 0.0) b[i] = 0.0;
  }
};

}  // namespace

// The projected initial guess (PcgOptions::projection_vectors) multiplies by S + R as the iterations
// do: held to the dense Galerkin projection with the assembled matrix.
TEST(PcgSolver, ProjectsItsInitialGuessWithTheRankOnePart) {
  const StepSystem sys({8, 6, 6});
  PcgOptions o;
  o.relative_tolerance = 1e-11;
  PcgSolver pcg(o);
  pcg.analyzeWithRankOne(sys.S, sys.R);
  pcg.factorizeWithRankOne(sys.S, sys.R);
  Eigen::VectorXd x1;
  ASSERT_TRUE(pcg.solve(sys.b, x1).converged);
  Eigen::VectorXd b2 = randomVector(sys.A.rows(), 22), b3 = randomVector(sys.A.rows(), 23);
  for (Eigen::Index i = 0; i < b2.size(); ++i)
    if (sys.R.free[i] == 0.0) b2[i] = b3[i] = 0.0;
  Eigen::VectorXd x2 = x1;
  ASSERT_TRUE(pcg.solve(b2, x2).converged);
  PcgOptions guess_only = o;
  guess_only.max_iterations = 0;
  pcg.setOptions(guess_only);
  Eigen::VectorXd x = x2;
  pcg.solve(b3, x);
  // span{x2, x1}, the fixed rows (b = 0 there) zero
  Eigen::MatrixXd W(b3.size(), 2);
  W << x2, x1;
  for (Eigen::Index i = 0; i < b3.size(); ++i)
    if (sys.R.free[i] == 0.0) W.row(i).setZero();
  const Eigen::MatrixXd A = Eigen::MatrixXd(sys.A);
  const Eigen::VectorXd ref = W * (W.transpose() * A * W).ldlt().solve(W.transpose() * b3);
  EXPECT_LE((x - ref).norm(), 1e-9 * ref.norm());
}

namespace {
// A preconditioner as it is, but without a float copy to offer: PCG then multiplies in double.
class WithoutFloatCopy : public Preconditioner {
 public:
  explicit WithoutFloatCopy(std::unique_ptr<Preconditioner> p) : p_(std::move(p)) {}
  void analyzePattern(const SparseMatrix& A) override { p_->analyzePattern(A); }
  void factorize(const SparseMatrix& A) override { p_->factorize(A); }
  void apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) override { p_->apply(r, z); }
  std::string name() const override { return p_->name(); }
  void reportConvergence(int iterations, double reduction) override { p_->reportConvergence(iterations, reduction); }
  bool acceptsRankOneSum() const override { return p_->acceptsRankOneSum(); }
  void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override { p_->analyzeWithRankOne(S, R); }
  void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override { p_->factorizeWithRankOne(S, R); }

 private:
  std::unique_ptr<Preconditioner> p_;
};
}  // namespace

// With a rank-one sum the multigrid's float copy holds S alone and PCG adds R's product in double:
// at a tolerance that uses the copy, the solve takes the iterations of the same multigrid without
// it (the slow reference, double products) and ends within the tolerance on S + R.
TEST(PcgSolver, MultipliesByTheFloatCopyOfSAndAddsTheRankOneProduct) {
  const StepSystem sys({8, 6, 6});
  const TetMesh coarse = makeBoxMesh({4, 3, 3}, {0.04, 0.03, 0.03});
  PcgOptions o;
  o.relative_tolerance = 1e-3;
  ASSERT_GE(o.relative_tolerance, kFloatProductMinTolerance);
  auto multigrid = [&] { return std::make_unique<MultigridPreconditioner>(MeshHierarchy({sys.anp.mesh, coarse})); };
  PcgSolver with_copy(o, multigrid());
  PcgSolver without(o, std::make_unique<WithoutFloatCopy>(multigrid()));
  Eigen::VectorXd xc, xd;
  SolveStats sc, sd;
  for (auto [pcg, x, st] : {std::tuple{&with_copy, &xc, &sc}, std::tuple{&without, &xd, &sd}}) {
    pcg->analyzeWithRankOne(sys.S, sys.R);
    pcg->factorizeWithRankOne(sys.S, sys.R);
    *st = pcg->solve(sys.b, *x);
    ASSERT_TRUE(st->converged);
    const double true_residual = (sys.b - sys.A * *x).norm() / sys.b.norm();
    EXPECT_LE(true_residual, o.relative_tolerance);
    EXPECT_NEAR(st->relative_residual, true_residual, 1e-9 * true_residual);
  }
  const Preconditioner::FloatBlocks copy = with_copy.preconditioner().floatBlocks();
  ASSERT_NE(copy.val, nullptr);
  EXPECT_EQ(copy.val[9 * copy.start[5]], static_cast<float>(sys.S.coeff(15, 3 * copy.col[copy.start[5]])));
  EXPECT_EQ(without.preconditioner().floatBlocks().val, nullptr);
  EXPECT_LE(std::abs(sc.iterations - sd.iterations), 1) << "float copy " << sc.iterations << ", double " << sd.iterations;
  EXPECT_LE((xc - xd).norm(), 1e-3 * xd.norm());
}

TEST(PcgSolver, SolvesTheSplitSystemAsCholmodSolvesTheAssembledOne) {
  const StepSystem sys({8, 6, 6});
  CholmodSolver direct;
  direct.analyzePattern(sys.A);
  direct.factorize(sys.A);
  Eigen::VectorXd ref;
  direct.solve(sys.b, ref);

  PcgOptions o;
  o.relative_tolerance = 1e-11;
  PcgSolver jacobi(o);
  ASSERT_TRUE(jacobi.acceptsRankOneSum());
  jacobi.analyzeWithRankOne(sys.S, sys.R);
  jacobi.factorizeWithRankOne(sys.S, sys.R);
  Eigen::VectorXd x;
  const SolveStats sj = jacobi.solve(sys.b, x);
  EXPECT_TRUE(sj.converged);
  EXPECT_LT((x - ref).norm(), 1e-8 * ref.norm());

  const TetMesh coarse = makeBoxMesh({4, 3, 3}, {0.04, 0.03, 0.03});
  for (auto smoother : {MultigridOptions::Smoother::kJacobi, MultigridOptions::Smoother::kChebyshev}) {
    SCOPED_TRACE(smoother == MultigridOptions::Smoother::kJacobi ? "jacobi" : "chebyshev");
    MultigridOptions mo;
    mo.smoother = smoother;
    mo.fine_eigenvalue_bound = 0.0;
    MultigridPcgSolver mg(MeshHierarchy({sys.anp.mesh, coarse}), o, mo);
    ASSERT_TRUE(mg.acceptsRankOneSum());
    mg.analyzeWithRankOne(sys.S, sys.R);
    mg.factorizeWithRankOne(sys.S, sys.R);
    Eigen::VectorXd xm;
    const SolveStats sm = mg.solve(sys.b, xm);
    EXPECT_TRUE(sm.converged);
    EXPECT_LT((xm - ref).norm(), 1e-8 * ref.norm());
    // The split multigrid converges as the assembled one does: its coarse operator sees R.
    MultigridPcgSolver whole(MeshHierarchy({sys.anp.mesh, coarse}), o, mo);
    whole.analyzePattern(sys.A);
    whole.factorize(sys.A);
    Eigen::VectorXd xw;
    const SolveStats sw = whole.solve(sys.b, xw);
    EXPECT_LE(sm.iterations, sw.iterations + 2) << "split " << sm.iterations << ", assembled " << sw.iterations;
    EXPECT_LT((mg.multigrid().levelMatrix(1) - whole.multigrid().levelMatrix(1)).norm(),
              1e-10 * whole.multigrid().levelMatrix(1).norm());
  }
  // Gauss–Seidel needs the rows of R one by one: refused with the reason.
  MultigridOptions gs;
  gs.smoother = MultigridOptions::Smoother::kGaussSeidel;
  MultigridPcgSolver mgs(MeshHierarchy({sys.anp.mesh, coarse}), o, gs);
  EXPECT_FALSE(mgs.acceptsRankOneSum());
  EXPECT_THROW(mgs.analyzeWithRankOne(sys.S, sys.R), std::logic_error);
  // A fixed row that the sum does not mask is refused.
  RankOneSum unmasked = sys.R;
  unmasked.free = nullptr;
  PcgSolver p2(o);
  p2.analyzeWithRankOne(sys.S, unmasked);
  EXPECT_THROW(p2.factorizeWithRankOne(sys.S, unmasked), std::logic_error);
}

TEST(DynamicSimulator, SplitStiffnessStepsAsTheAssembledOne) {
  // ANP with the barrier on a block under gravity, x_min fixed and the x_max face pulled by moving
  // targets: the multigrid run (split: one-ring matrix + rank-one sum) against CHOLMOD on the
  // assembled two-ring matrix, step by step, reactions included, then settled.
  const TetMesh mesh = makeBoxMesh({8, 4, 4}, {0.06, 0.03, 0.03});
  const TetMesh coarse = makeBoxMesh({4, 2, 2}, {0.06, 0.03, 0.03});
  SimulationSettings s;
  s.element = SimulationSettings::Element::kAnpTet;
  s.anp_inversion_barrier = 0.3;
  s.fixed_node_set = "x_min";
  s.dynamics.gravity_mps2 = Eigen::Vector3d(0.0, -9.81, 4.0);
  s.solver.relative_tolerance = 1e-11;
  s.solver.max_iterations = 500;
  std::unique_ptr<DynamicSimulator> sim[2];
  s.solver.kind = SolverSettings::Kind::kCholmod;
  sim[0] = std::move(buildSimulator(mesh, s).simulator);
  s.solver.kind = SolverSettings::Kind::kMultigrid;
  sim[1] = std::move(buildSimulator(mesh, s, {coarse}).simulator);
  EXPECT_FALSE(sim[0]->splitStiffness());
  EXPECT_TRUE(sim[1]->splitStiffness());
  const std::vector<int> pulled = mesh.nodeSet("x_max");
  for (int step = 0; step < 6; ++step) {
    Points targets(pulled.size(), 3);
    for (size_t i = 0; i < pulled.size(); ++i) targets.row(static_cast<Eigen::Index>(i)) << 1e-3 * (step + 1), 0.0, 0.0;
    for (auto& m : sim) {
      m->setNodeTargets(pulled, targets);
      m->step();
    }
    const double scale = sim[0]->state().displacement_m.norm();
    EXPECT_LT((sim[1]->state().displacement_m - sim[0]->state().displacement_m).norm(), 1e-7 * scale) << "step " << step;
    const double fscale = sim[0]->constraintForces().norm();
    EXPECT_LT((sim[1]->constraintForces() - sim[0]->constraintForces()).norm(), 1e-6 * fscale) << "step " << step;
  }
  SettleOptions so;
  so.increment_tolerance_m = 1e-9;
  for (auto& m : sim) EXPECT_TRUE(settle(*m, so).settled);
  const double scale = sim[0]->state().displacement_m.norm();
  EXPECT_LT((sim[1]->state().displacement_m - sim[0]->state().displacement_m).norm(), 1e-6 * scale);
}
