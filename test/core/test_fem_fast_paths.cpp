// The fast paths of the co-rotated FEM against slow references: the batched polar decomposition
// (rotationsOf) against rotationOf lane by lane, and CorotatedTetFem's batched update() (forces,
// von Mises stress, rotations) and its stiffness gather against an element-by-element Eigen
// evaluation of the same formulas, on a deformed mesh with inverted elements and an element count
// that leaves a partial batch.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/polar_decomposition.h"
#include "breast_sim/core/mesh/box_mesh.h"

using namespace breast_sim::core;

namespace {

Eigen::Matrix3d randomRotation(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  return Eigen::AngleAxisd(3.0 * u(rng), Eigen::Vector3d(u(rng), u(rng), u(rng)).normalized()).toRotationMatrix();
}

/// Deformation gradients of every kind rotationOf meets: small and large stretches, near-degenerate,
/// flat, inverted, zero.
std::vector<Eigen::Matrix3d> testMatrices(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const std::vector<Eigen::Vector3d> stretches = {{1.0, 1.0, 1.0},  {1.01, 0.995, 1.0}, {1.3, 0.8, 1.1}, {3.0, 0.2, 1.0},
                                                  {1.0, 1.0, 1e-3}, {1e-2, 1.0, 5.0},   {1.0, 1.0, 1e-8}, {2.0, 2.0, 2.0},
                                                  {1.2, 0.9, -0.3}, {1.0, 1.0, 0.0},    {1.4, 1.1, -1e-7}};
  std::vector<Eigen::Matrix3d> out;
  for (int trial = 0; trial < 300; ++trial) {
    const Eigen::Vector3d s = stretches[trial % stretches.size()].cwiseProduct(
        Eigen::Vector3d::Constant(1.0) + 0.05 * Eigen::Vector3d(u(rng), u(rng), u(rng)));
    out.push_back(randomRotation(rng) * s.asDiagonal() * randomRotation(rng));
  }
  out.push_back(Eigen::Matrix3d::Zero());
  Eigen::Matrix3d line = Eigen::Matrix3d::Zero();
  line(0, 0) = 1.0;
  out.push_back(line);
  return out;
}

/// Element-by-element reference of CorotatedTetFem::update(): F, R = rotationOf(F), σ, forces
/// −V R σ ∇N_i summed per node; von Mises stress per element; cof F ∇N_i for the determinant term.
struct Reference {
  Eigen::VectorXd f;
  Eigen::VectorXd von_mises;
  std::vector<Eigen::Matrix3d> rotations;
};

Reference referenceUpdate(const TetMesh& m, const ElasticMaterial& mat, const Eigen::VectorXd& factors, const Points& x,
                          bool determinant) {
  const double lambda = mat.lameLambda(), mu = mat.lameMu();
  Reference ref;
  ref.f = Eigen::VectorXd::Zero(3 * m.numNodes());
  ref.von_mises.resize(m.numTets());
  for (int e = 0; e < m.numTets(); ++e) {
    Eigen::Matrix3d Dm, Ds;
    for (int k = 0; k < 3; ++k) {
      Dm.col(k) = (m.nodes().row(m.tets()(e, k + 1)) - m.nodes().row(m.tets()(e, 0))).transpose();
      Ds.col(k) = (x.row(m.tets()(e, k + 1)) - x.row(m.tets()(e, 0))).transpose();
    }
    const double V = Dm.determinant() / 6.0;
    const Eigen::Matrix3d Dinv = Dm.inverse();
    Eigen::Matrix<double, 3, 4> G;  // columns ∇N_0..∇N_3
    G.rightCols<3>() = Dinv.transpose();
    G.col(0) = -G.rightCols<3>().rowwise().sum();
    const Eigen::Matrix3d F = Ds * Dinv;
    const Eigen::Matrix3d R = rotationOf(F);
    const Eigen::Matrix3d Fr = R.transpose() * F;
    const Eigen::Matrix3d eps = 0.5 * (Fr + Fr.transpose()) - Eigen::Matrix3d::Identity();
    Eigen::Matrix3d sigma;
    if (!determinant) {
      sigma = lambda * eps.trace() * Eigen::Matrix3d::Identity() + 2.0 * mu * eps;
    } else {
      const Eigen::Matrix3d cof = F.determinant() * F.inverse().transpose();
      const Eigen::Matrix3d rc = R.transpose() * cof;
      sigma = lambda * (F.determinant() - 1.0) * 0.5 * (rc + rc.transpose()) + 2.0 * mu * eps;
    }
    sigma *= factors[e];
    const Eigen::Matrix3d dev = sigma - sigma.trace() / 3.0 * Eigen::Matrix3d::Identity();
    ref.von_mises[e] = std::sqrt(1.5 * dev.squaredNorm());
    for (int i = 0; i < 4; ++i) ref.f.segment<3>(3 * m.tets()(e, i)) += -V * R * sigma * G.col(i);
    ref.rotations.push_back(R);
  }
  return ref;
}

/// A box of `cells` (6 tetrahedra per cell) under a rotation, a stretch and noise, with one node
/// mirrored through the opposite face of its element (inverting it and distorting its neighbours).
struct DeformedBox {
  TetMesh mesh;
  Points x;
};

DeformedBox deformedBox(const Eigen::Vector3i& cells) {
  DeformedBox d{makeBoxMesh(cells, {0.04, 0.03, 0.02}), {}};
  std::mt19937 rng(17);
  std::normal_distribution<double> noise(0, 1e-3);
  const Eigen::Matrix3d Q = randomRotation(rng);
  d.x = d.mesh.nodes() * (Q * Eigen::Vector3d(1.2, 0.9, 1.05).asDiagonal()).transpose();
  for (int i = 0; i < d.x.size(); ++i) d.x.data()[i] += noise(rng);
  // Invert an interior element: its node 0 goes to the mirror image across the opposite face.
  const int e = d.mesh.numTets() / 2;
  const auto t = d.mesh.tets().row(e);
  const Eigen::Vector3d a = d.x.row(t[1]), b = d.x.row(t[2]), c = d.x.row(t[3]), p = d.x.row(t[0]);
  const Eigen::Vector3d n = (b - a).cross(c - a).normalized();
  d.x.row(t[0]) = (p - 2.0 * (p - a).dot(n) * n).transpose();
  return d;
}

int invertedElements(const TetMesh& m, const Points& x) {
  int count = 0;
  for (int e = 0; e < m.numTets(); ++e) {
    Eigen::Matrix3d Ds;
    for (int k = 0; k < 3; ++k) Ds.col(k) = (x.row(m.tets()(e, k + 1)) - x.row(m.tets()(e, 0))).transpose();
    count += Ds.determinant() <= 0;
  }
  return count;
}

}  // namespace

