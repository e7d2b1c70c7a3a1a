// One tracker frame: decimation (PCL voxel grid), outlier removal and ICP pre-alignment with PCL's
// rules on a grid neighbour search, then the pipeline's target and Figure-2 iterations (see
// surface_tracker.h). The PCL versions of outlier removal and ICP are kept as the slow reference.
#include "breast_sim/ros_interface/surface_tracker.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <memory>
#include <sstream>

#include <Eigen/Geometry>
#include <pcl/filters/statistical_outlier_removal.h>
#include <pcl/filters/voxel_grid.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/registration/icp.h>
#include <pcl/search/kdtree.h>

#include "breast_sim/core/thread_budget.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/point_grid.h"

namespace breast_sim::ros_interface {

namespace {

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

pcl::PointCloud<pcl::PointXYZ>::Ptr toPcl(const core::Points& p) {
  pcl::PointCloud<pcl::PointXYZ>::Ptr c(new pcl::PointCloud<pcl::PointXYZ>);
  c->resize(static_cast<size_t>(p.rows()));
  for (Eigen::Index i = 0; i < p.rows(); ++i)
    (*c)[static_cast<size_t>(i)] = pcl::PointXYZ(static_cast<float>(p(i, 0)), static_cast<float>(p(i, 1)),
                                                 static_cast<float>(p(i, 2)));
  c->width = static_cast<uint32_t>(c->size());
  c->height = 1;
  c->is_dense = true;
  return c;
}

core::Points fromPcl(const pcl::PointCloud<pcl::PointXYZ>& c) {
  core::Points p(static_cast<Eigen::Index>(c.size()), 3);
  for (size_t i = 0; i < c.size(); ++i) p.row(static_cast<Eigen::Index>(i)) << c[i].x, c[i].y, c[i].z;
  return p;
}

std::vector<Eigen::Vector3f> toFloat(const pcl::PointCloud<pcl::PointXYZ>& c) {
  std::vector<Eigen::Vector3f> p(c.size());
  for (size_t i = 0; i < c.size(); ++i) p[i] = Eigen::Vector3f(c[i].x, c[i].y, c[i].z);
  return p;
}
using ros_interface::toFloat;  // the core::Points overload (point_grid.h)

/// PCL's voxel grid of a cloud [m] (`leaf_m` > 0).
pcl::PointCloud<pcl::PointXYZ>::Ptr voxelGrid(const pcl::PointCloud<pcl::PointXYZ>::Ptr& cloud, double leaf_m) {
  pcl::VoxelGrid<pcl::PointXYZ> grid;
  grid.setInputCloud(cloud);
  const float leaf = static_cast<float>(leaf_m);
  grid.setLeafSize(leaf, leaf, leaf);
  pcl::PointCloud<pcl::PointXYZ>::Ptr out(new pcl::PointCloud<pcl::PointXYZ>);
  grid.filter(*out);
  return out;
}

/// Grid cell for k-neighbour queries on `p`: twice the median distance to the k-th neighbour of up to
/// 16 evenly spaced sample points (brute force), so the 27 cells around a point nearly always hold its
/// k neighbours (a smaller cell needs farther rings, a larger one examines more points; 2× measured
/// fastest on the tracker's clouds).
double neighbourCell(const std::vector<Eigen::Vector3f>& p, int k) {
  const size_t n = p.size();
  const size_t samples = std::min<size_t>(16, n);
  std::vector<double> kth;
  std::vector<float> d;
  for (size_t s = 0; s < samples; ++s) {
    const Eigen::Vector3f& q = p[s * n / samples];
    if (!q.allFinite()) continue;
    d.clear();
    for (const auto& x : p)
      if (x.allFinite()) d.push_back(squaredDistanceF(q, x));
    if (d.size() <= static_cast<size_t>(k)) continue;
    std::nth_element(d.begin(), d.begin() + k, d.end());
    kth.push_back(std::sqrt(static_cast<double>(d[static_cast<size_t>(k)])));
  }
  double cell = 0;
  if (!kth.empty()) {
    std::nth_element(kth.begin(), kth.begin() + kth.size() / 2, kth.end());
    cell = 2 * kth[kth.size() / 2];
  }
  return cell > 0 && std::isfinite(cell) ? cell : 1e-3;
}

/// PCL's statistical outlier rule (StatisticalOutlierRemoval::applyFilterIndices, PCL 1.13) with the
/// same arithmetic: float squared distances, sorted, square roots summed in double, the mean distance
/// rounded to float; mean and σ in double over the valid points; `p` has more than k + 1 points.
std::vector<int> statisticalInliersF(const std::vector<Eigen::Vector3f>& p, int k, double stddev_mul) {
  const size_t n = p.size();
  std::vector<int> kept;
  if (k < 1 || n <= static_cast<size_t>(k) + 1) {
    kept.resize(n);
    for (size_t i = 0; i < n; ++i) kept[i] = static_cast<int>(i);
    return kept;
  }
  const PointGrid grid(p, neighbourCell(p, k));
  // k + 1: each point is among its own neighbours (distance 0); the nearest one is skipped.
  const size_t k1 = static_cast<size_t>(k) + 1;
  std::vector<float> d2(n * k1);
  std::vector<int> found(n);
  grid.selfNearestK(k + 1, d2.data(), found.data());
  std::vector<float> distances(n, 0.0f);
  int valid = 0;
  for (size_t i = 0; i < n; ++i) {
    // Fewer than k + 1: a non-finite point (or fewer than k + 1 finite points); PCL: distance 0.
    if (found[i] < k + 1) continue;
    double sum = 0.0;
    for (size_t j = 1; j < k1; ++j) sum += std::sqrt(static_cast<double>(d2[i * k1 + j]));
    distances[i] = static_cast<float>(sum / k);
    ++valid;
  }
  double sum = 0, sq_sum = 0;
  for (const float d : distances) {
    sum += d;
    sq_sum += d * d;  // float product, as PCL
  }
  const double mean = sum / static_cast<double>(valid);
  const double variance = (sq_sum - sum * sum / static_cast<double>(valid)) / (static_cast<double>(valid) - 1);
  const double threshold = mean + stddev_mul * std::sqrt(variance);
  kept.reserve(n);
  for (size_t i = 0; i < n; ++i)
    if (!(distances[i] > threshold)) kept.push_back(static_cast<int>(i));
  return kept;
}

}  // namespace

std::vector<int> statisticalInliers(const core::Points& cloud_m, int neighbours, double stddev_mul) {
  return statisticalInliersF(toFloat(cloud_m), neighbours, stddev_mul);
}

std::vector<int> statisticalInliersPcl(const core::Points& cloud_m, int neighbours, double stddev_mul) {
  auto cloud = toPcl(cloud_m);
  pcl::Indices kept;
  if (neighbours < 1 || cloud->size() <= static_cast<size_t>(neighbours) + 1) {
    kept.resize(cloud->size());
    for (size_t i = 0; i < kept.size(); ++i) kept[i] = static_cast<int>(i);
  } else {
    pcl::StatisticalOutlierRemoval<pcl::PointXYZ> sor;
    sor.setInputCloud(cloud);
    sor.setMeanK(neighbours);
    sor.setStddevMulThresh(stddev_mul);
    sor.filter(kept);
  }
  return std::vector<int>(kept.begin(), kept.end());
}

core::Points filterCloud(const core::Points& cloud_m, const CloudFilterOptions& options) {
  if (cloud_m.rows() == 0) return cloud_m;
  auto cloud = toPcl(cloud_m);
  if (options.voxel_leaf_m > 0) cloud = voxelGrid(cloud, options.voxel_leaf_m);
  if (options.remove_outliers && cloud->size() > static_cast<size_t>(options.outlier_neighbours) + 1) {
    const std::vector<Eigen::Vector3f> p = toFloat(*cloud);
    const std::vector<int> kept = statisticalInliersF(p, options.outlier_neighbours, options.outlier_stddev);
    core::Points out(static_cast<Eigen::Index>(kept.size()), 3);
    for (size_t i = 0; i < kept.size(); ++i) out.row(static_cast<Eigen::Index>(i)) = p[static_cast<size_t>(kept[i])].cast<double>();
    return out;
  }
  return fromPcl(*cloud);
}

core::Points filterCloudPcl(const core::Points& cloud_m, const CloudFilterOptions& options) {
  if (cloud_m.rows() == 0) return cloud_m;
  auto cloud = toPcl(cloud_m);
  if (options.voxel_leaf_m > 0) cloud = voxelGrid(cloud, options.voxel_leaf_m);
  if (options.remove_outliers && cloud->size() > static_cast<size_t>(options.outlier_neighbours) + 1) {
    pcl::StatisticalOutlierRemoval<pcl::PointXYZ> sor;
    sor.setInputCloud(cloud);
    sor.setMeanK(options.outlier_neighbours);
    sor.setStddevMulThresh(options.outlier_stddev);
    pcl::PointCloud<pcl::PointXYZ>::Ptr out(new pcl::PointCloud<pcl::PointXYZ>);
    sor.filter(*out);
    cloud = out;
  }
  return fromPcl(*cloud);
}

namespace {

/// The acceptance rules of a finished ICP run: `t` maps the cloud onto the reference; `fit` is the
/// aligned cloud's correspondences with the reference.
IcpResult judge(bool converged, const Correspondences& fit, const Eigen::Isometry3d& t, const IcpOptions& options) {
  IcpResult r;
  r.converged = converged;
  r.rms_m = fit.rms_m;
  r.inlier_fraction = fit.inlier_fraction;
  const double translation = t.translation().norm();
  const double rotation = Eigen::AngleAxisd(t.linear()).angle() * 180.0 / M_PI;
  r.transform = t;
  std::ostringstream note;
  note.setf(std::ios::fixed);
  note.precision(2);
  if (!r.converged) {
    note << "ICP did not converge";
  } else if (!(fit.inlier_fraction >= options.min_inlier_fraction)) {
    note << "ICP left " << 100 * fit.inlier_fraction << " % of the points within " << 1e3 * options.max_correspondence_m
         << " mm of the skin, fewer than " << 100 * options.min_inlier_fraction << " %";
  } else if (!(r.rms_m <= options.max_rms_m)) {
    note << "ICP residual " << 1e3 * r.rms_m << " mm RMS above " << 1e3 * options.max_rms_m << " mm";
  } else if (translation > options.max_translation_m || rotation > options.max_rotation_deg) {
    note << "ICP correction " << 1e3 * translation << " mm / " << rotation << " deg beyond the limits ("
         << 1e3 * options.max_translation_m << " mm / " << options.max_rotation_deg << " deg)";
  } else {
    r.applied = true;
    return r;
  }
  r.note = note.str();
  r.transform = Eigen::Isometry3d::Identity();
  return r;
}

/// PCL's search interface for ICP (a pcl::search::KdTree, which is what Registration accepts as the
/// target's search method) answered by a PointGrid instead of FLANN. ICP asks only nearestKSearch with
/// k = 1 (correspondences and fitness score); the squared distances are FLANN's, so PCL's ICP runs
/// exactly as with its own tree (up to which of two exactly equidistant points is returned).
class GridSearch : public pcl::search::KdTree<pcl::PointXYZ> {
 public:
  using Ptr = pcl::shared_ptr<GridSearch>;
  /// `cell_m`: the grid cell [m], about the distance of the queries (the correspondence distance).
  explicit GridSearch(double cell_m) : cell_(cell_m) {}

