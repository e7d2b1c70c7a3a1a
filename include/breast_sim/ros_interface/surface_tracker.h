#pragma once
/// @file surface_tracker.h
/// One tracker frame, from a cloud in the model frame to an updated model, without ROS transport:
///   1. PCL voxel-grid decimation (the scanner delivers far more points than the skin has vertices),
///   2. statistical outlier removal (drapes, instruments, stray returns), PCL's rule,
///   3. the distance gate: points farther than max_point_distance_m from the model's skin (a hand, an
///      instrument), or nearest to its rim band (where the chest skin around the breast begins), are
///      left out,
///   4. rigid pre-alignment by point-to-point ICP (PCL's algorithm) against the reference skin (the
///      model's skin where tracking started, after a reset(): the precomputed state), which corrects
///      the tracker's registration without following the model it feeds; a correction that is too
///      large or fits poorly refuses the frame,
///   5. unseen skin (farther than hold_unseen_skin_m from the cloud) is added to the target at its
///      current position, so only what the scanner sees pulls the model,
///   6. ProneToSupinePipeline::setTarget (the distance field of the cloud) and a few Figure-2
///      iterations (iterate()) in the pipeline's tracking mode: the chest wall held where it is and
///      the skin pulled along its normal (ProneToSupinePipeline::setTrackingMode).
/// The node and the latency benchmark both call this, so the benchmark measures what the node does.
///
/// Steps 2–5 compute what PCL's StatisticalOutlierRemoval, IterativeClosestPoint and KdTreeFLANN
/// compute, but their neighbour searches use a hashed uniform grid (point_grid.h) instead of PCL's
/// FLANN kd-tree, which is slow on voxel-decimated (lattice-like) clouds. The PCL versions are kept
/// (`*Pcl`, TrackerOptions::pcl_reference) as the slow reference the tests and the benchmark compare
/// with.

#include <memory>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::ros_interface {

struct CloudFilterOptions {
  double voxel_leaf_m = 0.003;      ///< voxel-grid leaf size [m]; 0 = no decimation
  bool remove_outliers = true;      ///< statistical outlier removal
  int outlier_neighbours = 8;       ///< neighbours for the mean distance
  double outlier_stddev = 2.0;      ///< points whose mean distance is above mean + this × σ are removed
};

struct IcpOptions {
  bool enabled = true;
  int max_iterations = 10;
  int max_points = 500;                ///< the cloud is sub-sampled (evenly) to this many points for ICP
  double max_correspondence_m = 0.01;  ///< pairs farther apart are ignored [m]
  /// A larger correction refuses the cloud [m]. The correction is what the tracker's registration of
  /// the cloud to the model frame may be off by: the lesions, published in the model frame, are off by
  /// as much in the tracker's frame, so this bounds that error.
  double max_translation_m = 0.003;
  double max_rotation_deg = 2.0;       ///< ... and a larger rotation [deg] (2° turns a point 60 mm away by 2.1 mm)
  /// A correction whose RMS distance over the best 90 % of the pairs within max_correspondence_m
  /// (correspondences()) is above this is refused [m]. A cloud on the skin gives 0.8 mm at 20.8k
  /// elements and 1.6 mm at 2.2k (0.5 mm noise), bench_tracking_drift.
  double max_rms_m = 0.0025;
  /// ... and so is one that leaves fewer than this share of the points within max_correspondence_m
  /// of the reference [-] (a small RMS over a few pairs is no fit).
  double min_inlier_fraction = 0.5;
};

