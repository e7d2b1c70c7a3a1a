#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <random>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <Eigen/SparseCholesky>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/polar_decomposition.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/tet_quality.h"

using namespace breast_sim::core;

namespace {

/// Reference solver for these tests: Eigen's sparse LDLᵀ (the project's solvers are tested against
/// it in test_solvers.cpp).
class EigenLdltSolver : public LinearSolver {
 public:
  void analyzePattern(const SparseMatrix& A) override { ldlt_.analyzePattern(Eigen::SparseMatrix<double>(A)); }
  void factorize(const SparseMatrix& A) override {
    ldlt_.factorize(Eigen::SparseMatrix<double>(A));
    if (ldlt_.info() != Eigen::Success) throw std::runtime_error("eigen-ldlt: not positive definite");
  }
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override {
    x = ldlt_.solve(b);
    return {0, 0.0, true, 0.0};
  }
  std::string name() const override { return "eigen-ldlt"; }

 private:
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt_;
};

Points positions(const TetMesh& m, const Eigen::VectorXd& u) {
  Points x = m.nodes();
  for (int n = 0; n < m.numNodes(); ++n) x.row(n) += u.segment<3>(3 * n).transpose();
  return x;
}

Eigen::VectorXd forcesAt(CorotatedTetFem& fem, const Points& x) {
  Eigen::VectorXd f;
  fem.update(x, f);
  return f;
}

SparseMatrix stiffnessAt(CorotatedTetFem& fem, const Points& x) {
  Eigen::VectorXd f;
  fem.update(x, f);
  SparseMatrix K = fem.pattern().matrix();
  fem.addStiffness(1.0, K);
  return K;
}

const TetMesh& smallBlock() {
  static const TetMesh m = makeBoxMesh({3, 2, 2}, {0.03, 0.02, 0.02});
  return m;
}

/// The rest nodes of `m`, each coordinate moved by a normal random amount of `sigma_m` [m].
Points jittered(const TetMesh& m, unsigned seed, double sigma_m) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> d(0, sigma_m);
  Points x = m.nodes();
  for (int i = 0; i < x.size(); ++i) x.data()[i] += d(rng);
  return x;
}

/// Static linear solve K u = f with the nodes of `fixed` held at `u_fixed` (per DOF).
Eigen::VectorXd staticSolve(const Eigen::MatrixXd& K, const Eigen::VectorXd& f, const std::vector<char>& fixed,
                            const Eigen::VectorXd& u_fixed) {
  std::vector<int> free_dofs, fixed_dofs;
  for (int i = 0; i < K.rows(); ++i) (fixed[i] ? fixed_dofs : free_dofs).push_back(i);
  Eigen::MatrixXd Kff(free_dofs.size(), free_dofs.size());
  Eigen::VectorXd rhs(free_dofs.size());
  for (size_t a = 0; a < free_dofs.size(); ++a) {
    rhs[a] = f[free_dofs[a]];
    for (int c : fixed_dofs) rhs[a] -= K(free_dofs[a], c) * u_fixed[c];
    for (size_t b = 0; b < free_dofs.size(); ++b) Kff(a, b) = K(free_dofs[a], free_dofs[b]);
  }
  const Eigen::VectorXd uf = Kff.ldlt().solve(rhs);
  Eigen::VectorXd u = u_fixed;
  for (size_t a = 0; a < free_dofs.size(); ++a) u[free_dofs[a]] = uf[a];
  return u;
}

}  // namespace

TEST(PolarDecomposition, HighamMatchesSvdOnWellConditionedMatrices) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> d(-0.4, 0.4);
  for (int trial = 0; trial < 50; ++trial) {
    SCOPED_TRACE("trial " + std::to_string(trial));
    Eigen::Matrix3d F = Eigen::Matrix3d::Identity();
    for (int i = 0; i < 9; ++i) F.data()[i] += d(rng);
    F = Eigen::AngleAxisd(trial * 0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() * F;
    if (F.determinant() <= 0.05) continue;
    const Eigen::Matrix3d R = rotationOf(F);
    EXPECT_LT((R - rotationOfBySvd(F)).norm(), 1e-9);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
    // The polar factor leaves a symmetric stretch: Rᵀ F = S.
    const Eigen::Matrix3d S = R.transpose() * F;
    EXPECT_LT((S - S.transpose()).norm(), 1e-9);
  }
}

TEST(PolarDecomposition, InvertedAndDegenerateMatricesGiveProperRotations) {
  Eigen::Matrix3d inverted = Eigen::Matrix3d::Identity();
  inverted(2, 2) = -0.5;  // an element pushed through itself
  Eigen::Matrix3d flat = Eigen::Matrix3d::Identity();
  flat(2, 2) = 0.0;       // collapsed to a plane
  Eigen::Matrix3d line = Eigen::Matrix3d::Zero();
  line(0, 0) = 1.0;       // collapsed to a line
  for (const auto& F : {inverted, flat, line, Eigen::Matrix3d(Eigen::Matrix3d::Zero())}) {
    const Eigen::Matrix3d R = rotationOf(F);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
    EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  }
}

