#pragma once
/// @file explicit_euler.h
/// Semi-implicit (symplectic) Euler with the same elements, lumped mass and Rayleigh damping as
/// DynamicSimulator: the contrast method of the stability map. It is only conditionally stable
/// (dt below about 2/ω_max of the mesh, and α_K ω_max² dt < 2 for the stiffness damping), so at the
/// time steps of the implicit method it blows up; it detects that and stops cleanly.

#include <memory>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/fem/element_formulation.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// When the explicit run counts as diverged.
struct DivergenceLimits {
  double max_displacement_m = 1.0;  ///< a node moved farther than this [m] (the breast is ~0.1 m)
  double max_speed_mps = 100.0;     ///< a node faster than this [m/s]
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// v_{t+1} = v_t + dt M⁻¹ (f_el(x_t) + f_ext + M g − α_M M v_t − α_K K(x_t) v_t),  u_{t+1} = u_t + dt v_{t+1};
/// fixed nodes keep their displacement (zero velocity).
class ExplicitEulerSimulator {
 public:
  /// @throws std::invalid_argument for invalid parameters or a formulation of another size.
  ExplicitEulerSimulator(const TetMesh& mesh, std::unique_ptr<ElementFormulation> elements,
                         const ElasticMaterial& material, const DynamicsParams& params,
                         const DivergenceLimits& limits = {});

  int numNodes() const { return static_cast<int>(mass_.size()); }
  void fixNodes(const std::vector<int>& nodes);
  void setGravity(const Eigen::Vector3d& g_mps2);
  const DynamicsParams& params() const { return params_; }

  /// One step. Returns false (and leaves the diverged state in place) when the new state is not
  /// finite or past the divergence limits; after that diverged() is true and step() does nothing.
  bool step();
  bool diverged() const { return diverged_; }
  bool nan() const { return nan_; }

  const SimulationState& state() const { return state_; }
  const Eigen::VectorXd& lumpedMass() const { return mass_; }
  const std::vector<char>& fixedNodes() const { return fixed_node_; }
  /// Elastic forces at the current state [N], 3N (updates the element linearisation).
  const Eigen::VectorXd& elasticForces();
  ElementFormulation& elements() { return *elements_; }

 private:
  const Points rest_;
  std::unique_ptr<ElementFormulation> elements_;
  DynamicsParams params_;
  DivergenceLimits limits_;
  Eigen::VectorXd mass_;
  std::vector<char> fixed_node_;
  SimulationState state_;
  SparseMatrix K_;
  Eigen::VectorXd f_el_, kv_;
  Points x_;
  bool diverged_ = false, nan_ = false;
};

}  // namespace breast_sim::core
