#pragma once
/// @file simulation_settings.h
/// Everything that sets up a gravity simulation of a model: material, time integration, linear
/// solver and which nodes are held; read from a case file's `simulation:` map and turned into a
/// ready DynamicSimulator, for a case's model or for any tetrahedral mesh (docs/design.md, "Driving
/// the core with your own mesh"). The node, the command-line tools and the benchmarks share this.

#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/multigrid.h"

namespace breast_sim::core {

struct ModelCase;
struct SimulationModel;

/// Which linear solver takes the implicit step, and how far it iterates.
struct SolverSettings {
  enum class Kind {
    kMultigrid,    ///< PCG with the geometric multigrid V-cycle (the default; solver/multigrid.h);
                   ///< needs coarse meshes of the domain: those of an image or phantom case, or
                   ///< the caller's (buildSimulator for a mesh)
    kCholmod,      ///< sparse direct Cholesky (exact; the reference)
    kJacobiPcg,    ///< PCG with diagonal scaling (no set-up; slow on fine meshes)
    kAggregation   ///< PCG with smoothed-aggregation multigrid (solver/aggregation_multigrid.h):
                   ///< needs no coarse meshes, so it suits any mesh
  };
  Kind kind = Kind::kMultigrid;
  /// PCG stops when ‖b − A v‖ ≤ this · ‖b‖, in (0, 1) (b = M v_t + dt f shrinks as the model settles,
  /// so a loose per-step tolerance still converges to the exact equilibrium; docs/benchmarks.md).
  double relative_tolerance = 1e-2;
  int max_iterations = 200;  ///< per step; a step that hits it is used anyway and counted
  /// PCG's initial guess from this many vectors: the step's warm start and the last solutions
  /// (PcgOptions::projection_vectors); 1 = the warm start alone.
  int projection_vectors = PcgOptions{}.projection_vectors;
  /// The geometric multigrid; its coarse operators are renewed when the PCG iterations lost to their
  /// age are worth a renewal, at least every 50th step (docs/benchmarks.md, "Renewing the coarse operators").
  MultigridOptions multigrid = [] {
    MultigridOptions o;
    o.coarse_update_interval = 50;
    o.coarse_update_adaptive = true;
    return o;
  }();
  CoarseningOptions coarsening;
  /// Used by solver 'cholmod' (the direct solve of every step). The coarsest levels of 'multigrid'
  /// and 'aggregation' factorize with their own options (one BLAS thread).
  CholmodOptions cholmod;

