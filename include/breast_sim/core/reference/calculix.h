#pragma once
/// @file calculix.h
/// An independent reference solver: the same mesh, material and gravity load solved by CalculiX
/// (`ccx`, Debian package calculix-ccx), a general-purpose non-linear FEM code that shares no code
/// with ours.
///
/// The science of the comparison: our model is co-rotated linear elasticity on linear tetrahedra,
/// settled dynamically. The reference is a static equilibrium of a compressible neo-Hookean solid
/// under finite strain (CalculiX `*STATIC` with `NLGEOM`, Newton–Raphson with load increments),
///   U = C10 (Ī1 − 3) + (1/D1) (J − 1)²   (CalculiX User's Manual, *HYPERELASTIC, NEO HOOKE),
/// whose small-strain limit has shear modulus μ = 2 C10 and bulk modulus K = 2 / D1. So the same
/// E and ν give C10 = μ / 2 = E / (4(1 + ν)) and D1 = 2 / K = 6(1 − 2ν) / E, and both models agree
/// for small loads; they differ by the material and geometric non-linearity at large strain, which
/// is what the reference is for. Elements: C3D4 (our linear tetrahedra, node for node: the same
/// discretisation) or C3D10 (quadratic tetrahedra on the same corner nodes: mid-edge nodes added,
/// which do not lock as ν → 0.5 the way linear tetrahedra do).
///
/// Units: the deck is written in SI (m, Pa, kg/m³, m/s²), so displacements come back in metres.
/// Body load: `*DLOAD` GRAV on every element, magnitude |g| along g / |g|, with the density; the
/// chest wall (a node set) is fixed by `*BOUNDARY`.
///
/// Results are cached (a solve of a 300k-element model takes minutes): the key is a 64-bit FNV-1a
/// hash of the complete input deck, which holds every node coordinate (14 significant digits, the
/// most CalculiX's 20-character fields take),
/// element, material constant, boundary condition and load, so any change to the mesh, material
/// or load makes a new key.

#include <array>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// Element type of the reference model.
enum class ReferenceElement {
  kC3D4,   ///< linear tetrahedra: our elements, node for node
  kC3D10,  ///< quadratic tetrahedra on the same corners (mid-edge nodes added): no volumetric locking
};

/// "C3D4" / "C3D10".
std::string referenceElementName(ReferenceElement e);
/// "c3d4" or "c3d10" (case-insensitive). @throws std::invalid_argument naming the choices.
ReferenceElement referenceElementFromName(const std::string& name);

/// A node held by single-DOF conditions and grounded springs along the global axes: e.g. a
/// chest-wall node sliding on the plane y = const, y fixed, the tangential x and z on springs to its
/// rest point (a tether). Springs are CalculiX SPRING1 elements (one element set per spring, linear,
/// along the global axis also under NLGEOM).
struct CalculixNodeSupport {
  int node = 0;                                             ///< mesh node (0-based)
  std::array<bool, 3> fixed{{false, false, false}};         ///< x, y, z held at zero displacement
  Eigen::Vector3d spring_n_per_m = Eigen::Vector3d::Zero(); ///< grounded spring per axis [N/m], ≥ 0
};