  void setInputCloud(const PointCloudConstPtr& cloud, const IndicesConstPtr& indices = IndicesConstPtr()) override {
    input_ = cloud;
    indices_ = indices;
    std::vector<Eigen::Vector3f> p;
    map_.clear();
    if (indices) {
      for (const auto i : *indices) {
        p.emplace_back((*cloud)[static_cast<size_t>(i)].x, (*cloud)[static_cast<size_t>(i)].y, (*cloud)[static_cast<size_t>(i)].z);
        map_.push_back(static_cast<int>(i));
      }
    } else {
      p = toFloat(*cloud);
    }
    grid_ = std::make_unique<PointGrid>(std::move(p), cell_);
  }

  int nearestKSearch(const pcl::PointXYZ& point, int k, pcl::Indices& k_indices,
                     std::vector<float>& k_sqr_distances) const override {
    return search(point, k, std::numeric_limits<double>::infinity(), k_indices, k_sqr_distances);
  }

  /// Points whose squared distance is below (float) radius² (FLANN's rule), nearest first, at most
  /// max_nn (0 = all). Not used by ICP; answered so that no FLANN call on an empty tree is inherited.
  int radiusSearch(const pcl::PointXYZ& point, double radius, pcl::Indices& k_indices,
                   std::vector<float>& k_sqr_distances, unsigned int max_nn = 0) const override {
    const int k = max_nn > 0 ? static_cast<int>(max_nn) : static_cast<int>(grid_ ? grid_->size() : 0);
    const double below = std::nextafter(static_cast<double>(static_cast<float>(radius * radius)), 0.0);
    return search(point, k, below, k_indices, k_sqr_distances);
  }