TEST(FemFastPaths, BatchedRotationsEqualRotationOfLaneByLane) {
  std::mt19937 rng(23);
  const std::vector<Eigen::Matrix3d> Fs = testMatrices(rng);
  constexpr int W = kRotationBatch;
  // Every batch size, and the matrices shuffled so that easy, hard, inverted and degenerate lanes
  // share batches (a lane must not be disturbed by its neighbours' iterations or fallbacks).
  std::vector<int> order(Fs.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = static_cast<int>(i);
  std::shuffle(order.begin(), order.end(), rng);
  int checked = 0, fallback = 0;
  for (size_t start = 0; start < order.size();) {
    const int count = std::min<int>(1 + static_cast<int>(start / W) % W, static_cast<int>(order.size() - start));
    double F[9 * W], R[9 * W];
    for (int l = 0; l < count; ++l)
      for (int k = 0; k < 9; ++k) F[k * W + l] = Fs[order[start + l]].data()[k];
    for (int l = count; l < W; ++l)
      for (int k = 0; k < 9; ++k) F[k * W + l] = std::nan("");  // must be ignored
    rotationsOf(F, R, count);
    for (int l = 0; l < count; ++l) {
      const Eigen::Matrix3d& Fl = Fs[order[start + l]];
      Eigen::Matrix3d Rl;
      for (int k = 0; k < 9; ++k) Rl.data()[k] = R[k * W + l];
      SCOPED_TRACE("matrix " + std::to_string(order[start + l]) + ", det " + std::to_string(Fl.determinant()));
      EXPECT_LT((Rl - rotationOf(Fl)).cwiseAbs().maxCoeff(), 1e-12);
      EXPECT_LT((Rl.transpose() * Rl - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), 1e-12);
      EXPECT_NEAR(Rl.determinant(), 1.0, 1e-12);
      fallback += Fl.determinant() <= 0;
      ++checked;
    }
    start += count;
  }
  EXPECT_EQ(checked, static_cast<int>(Fs.size()));
  EXPECT_GT(fallback, 30);  // the SVD path was exercised inside batches
  EXPECT_THROW(rotationsOf(nullptr, nullptr, W + 1), std::invalid_argument);
}

TEST(FemFastPaths, AssignStiffnessRejectsAMatrixOfAnotherPattern) {
  const TetMesh m = makeBoxMesh({2, 1, 1}, {0.02, 0.01, 0.01});
  CorotatedTetFem fem(m, ElasticMaterial{});
  SparseMatrix other(3 * m.numNodes(), 3 * m.numNodes());
  EXPECT_THROW(fem.assignStiffness(1.0, other), std::invalid_argument);
}

TEST(FemFastPaths, BatchedUpdateEqualsElementByElementReferenceWithInvertedElements) {
  // 3×2×2 cells: 72 tets (whole batches); 5×3×1: 90 (a partial batch of 2). Both kernels: the
  // AVX-512 one where the processor has it (CorotatedTetFem::updateHasSimd) and the portable one.
  for (const Eigen::Vector3i& cells : {Eigen::Vector3i(3, 2, 2), Eigen::Vector3i(5, 3, 1)}) {
    const DeformedBox d = deformedBox(cells);
    ASSERT_GT(invertedElements(d.mesh, d.x), 0);
    ElasticMaterial mat;
    mat.poisson_ratio = 0.45;
    const Eigen::VectorXd factors = Eigen::VectorXd::LinSpaced(d.mesh.numTets(), 1.0, 4.0);
    for (bool determinant : {false, true})
    for (bool simd : {true, false}) {
      SCOPED_TRACE(std::string(determinant ? "determinant" : "trace") + ", " + std::to_string(d.mesh.numTets()) +
                   " tets, " + (simd && CorotatedTetFem::updateHasSimd() ? "AVX-512" : "portable") + " kernels");
      CorotatedTetFem fem(d.mesh, mat);
      fem.setSimdKernels(simd);
      fem.setModulusFactors(factors);
      fem.setVolumeTerm(determinant ? CorotatedTetFem::VolumeTerm::kDeterminant : CorotatedTetFem::VolumeTerm::kTrace);
      Eigen::VectorXd f;
      fem.update(d.x, f);
      const Reference ref = referenceUpdate(d.mesh, mat, factors, d.x, determinant);
      const double fscale = ref.f.cwiseAbs().maxCoeff();
      ASSERT_GT(fscale, 0);
      EXPECT_LT((f - ref.f).cwiseAbs().maxCoeff(), 1e-12 * fscale);
      EXPECT_LT((fem.vonMisesStress() - ref.von_mises).cwiseAbs().maxCoeff(), 1e-12 * ref.von_mises.maxCoeff());
      for (int e = 0; e < d.mesh.numTets(); ++e)
        EXPECT_LT((fem.rotation(e) - ref.rotations[e]).cwiseAbs().maxCoeff(), 1e-12) << "element " << e;
      // The stiffness gather (packed records) against the dense element-by-element assembly.
      SparseMatrix K = fem.pattern().matrix();
      fem.addStiffness(2.5, K);
      const Eigen::MatrixXd dense = 2.5 * fem.denseStiffness();
      EXPECT_LT((Eigen::MatrixXd(K) - dense).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
      // assignStiffness overwrites whatever A held with the same values, bit for bit.
      SparseMatrix Kassigned = fem.pattern().matrix();
      for (Eigen::Index i = 0; i < Kassigned.nonZeros(); ++i) Kassigned.valuePtr()[i] = 1e9 + static_cast<double>(i);
      fem.assignStiffness(2.5, Kassigned);
      for (Eigen::Index i = 0; i < K.nonZeros(); ++i) ASSERT_EQ(Kassigned.valuePtr()[i], K.valuePtr()[i]) << "entry " << i;
      // New modulus factors after the update rescale the stiffness records (no update in between).
      const Eigen::VectorXd factors2 = Eigen::VectorXd::LinSpaced(d.mesh.numTets(), 3.0, 0.5);
      fem.setModulusFactors(factors2);
      fem.assignStiffness(1.0, Kassigned);
      const Eigen::MatrixXd dense2 = fem.denseStiffness();
      EXPECT_LT((Eigen::MatrixXd(Kassigned) - dense2).cwiseAbs().maxCoeff(), 1e-12 * dense2.cwiseAbs().maxCoeff());
      fem.setModulusFactors(factors);
      fem.assignStiffness(2.5, Kassigned);
      EXPECT_LT((Eigen::MatrixXd(Kassigned) - dense).cwiseAbs().maxCoeff(), 1e-12 * dense.cwiseAbs().maxCoeff());
    }
  }
}

TEST(FemFastPaths, LinearElementsMatchTheDenseStiffnessTimesDisplacement) {
  // Without co-rotation the forces are exactly −K (x − X): a check of the batched path's
  // identity-rotation lanes and of the partial batch, against the dense reference stiffness.
  const DeformedBox d = deformedBox({5, 3, 1});
  CorotatedTetFem fem(d.mesh, ElasticMaterial{});
  fem.setCorotated(false);
  fem.setModulusFactors(Eigen::VectorXd::LinSpaced(d.mesh.numTets(), 0.5, 2.0));
  Eigen::VectorXd f;
  fem.update(d.x, f);
  Eigen::VectorXd u(3 * d.mesh.numNodes());
  for (int n = 0; n < d.mesh.numNodes(); ++n) u.segment<3>(3 * n) = (d.x.row(n) - d.mesh.nodes().row(n)).transpose();
  const Eigen::VectorXd ref = -fem.denseStiffness() * u;
  EXPECT_LT((f - ref).cwiseAbs().maxCoeff(), 1e-10 * ref.cwiseAbs().maxCoeff());
  for (int e = 0; e < d.mesh.numTets(); ++e) EXPECT_TRUE(fem.rotation(e).isIdentity(0.0));
}

TEST(FemFastPaths, NodeForcesAreTheSameBitsOnAnyThreadCountAndRepeatExactly) {
  // The node forces are summed per fixed chunk of batches, then over the chunks in order
  // (CorotatedTetFem::withChunkForces): an update at the same positions sums the kept element
  // forces in the same order, and one, two or three threads give the same bits. A mesh of several
  // batches per chunk and a partial last batch (1620 tets).
  const DeformedBox d = deformedBox({15, 6, 3});
  ElasticMaterial mat;
  mat.poisson_ratio = 0.48;
  const int threads = omp_get_max_threads();
  Eigen::VectorXd fresh, again;
  {
    CorotatedTetFem fem(d.mesh, mat);
    fem.setVolumeTerm(CorotatedTetFem::VolumeTerm::kDeterminant);
    fem.update(d.x, fresh);
    fem.update(d.x, again);  // the same positions: the kept element forces
    ASSERT_EQ(fresh.size(), again.size());
    for (Eigen::Index r = 0; r < fresh.size(); ++r) ASSERT_EQ(fresh[r], again[r]) << "row " << r;
  }
  ASSERT_GT(fresh.cwiseAbs().maxCoeff(), 0.0);
  for (int t : {1, 2, 3}) {
    omp_set_num_threads(t);
    Eigen::VectorXd f;
    CorotatedTetFem fem(d.mesh, mat);
    fem.setVolumeTerm(CorotatedTetFem::VolumeTerm::kDeterminant);
    fem.update(d.x, f);
    for (Eigen::Index r = 0; r < f.size(); ++r) ASSERT_EQ(f[r], fresh[r]) << t << " threads, row " << r;
  }
  omp_set_num_threads(threads);
}

TEST(FemFastPaths, SimdStiffnessGatherEqualsTheScalarOne) {
  // The AVX-512VL gather (on this processor: gatherHasSimd()) against the portable scalar one, for
  // both volume terms, adding and assigning, on a deformed mesh with inverted elements and a partial
  // batch; the scalar one is checked against the dense element-by-element assembly above.
  if (!CorotatedTetFem::gatherHasSimd()) GTEST_SKIP() << "this processor has no AVX-512VL: only the scalar gather runs";
  const DeformedBox d = deformedBox({5, 3, 1});
  ElasticMaterial mat;
  mat.poisson_ratio = 0.48;
  for (bool determinant : {false, true}) {
    SCOPED_TRACE(determinant ? "determinant" : "trace");
    CorotatedTetFem fem(d.mesh, mat);
    fem.setModulusFactors(Eigen::VectorXd::LinSpaced(d.mesh.numTets(), 0.5, 3.0));
    fem.setVolumeTerm(determinant ? CorotatedTetFem::VolumeTerm::kDeterminant : CorotatedTetFem::VolumeTerm::kTrace);
    Eigen::VectorXd f;
    fem.update(d.x, f);
    SparseMatrix simd = fem.pattern().matrix(), scalar = fem.pattern().matrix();
    for (Eigen::Index i = 0; i < simd.nonZeros(); ++i) simd.valuePtr()[i] = scalar.valuePtr()[i] = 0.25 * static_cast<double>(i % 7);
    fem.addStiffness(1.5, simd);
    fem.setSimdKernels(false);
    fem.addStiffness(1.5, scalar);
    const double scale = Eigen::Map<const Eigen::VectorXd>(scalar.valuePtr(), scalar.nonZeros()).cwiseAbs().maxCoeff();
    for (Eigen::Index i = 0; i < simd.nonZeros(); ++i)
      ASSERT_NEAR(simd.valuePtr()[i], scalar.valuePtr()[i], 1e-13 * scale) << "entry " << i;
    fem.assignStiffness(1.5, scalar);
    fem.setSimdKernels(true);
    fem.assignStiffness(1.5, simd);
    for (Eigen::Index i = 0; i < simd.nonZeros(); ++i)
      ASSERT_NEAR(simd.valuePtr()[i], scalar.valuePtr()[i], 1e-13 * scale) << "entry " << i;
    EXPECT_LT((Eigen::MatrixXd(simd) - 1.5 * fem.denseStiffness()).cwiseAbs().maxCoeff(), 1e-12 * scale);
  }
}