TEST(PolarDecomposition, EarlyStopStillMatchesSvdToRoundOffOverWideStretches) {
  // rotationOf stops one Newton step after the step change drops below ~3e-7: the result must be
  // the SVD rotation to 1e-10 and orthonormal to 1e-12, from small strains to near-degenerate F.
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  auto randomRotation = [&]() {
    return Eigen::AngleAxisd(3.0 * u(rng), Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized()).toRotationMatrix();
  };
  const std::vector<Eigen::Vector3d> stretches = {{1.0, 1.0, 1.0},    {1.01, 0.995, 1.0}, {1.3, 0.8, 1.1},
                                                  {3.0, 0.2, 1.0},    {1.0, 1.0, 1e-3},   {1e-2, 1.0, 5.0},
                                                  {1.0, 1.0, 1e-8},   {2.0, 2.0, 2.0}};
  for (int trial = 0; trial < 200; ++trial) {
    const Eigen::Vector3d sigma = stretches[trial % stretches.size()].cwiseProduct(
        Eigen::Vector3d::Constant(1.0) + 0.05 * Eigen::Vector3d(u(rng), u(rng), u(rng)));
    const Eigen::Matrix3d F = randomRotation() * sigma.asDiagonal() * randomRotation();
    SCOPED_TRACE("trial " + std::to_string(trial));
    const Eigen::Matrix3d R = rotationOf(F);
    EXPECT_LT((R - rotationOfBySvd(F)).norm(), 1e-10);
    EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 1e-12);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
  }
  // Inverted: the reflection-fixed rotation of the SVD path.
  for (int trial = 0; trial < 20; ++trial) {
    Eigen::Matrix3d F = randomRotation() * Eigen::Vector3d(1.2, 0.9, -0.3).asDiagonal() * randomRotation();
    const Eigen::Matrix3d R = rotationOf(F);
    EXPECT_LT((R - rotationOfBySvd(F)).norm(), 1e-12);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
  }
}

TEST(CorotatedTetFem, RigidRotationAndTranslationGiveZeroElasticForce) {
  const TetMesh& m = smallBlock();
  CorotatedTetFem fem(m, ElasticMaterial{});
  const Eigen::Matrix3d R = Eigen::AngleAxisd(1.1, Eigen::Vector3d(0.3, -1, 0.5).normalized()).toRotationMatrix();
  const Eigen::RowVector3d t(0.05, -0.2, 0.01);
  Points x = m.nodes() * R.transpose();
  x.rowwise() += t;
  const Eigen::VectorXd f = forcesAt(fem, x);
  // Scale: the force a 1% strain would give.
  const double scale = ElasticMaterial{}.youngs_modulus_pa * 0.01 * 1e-4;
  EXPECT_LT(f.cwiseAbs().maxCoeff(), 1e-9 * scale);
  // Linear (not co-rotated) FEM does produce spurious forces under the same rotation.
  CorotatedTetFem linear(m, ElasticMaterial{});
  linear.setCorotated(false);
  EXPECT_GT(forcesAt(linear, x).cwiseAbs().maxCoeff(), scale);
}

