#pragma once
/// @file element_formulation.h
/// What the time integrator needs from an element formulation. Co-rotated linear tetrahedra are one
/// (corotated_tet_fem.h); a locking-free variant (average nodal pressure, quadratic tetrahedra) can
/// be another without touching the solvers or the pipeline.

#include <algorithm>
#include <stdexcept>

#include <Eigen/Core>
#include <Eigen/LU>

#include "breast_sim/core/fem/block_pattern.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/linear_solver.h"
#include "breast_sim/core/solver/rank_one_sum.h"

namespace breast_sim::core {

/// Shape-function gradients of linear tetrahedron e at rest: g = ∇N_0..∇N_3 (12, [1/m]; the rows of
/// Dm⁻¹ are ∇N_1..∇N_3, Dm = [x1 − x0, x2 − x0, x3 − x0], and ∇N_0 = −their sum). Returns the
/// signed rest volume [m³].
inline double restShapeGradients(const Points& rest, const Tets& tets, int e, double* g) {
  const Eigen::Vector3d a = rest.row(tets(e, 0)).transpose();
  Eigen::Matrix3d Dm;
  for (int k = 0; k < 3; ++k) Dm.col(k) = rest.row(tets(e, k + 1)).transpose() - a;
  const Eigen::Matrix3d Dinv = Dm.inverse();
  for (int i = 1; i < 4; ++i)
    for (int c = 0; c < 3; ++c) g[3 * i + c] = Dinv(i - 1, c);
  for (int c = 0; c < 3; ++c) g[c] = -(g[3 + c] + g[6 + c] + g[9 + c]);
  return Dm.determinant() / 6.0;
}

/// Elastic forces and stiffness of a mesh, linearised about the current pose.
/// \note Forces are those acting ON the nodes (they point back towards the rest shape); the
/// stiffness K is the positive semi-definite matrix with f(x + dx) ≈ f(x) − K dx.
/// \note DOF order: x0 y0 z0 x1 … (3 per node).
class ElementFormulation {
 public:
  virtual ~ElementFormulation() = default;

  /// Updates the per-element linearisation (e.g. rotations) at positions x (#N×3 [m]) and returns
  /// the elastic forces there: f (3N) [N].
  virtual void update(const Points& x, Eigen::VectorXd& f) = 0;
  /// Adds scale · K (from the last update) to A, whose pattern is pattern().matrix().
  virtual void addStiffness(double scale, SparseMatrix& A) const = 0;
  /// Sets A = scale · K. This default zeroes A and adds; a formulation may do it in one pass.
  virtual void assignStiffness(double scale, SparseMatrix& A) const {
    std::fill(A.valuePtr(), A.valuePtr() + A.nonZeros(), 0.0);
    addStiffness(scale, A);
  }
  virtual const BlockPattern& pattern() const = 0;

  /// A formulation whose stiffness splits as K = K_c + R, K_c on a narrower pattern and R a
  /// rank-one sum (solver/rank_one_sum.h), lets a solver that takes such a sum
  /// (LinearSolver::acceptsRankOneSum) apply R without assembling it: compactPattern() is K_c's
  /// pattern. nullptr (the default): no split; pattern() is K's.
  virtual const BlockPattern* compactPattern() const { return nullptr; }
  /// Sets A = scale · K_c from the last update (A's pattern: compactPattern()->matrix()).
  virtual void assignCompactStiffness(double scale, SparseMatrix& A) const {
    (void)scale;
    (void)A;
    throw std::logic_error("this element formulation has no compact stiffness (compactPattern() is nullptr)");
  }
  /// R from the last update (scale 1, no mask); its arrays stay valid and unchanged until the next
  /// update() or modulus change. Empty when compactPattern() is nullptr.
  virtual RankOneSum rankOneStiffness() const { return {}; }

  /// Per-element modulus factor E_r (E = E_r · E0), #T, all 1 initially.
  virtual const Eigen::VectorXd& modulusFactors() const = 0;
  /// @throws std::invalid_argument if the size is not #T or a factor is not positive and finite.
  virtual void setModulusFactors(const Eigen::VectorXd& factors) = 0;
  /// Von Mises norm of the element stress at the last update [Pa], #T (seed equation 1).
  virtual const Eigen::VectorXd& vonMisesStress() const = 0;
  /// The volume ratio J at or below which an element counts as collapsed, as invalid as an inverted
  /// one (J ≤ 0), for the stiffening's reversal (material/stiffening.h): a step that leaves one is
  /// repeated. 0 (the default): only inverted elements. A formulation whose elements can lose their
  /// own volume without resisting it (the average nodal pressure element) sets it above 0: from a
  /// nearly flat element no linearised step can be kept valid, however stiff the material.
  virtual double collapsedVolumeRatio() const { return 0.0; }
};

}  // namespace breast_sim::core
