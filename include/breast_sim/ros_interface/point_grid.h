#pragma once
/// @file point_grid.h
/// Exact nearest-neighbour queries for the tracker's clouds on a uniform grid of cubic cells.
///
/// Why not PCL's KdTreeFLANN: after the voxel grid a cloud lies close to a regular lattice (one point
/// per 3 mm voxel); many points then sit at equal distances from a query and from the tree's splitting
/// planes, so the kd-tree cannot prune and a 9-neighbour query costs ~4 µs (measured ~1 µs on random
/// points). A grid whose cell is about the queried distance answers the same queries by looking at the
/// 27 cells around the query (and further rings only when needed): the 9 neighbours of each of the
/// 3.7k points of a decimated 10k-point tracker cloud take 1.8 ms with selfNearestK (0.5 µs a point;
/// PCL's StatisticalOutlierRemoval spends 12-15 ms on the same cloud).
///
/// The points are stored in single precision and squared distances are computed in single precision
/// in the order x, y, z, exactly as PCL's clouds and FLANN's L2_Simple<float> do, so a query returns the
/// same squared distances PCL's kd-tree returned (which point is returned among exactly equidistant ones
/// may differ). Cells are found through an open-addressing hash of the occupied cells, so a few far-away
/// stray points cost nothing.

#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::ros_interface {

/// #×3 points [m] as single-precision vectors (what the grid and PCL search in).
std::vector<Eigen::Vector3f> toFloat(const core::Points& p);

/// Squared distance [m²] of two single-precision points, computed as FLANN's L2_Simple<float> does
/// (differences and their squares in float, summed x, y, z).
inline float squaredDistanceF(const Eigen::Vector3f& a, const Eigen::Vector3f& b) {
  const float dx = a.x() - b.x(), dy = a.y() - b.y(), dz = a.z() - b.z();
  float r = dx * dx;
  r += dy * dy;
  r += dz * dz;
  return r;
}

class PointGrid {
 public:
  /// Grid over `points_m` (#×3 [m], rounded to float) with cubic cells of edge `cell_m` [m]; non-finite
  /// points are kept in the numbering but never returned. Queries are fastest when cell_m is about the
  /// distance they reach (the k-th neighbour distance, the search radius).
  /// @throws std::invalid_argument when cell_m is not positive and finite.
  PointGrid(const core::Points& points_m, double cell_m);
  /// The same from single-precision points [m].
  PointGrid(std::vector<Eigen::Vector3f> points_m, double cell_m);

  /// Number of points (finite or not).
  size_t size() const { return points_.size(); }
  /// Point i [m] as stored (single precision).
  const Eigen::Vector3f& point(int i) const { return points_[static_cast<size_t>(i)]; }
  /// Cell edge [m] in use (the requested one, enlarged only when the cloud spans more than 2^21 cells).
  double cellSize() const { return cell_; }

  /// The min(k, #finite points) nearest points to `q` with squared distance ≤ max_d2 [m²]: their indices
  /// and squared distances [m²], sorted by increasing distance. Returns how many were found. Exact:
  /// the rings of cells around q are visited until no unvisited cell can hold a closer point.
  int nearestK(const Eigen::Vector3f& q, int k, int* index, float* d2,
               double max_d2 = std::numeric_limits<double>::infinity()) const;
  /// For every point, the squared distances [m²] of its min(k, #finite points) nearest points (itself
  /// included, so the first is 0), sorted increasing, into d2[i·k … i·k + found[i] − 1]; found[i] = 0
  /// for a non-finite point. Exactly nearestK(point(i), k, …) for each i, but the 27 cells around a
  /// cell are gathered once for all its points (a point needing farther rings falls back to nearestK).
  void selfNearestK(int k, float* d2, int* found) const;
  /// The nearest point with squared distance ≤ radius_m² to `q`: its index, or -1 if there is none;
  /// `d2` receives its squared distance [m²].
  int nearestWithin(const Eigen::Vector3f& q, double radius_m, float* d2) const;
  /// Whether some point has squared distance ≤ radius_m² to `q` (stops at the first one).
  bool anyWithin(const Eigen::Vector3f& q, double radius_m) const;

 private:
  struct Slot {
    uint64_t key;
    uint32_t begin, end;  ///< range in sorted_
  };
  void build(double cell_m);
  /// Cell coordinate of a coordinate along axis a (may be outside [0, extent_)).
  int64_t cellOf(float v, int a) const;
  const Slot* find(int64_t i, int64_t j, int64_t k) const;
  template <typename Visit>
  bool visitBox(const Eigen::Vector3f& q, double radius, Visit&& visit) const;

  std::vector<Eigen::Vector3f> points_;
  std::vector<Eigen::Vector3f> sorted_;       ///< points grouped by cell
  std::vector<int> sorted_index_;             ///< their indices in points_
  std::vector<Slot> table_;                   ///< open-addressing hash of the occupied cells
  uint64_t mask_ = 0;
  int shift_ = 64;
  double cell_ = 0, inv_cell_ = 0;
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();  ///< corner of cell (0, 0, 0) [m]
  Eigen::Matrix<int64_t, 3, 1> extent_ = Eigen::Matrix<int64_t, 3, 1>::Zero();  ///< occupied cells per axis
  int finite_ = 0;
};

}  // namespace breast_sim::ros_interface