TEST(CorotatedTetFem, SparseAssemblyEqualsDenseElementByElementAssembly) {
  const TetMesh& m = smallBlock();
  ElasticMaterial mat;
  mat.poisson_ratio = 0.45;
  CorotatedTetFem fem(m, mat);
  Eigen::VectorXd factors = Eigen::VectorXd::LinSpaced(m.numTets(), 1.0, 3.0);
  fem.setModulusFactors(factors);
  std::mt19937 rng(5);
  std::normal_distribution<double> d(0, 2e-3);
  Points x = m.nodes();
  for (int i = 0; i < x.size(); ++i) x.data()[i] += d(rng);
  const SparseMatrix K = stiffnessAt(fem, x);
  const Eigen::MatrixXd dense = fem.denseStiffness();
  EXPECT_LT((Eigen::MatrixXd(K) - dense).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
  EXPECT_LT((dense - dense.transpose()).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
}

TEST(CorotatedTetFem, ForcesMatchTheStiffnessByFiniteDifferences) {
  const TetMesh& m = smallBlock();
  std::mt19937 rng(9);
  std::normal_distribution<double> d(0, 1.0);
  Eigen::VectorXd dx(3 * m.numNodes());
  for (int i = 0; i < dx.size(); ++i) dx[i] = d(rng);
  dx *= 1e-3 / dx.norm();
  const double h = 1e-4;
  struct Case {
    const char* name;
    bool corotated;
    Points x;
    double tolerance;
  };
  std::normal_distribution<double> small(0, 3e-4);
  Points deformed = m.nodes();
  for (int i = 0; i < deformed.size(); ++i) deformed.data()[i] += small(rng);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
  const Points rotated = m.nodes() * R.transpose();
  // Linear FEM is exactly linear; co-rotated K omits ∂R/∂x, which vanishes at zero strain (a rigid
  // pose) and is of the order of the strain otherwise.
  const std::vector<Case> cases = {{"linear, deformed", false, deformed, 1e-7},
                                   {"corotated, rigidly rotated", true, rotated, 1e-6},
                                   {"corotated, slightly deformed", true, deformed, 5e-2}};
  for (const auto& c : cases) {
    SCOPED_TRACE(c.name);
    CorotatedTetFem fem(m, ElasticMaterial{});
    fem.setCorotated(c.corotated);
    const SparseMatrix K = stiffnessAt(fem, c.x);
    Points xp = c.x, xm = c.x;
    for (int n = 0; n < m.numNodes(); ++n) {
      xp.row(n) += h * dx.segment<3>(3 * n).transpose();
      xm.row(n) -= h * dx.segment<3>(3 * n).transpose();
    }
    const Eigen::VectorXd fd = (forcesAt(fem, xp) - forcesAt(fem, xm)) / (2 * h);
    const Eigen::VectorXd analytic = -(K * dx);
    EXPECT_LT((fd - analytic).norm(), c.tolerance * analytic.norm()) << "fd " << fd.norm() << " analytic " << analytic.norm();
  }
}

TEST(CorotatedTetFem, PatchTestReproducesALinearField) {
  // Boundary nodes follow an affine displacement; the interior must follow it exactly.
  const TetMesh m = makeBoxMesh({3, 3, 3}, {0.03, 0.03, 0.03});
  for (bool corotated : {false, true}) {
    SCOPED_TRACE(corotated ? "corotated" : "linear");
    CorotatedTetFem fem(m, ElasticMaterial{});
    fem.setCorotated(corotated);
    Eigen::Matrix3d G;
    G << 1e-3, 2e-4, -3e-4, 0, -5e-4, 1e-4, 2e-4, 0, 8e-4;  // small: co-rotation ≈ identity
    Eigen::VectorXd u_exact(3 * m.numNodes());
    for (int n = 0; n < m.numNodes(); ++n) u_exact.segment<3>(3 * n) = G * m.nodes().row(n).transpose();
    std::vector<char> fixed(3 * m.numNodes(), 0);
    for (int n : m.nodeSet("boundary"))
      for (int c = 0; c < 3; ++c) fixed[3 * n + c] = 1;
    // Linearise at the exact state and solve K Δu = f for the interior, starting from rest.
    const SparseMatrix K = stiffnessAt(fem, positions(m, u_exact));
    const Eigen::VectorXd f = forcesAt(fem, positions(m, u_exact));
    for (int i = 0; i < f.size(); ++i)
      if (!fixed[i]) {
        EXPECT_NEAR(f[i], 0.0, 1e-12) << "interior force at the exact field, DOF " << i;
      }
    Eigen::VectorXd u_fixed = Eigen::VectorXd::Zero(u_exact.size());
    for (int i = 0; i < u_exact.size(); ++i)
      if (fixed[i]) u_fixed[i] = u_exact[i];
    if (!corotated) {
      const Eigen::VectorXd u = staticSolve(Eigen::MatrixXd(K), Eigen::VectorXd::Zero(u_exact.size()), fixed, u_fixed);
      EXPECT_LT((u - u_exact).cwiseAbs().maxCoeff(), 1e-12);
    }
  }
}

TEST(DynamicSimulator, MetresAndMillimetresGiveTheSameDisplacements) {
  // The same block under gravity, once in SI and once in (mm, kg, s): lengths ×1e3, so pressure
  // (kg·mm⁻¹·s⁻²) = Pa × 1e-3, density kg/mm³ = kg/m³ × 1e-9, gravity mm/s² = m/s² × 1e3.
  const Eigen::Vector3i cells(4, 2, 2);
  const TetMesh si = makeBoxMesh(cells, {0.04, 0.02, 0.02});
  const TetMesh mm = makeBoxMesh(cells, {40.0, 20.0, 20.0});
  ElasticMaterial mat_si, mat_mm;
  mat_mm.youngs_modulus_pa = mat_si.youngs_modulus_pa * 1e-3;
  mat_mm.density_kg_per_m3 = mat_si.density_kg_per_m3 * 1e-9;
  DynamicsParams p_si, p_mm;
  p_si.gravity_mps2 = {0, 0, -9.81};
  p_mm.gravity_mps2 = {0, 0, -9810.0};
  DynamicSimulator a(si, std::make_unique<CorotatedTetFem>(si, mat_si), mat_si, p_si, std::make_unique<EigenLdltSolver>());
  DynamicSimulator b(mm, std::make_unique<CorotatedTetFem>(mm, mat_mm), mat_mm, p_mm, std::make_unique<EigenLdltSolver>());
  a.fixNodes(si.nodeSet("x_min"));
  b.fixNodes(mm.nodeSet("x_min"));
  for (int s = 0; s < 10; ++s) {
    a.step();
    b.step();
  }
  const Eigen::VectorXd ua = a.state().displacement_m, ub = b.state().displacement_m * 1e-3;
  EXPECT_GT(ua.cwiseAbs().maxCoeff(), 1e-3);  // it did sag
  EXPECT_LT((ua - ub).cwiseAbs().maxCoeff(), 1e-9 * ua.cwiseAbs().maxCoeff());
}

TEST(DynamicSimulator, DampedMotionSettlesToStaticEquilibrium) {
  const TetMesh m = makeBoxMesh({6, 2, 2}, {0.06, 0.02, 0.02});
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 20e3;  // small load: deflection of a few mm
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, mat), mat, p, std::make_unique<EigenLdltSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  for (int s = 0; s < 300; ++s) sim.step();
  EXPECT_LT(sim.state().velocity_mps.cwiseAbs().maxCoeff(), 1e-6);
  // Equilibrium: elastic forces balance gravity on every free node.
  const Eigen::VectorXd& f = sim.elasticForces();
  std::vector<char> fixed(m.numNodes(), 0);
  for (int n : m.nodeSet("x_min")) fixed[n] = 1;
  double worst = 0, weight = 0;
  for (int n = 0; n < m.numNodes(); ++n) {
    const double g = sim.lumpedMass()[n] * 9.81;
    weight = std::max(weight, g);
    if (!fixed[n]) worst = std::max(worst, std::abs(f[3 * n + 2] - g) + std::abs(f[3 * n]) + std::abs(f[3 * n + 1]));
  }
  EXPECT_LT(worst, 1e-6 * weight);
}

TEST(DynamicSimulator, CantileverConvergesTowardsEulerBernoulliUnderRefinement) {
  // Beam L × h × h fixed at x = 0 under its own weight, ν = 0, small load: tip deflection
  // δ = q L⁴ / (8 E I), q = ρ g h², I = h⁴ / 12. Linear tetrahedra are too stiff in bending; the
  // error must shrink with refinement.
  const double L = 0.1, h = 0.01;
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 1e6;
  mat.poisson_ratio = 0.0;
  const double q = mat.density_kg_per_m3 * 9.81 * h * h, I = std::pow(h, 4) / 12.0;
  const double delta = q * std::pow(L, 4) / (8.0 * mat.youngs_modulus_pa * I);
  std::vector<double> errors;
  for (int level = 0; level < 4; ++level) {
    const int across = 1 << level;
    const TetMesh m = makeBoxMesh({10 * across, across, across}, {L, h, h});
    CorotatedTetFem fem(m, mat);
    const SparseMatrix K = stiffnessAt(fem, m.nodes());
    Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * m.numNodes());
    const Eigen::VectorXd vol = m.tetVolumes();
    for (int e = 0; e < m.numTets(); ++e)
      for (int i = 0; i < 4; ++i) f[3 * m.tets()(e, i) + 2] -= 0.25 * mat.density_kg_per_m3 * 9.81 * vol[e];
    std::vector<char> fixed(3 * m.numNodes(), 0);
    for (int n : m.nodeSet("x_min"))
      for (int c = 0; c < 3; ++c) fixed[3 * n + c] = 1;
    // Sparse direct solve on the free DOFs (unit rows for the fixed ones).
    SparseMatrix A = K;
    for (int r = 0; r < A.rows(); ++r)
      for (SparseMatrix::InnerIterator it(A, r); it; ++it)
        if (fixed[r] || fixed[it.col()]) it.valueRef() = (r == it.col()) ? 1.0 : 0.0;
    for (int r = 0; r < A.rows(); ++r)
      if (fixed[r]) f[r] = 0;
    const Eigen::SparseMatrix<double> Acol = A;
    Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(Acol);
    const Eigen::VectorXd u = ldlt.solve(f);
    double tip = 0;
    const auto& tip_nodes = m.nodeSet("x_max");
    for (int n : tip_nodes) tip += u[3 * n + 2] / tip_nodes.size();
    errors.push_back(std::abs(-tip - delta) / delta);
    std::cout << "[ cantilever ] level " << level << ": " << m.numTets() << " tets, tip " << -tip * 1e3
              << " mm, Euler-Bernoulli " << delta * 1e3 << " mm, error " << 100 * errors.back() << " %\n";
  }
  // Measured: 75 %, 45 %, 17 %, 4.4 % from 60 to 30,720 tetrahedra.
  for (size_t i = 1; i < errors.size(); ++i) EXPECT_LT(errors[i], 0.7 * errors[i - 1]) << "level " << i;
  EXPECT_LT(errors.back(), 0.08);
}