 private:
  int search(const pcl::PointXYZ& point, int k, double max_d2, pcl::Indices& k_indices,
             std::vector<float>& k_sqr_distances) const {
    if (!grid_ || k <= 0) {
      k_indices.clear();
      k_sqr_distances.clear();
      return 0;
    }
    k = std::min(k, static_cast<int>(grid_->size()));
    std::vector<int> index(static_cast<size_t>(k));
    k_sqr_distances.resize(static_cast<size_t>(k));
    const int n = grid_->nearestK(Eigen::Vector3f(point.x, point.y, point.z), k, index.data(), k_sqr_distances.data(), max_d2);
    k_sqr_distances.resize(static_cast<size_t>(n));
    k_indices.resize(static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) k_indices[static_cast<size_t>(i)] = map_.empty() ? index[static_cast<size_t>(i)] : map_[static_cast<size_t>(index[static_cast<size_t>(i)])];
    return n;
  }

  double cell_;
  std::unique_ptr<PointGrid> grid_;
  std::vector<int> map_;  ///< grid index → cloud index when indices were given
};

/// PCL's ICP onto `target` with `search` as its target search (null: PCL's own kd-tree), judged by `fit`.
template <typename Fit>
IcpResult pclIcp(const core::Points& cloud_m, const pcl::PointCloud<pcl::PointXYZ>::Ptr& target,
                 const pcl::search::KdTree<pcl::PointXYZ>::Ptr& search, const Eigen::Isometry3d& guess,
                 const IcpOptions& options, Fit&& fit) {
  if (cloud_m.rows() < 10 || target->size() < 10) {
    IcpResult r;
    r.note = "too few points for ICP";
    return r;
  }
  pcl::IterativeClosestPoint<pcl::PointXYZ, pcl::PointXYZ> icp;
  icp.setInputSource(toPcl(cloud_m));
  icp.setInputTarget(target);
  if (search) icp.setSearchMethodTarget(search, true);  // already built on `target`
  icp.setMaximumIterations(options.max_iterations);
  icp.setMaxCorrespondenceDistance(options.max_correspondence_m);
  icp.setTransformationEpsilon(1e-10);
  icp.setEuclideanFitnessEpsilon(1e-12);
  pcl::PointCloud<pcl::PointXYZ> aligned;
  icp.align(aligned, guess.matrix().cast<float>());
  const Eigen::Isometry3d t(icp.getFinalTransformation().cast<double>());
  return judge(icp.hasConverged(), fit(transformPoints(t, cloud_m), options.max_correspondence_m), t, options);
}

}  // namespace

namespace {

/// Inlier share and trimmed RMS from the squared distances [m²] of the pairs within the gate.
Correspondences trimmedFit(std::vector<float> d2s, Eigen::Index points) {
  Correspondences c;
  c.inlier_fraction = points > 0 ? static_cast<double>(d2s.size()) / static_cast<double>(points) : 0.0;
  if (d2s.empty()) return c;
  std::sort(d2s.begin(), d2s.end());
  const size_t keep = std::max<size_t>(1, static_cast<size_t>(std::ceil(kFitShare * static_cast<double>(d2s.size()))));
  double sum = 0;
  for (size_t i = 0; i < keep; ++i) sum += d2s[i];
  c.rms_m = std::sqrt(sum / static_cast<double>(keep));
  return c;
}

}  // namespace

struct SkinIndex::Impl {
  core::Points points;
  std::vector<char> rim;
  double gate_m = 0;
  std::unique_ptr<PointGrid> fine;    // cells of about the points' spacing: the nearest in the first rings
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud;
  GridSearch::Ptr search;             // ICP's target search on `cloud`, built once
};

SkinIndex::SkinIndex(const core::Points& skin_m, std::vector<char> rim, double gate_m) {
  if (rim.size() != static_cast<size_t>(skin_m.rows()))
    throw std::invalid_argument("SkinIndex: " + std::to_string(rim.size()) + " rim flags for " +
                                std::to_string(skin_m.rows()) + " points");
  auto impl = std::make_shared<Impl>();
  impl->points = skin_m;
  impl->rim = std::move(rim);
  impl->gate_m = gate_m;
  std::vector<Eigen::Vector3f> p = toFloat(skin_m);
  const double cell = neighbourCell(p, 1);
  impl->fine = std::make_unique<PointGrid>(std::move(p), cell);
  impl->cloud = toPcl(skin_m);
  impl->search.reset(new GridSearch(cell));
  impl->search->setInputCloud(impl->cloud);
  impl_ = std::move(impl);
}

const core::Points& SkinIndex::points() const {
  static const core::Points none(0, 3);
  return impl_ ? impl_->points : none;
}

const std::vector<char>& SkinIndex::rim() const {
  static const std::vector<char> none;
  return impl_ ? impl_->rim : none;
}

namespace {

/// Each cloud point's nearest point of `grid` within squared distance `max_d2` (float coordinates),
/// point by point in parallel: `index` −1 where there is none. Each point's answer is its own, so the
/// result does not depend on the thread count.
void nearestWithin(const PointGrid& grid, const core::Points& cloud_m, double max_d2, std::vector<int>& index,
                   std::vector<float>& d2) {
  const long n_points = static_cast<long>(cloud_m.rows());
  index.assign(static_cast<size_t>(n_points), -1);
  d2.assign(static_cast<size_t>(n_points), 0.0f);
#pragma omp parallel for schedule(static) if (n_points > 2048)
  for (long i = 0; i < n_points; ++i) {
    const Eigen::Vector3f q(static_cast<float>(cloud_m(i, 0)), static_cast<float>(cloud_m(i, 1)), static_cast<float>(cloud_m(i, 2)));
    int n = -1;
    float d = 0;
    if (grid.nearestK(q, 1, &n, &d, max_d2) > 0) index[static_cast<size_t>(i)] = n, d2[static_cast<size_t>(i)] = d;
  }
}

}  // namespace

std::vector<int> SkinIndex::near(const core::Points& cloud_m) const {
  std::vector<int> kept;
  if (!impl_ || impl_->points.rows() == 0 || !(impl_->gate_m > 0)) return kept;
  std::vector<int> nearest;
  std::vector<float> d2;
  const double gate2 = static_cast<double>(static_cast<float>(impl_->gate_m * impl_->gate_m));
  nearestWithin(*impl_->fine, cloud_m, gate2, nearest, d2);
  for (size_t i = 0; i < nearest.size(); ++i)
    if (nearest[i] >= 0 && !impl_->rim[static_cast<size_t>(nearest[i])]) kept.push_back(static_cast<int>(i));
  return kept;
}

Correspondences SkinIndex::fit(const core::Points& cloud_m, double gate_m) const {
  if (!impl_ || cloud_m.rows() == 0 || impl_->points.rows() == 0 || !(gate_m > 0)) return Correspondences{};
  std::vector<int> nearest;
  std::vector<float> d2;
  nearestWithin(*impl_->fine, cloud_m, static_cast<double>(static_cast<float>(gate_m * gate_m)), nearest, d2);
  std::vector<float> d2s;
  d2s.reserve(d2.size());
  for (size_t i = 0; i < nearest.size(); ++i)
    if (nearest[i] >= 0) d2s.push_back(d2[i]);
  return trimmedFit(std::move(d2s), cloud_m.rows());
}

IcpResult SkinIndex::align(const core::Points& cloud_m, const Eigen::Isometry3d& guess, const IcpOptions& options) const {
  if (!impl_) {
    IcpResult r;
    r.note = "too few points for ICP";
    return r;
  }
  return pclIcp(cloud_m, impl_->cloud, impl_->search, guess, options,
                [this](const core::Points& moved, double gate) { return fit(moved, gate); });
}

Correspondences correspondences(const core::Points& cloud_m, const core::Points& reference_m, double gate_m) {
  if (cloud_m.rows() == 0 || reference_m.rows() == 0 || !(gate_m > 0)) return Correspondences{};
  return SkinIndex(reference_m, std::vector<char>(static_cast<size_t>(reference_m.rows()), 0), gate_m).fit(cloud_m, gate_m);
}

Correspondences correspondencesPcl(const core::Points& cloud_m, const core::Points& reference_m, double gate_m) {
  Correspondences c;
  if (cloud_m.rows() == 0 || reference_m.rows() == 0 || !(gate_m > 0)) return c;
  pcl::KdTreeFLANN<pcl::PointXYZ> tree;
  tree.setInputCloud(toPcl(reference_m));
  std::vector<int> index(1);
  std::vector<float> d2(1);
  const float gate2 = static_cast<float>(gate_m * gate_m);
  std::vector<float> d2s;
  for (Eigen::Index i = 0; i < cloud_m.rows(); ++i) {
    const pcl::PointXYZ p(static_cast<float>(cloud_m(i, 0)), static_cast<float>(cloud_m(i, 1)), static_cast<float>(cloud_m(i, 2)));
    if (tree.nearestKSearch(p, 1, index, d2) > 0 && d2[0] <= gate2) d2s.push_back(d2[0]);
  }
  return trimmedFit(std::move(d2s), cloud_m.rows());
}

std::vector<int> pointsNear(const core::Points& cloud_m, const core::Points& skin_m, const std::vector<char>& rim,
                            double gate_m) {
  if (skin_m.rows() == 0 || !(gate_m > 0)) return {};
  return SkinIndex(skin_m, rim, gate_m).near(cloud_m);
}

std::vector<int> pointsNearPcl(const core::Points& cloud_m, const core::Points& skin_m, const std::vector<char>& rim,
                               double gate_m) {
  std::vector<int> kept;
  if (skin_m.rows() == 0 || !(gate_m > 0)) return kept;
  pcl::KdTreeFLANN<pcl::PointXYZ> tree;
  tree.setInputCloud(toPcl(skin_m));
  std::vector<int> index(1);
  std::vector<float> d2(1);
  const float gate2 = static_cast<float>(gate_m * gate_m);
  for (Eigen::Index i = 0; i < cloud_m.rows(); ++i) {
    const pcl::PointXYZ p(static_cast<float>(cloud_m(i, 0)), static_cast<float>(cloud_m(i, 1)), static_cast<float>(cloud_m(i, 2)));
    if (tree.nearestKSearch(p, 1, index, d2) < 1 || d2[0] > gate2) continue;
    if (rim[static_cast<size_t>(index[0])]) continue;
    kept.push_back(static_cast<int>(i));
  }
  return kept;
}

IcpResult rigidAlign(const core::Points& cloud_m, const core::Points& reference_m, const Eigen::Isometry3d& guess,
                     const IcpOptions& options) {
  if (reference_m.rows() < 10) {
    IcpResult r;
    r.note = "too few points for ICP";
    return r;
  }
  // The grid's cell: the correspondence distance at most (the old choice), the points' spacing at least.
  return SkinIndex(reference_m, std::vector<char>(static_cast<size_t>(reference_m.rows()), 0), options.max_correspondence_m)
      .align(cloud_m, guess, options);
}

IcpResult rigidAlignPcl(const core::Points& cloud_m, const core::Points& reference_m, const Eigen::Isometry3d& guess,
                        const IcpOptions& options) {
  return pclIcp(cloud_m, toPcl(reference_m), nullptr, guess, options,
                [&reference_m](const core::Points& moved, double gate) { return correspondencesPcl(moved, reference_m, gate); });
}

namespace {

/// The skin at positions `x_m` as ICP's reference and the gate's: its vertices, face centroids and
/// edge midpoints (ICP pairs a cloud point with its nearest sample, so the pairs' distances are those
/// to the surface within a quarter of an edge instead of half an edge), each sample once, with the
/// rim band flagged: the rim nodes (of skin edges only one skin triangle has) and the centroids and
/// midpoints of the triangles that touch one.
SkinIndex referenceSkin(const core::TetMesh& mesh, const std::vector<int>& skin, const core::Points& x_m, double gate_m) {
  const core::Triangles tris = core::skinTriangles(mesh, skin);
  struct Edge {
    int triangles = 0;
    char band = 0;
  };
  std::map<std::pair<int, int>, Edge> edges;
  auto edge = [&edges](int a, int b) -> Edge& { return edges[{std::min(a, b), std::max(a, b)}]; };
  for (Eigen::Index t = 0; t < tris.rows(); ++t)
    for (int k = 0; k < 3; ++k) ++edge(tris(t, k), tris(t, (k + 1) % 3)).triangles;
  std::vector<char> rim_node(static_cast<size_t>(x_m.rows()), 0);
  for (const auto& [e, info] : edges)
    if (info.triangles == 1) rim_node[static_cast<size_t>(e.first)] = rim_node[static_cast<size_t>(e.second)] = 1;
  std::vector<char> band_tri(static_cast<size_t>(tris.rows()), 0);
  for (Eigen::Index t = 0; t < tris.rows(); ++t) {
    for (int k = 0; k < 3; ++k) band_tri[static_cast<size_t>(t)] |= rim_node[static_cast<size_t>(tris(t, k))];
    for (int k = 0; k < 3; ++k) edge(tris(t, k), tris(t, (k + 1) % 3)).band |= band_tri[static_cast<size_t>(t)];
  }
  const Eigen::Index nv = static_cast<Eigen::Index>(skin.size());
  core::Points samples(nv + tris.rows() + static_cast<Eigen::Index>(edges.size()), 3);
  std::vector<char> rim(static_cast<size_t>(samples.rows()), 0);
  Eigen::Index r = 0;
  for (int n : skin) {
    rim[static_cast<size_t>(r)] = rim_node[static_cast<size_t>(n)];
    samples.row(r++) = x_m.row(n);
  }
  for (Eigen::Index t = 0; t < tris.rows(); ++t) {
    rim[static_cast<size_t>(r)] = band_tri[static_cast<size_t>(t)];
    samples.row(r++) = (x_m.row(tris(t, 0)) + x_m.row(tris(t, 1)) + x_m.row(tris(t, 2))) / 3.0;
  }
  for (const auto& [e, info] : edges) {
    rim[static_cast<size_t>(r)] = info.band;
    samples.row(r++) = 0.5 * (x_m.row(e.first) + x_m.row(e.second));
  }
  return SkinIndex(samples, std::move(rim), gate_m);
}

}  // namespace

TrackResult SurfaceTracker::track(core::ProneToSupinePipeline& pipeline, const core::Points& cloud_m) {
  // The filters and ICP run on as many threads as the model's steps (core/thread_budget.h).
  const core::ThreadCountScope threads(core::ThreadCountScope::Sample::reuse);
  TrackResult res;
  res.points_in = static_cast<size_t>(cloud_m.rows());
  auto t0 = std::chrono::steady_clock::now();
  core::Points cloud =
      options_.pcl_reference ? filterCloudPcl(cloud_m, options_.filter) : filterCloud(cloud_m, options_.filter);
  res.points_decimated = static_cast<size_t>(cloud.rows());
  // The model does not move before iterate(): one copy of its positions serves the gate, ICP and the
  // unseen skin.
  const core::Points x = pipeline.positions();
  const std::vector<int>& skin = pipeline.model().mesh.nodeSet(core::node_sets::kSkin);
  // Tracking starts here: the reference, indexed once.
  if (reference_.empty()) reference_ = referenceSkin(pipeline.model().mesh, skin, x, options_.max_point_distance_m);
  if (options_.max_point_distance_m > 0 && cloud.rows() > 0) {
    // Against the skin where tracking started (which ICP aligns to), where the last ICP correction
    // puts the cloud.
    const core::Points seen_as = guess_.matrix().isIdentity(0) ? cloud : transformPoints(guess_, cloud);
    const std::vector<int> kept =
        options_.pcl_reference ? pointsNearPcl(seen_as, reference_.points(), reference_.rim(), options_.max_point_distance_m)
                               : reference_.near(seen_as);
    res.points_gated = static_cast<size_t>(cloud.rows()) - kept.size();
    if (res.points_gated > 0) {
      core::Points near(static_cast<Eigen::Index>(kept.size()), 3);
      for (size_t i = 0; i < kept.size(); ++i) near.row(static_cast<Eigen::Index>(i)) = cloud.row(kept[i]);
      cloud = std::move(near);
    }
  }
  res.filter_s = since(t0);
  if (cloud.rows() < options_.min_points) {
    res.reason = std::to_string(cloud.rows()) + " points after decimation, outlier removal and the distance gate (" +
                 std::to_string(res.points_gated) + " beyond it), fewer than min_points = " +
                 std::to_string(options_.min_points);
    return res;
  }
  const auto align = [this](const core::Points& c, const Eigen::Isometry3d& guess) {
    return options_.pcl_reference ? rigidAlignPcl(c, reference_.points(), guess, options_.icp)
                                  : reference_.align(c, guess, options_.icp);
  };
  if (options_.icp.enabled) {
    t0 = std::chrono::steady_clock::now();
    // ICP needs far fewer points than the morphing: an even sub-sample.
    Eigen::Index stride = 1;
    if (options_.icp.max_points > 0 && cloud.rows() > options_.icp.max_points)
      stride = (cloud.rows() + options_.icp.max_points - 1) / options_.icp.max_points;
    core::Points sample((cloud.rows() + stride - 1) / stride, 3);
    for (Eigen::Index i = 0; i < sample.rows(); ++i) sample.row(i) = cloud.row(i * stride);
    IcpResult icp = align(sample, guess_);
    if (!icp.applied && !guess_.matrix().isIdentity(0)) {
      // The previous correction may be what is wrong now: try once from identity.
      IcpResult again = align(sample, Eigen::Isometry3d::Identity());
      if (again.applied) icp = again;
    }
    res.icp_rms_m = icp.rms_m;
    res.icp_inlier_fraction = icp.inlier_fraction;
    res.icp_s = since(t0);
    if (!icp.applied) {
      // A cloud that cannot be brought onto the skin by a small rigid correction is not the skin as
      // registered (a wrong pose, another surface): it would pull the model off its shape.
      guess_ = Eigen::Isometry3d::Identity();
      res.icp_refused = true;
      res.icp_note = icp.note;
      res.reason = "ICP refused the cloud: " + icp.note;
      return res;
    }
    cloud = transformPoints(icp.transform, cloud);
    guess_ = icp.transform;
    res.icp_applied = true;
    res.icp_translation_m = icp.transform.translation().norm();
    res.icp_rotation_deg = Eigen::AngleAxisd(icp.transform.linear()).angle() * 180.0 / M_PI;
  }
  res.points_used = static_cast<size_t>(cloud.rows());
  t0 = std::chrono::steady_clock::now();
  core::TargetSurface target;
  held_.assign(static_cast<size_t>(x.rows()), 0);
  if (options_.hold_unseen_skin_m > 0) {
    // Skin vertices the scanner did not see (no cloud point within hold_unseen_skin_m, float squared
    // distances as PCL computes them) keep their current positions as their target.
    std::vector<int> held;
    if (options_.pcl_reference) {
      pcl::KdTreeFLANN<pcl::PointXYZ> tree;
      tree.setInputCloud(toPcl(cloud));
      std::vector<int> index(1);
      std::vector<float> d2(1);
      const double limit2 = options_.hold_unseen_skin_m * options_.hold_unseen_skin_m;
      for (int n : skin) {
        const pcl::PointXYZ p(static_cast<float>(x(n, 0)), static_cast<float>(x(n, 1)), static_cast<float>(x(n, 2)));
        if (tree.nearestKSearch(p, 1, index, d2) < 1 || d2[0] > limit2) held.push_back(n);
      }
    } else {
      const PointGrid grid(cloud, options_.hold_unseen_skin_m);
      for (int n : skin) {
        const Eigen::Vector3f p(static_cast<float>(x(n, 0)), static_cast<float>(x(n, 1)), static_cast<float>(x(n, 2)));
        if (!grid.anyWithin(p, options_.hold_unseen_skin_m)) held.push_back(n);
      }
    }
    for (int n : held) held_[static_cast<size_t>(n)] = 1;
    res.skin_held = static_cast<int>(held.size());
    res.skin_seen = static_cast<int>(skin.size() - held.size());
    target.vertices_m.resize(cloud.rows() + static_cast<Eigen::Index>(held.size()), 3);
    target.vertices_m.topRows(cloud.rows()) = cloud;
    for (size_t i = 0; i < held.size(); ++i) target.vertices_m.row(cloud.rows() + static_cast<Eigen::Index>(i)) = x.row(held[i]);
  } else {
    res.skin_seen = static_cast<int>(skin.size());
    target.vertices_m = std::move(cloud);
  }
  pipeline.setTarget(target);
  res.field_s = since(t0);
  t0 = std::chrono::steady_clock::now();
  // The frame's solver tolerance, put back on every way out (iterate() may throw).
  struct ToleranceScope {
    core::LinearSolver& solver;
    double saved;
    ToleranceScope(core::LinearSolver& s, double tolerance) : solver(s), saved(s.relativeTolerance()) {
      if (tolerance > 0 && saved > 0) solver.setRelativeTolerance(tolerance);
    }
    ~ToleranceScope() {
      if (saved > 0) solver.setRelativeTolerance(saved);
    }
  } tolerance_scope(pipeline.simulator().solver(), options_.solver_relative_tolerance);
  pipeline.setTrackingMode(true);
  for (int i = 0; i < options_.iterations_per_frame; ++i) {
    res.last = pipeline.iterate();
    ++res.iterations;
    res.reversals += res.last.reversals;
    if (i == 0 && pipeline.morphing()) {
      // The first iteration's distances are those of this cloud to the model as it arrived.
      const core::SurfaceMorphing& m = *pipeline.morphing();
      std::vector<double> seen;
      seen.reserve(m.vertices().size());
      for (size_t k = 0; k < m.vertices().size(); ++k)
        if (!held_[static_cast<size_t>(m.vertices()[k])]) seen.push_back(m.lastDistances()[static_cast<Eigen::Index>(k)]);
      if (!seen.empty()) {
        const core::DistanceStats d = core::distanceStats(seen);
        res.seen_mean_m = d.mean_m;
        res.seen_p95_m = d.p95_m;
      }
    }
  }
  res.iterate_s = since(t0);
  res.tracked = true;
  return res;
}

}  // namespace breast_sim::ros_interface
