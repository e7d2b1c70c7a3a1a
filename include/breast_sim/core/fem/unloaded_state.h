#pragma once
/// @file unloaded_state.h
/// The unloaded (gravity-free) reference shape of a body imaged under gravity: the rest shape X0
/// whose equilibrium under the imaging gravity is the imaged shape. A prone MRI shows the breast
/// already hanging; loading X0 with supine gravity then gives the supine shape without taking the
/// prone shape as stress-free. Method, contract and measurements: docs/unloaded_state.md.

#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/point_embedding.h"

namespace breast_sim::core {

/// How recoverUnloadedShape iterates.
struct UnloadedStateOptions {
  int max_iterations = 30;   ///< forward loadings at most, ≥ 1
  /// Converged when every node of the re-loaded shape x(X0) is within this of the loaded shape [m], > 0.
  double tolerance_m = 1e-5;
  /// Stops (converged = false) after this many loadings in a row that found no X0 with a smaller
  /// largest residual than the best so far, ≥ 1.
  int max_growing_iterations = 3;
  /// The stiffening driver of the forward loadings when settings.stiffening is set (the pipeline's
  /// `stiffening:` map); unused otherwise.
  StiffeningParams stiffening;
  /// Where the iteration starts, #N×3 [m]; empty = the loaded shape itself. Fixed nodes are taken
  /// from the loaded shape whatever is given here.
  Points initial_unloaded_nodes_m;
  /// Solver 'multigrid': its coarse levels, meshes of the loaded shape's domain as buildSimulator
  /// takes them (coarsest last). Each loading's multigrid takes its prolongations from the loaded
  /// shape (buildSimulator's meshed_nodes_m), whatever its X0 (a preconditioner: the answer does not
  /// depend on them).
  std::vector<TetMesh> coarse_meshes;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// One forward loading of the iteration.
struct UnloadedIteration {
  double max_residual_m = 0.0;   ///< largest ‖x(X0) − x_loaded‖ over the nodes [m]
  double mean_residual_m = 0.0;  ///< its mean over all nodes [m]
  int settle_steps = 0;          ///< accepted time steps of the forward settle
  bool accelerated = false;      ///< this X0 came from the Anderson step (else the plain fixed-point step)
  /// The share of the residual in the step that gave this X0: 1; for the best X0's plain step after
  /// g loadings in a row that found none better 1/2^g, and less than half of the last plain step's
  /// share when that one started at the best X0 too; for a mixing step the smallest share of the
  /// step backs so far; halved further until no element of X0 is inverted.
  double step_fraction = 1.0;
  double seconds = 0.0;          ///< wall time of the loading, simulator build included [s]
};

/// What recoverUnloadedShape found.
struct UnloadedStateResult {
  /// #N×3 [m]: the unloaded shape X0 whose loading was measured last with the smallest largest
  /// residual (the loaded shape itself when no loading succeeded). Fixed nodes equal the loaded shape.
  Points unloaded_nodes_m;
  /// #N×3 [m]: X0 loaded with the gravity (the re-loaded shape), same rows; empty when no loading succeeded.
  Points reloaded_nodes_m;
  int iterations = 0;            ///< forward loadings done (successful or not)
  bool converged = false;        ///< max_residual_m ≤ tolerance_m
  double max_residual_m = 0.0;   ///< of unloaded_nodes_m: largest ‖x(X0) − x_loaded‖ [m]
  double mean_residual_m = 0.0;  ///< of unloaded_nodes_m: mean over all nodes [m]
  /// Inverted elements of the candidate X0 or of its loading that ended the run (0 unless `failure`
  /// says so).
  int inverted_elements = 0;
  /// Why the run stopped without converging, naming the iteration ("" when converged).
  std::string failure;
  std::vector<UnloadedIteration> history;  ///< one entry per successful forward loading, in order
  double seconds = 0.0;                    ///< wall time of the whole call [s]
};

/// Recovers the unloaded shape X0 of `loaded` (its nodes: the shape under gravity `gravity_mps2`):
/// the fixed-point iteration X0 ← X0 − (x(X0) − x_loaded) with Anderson mixing of the last steps,
/// x(X0) being X0 settled under the gravity with the fixed node set held. Each loading builds a
/// simulator (buildSimulator) on a copy of `loaded` with nodes X0 (same elements, region labels and
/// node sets) and settles it from the previous loading's displacement: with settings.stiffening by
/// the stiffening driver (options.stiffening) until it is settled at the base material's
/// equilibrium and its increment is within the settle tolerance, else by settle(). The settle
/// increment tolerance is capped at options.tolerance_m / 4 (a looser forward settle would stall
/// the iteration).
///
/// A loading whose largest residual is not below the best one's sends the iteration back to the
/// best X0, whose plain step it takes halved once per such loading in a row (and at most half the
/// last plain step from the best X0, so that no X0 is loaded twice), and the mixing starts again
/// there, its later steps shortened as much (where the map does not contract at a few nodes, a full
/// step overshoots them). A
/// candidate X0 with inverted elements is replaced by the plain step, halved until no element is
/// inverted (down to 1/64 of the residual), and the mixing starts again. A forward loading that does not
/// settle or whose solver fails, a candidate X0 still inverted then, a loading that inverts
/// elements, options.max_growing_iterations loadings in a row that found no better X0 or the
/// iteration limit end the run with converged = false and `failure` naming the iteration and the
/// reason; none of them throws.
/// @param loaded  the loaded shape with the node set settings.fixed_node_set (unless that is "")
/// @param settings  material, elements, solver ('multigrid' with options.coarse_meshes,
///        'aggregation', 'cholmod' or 'jacobi-pcg'), settle options, fixed node set;
///        settings.dynamics.gravity_mps2 is replaced by gravity_mps2
/// @param gravity_mps2  the gravity of the loaded shape [m/s²] (prone: the image's prone gravity)
/// @throws std::invalid_argument for non-finite gravity (naming it), invalid options or settings
///         (naming the field), solver 'multigrid' without coarse meshes (naming 'aggregation' and
///         'cholmod') or coarse meshes with another solver, a fixed node set the mesh lacks, an
///         initial shape of the wrong size or with inverted elements.
UnloadedStateResult recoverUnloadedShape(const TetMesh& loaded, const SimulationSettings& settings,
                                         const Eigen::Vector3d& gravity_mps2, const UnloadedStateOptions& options = {});

/// One settle of a rest shape under gravity (a forward loading of the iteration).
struct GravityLoading {
  bool settled = false;    ///< settled, with no inverted element
  std::string failure;     ///< why not ("" when settled)
  int steps = 0;           ///< accepted time steps
  int inverted_elements = 0;  ///< at the end (rest + displacement)
  Points displacement_m;   ///< #N×3 [m] at the end (empty after a solver failure)
  double seconds = 0.0;    ///< wall time, simulator build included [s]
};

/// Settles `rest` under `gravity_mps2` with settings.fixed_node_set held, from
/// `initial_displacement_m` (#N×3 [m], empty = at rest): with settings.stiffening by the stiffening
/// driver (`stiffening`) until it is settled at the base material's equilibrium and the largest step
/// increment stayed within settings.settle.increment_tolerance_m for settings.settle.consecutive_steps
/// steps (the α search starts at its floor), else by settle(). Never
/// throws for a loading that fails (a solver failure, no settling, inverted elements): `failure`
/// says what happened.
/// @param coarse_meshes, meshed_nodes_m  solver 'multigrid': its coarse levels and rest's nodes in
///        the shape they mesh (empty: rest's own), as buildSimulator takes them
/// @throws std::invalid_argument as buildSimulator (settings, solver 'multigrid' without coarse
///         meshes, a missing node set, with it meshed nodes of another count) and for an initial
///         displacement of the wrong size.
GravityLoading loadWithGravity(const TetMesh& rest, const SimulationSettings& settings,
                               const Eigen::Vector3d& gravity_mps2, const StiffeningParams& stiffening = {},
                               const Points& initial_displacement_m = Points(),
                               std::vector<TetMesh> coarse_meshes = {}, const Points& meshed_nodes_m = Points());

/// `mesh` with its nodes replaced by `nodes_m` (#N×3 [m]): the same elements, region labels and node
/// sets. @throws std::invalid_argument for a row count that differs, or for elements that are inverted
/// or degenerate at `nodes_m` (naming the first; TetMesh would turn inverted ones over silently).
TetMesh withNodes(const TetMesh& mesh, const Points& nodes_m);

}  // namespace breast_sim::core
