#pragma once
/// @file stability_map.h
/// "Test stability where methods fail": one load case run by seven methods over a grid of
/// Poisson ratio, Young's modulus, time step and initial α, with an outcome per run. The command is
/// breast_sim_stability_map (src/tools); the results and their plots are in docs/stability_map.

#include <algorithm>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// The compared methods. All but explicit Euler are implicit Euler steps of DynamicSimulator.
enum class StabilityMethod {
  kLinear,              ///< plain linear FEM (CorotatedTetFem::setCorotated(false)), fixed E
  kCorotatedFixed,      ///< co-rotated FEM, fixed E
  kVonMisesNoReversal,  ///< co-rotated, E_r = 1 + α s_VM every step with α fixed at its initial value, no reversal
  kFullMethod,          ///< co-rotated, von Mises update with time-step reversal and the α controller (seed 2.3)
  kExplicitEuler,       ///< co-rotated, fixed E, semi-implicit (symplectic) Euler (explicit_euler.h)
  kAnpFixed,            ///< average-nodal-pressure tetrahedra with the inversion barrier (J_b 0.3), fixed E
  kAnpFull              ///< the same element with the von Mises update, time-step reversal and the α controller
};

/// The ANP methods' inversion barrier: the volume ratio below which an element resists on its own
/// (docs/speed_accuracy.md: the barrier value measured against CalculiX).
inline constexpr double kStabilityAnpBarrier = 0.3;

/// "linear", "corotated", "vonmises_no_reversal", "full", "explicit_euler", "anp", "anp_full".
const char* methodName(StabilityMethod m);
/// @throws std::invalid_argument naming the accepted names.
StabilityMethod parseStabilityMethod(const std::string& name);
std::vector<StabilityMethod> allStabilityMethods();

/// The load case: a mesh with its fixed nodes, loaded by gravity from its rest shape.
struct StabilityLoadCase {
  std::string name;
  TetMesh mesh;
  std::vector<int> fixed_nodes;
  Eigen::Vector3d gravity_mps2 = Eigen::Vector3d::Zero();  ///< [m/s²]
};

/// The phantom case file with meshing.target_elements overridden: the prone shape is the rest
/// shape, the chest-wall node set is fixed and the phantom's supine gravity is applied (the hard
/// case: gravity turned by 170° from the one the rest shape hangs under).
/// @throws std::runtime_error when the case is not a phantom case (no supine gravity) or as
///         loadModelCase / buildSimulationModel.
StabilityLoadCase makePhantomLoadCase(const std::string& case_yaml, int target_elements);
/// config/phantom_default.yaml of the source tree this library was built from.
std::string defaultPhantomCasePath();

/// One run of the map.
struct StabilityRun {
  StabilityMethod method = StabilityMethod::kFullMethod;
  double youngs_modulus_pa = 2000.0;  ///< E0 [Pa]
  double poisson_ratio = 0.48;
  double time_step_s = 0.033;         ///< dt [s]
  double alpha_scale = 1.0;           ///< initial α = this × AlphaControllerParams default (methods with α)
  std::string axis = "nu_dt";         ///< which sub-grid it belongs to: nu_dt, E, alpha
  double max_time_s = 4.0;            ///< simulated time limit [s]
  long max_steps = 400;               ///< accepted-step limit (step calls are limited to twice this)
  /// The time limit is raised to this many steps for large dt (max(max_time_s, min_steps · dt)):
  /// the full method settles its shape and then releases α to the material's equilibrium.
  long min_steps = 80;
  /// Simulated-time limit of the run [s].
  double timeLimit() const { return std::max(max_time_s, static_cast<double>(min_steps) * time_step_s); }
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Outcome of one run.
struct StabilityResult {
  StabilityRun run;
  RunStats stats;
  /// "settled", "not_settled", "inverted", "stalled" (full method: the last step could not be taken
  /// without inversion within the reversal limit), "nan" or "exploded".
  std::string outcome;
  std::string reason;  ///< short human explanation with numbers
  double initial_alpha_per_pa = 0.0;  ///< 0 for methods without α
};

/// Runs one configuration on the load case (CHOLMOD for the implicit methods). Never throws for a
/// numerical failure (that is an outcome); throws std::invalid_argument for an invalid run.
StabilityResult runStability(const StabilityLoadCase& load, const StabilityRun& run,
                             const StiffeningParams& base = StiffeningParams{});

/// The sweep: per method the full ν × dt grid at E = 1 kPa (the soft end of the seed's 1–3 kPa: at
/// 2 kPa nothing inverts in this load case) and α 1×; at ν = 0.48, dt = 0.033 s the moduli
/// E ∈ {2, 3 kPa} and E = 2 μ (1 + ν) for μ ∈ {0.3, 0.5, 0.7 kPa}; for the three methods with α,
/// α ∈ {0.1×, 10×} at dt ∈ {0.033, 0.33 s}, E = 1 kPa. quick: ν ∈ {0.28, 0.48, 0.495} × dt ∈ {0.033, 0.33 s},
/// no E or α axis except α 10× for the two full methods, and 2 s of simulated time.
std::vector<StabilityRun> stabilityGrid(bool quick);

}  // namespace breast_sim::core
