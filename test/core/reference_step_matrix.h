#pragma once
/// @file reference_step_matrix.h
/// A slow, element-by-element assembly of one implicit step's system for the solver tests and
/// bench_solvers (the project's own assembly is fem/): A = M/dt² + K of co-rotated linear
/// tetrahedra, lumped mass, in the 3×3-block layout of fem/block_pattern.h.

#include <vector>

#include <Eigen/Dense>
#include <Eigen/SparseCore>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::test_support {

/// A = M/dt² + K [N/m]: element stiffness E_r R K_e Rᵀ with R = rotation(e) and E_r = modulus(e)
/// (identity and 1 at rest), K_e of linear elasticity with E [Pa] and ν, mass density ρ [kg/m³]
/// lumped to the nodes, time step dt [s]; fixed nodes get zero rows and columns with a unit diagonal.
template <typename RotationFn, typename ModulusFn>
core::SparseMatrix stepMatrix(const core::TetMesh& mesh, const std::vector<int>& fixed_nodes, RotationFn rotation,
                              ModulusFn modulus, double E_pa = 2000.0, double nu = 0.48, double density = 1000.0,
                              double dt = 0.033) {
  const double lambda = E_pa * nu / ((1 + nu) * (1 - 2 * nu)), mu = E_pa / (2 * (1 + nu));
  std::vector<Eigen::Triplet<double, int>> t;
  t.reserve(static_cast<size_t>(mesh.numTets()) * 144 + 3 * static_cast<size_t>(mesh.numNodes()));
  for (int e = 0; e < mesh.numTets(); ++e) {
    Eigen::Matrix3d Dm;
    for (int k = 0; k < 3; ++k)
      Dm.col(k) = (mesh.nodes().row(mesh.tets()(e, k + 1)) - mesh.nodes().row(mesh.tets()(e, 0))).transpose();
    const double V = Dm.determinant() / 6.0;
    const Eigen::Matrix3d Dinv = Dm.inverse();
    Eigen::Matrix<double, 4, 3> G;  // shape-function gradients [1/m]
    G.row(0) = -Dinv.colwise().sum();
    G.bottomRows(3) = Dinv;
    const Eigen::Matrix3d R = rotation(e);
    const double Er = modulus(e);
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) {
        const Eigen::Vector3d ga = G.row(a).transpose(), gb = G.row(b).transpose();
        const Eigen::Matrix3d K0 = V * (lambda * ga * gb.transpose() + mu * gb * ga.transpose() +
                                        mu * ga.dot(gb) * Eigen::Matrix3d::Identity());
        const Eigen::Matrix3d K = Er * R * K0 * R.transpose();
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) t.emplace_back(3 * mesh.tets()(e, a) + i, 3 * mesh.tets()(e, b) + j, K(i, j));
      }
    for (int a = 0; a < 4; ++a)
      for (int i = 0; i < 3; ++i)
        t.emplace_back(3 * mesh.tets()(e, a) + i, 3 * mesh.tets()(e, a) + i, density * V / 4 / (dt * dt));
  }
  core::SparseMatrix A(3 * mesh.numNodes(), 3 * mesh.numNodes());
  A.setFromTriplets(t.begin(), t.end());
  std::vector<bool> fixed(static_cast<size_t>(A.rows()), false);
  for (int v : fixed_nodes)
    for (int i = 0; i < 3; ++i) fixed[3 * v + i] = true;
  for (int r = 0; r < A.outerSize(); ++r)
    for (core::SparseMatrix::InnerIterator it(A, r); it; ++it)
      if (fixed[it.row()] || fixed[it.col()]) it.valueRef() = it.row() == it.col() ? 1.0 : 0.0;
  return A;
}

/// The system at rest (no rotation, E_r = 1).
inline core::SparseMatrix restStepMatrix(const core::TetMesh& mesh, const std::vector<int>& fixed_nodes,
                                         double E_pa = 2000.0, double nu = 0.48, double density = 1000.0,
                                         double dt = 0.033) {
  return stepMatrix(
      mesh, fixed_nodes, [](int) { return Eigen::Matrix3d::Identity(); }, [](int) { return 1.0; }, E_pa, nu, density,
      dt);
}

}  // namespace breast_sim::test_support