struct TrackerOptions {
  CloudFilterOptions filter;
  IcpOptions icp;
  int iterations_per_frame = 1;  ///< Figure-2 iterations per frame
  /// Relative residual at which the step's PCG solve stops during a tracking frame; 0 = the case's
  /// own (simulation.solver_relative_tolerance, 1e-2 in the shipped cases). Each frame is one step
  /// that starts from the last, so a looser solve here is corrected by the frames after it: on the
  /// phantom 0.3 takes 4 PCG iterations per frame where 0.1 takes 7 (20.8k and 48.8k elements), at
  /// the same skin residual and with the lesions of a 5-minute scan of the model's own skin within
  /// 0.732 mm (0.734 at 0.1, 0.738 at 0.5; docs/tracking.md, "Latency"). Restored after the frame,
  /// so a precomputation keeps its tolerance. Ignored by a direct solver.
  double solver_relative_tolerance = 0.3;
  /// A scanner sees only part of the skin. Skin vertices farther than this from every cloud point are
  /// unseen: their current positions are added to the target, so the morphing holds them where they
  /// are instead of pulling them onto the rim of the seen patch [m]. 0 = off (every skin vertex is
  /// pulled to the cloud).
  double hold_unseen_skin_m = 0.005;
  /// Cloud points farther than this from the skin where tracking started (vertices, edge midpoints
  /// and centroids, after the last ICP correction) are left out before ICP and morphing: a hand, an
  /// instrument [m]; 0 = keep every point. Points nearest to the skin's rim band (the triangles on
  /// its edge at the chest wall) are left out too: there the breast's skin and the chest's around it
  /// cannot be told apart.
  double max_point_distance_m = 0.02;
  int min_points = 50;           ///< fewer points after filtering and the gate: the frame is refused
  /// Outlier removal, ICP and the unseen-skin test with PCL's own classes (StatisticalOutlierRemoval,
  /// IterativeClosestPoint, KdTreeFLANN): the slow reference, for tests and benchmarks only.
  bool pcl_reference = false;
};

/// Timings [s] and outcome of one frame.
struct TrackResult {
  bool tracked = false;       ///< false: refused (see reason); the model was not touched
  std::string reason;
  size_t points_in = 0, points_decimated = 0, points_used = 0;
  size_t points_gated = 0;    ///< left out by the distance gate (max_point_distance_m)
  bool icp_applied = false;
  bool icp_refused = false;   ///< ICP ran and refused its correction, so the frame was refused
  double icp_rms_m = -1;      ///< RMS over the best 90 % of the pairs within the correspondence distance [m]
  double icp_inlier_fraction = -1;
  double icp_translation_m = 0, icp_rotation_deg = 0;
  std::string icp_note;       ///< why a correction was refused
  double filter_s = 0, icp_s = 0, field_s = 0, iterate_s = 0;
  int iterations = 0, reversals = 0;
  int skin_seen = 0, skin_held = 0;  ///< skin vertices near the cloud / held where they are
  /// The seen skin vertices' distances to the cloud before the step (their component along the skin
  /// normal, which the tracking pulls on) [m]: how well the model explained this cloud. −1 when
  /// none is seen.
  double seen_mean_m = -1, seen_p95_m = -1;
  core::IterationReport last;  ///< the last iteration
};

/// Voxel-grid decimation and outlier removal of a cloud [m].
core::Points filterCloud(const core::Points& cloud_m, const CloudFilterOptions& options);
/// The same with PCL's StatisticalOutlierRemoval (the slow reference).
core::Points filterCloudPcl(const core::Points& cloud_m, const CloudFilterOptions& options);

/// Indices (increasing) of the points of `cloud_m` (#×3 [m], used in single precision as PCL does) kept
/// by PCL's statistical outlier rule: a point's distance is the mean distance to its `neighbours`
/// nearest other points; points whose distance is above mean + stddev_mul × σ of all distances are
/// removed. Non-finite points are kept (distance 0, not counted in mean and σ), as PCL does. With
/// `neighbours` + 1 or fewer points every point is kept.
std::vector<int> statisticalInliers(const core::Points& cloud_m, int neighbours, double stddev_mul);
/// The same with PCL's StatisticalOutlierRemoval (the slow reference).
std::vector<int> statisticalInliersPcl(const core::Points& cloud_m, int neighbours, double stddev_mul);

/// ICP result: `transform` maps the cloud onto the reference (identity when refused).
struct IcpResult {
  bool applied = false;
  bool converged = false;
  Eigen::Isometry3d transform = Eigen::Isometry3d::Identity();
  double rms_m = -1;               ///< over the best 90 % of the pairs within max_correspondence_m [m]
  double inlier_fraction = -1;     ///< share of the points with such a pair
  std::string note;
};

/// How closely `cloud_m` lies on `reference_m` (both #×3 [m]): the share of the cloud points whose
/// nearest reference point is within gate_m [m] (squared float distances ≤ gate², as FLANN computes
/// them), and the RMS [m] over the kFitShare of those pairs that fit best (−1 when there is none):
/// trimmed, as trimmed ICP judges a partial overlap, so a rim of chest skin or a stray patch the
/// gate kept does not decide the fit; a misregistration moves every pair.
constexpr double kFitShare = 0.9;
struct Correspondences {
  double inlier_fraction = 0.0;
  double rms_m = -1;
};
Correspondences correspondences(const core::Points& cloud_m, const core::Points& reference_m, double gate_m);
/// The same from PCL's getFitnessScore(gate²) (which compares squared distances with its argument)
/// and a KdTreeFLANN count (the slow reference).
Correspondences correspondencesPcl(const core::Points& cloud_m, const core::Points& reference_m, double gate_m);

