#include "breast_sim/core/fem/equilibrium.h"

#include <chrono>

namespace breast_sim::core {

double maxNodalNorm(const Eigen::VectorXd& v) {
  double m = 0.0;
  for (Eigen::Index n = 0; 3 * n + 2 < v.size(); ++n) m = std::max(m, v.segment<3>(3 * n).squaredNorm());
  return std::sqrt(m);
}

SettleResult settle(DynamicSimulator& sim, const SettleOptions& options, const std::function<void(int, double)>& progress) {
  options.validate();
  const DynamicsParams saved = sim.params();
  if (options.time_step_s > 0) {
    DynamicsParams p = saved;
    p.time_step_s = options.time_step_s;
    sim.setParams(p);
  }
  SettleResult r;
  const auto t0 = std::chrono::steady_clock::now();
  Eigen::VectorXd previous = sim.state().displacement_m;
  int quiet = 0;
  try {
    while (r.steps < options.max_steps) {
      const StepStats st = sim.step();
      ++r.steps;
      r.assembly_seconds += st.assembly_seconds;
      r.setup_seconds += st.setup_seconds;
      r.solve_seconds += st.solve.seconds;
      r.solver_iterations += st.solve.iterations;
      if (!st.solve.converged) ++r.unconverged_solves;
      const Eigen::VectorXd& u = sim.state().displacement_m;
      r.last_increment_m = maxNodalNorm(u - previous);
      previous = u;
      if (progress) progress(r.steps, r.last_increment_m);
      quiet = r.last_increment_m <= options.increment_tolerance_m ? quiet + 1 : 0;
      if (quiet >= options.consecutive_steps) {
        r.settled = true;
        break;
      }
    }
  } catch (...) {
    sim.setParams(saved);
    throw;
  }
  sim.setParams(saved);
  if (r.settled) {
    SimulationState s = sim.state();
    s.velocity_mps.setZero();
    sim.restore(s);
  }
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  r.max_displacement_m = maxNodalNorm(sim.state().displacement_m);
  return r;
}

}  // namespace breast_sim::core