  static std::string kindName(Kind k);
  /// "multigrid", "aggregation", "cholmod" or "jacobi-pcg". @throws std::invalid_argument naming the choices.
  static Kind kindFromName(const std::string& name);
};

/// When a quasi-static loading counts as settled (fem/equilibrium.h).
struct SettleOptions {
  /// Time step of the settling run [s], ≥ 0; 0 = the dynamics time step. Backward Euler is stable for
  /// any step, and a step much longer than α_K is nearly a Newton step of the static problem, so long
  /// steps settle in a few (docs/benchmarks.md).
  double time_step_s = 0.33;
  /// Settled when the largest nodal displacement change of a step is at most this [m] …
  double increment_tolerance_m = 1e-5;
  /// … for this many consecutive steps.
  int consecutive_steps = 2;
  int max_steps = 400;  ///< gives up (settled = false) after this many steps
  void validate() const;
};

/// The simulation part of a case file.
struct SimulationSettings {
  ElasticMaterial material;
  DynamicsParams dynamics;  ///< gravity is set by the run (prone, supine, a patient pose)
  SolverSettings solver;
  SettleOptions settle;
  /// Nodes held fixed (Dirichlet): a node set of the model, "chest_wall" by default; "" = none.
  std::string fixed_node_set = "chest_wall";
  /// Magnitude of gravity [m/s²] for loads the run derives from the case's directions.
  double gravity_mps2 = 9.81;
  /// Von Mises stiffening with time-step reversal (material/stiffening.h) while settling: no element
  /// ends inverted. false = co-rotated FEM with fixed E (faster; soft loads only).
  bool stiffening = true;
  /// Volumetric term of the co-rotated tetrahedra (fem/corotated_tet_fem.h): kDeterminant, the
  /// "fixed co-rotated" J − 1 term (Stomakhin et al. 2012), or kTrace, the seed's linear tr(S) − 3,
  /// which lets elements at the clamped rim flatten and invert under the supine load (docs/speed_accuracy.md).
  CorotatedTetFem::VolumeTerm volume_term = CorotatedTetFem::kDefaultVolumeTerm;
  /// The element formulation. kAnpTet (the default): average-nodal-pressure tetrahedra (AnpTetFem,
  /// fem/anp_tet_fem.h), which do not lock as ν → 0.5: about twice as close to a quadratic-element
  /// reference as kLinearTet on the phantom and VICTRE (docs/speed_accuracy.md); volume_term is not
  /// used (ANP has its own nodal J − 1 term), and its stiffness couples nodes two element layers apart
  /// (the solvers take it as a one-ring matrix and a rank-one sum). kLinearTet: co-rotated linear
  /// tetrahedra with `volume_term` (CorotatedTetFem), 1.3–1.5× faster per step.
  enum class Element { kLinearTet, kAnpTet };
  Element element = Element::kAnpTet;
  /// With element kAnpTet: the share β ∈ [0, 1] of the bulk modulus kept on each element's own
  /// volume ratio (AnpTetFem::setElementVolumeFraction; 0 = pure average nodal pressure).
  double anp_element_volume_fraction = 0.0;
  /// With element kAnpTet: the volume ratio J_b ∈ [0, 1) below which an element resists further
  /// compression with the bulk modulus (AnpTetFem::setInversionBarrier; 0 = off). The averaged
  /// pressure alone lets a single element of the clamped rim fold; 0.3 keeps every element valid.
  double anp_inversion_barrier = 0.3;
  /// Its stiffness as a multiple of the bulk modulus (c of AnpTetFem::setInversionBarrier).
  double anp_inversion_barrier_stiffness = 100.0;
  /// Sliding of the chest-wall nodes on the wall (prone_to_supine.h, `sliding:` of a case file)
  /// after the fixed-wall settle; needs stiffening and a fixed node set.
  bool sliding = true;
  /// The rest shape of the pipeline's runs (prone_to_supine.h). kProne: the prone shape taken as
  /// stress-free and loaded with g_supine − g_prone (the seed's way). kUnloaded: the gravity-free
  /// shape X0 recovered from the prone shape (fem/unloaded_state.h), loaded with supine gravity
  /// itself; the wall then carries the supine weight only, half the superposition's normal load, so
  /// free sliding (sliding.tether_stiffness 0) needs friction above the wall's slope
  /// (docs/unloaded_state.md). kCaseDefault (not set): kUnloaded for a patient's label image, MRI
  /// or mesh, kProne for the software phantom, whose supine gravity tilts 10° along its wall, beyond
  /// the kinetic friction angle, and whose analytic supine target was made for the superposition
  /// (resolvedReferenceState). buildSimulator does not read it.
  enum class ReferenceState { kUnloaded, kProne, kCaseDefault };
  ReferenceState reference_state = ReferenceState::kCaseDefault;
  /// reference_state with kCaseDefault resolved for a case that is (`software_phantom`) or is not
  /// the software phantom.
  ReferenceState resolvedReferenceState(bool software_phantom) const {
    if (reference_state != ReferenceState::kCaseDefault) return reference_state;
    return software_phantom ? ReferenceState::kProne : ReferenceState::kUnloaded;
  }
  /// Young's modulus per tissue [Pa], keyed by the elements' region label (the tissue class of
  /// model/tissue_labels.h: 1 fat, 2 fibroglandular, 3 skin, 4 lesion), e.g. {4: 20000}: a lesion
  /// ten times stiffer than 2 kPa tissue. Regions not listed take material.youngs_modulus_pa (E0).
  /// The stiffening factor E_r multiplies each element's base modulus (CorotatedTetFem::
  /// setElementYoungsModuli); ν and ρ stay those of `material`. Empty (the default) = E0 everywhere.
  std::map<int, double> region_youngs_modulus_pa;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Each element's base Young's modulus [Pa] (#T) from settings.region_youngs_modulus_pa and the
/// mesh's region labels; empty when the map is empty (E0 everywhere).
Eigen::VectorXd elementYoungsModuli(const TetMesh& mesh, const SimulationSettings& settings);

/// Reads the `simulation:` map of a case file (absent = defaults). Keys, with units:
///   youngs_modulus_pa, poisson_ratio, density_kg_per_m3, time_step_s, mass_damping_per_s,
///   stiffness_damping_s, solver (multigrid | aggregation | cholmod | jacobi-pcg), solver_relative_tolerance,
///   solver_max_iterations, multigrid_smoother (jacobi | gauss-seidel | chebyshev),
///   multigrid_chebyshev_ratio, multigrid_smoothing_steps,
///   multigrid_coarse_update_interval, multigrid_max_coarsest_elements, fixed_node_set, gravity_mps2, stiffening,
///   volume_term (trace | determinant), element (linear | anp), anp_element_volume_fraction (0..1),
///   anp_inversion_barrier (volume ratio in [0, 1), 0 = off), anp_inversion_barrier_stiffness (× bulk modulus),
///   sliding, reference_state (unloaded | prone),
///   settle_time_step_s, settle_increment_tolerance_mm, settle_max_steps, tissue_youngs_modulus_pa
///   (a map tissue name → Pa: {fat, fibroglandular, skin, lesion}, e.g. {lesion: 20000}; see
///   SimulationSettings::region_youngs_modulus_pa).
/// @throws std::runtime_error naming the file, the key and what is expected.
SimulationSettings loadSimulationSettings(const std::string& yaml_path);

/// A simulator ready to step, and what building it cost.
struct SimulatorBuild {
  std::unique_ptr<DynamicSimulator> simulator;
  int multigrid_levels = 0;        ///< levels including the fine one (0 without multigrid)
  std::vector<int> level_nodes;    ///< nodes per level, fine first
  /// Meshing the coarse levels (a case's only), their prolongations and constructing the solver [s]
  double hierarchy_seconds = 0.0;
  double setup_seconds = 0.0;      ///< element set-up and the solver's pattern analysis [s]
};

/// Builds, for any tetrahedral mesh, the element formulation (settings.element, with the per-region
/// moduli of settings.region_youngs_modulus_pa keyed by the mesh's region labels), the solver
/// (settings.solver) and the simulator, and fixes the nodes of settings.fixed_node_set.
/// Stiffening (settings.stiffening) and sliding are not set up here: they belong to the runs of
/// pipeline/ (settle() then settles the plain co-rotated model).
/// @param mesh  kept by reference by the simulator and its elements: it must outlive the simulator
/// @param coarse_meshes  for solver 'multigrid' only, and required by it: meshes of the same domain,
///        each coarser than the one before (coarsest last); every node of a level must lie in the next
///        coarser mesh (within its mean boundary edge length). The hierarchy is
///        MeshHierarchy({mesh, coarse_meshes...}).
/// @param meshed_nodes_m  solver 'multigrid': the mesh's nodes in the shape the coarse meshes mesh,
///        #N×3 [m] (empty: the mesh's own). A rest shape other than the meshed domain (the unloaded
///        X0 of a prone image) takes the prolongations of that domain: a coarse level then spans the
///        same tissue however far X0 lies from it. Other solvers do not read it.
/// @throws std::invalid_argument for invalid settings; a fixed_node_set the mesh lacks (naming the sets
///         it has and a near match, TetMesh::nearestNodeSetName); solver 'multigrid' without coarse
///         meshes (naming the alternatives 'aggregation' and 'cholmod'); coarse meshes with another
///         solver; a level that does not fit in the next coarser one (MeshHierarchy); with solver
///         'multigrid', meshed nodes of another count than the mesh's or that invert an element.
SimulatorBuild buildSimulator(const TetMesh& mesh, const SimulationSettings& settings,
                              std::vector<TetMesh> coarse_meshes = {}, const Points& meshed_nodes_m = Points());

/// buildSimulator(model.mesh, settings, coarse meshes) for a case's model: for solver 'multigrid' the
/// coarse meshes are meshed from the case's label image (buildCoarseMeshes with
/// settings.solver.coarsening; none when the fine mesh is already small enough, which leaves the
/// multigrid a direct solve), and hierarchy_seconds includes that meshing.
/// @param model  its mesh must outlive the simulator
/// @param coarse_meshes  solver 'multigrid': the coarse levels when they are meshed already (as
///        buildCoarseMeshes gave them for this case, model and coarsening; an empty list is a
///        multigrid of the fine level alone); nullopt meshes them here. Other solvers: nullopt.
/// @throws std::invalid_argument for invalid settings or a missing node set (names it and the sets
///         the model has), coarse meshes that do not nest (MeshHierarchy); std::runtime_error as
///         meshing the coarse levels does.
/// @param meshed_nodes_m  as in the overload above: the model's nodes in the case's own (prone) shape
///        when the model's rest shape is another (empty: the model's own)
SimulatorBuild buildSimulator(const ModelCase& model_case, const SimulationModel& model,
                              const SimulationSettings& settings,
                              std::optional<std::vector<TetMesh>> coarse_meshes = std::nullopt,
                              const Points& meshed_nodes_m = Points());

}  // namespace breast_sim::core