/// The tracker's distance gate: indices (increasing) of the points of `cloud_m` whose nearest point of
/// `skin_m` (squared float distances, as PCL computes them) is within `gate_m` [m] and not in the rim
/// band (`rim[i]` != 0: the skin's edge, where it meets the chest wall, and the triangles on it). There
/// a scan cannot tell the breast's skin from the chest's around it, which would pull the rim outward
/// and lift ICP's residual; the band's skin is held as unseen.
std::vector<int> pointsNear(const core::Points& cloud_m, const core::Points& skin_m, const std::vector<char>& rim,
                            double gate_m);
/// The same with PCL's KdTreeFLANN (the slow reference).
std::vector<int> pointsNearPcl(const core::Points& cloud_m, const core::Points& skin_m, const std::vector<char>& rim,
                               double gate_m);

/// A fixed skin (the reference tracking started from) indexed once for the per-frame queries of the
/// gate (pointsNear), the fit (correspondences) and ICP (rigidAlign), which the free functions
/// answer by building one of these for their call. Copies share the index.
class SkinIndex {
 public:
  SkinIndex() = default;
  /// @param skin_m #×3 [m]; @param rim per point, in the rim band; @param gate_m the distance gate [m]
  SkinIndex(const core::Points& skin_m, std::vector<char> rim, double gate_m);
  bool empty() const { return !impl_; }
  const core::Points& points() const;
  const std::vector<char>& rim() const;
  std::vector<int> near(const core::Points& cloud_m) const;                  ///< pointsNear
  Correspondences fit(const core::Points& cloud_m, double gate_m) const;     ///< correspondences
  IcpResult align(const core::Points& cloud_m, const Eigen::Isometry3d& guess, const IcpOptions& options) const;

 private:
  struct Impl;
  std::shared_ptr<const Impl> impl_;
};

/// Rigid alignment of `cloud_m` onto `reference_m` (both #×3 [m]) starting from `guess`: PCL's
/// IterativeClosestPoint (point-to-point, pairs within max_correspondence_m, PCL's default convergence
/// criteria with 1e-10 transformation and 1e-12 fitness epsilons), its nearest-neighbour queries
/// answered by a PointGrid (point_grid.h) instead of FLANN — the same pairs, so the same transform.
/// The fit is judged in metres by correspondences() of the aligned cloud with max_correspondence_m
/// as the gate. The correction is applied when ICP converged, the RMS is at most max_rms_m, the
/// inlier share at least min_inlier_fraction, and it is within max_translation_m / max_rotation_deg.
IcpResult rigidAlign(const core::Points& cloud_m, const core::Points& reference_m, const Eigen::Isometry3d& guess,
                     const IcpOptions& options);
/// The same with PCL's IterativeClosestPoint (the slow reference).
IcpResult rigidAlignPcl(const core::Points& cloud_m, const core::Points& reference_m, const Eigen::Isometry3d& guess,
                        const IcpOptions& options);

class SurfaceTracker {
 public:
  explicit SurfaceTracker(const TrackerOptions& options = {}) : options_(options) {}
  /// One frame: `cloud_m` in the model frame [m]. A refused frame (too few points, ICP refused)
  /// leaves the model untouched. Throws only what the pipeline throws.
  TrackResult track(core::ProneToSupinePipeline& pipeline, const core::Points& cloud_m);
  /// Forgets the last ICP correction and the reference skin (a new model, a precomputation, a loaded
  /// state or a reset): the next frame's model skin becomes the reference ICP aligns to.
  void reset() {
    guess_ = Eigen::Isometry3d::Identity();
    reference_ = SkinIndex();
  }
  const TrackerOptions& options() const { return options_; }
  void setOptions(const TrackerOptions& o) { options_ = o; }

 private:
  TrackerOptions options_;
  Eigen::Isometry3d guess_ = Eigen::Isometry3d::Identity();
  /// The skin where tracking started (vertices, edge midpoints, face centroids [m]) with its rim band.
  SkinIndex reference_;
  std::vector<char> held_;       ///< per mesh node, for the seen residual (kept buffer)
};

}  // namespace breast_sim::ros_interface
