#pragma once
/// @file solver_fixture.h
/// The system of an implicit step of linear elasticity (A = M/dt² + K, Dirichlet on the chest wall) on
/// the phantom at ~8000 elements with its three-level mesh hierarchy, built once per test executable,
/// for test_solvers and test_multigrid.

#include <random>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/SparseCholesky>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/multigrid.h"
#include "reference_step_matrix.h"

namespace breast_sim::core::test_fixtures {

// ---------------------------------------------------------------------------------------------------
// Test-local assembly (the project's FEM lives in fem/; this one only has to be SPD and realistic).

/// A = M/dt² + K of linear tetrahedra at rest [N/m] (reference_step_matrix.h).
inline SparseMatrix implicitStepMatrix(const TetMesh& mesh, const std::vector<int>& fixed_nodes,
                                       double E_pa = 2000.0, double nu = 0.48, double density = 1000.0,
                                       double dt = 0.033) {
  return breast_sim::test_support::restStepMatrix(mesh, fixed_nodes, E_pa, nu, density, dt);
}

/// Gravity on the lumped masses plus a random load [N]; fixed DOFs get `fixed_value` [m].
inline Eigen::VectorXd load(const SparseMatrix& A, const TetMesh& mesh, const std::vector<int>& fixed_nodes,
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

inline double relativeDifference(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  return (a - b).norm() / b.norm();
}

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

inline const Fixture& fixture() {
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

}  // namespace breast_sim::core::test_fixtures
