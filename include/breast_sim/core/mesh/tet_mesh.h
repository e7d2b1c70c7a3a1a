#pragma once
/// @file tet_mesh.h
/// The tetrahedral simulation mesh: nodes [m], linear tetrahedra, region labels, named node sets and
/// the boundary surface.

#include <map>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace breast_sim::core {

/// #N×3 point coordinates [m], one row per point (row-major, so the memory is x0 y0 z0 x1 …).
using Points = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
/// #T×4 node indices of linear tetrahedra.
using Tets = Eigen::Matrix<int, Eigen::Dynamic, 4, Eigen::RowMajor>;
/// #F×3 node indices of triangles.
using Triangles = Eigen::Matrix<int, Eigen::Dynamic, 3, Eigen::RowMajor>;

/// Standard node-set names used across the project.
namespace node_sets {
inline constexpr const char* kChestWall = "chest_wall";  ///< tissue nodes on the chest-wall interface
inline constexpr const char* kSkin = "skin";              ///< tissue nodes on the boundary facing air
inline constexpr const char* kNipple = "nipple";          ///< node(s) nearest each nipple point
}  // namespace node_sets

/// Boundary of a tetrahedral mesh: the faces that belong to exactly one tetrahedron.
struct BoundarySurface {
  /// #F×3 node indices; the right-hand rule (b−a)×(c−a) gives the outward normal.
  Triangles triangles;
  /// #F index of the tetrahedron each face belongs to.
  std::vector<int> owner_tet;
  /// #F×3 unit outward normals (at the rest positions).
  Points normals;
  /// Sorted, unique node indices on the boundary.
  std::vector<int> nodes;
};

/// A linear tetrahedral mesh in its rest (reference) configuration.
///
/// \note Orientation: every tetrahedron (a, b, c, d) is stored with positive signed volume
/// (b−a)·((c−a)×(d−a)) / 6 > 0. The constructor swaps c and d of negatively oriented input.
/// \note Region labels are free integers (by convention the tissue class of the label image, see
/// model/label_groups.h); they default to 0.
class TetMesh {
 public:
  TetMesh() = default;

  /// Builds and validates a mesh.
  /// @param nodes_m  #N×3 rest positions [m]
  /// @param tets     #T×4 node indices in [0, N)
  /// @param region_labels  #T labels, or empty for all 0
  /// @throws std::invalid_argument naming the offending element or node when an index is out of
  ///         range, a coordinate is not finite, a tetrahedron repeats a node or has zero volume, or
  ///         elements overlap (a face shared by more than two tetrahedra or twice from one side).
  TetMesh(Points nodes_m, Tets tets, std::vector<int> region_labels = {});

  int numNodes() const { return static_cast<int>(nodes_.rows()); }
  int numTets() const { return static_cast<int>(tets_.rows()); }

  /// #N×3 rest positions [m].
  const Points& nodes() const { return nodes_; }
  /// #T×4 positively oriented tetrahedra.
  const Tets& tets() const { return tets_; }
  /// #T region labels.
  const std::vector<int>& regionLabels() const { return region_labels_; }

  /// Adds or replaces a named node set.
  /// @throws std::invalid_argument if a node index is out of range or the name is empty.
  void setNodeSet(const std::string& name, std::vector<int> node_indices);
  bool hasNodeSet(const std::string& name) const { return node_sets_.count(name) != 0; }
  /// @throws std::out_of_range naming the set, listing those present and suggesting
  ///         nearestNodeSetName(name) when there is one. Names match exactly (case-sensitive).
  const std::vector<int>& nodeSet(const std::string& name) const;
  /// The node-set name a misspelt `name` most likely meant, for error messages: a set whose name
  /// equals `name` ignoring case, else the one with the fewest edits (insertions, deletions,
  /// substitutions, transpositions of neighbours; compared ignoring case) if at most 2 (1 for names
  /// of up to 3 characters); ties go to the first in nodeSets() order. `name` itself when it is a set;
  /// "" when no set is near. Never used to look a set up: of "Skin" and "skin" either may be meant.
  std::string nearestNodeSetName(const std::string& name) const;
  /// The node-set names, comma-separated in alphabetical order ("" when there are none).
  std::string nodeSetNames() const;
  /// For an error about the missing set `name`: " (it has: a, b); did you mean 'x'?" (the suggestion
  /// only when nearestNodeSetName finds one), or " (it has none)".
  std::string nodeSetHint(const std::string& name) const;
  const std::map<std::string, std::vector<int>>& nodeSets() const { return node_sets_; }

  /// Boundary faces with outward normals (computed once at construction).
  const BoundarySurface& boundary() const { return boundary_; }

  /// Rest volume of each tetrahedron [m³].
  Eigen::VectorXd tetVolumes() const;
  /// Total rest volume [m³] (the sum of tetVolumes(), computed once at construction: the rest
  /// shape never changes, and per-step volume measures divide by it).
  double volume() const { return volume_m3_; }
  /// Axis-aligned bounds of the rest positions [m].
  Eigen::Vector3d boundsMin() const;
  Eigen::Vector3d boundsMax() const;

  /// Nodes attached to at least one tetrahedron, as a mask of length #N.
  std::vector<bool> usedNodes() const;

 private:
  Points nodes_;
  Tets tets_;
  std::vector<int> region_labels_;
  std::map<std::string, std::vector<int>> node_sets_;
  BoundarySurface boundary_;
  double volume_m3_ = 0.0;
};

/// Signed volume (b−a)·((c−a)×(d−a)) / 6 of a tetrahedron [m³]; positive when (a, b, c, d) is
/// positively oriented.
double signedTetVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                       const Eigen::Vector3d& d);

/// Boundary faces of a tetrahedral connectivity, oriented outward given positively oriented tets.
/// @param positions  #N×3 positions used for the normals [m]
/// @throws std::invalid_argument naming the tetrahedra when a face is shared by more than two of
///         them or by two from the same side (overlapping or duplicate elements).
BoundarySurface extractBoundary(const Tets& tets, const Points& positions);

/// Whether a triangle surface is closed and edge-manifold: every edge is shared by exactly two
/// triangles that traverse it in opposite directions.
bool isClosedManifold(const Triangles& triangles);

/// The same mesh with nodes renumbered along a Morton (Z-order) curve of their positions and
/// tetrahedra along that of their centroids; node sets and region labels follow. Neighbouring nodes
/// get nearby numbers, so the rows a sparse kernel touches together share cache lines: the Galerkin
/// product, smoothing and assembly on a mesher's near-random numbering are bound by memory latency.
/// @param old_to_new  when not null, set to #N: the new index of each old node
TetMesh mortonOrdered(const TetMesh& mesh, std::vector<int>* old_to_new = nullptr);

}  // namespace breast_sim::core