TEST(DynamicSimulator, RestoredStateContinuesExactlyAsBefore) {
  const TetMesh m = makeBoxMesh({4, 2, 2}, {0.04, 0.02, 0.02});
  DynamicsParams p;
  p.gravity_mps2 = {0, -9.81, 0};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, ElasticMaterial{}), ElasticMaterial{}, p,
                       std::make_unique<EigenLdltSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  for (int s = 0; s < 3; ++s) sim.step();
  const SimulationState saved = sim.state();
  for (int s = 0; s < 4; ++s) sim.step();
  const SimulationState after = sim.state();
  sim.restore(saved);
  EXPECT_EQ(sim.state().step, saved.step);
  for (int s = 0; s < 4; ++s) sim.step();
  EXPECT_EQ(sim.state().displacement_m, after.displacement_m);  // bit for bit
  EXPECT_EQ(sim.state().velocity_mps, after.velocity_mps);
  SimulationState wrong = saved;
  wrong.displacement_m.resize(6);
  EXPECT_THROW(sim.restore(wrong), std::invalid_argument);
}

TEST(DynamicSimulator, TargetNodesReachTheirDisplacementAndFixedNodesStay) {
  const TetMesh m = makeBoxMesh({4, 2, 2}, {0.04, 0.02, 0.02});
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, ElasticMaterial{}), ElasticMaterial{}, p,
                       std::make_unique<EigenLdltSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  const auto& moved = m.nodeSet("x_max");
  Points targets(moved.size(), 3);
  targets.rowwise() = Eigen::RowVector3d(0.002, 0.0, 0.001);
  sim.setNodeTargets(moved, targets);
  sim.step();
  const Points u = sim.displacement();
  for (size_t i = 0; i < moved.size(); ++i) EXPECT_LT((u.row(moved[i]) - targets.row(i)).norm(), 1e-14);
  for (int n : m.nodeSet("x_min")) EXPECT_EQ(u.row(n).norm(), 0.0);
  EXPECT_THROW(sim.setNodeTargets({0}, Points::Zero(2, 3)), std::invalid_argument);
  EXPECT_THROW(sim.fixNodes({m.numNodes()}), std::invalid_argument);
}

TEST(DynamicSimulator, ChangingTheConstraintSetBetweenStepsTakesEffect) {
  // step() keeps elimination lists for the constraint set; they must follow every change.
  const TetMesh m = makeBoxMesh({4, 2, 2}, {0.04, 0.02, 0.02});
  DynamicsParams p;
  p.gravity_mps2 = {0, 0, -9.81};
  DynamicSimulator sim(m, std::make_unique<CorotatedTetFem>(m, ElasticMaterial{}), ElasticMaterial{}, p,
                       std::make_unique<EigenLdltSolver>());
  sim.fixNodes(m.nodeSet("x_min"));
  for (int s = 0; s < 3; ++s) sim.step();
  for (int n : m.nodeSet("x_min")) EXPECT_EQ(sim.displacement().row(n).norm(), 0.0);
  // Swap the clamped end.
  sim.clearConstraints();
  sim.fixNodes(m.nodeSet("x_max"));
  const Points before = sim.displacement();
  sim.step();
  const Points after = sim.displacement();
  for (int n : m.nodeSet("x_max")) EXPECT_EQ((after.row(n) - before.row(n)).norm(), 0.0);
  for (int n : m.nodeSet("x_min")) EXPECT_GT((after.row(n) - before.row(n)).norm(), 0.0);
  // Targets on the free end, same set as fixed nodes elsewhere: reached exactly.
  Points targets(m.nodeSet("x_min").size(), 3);
  targets.rowwise() = Eigen::RowVector3d(0.0, 0.001, 0.0);
  sim.setNodeTargets(m.nodeSet("x_min"), targets);
  sim.step();
  for (int n : m.nodeSet("x_min")) EXPECT_LT((sim.displacement().row(n) - targets.row(0)).norm(), 1e-14);
  for (int n : m.nodeSet("x_max")) EXPECT_EQ((sim.displacement().row(n) - before.row(n)).norm(), 0.0);
  // All free again: the previously fixed end moves.
  sim.clearConstraints();
  const Points held = sim.displacement();
  sim.step();
  double moved = 0;
  for (int n : m.nodeSet("x_max")) moved = std::max(moved, (sim.displacement().row(n) - held.row(n)).norm());
  EXPECT_GT(moved, 0.0);
}

