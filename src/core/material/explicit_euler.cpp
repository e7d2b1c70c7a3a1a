#include "breast_sim/core/material/explicit_euler.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "breast_sim/core/solver/pcg_solver.h"  // parallelMultiply

namespace breast_sim::core {

void DivergenceLimits::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "divergence limit '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(max_displacement_m > 0) || !std::isfinite(max_displacement_m))
    bad("max_displacement_m", max_displacement_m, "a positive length [m], e.g. 1");
  if (!(max_speed_mps > 0) || !std::isfinite(max_speed_mps)) bad("max_speed_mps", max_speed_mps, "a positive speed [m/s], e.g. 100");
}

ExplicitEulerSimulator::ExplicitEulerSimulator(const TetMesh& mesh, std::unique_ptr<ElementFormulation> elements,
                                               const ElasticMaterial& material, const DynamicsParams& params,
                                               const DivergenceLimits& limits)
    : rest_(mesh.nodes()), elements_(std::move(elements)), params_(params), limits_(limits) {
  params_.validate();
  material.validate();
  limits_.validate();
  if (!elements_) throw std::invalid_argument("ExplicitEulerSimulator: an element formulation is required");
  if (elements_->modulusFactors().size() != mesh.numTets())
    throw std::invalid_argument("ExplicitEulerSimulator: the element formulation does not match the mesh");
  const int nn = mesh.numNodes();
  mass_ = Eigen::VectorXd::Zero(nn);
  const Eigen::VectorXd vol = mesh.tetVolumes();
  for (int e = 0; e < mesh.numTets(); ++e)
    for (int i = 0; i < 4; ++i) mass_[mesh.tets()(e, i)] += 0.25 * material.density_kg_per_m3 * vol[e];
  const double floor = 1e-9 * mass_.maxCoeff();
  for (int n = 0; n < nn; ++n) mass_[n] = std::max(mass_[n], floor);
  fixed_node_.assign(nn, 0);
  state_.displacement_m = Eigen::VectorXd::Zero(3 * nn);
  state_.velocity_mps = Eigen::VectorXd::Zero(3 * nn);
  K_ = elements_->pattern().matrix();
  x_ = rest_;
}

void ExplicitEulerSimulator::fixNodes(const std::vector<int>& nodes) {
  for (int n : nodes) {
    if (n < 0 || n >= numNodes())
      throw std::invalid_argument("fixNodes: node " + std::to_string(n) + " is not in [0, " + std::to_string(numNodes()) + ")");
    fixed_node_[n] = 1;
    state_.velocity_mps.segment<3>(3 * n).setZero();
  }
}

void ExplicitEulerSimulator::setGravity(const Eigen::Vector3d& g) {
  DynamicsParams p = params_;
  p.gravity_mps2 = g;
  p.validate();
  params_ = p;
}

const Eigen::VectorXd& ExplicitEulerSimulator::elasticForces() {
  for (int n = 0; n < numNodes(); ++n) x_.row(n) = rest_.row(n) + state_.displacement_m.segment<3>(3 * n).transpose();
  elements_->update(x_, f_el_);
  return f_el_;
}

bool ExplicitEulerSimulator::step() {
  if (diverged_) return false;
  const double dt = params_.time_step_s;
  elasticForces();
  if (params_.stiffness_damping_s > 0) {
    std::fill(K_.valuePtr(), K_.valuePtr() + K_.nonZeros(), 0.0);
    elements_->addStiffness(1.0, K_);
    parallelMultiply(K_, state_.velocity_mps, kv_);
  } else {
    kv_.setZero(state_.velocity_mps.size());
  }
  const int nn = numNodes();
  double vmax2 = 0.0, umax2 = 0.0;
  bool finite = true;
  for (int n = 0; n < nn; ++n) {
    if (fixed_node_[n]) continue;
    for (int c = 0; c < 3; ++c) {
      const int r = 3 * n + c;
      const double m = mass_[n];
      const double f = f_el_[r] + m * params_.gravity_mps2[c] - params_.mass_damping_per_s * m * state_.velocity_mps[r] -
                       params_.stiffness_damping_s * kv_[r];
      state_.velocity_mps[r] += dt * f / m;
      state_.displacement_m[r] += dt * state_.velocity_mps[r];
    }
    const double v2 = state_.velocity_mps.segment<3>(3 * n).squaredNorm();
    const double u2 = state_.displacement_m.segment<3>(3 * n).squaredNorm();
    if (!std::isfinite(v2) || !std::isfinite(u2)) finite = false;
    vmax2 = std::max(vmax2, v2);
    umax2 = std::max(umax2, u2);
  }
  state_.time_s += dt;
  ++state_.step;
  nan_ = !finite;
  diverged_ = !finite || std::sqrt(umax2) > limits_.max_displacement_m || std::sqrt(vmax2) > limits_.max_speed_mps;
  return !diverged_;
}

}  // namespace breast_sim::core