/// The reference problem: material, load, support and how CalculiX solves it.
struct CalculixLoadCase {
  ElasticMaterial material;  ///< E0 [Pa], ν, ρ [kg/m³]
  /// Optional per-element modulus factors (#T; E = factor · E0, same ν), e.g. a stiff inclusion;
  /// empty = 1 everywhere. Elements with equal factors share one CalculiX material.
  Eigen::VectorXd modulus_factors;
  Eigen::Vector3d gravity_mps2 = Eigen::Vector3d::Zero();  ///< body load g [m/s²]
  std::string fixed_node_set = "chest_wall";  ///< held fixed (all three DOFs); must be a node set of the mesh; "" = none
  /// Further supports per node (single DOFs, grounded springs); linear elements (C3D4) only: the
  /// mid-edge nodes of C3D10 would need springs of their own, consistent with the corners'.
  std::vector<CalculixNodeSupport> node_supports;
  ReferenceElement element = ReferenceElement::kC3D4;
  /// true: neo-Hookean (*HYPERELASTIC, NEO HOOKE); false: linear isotropic (*ELASTIC).
  bool hyperelastic = true;
  bool nlgeom = true;  ///< finite strain (NLGEOM); false = small-strain analysis
  /// *STATIC increments as fractions of the load: first, smallest, largest.
  double initial_increment = 0.1;
  double min_increment = 1e-5;
  double max_increment = 0.25;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// The complete CalculiX input deck (SI units) for a mesh and a load case. Nodes 1..N are the mesh's
/// nodes in order; with C3D10 the mid-edge nodes follow as N+1, … (a mid-edge node is fixed when
/// both its corners are: the edge of a linear mesh between two fixed nodes does not move either).
/// Node supports: `*BOUNDARY` lines for their fixed DOFs, and SPRING1 elements numbered after the
/// tetrahedra, each in its own element set with its `*SPRING` stiffness.
/// @throws std::invalid_argument for an invalid load case, a missing fixed node set (naming the sets
///         the mesh has), modulus factors of the wrong size, a support naming a node out of range or
///         a negative or non-finite spring, or supports with C3D10.
std::string calculixInputDeck(const TetMesh& mesh, const CalculixLoadCase& load);

/// Writes calculixInputDeck() to a file. @throws std::runtime_error naming a file that cannot be written.
void writeCalculixInput(const std::string& path, const TetMesh& mesh, const CalculixLoadCase& load);

/// Displacements read from a CalculiX `.dat` file (`*NODE PRINT` U): the LAST block printed (the
/// end of the step), nodes 1..num_nodes (further nodes, e.g. mid-edge ones, are skipped).
/// @param time_out  if not null, receives the step time of that block (1 = the full load)
/// @return #num_nodes×3 [the deck's length unit; m for our decks]
/// @throws std::runtime_error naming the file when it cannot be read, holds no displacement block,
///         or the block misses one of the nodes.
Points readCalculixDisplacements(const std::string& dat_path, int num_nodes, double* time_out = nullptr);

/// How solveWithCalculix runs CalculiX.
struct CalculixOptions {
  std::string executable = "ccx";  ///< looked up on PATH unless it contains a '/'
  /// Result cache; "" = no cache. See defaultReferenceCacheDir().
  std::string cache_dir = defaultReferenceCacheDir();
  /// Where the job runs; "" = a fresh folder under the system temporary directory, removed after
  /// a successful run unless keep_files.
  std::string work_dir;
  bool keep_files = false;
  int threads = 0;  ///< OMP_NUM_THREADS and CCX_NPROC_EQUATION_SOLVER for ccx; 0 = inherit
  /// Recompute even when a cached result exists (the new one replaces it).
  bool refresh = false;

  /// $BREAST_SIM_REFERENCE_CACHE, else $XDG_CACHE_HOME/breast_sim/reference, else
  /// ~/.cache/breast_sim/reference.
  static std::string defaultReferenceCacheDir();
};

/// A reference solution.
struct CalculixResult {
  Points displacement_m;      ///< #N×3 at the mesh's nodes (corner nodes) [m]
  double solve_seconds = 0.0; ///< wall time of the ccx run [s] (of the original run when cached)
  bool from_cache = false;
  std::string key;            ///< cache key (16 hex digits)
  std::string work_dir;       ///< where ccx ran ("" when from the cache)
  int deck_nodes = 0;         ///< nodes in the deck (N, or N + mid-edge nodes for C3D10)
};

/// Whether a CalculiX executable runs (`ccx -v`).
bool calculixAvailable(const std::string& executable = "ccx");

/// 64-bit FNV-1a hash of a text as 16 hex digits (the cache key of a deck).
std::string referenceCacheKey(const std::string& deck_text);

/// Solves the load case with CalculiX (or returns the cached result of the identical deck).
/// @throws std::invalid_argument as calculixInputDeck; std::runtime_error when ccx cannot be run,
///         reports an *ERROR, or stops before the full load (names the work folder and the log).
CalculixResult solveWithCalculix(const TetMesh& mesh, const CalculixLoadCase& load,
                                 const CalculixOptions& options = {});

}  // namespace breast_sim::core
