#pragma once
/// @file tet_quality.h
/// Element quality measures and the inverted-element check, on rest or deformed positions.

#include <vector>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// Quality of one tetrahedron.
struct TetQuality {
  double volume_m3 = 0.0;        ///< signed volume [m³]; ≤ 0 means inverted or degenerate
  double aspect_ratio = 0.0;     ///< circumradius / (3 · inradius): 1 for a regular tet, grows without bound
  double min_dihedral_deg = 0.0; ///< smallest of the six dihedral angles [degrees]; 70.53 for a regular tet
};

/// Quality of tetrahedron (a, b, c, d) (positions in [m]).
TetQuality tetQuality(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                      const Eigen::Vector3d& d);

/// Summary over a mesh.
struct QualityStats {
  int num_tets = 0;
  int num_inverted = 0;            ///< tets with signed volume ≤ 0 or NaN
  double total_volume_m3 = 0.0;
  double min_volume_m3 = 0.0, max_volume_m3 = 0.0;
  double max_aspect_ratio = 0.0, mean_aspect_ratio = 0.0;
  double min_dihedral_deg = 0.0, mean_min_dihedral_deg = 0.0;
  int num_dihedral_below_10deg = 0; ///< slivers
};

/// Quality summary of `tets` at `positions` (#N×3 [m]: rest or deformed positions).
QualityStats qualityStats(const Tets& tets, const Points& positions);

/// Indices of tetrahedra whose signed volume at `positions` is ≤ `min_volume_m3` (inverted or
/// collapsed) or not a number (a diverged solve). Runs in parallel; this is the per-step check of
/// the material update loop.
std::vector<int> invertedTets(const Tets& tets, const Points& positions, double min_volume_m3 = 0.0);

}  // namespace breast_sim::core