// ---- Large compression, near-degenerate and inverted elements (docs/speed_accuracy.md) ----------

namespace {

/// One tetrahedron: the unit corner tet scaled to 1 cm.
TetMesh singleTet() {
  Points x(4, 3);
  x << 0, 0, 0, 0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01;
  Tets t(1, 4);
  t << 0, 1, 2, 3;
  return TetMesh(x, t);
}

/// Positions of mesh m under the affine map x ↦ F x.
Points affine(const TetMesh& m, const Eigen::Matrix3d& F) { return m.nodes() * F.transpose(); }

/// Force along the direction that increases the element volume fastest (dx_i = cof F ∇N_i, i.e.
/// dF = cof F): the elastic resistance to collapse [N·m] (positive = pushes the volume back up).
double volumeRestoringForce(CorotatedTetFem& fem, const TetMesh& m, const Eigen::Matrix3d& F) {
  const Eigen::VectorXd f = forcesAt(fem, affine(m, F));
  Eigen::Matrix3d cof;
  cof.col(0) = F.col(1).cross(F.col(2));
  cof.col(1) = F.col(2).cross(F.col(0));
  cof.col(2) = F.col(0).cross(F.col(1));
  // dx_i = cof F X_i (X_i rest positions; the constant part is a translation, which does no work).
  double w = 0;
  for (int n = 0; n < m.numNodes(); ++n) w += f.segment<3>(3 * n).dot(cof * m.nodes().row(n).transpose());
  return w;
}

}  // namespace

TEST(CorotatedTetFem, TraceVolumeTermResistsFlatteningOnlyWithTheShearModulus) {
  // The classic co-rotated volumetric term λ (tr S − 3) vanishes for stretches (1.5, 1.5, 0): the
  // element has zero volume but tr S = 3, so only μ resists its collapse, and through inversion
  // (1.6, 1.6, −0.2) as well. The J − 1 term resists with λ (here λ/μ = 24). This is what let the
  // supine phantom collapse and invert elements.
  const TetMesh m = singleTet();
  const ElasticMaterial mat;  // ν = 0.48
  const double lambda = mat.lameLambda(), mu = mat.lameMu();
  const double V = 1e-6 / 6;
  for (const Eigen::Vector3d& s : {Eigen::Vector3d(1.5, 1.5, 0.0), Eigen::Vector3d(1.6, 1.6, -0.2)}) {
    SCOPED_TRACE("stretches " + std::to_string(s[0]) + " " + std::to_string(s[1]) + " " + std::to_string(s[2]));
    const Eigen::Matrix3d F = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() * s.asDiagonal();
    CorotatedTetFem trace(m, mat), det(m, mat);
    trace.setVolumeTerm(CorotatedTetFem::VolumeTerm::kTrace);
    det.setVolumeTerm(CorotatedTetFem::VolumeTerm::kDeterminant);
    const double wt = volumeRestoringForce(trace, m, F), wd = volumeRestoringForce(det, m, F);
    // Exact: −V P : cof F with R = Q, S = diag(s), cof F = Q diag(c), c = (s2 s3, s1 s3, s1 s2),
    // P = Q (2μ(S − I) + λ v) with v = (tr S − 3) I or (J − 1) diag(c).
    const Eigen::Vector3d c(s[1] * s[2], s[0] * s[2], s[0] * s[1]);
    double wt_exact = 0, wd_exact = 0;
    for (int k = 0; k < 3; ++k) {
      wt_exact -= V * (2 * mu * (s[k] - 1) + lambda * (s.sum() - 3)) * c[k];
      wd_exact -= V * (2 * mu * (s[k] - 1) + lambda * (s.prod() - 1) * c[k]) * c[k];
    }
    EXPECT_NEAR(wt, wt_exact, 1e-9 * V * lambda);
    EXPECT_NEAR(wd, wd_exact, 1e-9 * V * lambda);
    EXPECT_LT(wt, 10 * mu * V);   // only μ resists (tr S = 3)
    EXPECT_GT(wd, 5 * wt);        // λ does with J − 1
  }
}

