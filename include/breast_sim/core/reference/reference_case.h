#pragma once
/// @file reference_case.h
/// The load cases of the speed–accuracy study, shared by the reference tool and the benchmark, so
/// that our runs and CalculiX's solve the same problem.
///
/// Gravity on the prone model: the prone image shows the breast already hanging under prone
/// gravity, and the model takes that shape as its rest state (no gravity-free state is recovered,
/// as in the seed paper). Two loads are studied:
///  - prone → supine: g_supine − g_prone, the first-order change of load from the prone to the
///    supine position (what the main job, breast_sim_run, settles);
///  - hanging prone: g_prone itself on the prone shape, a second load direction (along the depth
///    axis instead of across it).

#include <string>

#include <Eigen/Core>

#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/reference/calculix.h"

namespace breast_sim::core {

enum class GravityLoadCase {
  kProneToSupine,  ///< g_supine − g_prone
  kProneHanging,   ///< g_prone
};

/// "supine" / "hanging".
std::string gravityLoadCaseName(GravityLoadCase c);
/// "supine" or "hanging". @throws std::invalid_argument naming the choices.
GravityLoadCase gravityLoadCaseFromName(const std::string& name);

/// The gravity load [m/s²] of a case: prone gravity is g · prone_gravity_direction; supine gravity
/// is the phantom's own (tilted) supine gravity, or for an image case the prone direction reversed.
/// @param g_mps2  magnitude of gravity [m/s²], > 0
/// @throws std::invalid_argument for a non-positive magnitude or a zero prone direction.
Eigen::Vector3d gravityLoad(const ModelCase& model_case, GravityLoadCase which, double g_mps2);

/// The case's simulation model, kept in a cache folder so that a cached reference solve can be used
/// again: meshing is not repeatable from run to run (CGAL's sliver perturbation and exudation stop
/// on time limits), and a reference belongs to one mesh. The key hashes the case file's text (or
/// the case name without a file), the meshing options and the lesions; the mesh is stored as
/// `<key>.model.vtu` (node sets and region labels included). Lesions are embedded again on loading.
/// @param cache_dir  "" = no cache (meshes every time)
/// @param from_cache if not null, set to whether the mesh came from the cache
/// @throws as buildSimulationModel, and std::runtime_error for an unreadable cached mesh.
SimulationModel cachedSimulationModel(const ModelCase& model_case, const std::string& cache_dir,
                                      bool* from_cache = nullptr);

/// The CalculiX problem matching a simulation's settings: its material, its fixed node set, the
/// given gravity load, neo-Hookean with NLGEOM.
/// @throws std::invalid_argument when the settings give per-tissue moduli
///         (region_youngs_modulus_pa): they need the mesh, use the overload below.
CalculixLoadCase referenceLoadCase(const SimulationSettings& settings, const Eigen::Vector3d& gravity_mps2,
                                   ReferenceElement element = ReferenceElement::kC3D4);

/// The same for a mesh: per-tissue moduli (settings.region_youngs_modulus_pa, by the mesh's region
/// labels) become per-element modulus factors E_e / E0, which the deck writes as one element set
/// and *MATERIAL per distinct modulus (same ν and density).
CalculixLoadCase referenceLoadCase(const SimulationSettings& settings, const TetMesh& mesh,
                                   const Eigen::Vector3d& gravity_mps2,
                                   ReferenceElement element = ReferenceElement::kC3D4);

}  // namespace breast_sim::core
