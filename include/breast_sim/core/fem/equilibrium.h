#pragma once
/// @file equilibrium.h
/// Running a dynamic simulation until it settles under its current loads (quasi-static loading).

#include <functional>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/simulation_settings.h"

namespace breast_sim::core {

/// What a settling run did.
struct SettleResult {
  bool settled = false;
  int steps = 0;
  double seconds = 0.0;              ///< wall time of the steps [s]
  double assembly_seconds = 0.0;     ///< of which rotations, forces and matrix [s]
  double setup_seconds = 0.0;        ///< of which solver set-up (coarse operators, factorization) [s]
  double solve_seconds = 0.0;        ///< of which solves [s]
  long solver_iterations = 0;        ///< summed over the steps
  int unconverged_solves = 0;        ///< steps whose solve hit its iteration limit
  double last_increment_m = 0.0;     ///< largest nodal displacement change of the last step [m]
  double max_displacement_m = 0.0;   ///< largest nodal displacement at the end [m]
};

/// Steps `sim` with options.time_step_s (restored afterwards) until the largest nodal displacement
/// change of a step stays ≤ options.increment_tolerance_m for options.consecutive_steps steps, or
/// options.max_steps is reached. The velocity is zeroed at the end when settled (a state at rest).
/// @param progress  called after every step with (step, largest increment [m]); may be empty
/// @throws std::invalid_argument for invalid options; std::runtime_error as DynamicSimulator::step.
SettleResult settle(DynamicSimulator& sim, const SettleOptions& options,
                    const std::function<void(int, double)>& progress = {});

/// Largest nodal norm of a 3N vector (a displacement or its change) [m].
double maxNodalNorm(const Eigen::VectorXd& v);

}  // namespace breast_sim::core