TEST(CorotatedTetFem, DeterminantVolumeTermKeepsRigidInvarianceAndTheSmallStrainResponse) {
  const TetMesh& m = smallBlock();
  CorotatedTetFem det(m, ElasticMaterial{}), trace(m, ElasticMaterial{});
  trace.setVolumeTerm(CorotatedTetFem::VolumeTerm::kTrace);
  det.setVolumeTerm(CorotatedTetFem::VolumeTerm::kDeterminant);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(1.1, Eigen::Vector3d(0.3, -1, 0.5).normalized()).toRotationMatrix();
  Points x = m.nodes() * R.transpose();
  x.rowwise() += Eigen::RowVector3d(0.05, -0.2, 0.01);
  const double scale = ElasticMaterial{}.youngs_modulus_pa * 0.01 * 1e-4;  // the force of a 1% strain
  EXPECT_LT(forcesAt(det, x).cwiseAbs().maxCoeff(), 1e-9 * scale);
  // Strain ~1e-3 (rotated): the two terms differ by O(strain²), a relative 1e-3 of the force.
  std::mt19937 rng(3);
  std::normal_distribution<double> d(0, 1e-5);
  for (int i = 0; i < x.size(); ++i) x.data()[i] += d(rng);
  const Eigen::VectorXd fd = forcesAt(det, x), ft = forcesAt(trace, x);
  EXPECT_LT((fd - ft).norm(), 1e-2 * ft.norm());
  EXPECT_GT((fd - ft).norm(), 1e-6 * ft.norm());  // they are different models
  // The stiffness is the same R K_e0 Rᵀ and matches the forces as for kTrace.
  std::normal_distribution<double> n1(0, 1.0);
  Eigen::VectorXd dx(3 * m.numNodes());
  for (int i = 0; i < dx.size(); ++i) dx[i] = n1(rng);
  dx *= 1e-3 / dx.norm();
  const SparseMatrix K = stiffnessAt(det, x);
  Points xp = x, xm = x;
  const double h = 1e-4;
  for (int n = 0; n < m.numNodes(); ++n) {
    xp.row(n) += h * dx.segment<3>(3 * n).transpose();
    xm.row(n) -= h * dx.segment<3>(3 * n).transpose();
  }
  const Eigen::VectorXd fdiff = (forcesAt(det, xp) - forcesAt(det, xm)) / (2 * h);
  EXPECT_LT((fdiff + K * dx).norm(), 2e-2 * (K * dx).norm());
  // Its own assembly path equals the dense element-by-element one, also compressed and scaled.
  Eigen::VectorXd factors = Eigen::VectorXd::LinSpaced(m.numTets(), 1.0, 3.0);
  det.setModulusFactors(factors);
  Points squeezed = x;
  squeezed.col(2) *= 0.6;
  const SparseMatrix Ks = stiffnessAt(det, squeezed);
  const Eigen::MatrixXd dense = det.denseStiffness();
  EXPECT_LT((Eigen::MatrixXd(Ks) - dense).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
  EXPECT_LT((dense - dense.transpose()).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(dense).eigenvalues().minCoeff(), -1e-9 * dense.norm());
}

TEST(CorotatedTetFem, ForcesAreConservativeAndContinuousThroughInversion) {
  // The stiffness R K_e0 Rᵀ is not the tangent of strongly deformed or inverted elements (it omits
  // ∂R/∂x), so the finite-difference test above stays near rest. Here the forces themselves are
  // checked where it matters: they are the gradient of an energy (their Jacobian, by central
  // differences, is symmetric) on near-flat and inverted elements with the reflection-fixed
  // rotation, and they do not jump when an element passes through zero volume.
  const TetMesh m = singleTet();
  const Eigen::Matrix3d Q = Eigen::AngleAxisd(0.9, Eigen::Vector3d(-1, 2, 0.5).normalized()).toRotationMatrix();
  const Eigen::Matrix3d Q2 = Eigen::AngleAxisd(0.3, Eigen::Vector3d(2, 1, -1).normalized()).toRotationMatrix();
  for (auto term : {CorotatedTetFem::VolumeTerm::kTrace, CorotatedTetFem::VolumeTerm::kDeterminant}) {
    CorotatedTetFem fem(m, ElasticMaterial{});
    fem.setVolumeTerm(term);
    for (const Eigen::Vector3d& s : {Eigen::Vector3d(1.3, 0.9, 0.05), Eigen::Vector3d(1.4, 1.1, -0.3),
                                    Eigen::Vector3d(0.8, 1.2, 0.4)}) {
      SCOPED_TRACE(std::string(term == CorotatedTetFem::VolumeTerm::kTrace ? "trace" : "determinant") + ", s3 " +
                   std::to_string(s[2]));
      const Points x = affine(m, Q * s.asDiagonal() * Q2);
      const double h = 1e-7;  // [m] on a 1 cm element
      Eigen::MatrixXd Jac(12, 12);
      for (int k = 0; k < 12; ++k) {
        Points xp = x, xm = x;
        xp(k / 3, k % 3) += h;
        xm(k / 3, k % 3) -= h;
        Jac.col(k) = (forcesAt(fem, xp) - forcesAt(fem, xm)) / (2 * h);
      }
      EXPECT_LT((Jac - Jac.transpose()).norm(), 1e-5 * Jac.norm());
    }
    // Through zero volume: s3 = ±1e-6 give forces 2e-6 (relative) apart at most.
    const Eigen::VectorXd fp = forcesAt(fem, affine(m, Q * Eigen::Vector3d(1.2, 0.9, 1e-6).asDiagonal() * Q2));
    const Eigen::VectorXd fm = forcesAt(fem, affine(m, Q * Eigen::Vector3d(1.2, 0.9, -1e-6).asDiagonal() * Q2));
    EXPECT_LT((fp - fm).norm(), 1e-5 * fp.norm());
  }
}

TEST(DynamicSimulator, NearlyIncompressibleBlockPressedOntoItsClampKeepsItsVolume) {
  // The supine breast in miniature: a soft, nearly incompressible (ν = 0.48) block held at its base
  // and loaded by a body force towards that base, as large as the phantom's (ρ g h / E ≈ 0.7).
  // The tissue must bulge sideways at constant volume. With the J − 1 volume term it does; the
  // classic tr S − 3 term lets the elements at the clamped rim flatten and invert instead (the
  // failure measured on the phantom).
  const TetMesh m = makeBoxMesh({4, 4, 4}, {0.04, 0.04, 0.04});
  ElasticMaterial mat;  // 2 kPa, ν = 0.48
  DynamicsParams p;
  p.time_step_s = 0.33;
  p.gravity_mps2 = {0, 0, -35.0};
  auto settleWith = [&](CorotatedTetFem::VolumeTerm term, int& inverted) {
    auto fem = std::make_unique<CorotatedTetFem>(m, mat);
    fem->setVolumeTerm(term);
    DynamicSimulator sim(m, std::move(fem), mat, p, std::make_unique<EigenLdltSolver>());
    sim.fixNodes(m.nodeSet("z_min"));
    for (int s = 0; s < 150; ++s) {
      try {
        sim.step();
      } catch (const std::runtime_error& e) {
        ADD_FAILURE() << (term == CorotatedTetFem::VolumeTerm::kTrace ? "tr S - 3" : "J - 1") << ", step " << s << ": "
                      << e.what();
        inverted = -1;
        return 1.0;
      }
    }
    EXPECT_LT(sim.state().velocity_mps.cwiseAbs().maxCoeff(), 1e-6);
    const Points x = m.nodes() + sim.displacement();
    inverted = static_cast<int>(invertedTets(m.tets(), x).size());
    double v = 0;  // signed: inverted elements count negative
    for (int e = 0; e < m.numTets(); ++e) {
      const Eigen::Vector3d a = x.row(m.tets()(e, 0));
      v += (Eigen::Vector3d(x.row(m.tets()(e, 1))) - a)
               .cross(Eigen::Vector3d(x.row(m.tets()(e, 2))) - a)
               .dot(Eigen::Vector3d(x.row(m.tets()(e, 3))) - a) / 6.0;
    }
    return v / m.volume() - 1.0;
  };
  int inv_trace = 0, inv_det = 0;
  const double dv_trace = settleWith(CorotatedTetFem::VolumeTerm::kTrace, inv_trace);
  const double dv_det = settleWith(CorotatedTetFem::VolumeTerm::kDeterminant, inv_det);
  std::cout << "volume change: tr S - 3 " << 100 * dv_trace << " % (" << inv_trace << " inverted), J - 1 "
            << 100 * dv_det << " % (" << inv_det << " inverted)\n";
  EXPECT_EQ(inv_det, 0);
  EXPECT_LT(std::abs(dv_det), 0.03);
  EXPECT_GT(std::abs(dv_trace), 2 * std::abs(dv_det));  // the flaw this guards against
}

// Per-element base moduli (setElementYoungsModuli, a stiff inclusion): they must act exactly as the
// same numbers given as stiffening factors E_r would (stress, forces, stiffness scale with E_r b_e),
// for both volume terms, while modulusFactors() keeps E_r alone; setting them after an update
// rescales the stiffness records (no update in between).
TEST(CorotatedTetFem, ElementModuliActAsBaseFactorsUnderTheStiffeningFactors) {
  const TetMesh& m = smallBlock();
  ElasticMaterial mat;
  mat.poisson_ratio = 0.45;
  const Points x = jittered(m, 17, 2e-3);
  const Eigen::VectorXd factors = Eigen::VectorXd::LinSpaced(m.numTets(), 1.0, 2.5);  // E_r
  Eigen::VectorXd moduli(m.numTets());                                             // E_e [Pa]
  for (int e = 0; e < m.numTets(); ++e) moduli[e] = mat.youngs_modulus_pa * (e % 3 == 0 ? 10.0 : 1.0 + 0.1 * (e % 5));
  const Eigen::VectorXd b = moduli / mat.youngs_modulus_pa;
  for (const auto term : {CorotatedTetFem::VolumeTerm::kTrace, CorotatedTetFem::VolumeTerm::kDeterminant}) {
    SCOPED_TRACE(term == CorotatedTetFem::VolumeTerm::kTrace ? "tr S - 3" : "J - 1");
    CorotatedTetFem with(m, mat), folded(m, mat);
    with.setVolumeTerm(term);
    folded.setVolumeTerm(term);
    with.setModulusFactors(factors);
    Eigen::VectorXd f_with, f_folded;
    with.update(x, f_with);
    with.setElementYoungsModuli(moduli);  // after the update: the records are rescaled
    with.update(x, f_with);
    folded.setModulusFactors(factors.cwiseProduct(b));
    const SparseMatrix K_folded = stiffnessAt(folded, x);
    folded.update(x, f_folded);
    EXPECT_LT((f_with - f_folded).cwiseAbs().maxCoeff(), 1e-12 * f_folded.cwiseAbs().maxCoeff());
    EXPECT_LT((with.vonMisesStress() - folded.vonMisesStress()).cwiseAbs().maxCoeff(),
              1e-12 * folded.vonMisesStress().maxCoeff());
    EXPECT_EQ((with.modulusFactors() - factors).cwiseAbs().maxCoeff(), 0.0);
    EXPECT_LT((with.baseModulusScales() - b).cwiseAbs().maxCoeff(), 1e-15 * b.maxCoeff());
    // Rescaled records: new stiffening factors and new moduli without an update in between.
    with.setModulusFactors(2.0 * factors);
    with.setElementYoungsModuli(moduli);  // the same moduli again: no change
    folded.setModulusFactors(2.0 * factors.cwiseProduct(b));
    SparseMatrix K_with = with.pattern().matrix();
    with.addStiffness(1.0, K_with);
    SparseMatrix K_f2 = folded.pattern().matrix();
    folded.addStiffness(1.0, K_f2);
    const Eigen::MatrixXd dense = with.denseStiffness();
    EXPECT_LT((Eigen::MatrixXd(K_with) - Eigen::MatrixXd(K_f2)).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
    EXPECT_LT((Eigen::MatrixXd(K_with) - dense).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
    // And back to E0 everywhere (empty): the same as no moduli at all.
    with.setElementYoungsModuli(Eigen::VectorXd());
    CorotatedTetFem plain(m, mat);
    plain.setVolumeTerm(term);
    plain.setModulusFactors(2.0 * factors);
    Eigen::VectorXd f_plain;
    plain.update(x, f_plain);
    with.update(x, f_with);
    EXPECT_LT((f_with - f_plain).cwiseAbs().maxCoeff(), 1e-12 * f_plain.cwiseAbs().maxCoeff());
  }
  CorotatedTetFem fem(m, mat);
  EXPECT_THROW(fem.setElementYoungsModuli(Eigen::VectorXd::Ones(3)), std::invalid_argument);
  Eigen::VectorXd bad = moduli;
  bad[4] = -1.0;
  EXPECT_THROW(fem.setElementYoungsModuli(bad), std::invalid_argument);
}

// A bar of two materials in series (ν = 0: no lateral contraction, so the 1-D answer is exact for
// linear tetrahedra): clamped at x = 0, pulled to u = δ at x = L, with E1 on [0, L/2] and
// E2 = 10 E1 on [L/2, L]. The stress σ = δ / (L1/E1 + L2/E2) is uniform and u(x) is piecewise
// linear: u(L/2) = σ L1 / E1 = δ · 10/11. Uniform E would give δ/2.
TEST(CorotatedTetFem, TwoMaterialBarInSeriesMatchesTheAnalyticStretch) {
  const double L = 0.08, delta = 1e-4, E1 = 2000.0, E2 = 20000.0;
  const TetMesh m = makeBoxMesh({8, 2, 2}, {L, 0.02, 0.02});
  ElasticMaterial mat;
  mat.youngs_modulus_pa = E1;
  mat.poisson_ratio = 0.0;
  Eigen::VectorXd moduli(m.numTets());
  for (int e = 0; e < m.numTets(); ++e) {
    double cx = 0;
    for (int k = 0; k < 4; ++k) cx += 0.25 * m.nodes()(m.tets()(e, k), 0);
    moduli[e] = cx < 0.5 * L ? E1 : E2;
  }
  for (const bool corotated : {false, true}) {
    SCOPED_TRACE(corotated ? "corotated" : "linear");
    CorotatedTetFem fem(m, mat);
    fem.setCorotated(corotated);
    fem.setElementYoungsModuli(moduli);
    Eigen::VectorXd f;
    fem.update(m.nodes(), f);
    const Eigen::MatrixXd K = fem.denseStiffness();
    std::vector<char> fixed(3 * m.numNodes(), 0);
    Eigen::VectorXd u_fixed = Eigen::VectorXd::Zero(3 * m.numNodes());
    for (int n : m.nodeSet("x_min")) fixed[3 * n] = fixed[3 * n + 1] = fixed[3 * n + 2] = 1;
    for (int n : m.nodeSet("x_max")) fixed[3 * n] = 1, u_fixed[3 * n] = delta;
    const Eigen::VectorXd u = staticSolve(K, Eigen::VectorXd::Zero(3 * m.numNodes()), fixed, u_fixed);
    const double sigma = delta / (0.5 * L / E1 + 0.5 * L / E2);
    double worst = 0;
    for (int n = 0; n < m.numNodes(); ++n) {
      const double x = m.nodes()(n, 0);
      const double exact = x <= 0.5 * L ? sigma * x / E1 : sigma * (0.5 * L / E1 + (x - 0.5 * L) / E2);
      worst = std::max({worst, std::abs(u[3 * n] - exact), std::abs(u[3 * n + 1]), std::abs(u[3 * n + 2])});
    }
    EXPECT_LT(worst, 1e-9 * delta);
    EXPECT_NEAR(sigma * 0.5 * L / E1, delta * 10.0 / 11.0, 1e-15);
    // At that state the element forces balance at every node off the two ends (the force path).
    const Points x = positions(m, u);
    const Eigen::VectorXd fx = forcesAt(fem, x);
    const double reaction = sigma * 0.02 * 0.02;  // σ A [N]
    for (int n = 0; n < m.numNodes(); ++n)
      if (!fixed[3 * n]) EXPECT_LT(fx.segment<3>(3 * n).norm(), 1e-9 * reaction) << "node " << n;
    double pull = 0;
    for (int n : m.nodeSet("x_max")) pull -= fx[3 * n];
    EXPECT_NEAR(pull, reaction, 1e-9 * reaction);
  }
}

TEST(CorotatedTetFem, UpdateAtTheSamePositionsAfterNewFactorsEqualsAFreshUpdate) {
  // The stiffening loop evaluates the stress after a step, sets new factors, and the next step
  // updates at the same positions: that update reuses the rotations with forces, von Mises stresses
  // and stiffness records rescaled to the new factors. Reference: a fresh element set.
  const TetMesh& m = smallBlock();
  ElasticMaterial mat;
  mat.poisson_ratio = 0.48;
  Points x = jittered(m, 23, 3e-3);
  const Eigen::VectorXd first = Eigen::VectorXd::LinSpaced(m.numTets(), 1.0, 3.0);
  Eigen::VectorXd second(m.numTets());
  for (int e = 0; e < m.numTets(); ++e) second[e] = 1.0 + 0.37 * (e % 7);
  for (const auto term : {CorotatedTetFem::VolumeTerm::kTrace, CorotatedTetFem::VolumeTerm::kDeterminant}) {
    SCOPED_TRACE(term == CorotatedTetFem::VolumeTerm::kTrace ? "tr S - 3" : "J - 1");
    CorotatedTetFem reused(m, mat), fresh(m, mat);
    reused.setVolumeTerm(term);
    fresh.setVolumeTerm(term);
    reused.setModulusFactors(first);
    Eigen::VectorXd f;
    reused.update(x, f);
    reused.setModulusFactors(second);
    const SparseMatrix K_reused = stiffnessAt(reused, x);  // update at the same x: reused
    const Eigen::VectorXd f_reused = forcesAt(reused, x);
    fresh.setModulusFactors(second);
    const SparseMatrix K_fresh = stiffnessAt(fresh, x);
    const Eigen::VectorXd f_fresh = forcesAt(fresh, x);
    EXPECT_LT((f_reused - f_fresh).cwiseAbs().maxCoeff(), 1e-12 * f_fresh.cwiseAbs().maxCoeff());
    EXPECT_LT((reused.vonMisesStress() - fresh.vonMisesStress()).cwiseAbs().maxCoeff(),
              1e-12 * fresh.vonMisesStress().maxCoeff());
    EXPECT_LT(Eigen::MatrixXd(K_reused - K_fresh).cwiseAbs().maxCoeff(),
              1e-12 * Eigen::MatrixXd(K_fresh).cwiseAbs().maxCoeff());
    // A move of one node is seen: the next update recomputes.
    x(0, 0) += 1e-4;
    const Eigen::VectorXd f_moved = forcesAt(reused, x);
    CorotatedTetFem other(m, mat);
    other.setVolumeTerm(term);
    other.setModulusFactors(second);
    EXPECT_LT((f_moved - forcesAt(other, x)).cwiseAbs().maxCoeff(), 1e-12 * f_fresh.cwiseAbs().maxCoeff());
    EXPECT_GT((f_moved - f_reused).cwiseAbs().maxCoeff(), 1e-6 * f_fresh.cwiseAbs().maxCoeff());
    x(0, 0) -= 1e-4;
  }
}
