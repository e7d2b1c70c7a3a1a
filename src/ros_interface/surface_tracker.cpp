// One tracker frame: PCL decimation, outlier removal and ICP pre-alignment, then the pipeline's
// target and Figure-2 iterations (see surface_tracker.h).
#include "breast_sim/ros_interface/surface_tracker.h"

#include <chrono>
#include <cmath>

#include <pcl/filters/statistical_outlier_removal.h>
#include <pcl/filters/voxel_grid.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/registration/icp.h>

#include "breast_sim/ros_interface/conversions.h"

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

}  // namespace

core::Points filterCloud(const core::Points& cloud_m, const CloudFilterOptions& options) {
  if (cloud_m.rows() == 0) return cloud_m;
  auto cloud = toPcl(cloud_m);
  if (options.voxel_leaf_m > 0) {
    pcl::VoxelGrid<pcl::PointXYZ> grid;
    grid.setInputCloud(cloud);
    const float leaf = static_cast<float>(options.voxel_leaf_m);
    grid.setLeafSize(leaf, leaf, leaf);
    pcl::PointCloud<pcl::PointXYZ>::Ptr out(new pcl::PointCloud<pcl::PointXYZ>);
    grid.filter(*out);
    cloud = out;
  }
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

IcpResult rigidAlign(const core::Points& cloud_m, const core::Points& reference_m, const Eigen::Isometry3d& guess,
                     const IcpOptions& options) {
  IcpResult r;
  if (cloud_m.rows() < 10 || reference_m.rows() < 10) {
    r.note = "too few points for ICP";
    return r;
  }
  pcl::IterativeClosestPoint<pcl::PointXYZ, pcl::PointXYZ> icp;
  icp.setInputSource(toPcl(cloud_m));
  icp.setInputTarget(toPcl(reference_m));
  icp.setMaximumIterations(options.max_iterations);
  icp.setMaxCorrespondenceDistance(options.max_correspondence_m);
  icp.setTransformationEpsilon(1e-10);
  icp.setEuclideanFitnessEpsilon(1e-12);
  pcl::PointCloud<pcl::PointXYZ> aligned;
  icp.align(aligned, guess.matrix().cast<float>());
  r.converged = icp.hasConverged();
  const double fitness = icp.getFitnessScore(options.max_correspondence_m);  // mean squared distance [m²]
  r.rms_m = std::sqrt(std::max(0.0, fitness));
  Eigen::Isometry3d t(icp.getFinalTransformation().cast<double>());
  const double translation = t.translation().norm();
  const double rotation = Eigen::AngleAxisd(t.linear()).angle() * 180.0 / M_PI;
  r.transform = t;
  if (!r.converged) {
    r.note = "ICP did not converge";
  } else if (!(r.rms_m <= options.max_rms_m)) {
    r.note = "ICP residual " + std::to_string(1e3 * r.rms_m) + " mm above " + std::to_string(1e3 * options.max_rms_m) + " mm";
  } else if (translation > options.max_translation_m || rotation > options.max_rotation_deg) {
    r.note = "ICP correction " + std::to_string(1e3 * translation) + " mm / " + std::to_string(rotation) +
             " deg beyond the limits";
  } else {
    r.applied = true;
    return r;
  }
  r.transform = Eigen::Isometry3d::Identity();
  return r;
}

TrackResult SurfaceTracker::track(core::ProneToSupinePipeline& pipeline, const core::Points& cloud_m) {
  TrackResult res;
  res.points_in = static_cast<size_t>(cloud_m.rows());
  auto t0 = std::chrono::steady_clock::now();
  core::Points cloud = filterCloud(cloud_m, options_.filter);
  res.points_decimated = static_cast<size_t>(cloud.rows());
  res.filter_s = since(t0);
  if (cloud.rows() < options_.min_points) {
    res.reason = std::to_string(cloud.rows()) + " points after decimation and outlier removal, fewer than min_points = " +
                 std::to_string(options_.min_points);
    return res;
  }
  if (options_.icp.enabled) {
    t0 = std::chrono::steady_clock::now();
    const core::Points x = pipeline.positions();
    const std::vector<int>& skin = pipeline.model().mesh.nodeSet(core::node_sets::kSkin);
    core::Points reference(static_cast<Eigen::Index>(skin.size()), 3);
    for (size_t i = 0; i < skin.size(); ++i) reference.row(static_cast<Eigen::Index>(i)) = x.row(skin[i]);
    // ICP needs far fewer points than the morphing: an even sub-sample.
    core::Points sample = cloud;
    if (options_.icp.max_points > 0 && cloud.rows() > options_.icp.max_points) {
      const Eigen::Index stride = (cloud.rows() + options_.icp.max_points - 1) / options_.icp.max_points;
      sample.resize((cloud.rows() + stride - 1) / stride, 3);
      for (Eigen::Index i = 0; i < sample.rows(); ++i) sample.row(i) = cloud.row(i * stride);
    }
    IcpResult icp = rigidAlign(sample, reference, guess_, options_.icp);
    if (!icp.applied && !guess_.matrix().isIdentity(0)) {
      // The previous correction may be what is wrong now: try once from identity.
      IcpResult again = rigidAlign(sample, reference, Eigen::Isometry3d::Identity(), options_.icp);
      if (again.applied) icp = again;
    }
    res.icp_rms_m = icp.rms_m;
    res.icp_s = since(t0);
    if (icp.applied) {
      cloud = transformPoints(icp.transform, cloud);
      guess_ = icp.transform;
      res.icp_applied = true;
      res.icp_translation_m = icp.transform.translation().norm();
      res.icp_rotation_deg = Eigen::AngleAxisd(icp.transform.linear()).angle() * 180.0 / M_PI;
    } else {
      guess_ = Eigen::Isometry3d::Identity();
      res.icp_note = icp.note + "; the cloud is used as transformed by tf";
    }
  }
  res.points_used = static_cast<size_t>(cloud.rows());
  t0 = std::chrono::steady_clock::now();
  core::TargetSurface target;
  if (options_.hold_unseen_skin_m > 0) {
    // Skin vertices the scanner did not see keep their current positions as their target.
    const core::Points x = pipeline.positions();
    const std::vector<int>& skin = pipeline.model().mesh.nodeSet(core::node_sets::kSkin);
    pcl::KdTreeFLANN<pcl::PointXYZ> tree;
    tree.setInputCloud(toPcl(cloud));
    std::vector<int> index(1);
    std::vector<float> d2(1);
    const double limit2 = options_.hold_unseen_skin_m * options_.hold_unseen_skin_m;
    std::vector<int> held;
    for (int n : skin) {
      const pcl::PointXYZ p(static_cast<float>(x(n, 0)), static_cast<float>(x(n, 1)), static_cast<float>(x(n, 2)));
      if (tree.nearestKSearch(p, 1, index, d2) < 1 || d2[0] > limit2) held.push_back(n);
    }
    res.skin_held = static_cast<int>(held.size());
    res.skin_seen = static_cast<int>(skin.size() - held.size());
    target.vertices_m.resize(cloud.rows() + static_cast<Eigen::Index>(held.size()), 3);
    target.vertices_m.topRows(cloud.rows()) = cloud;
    for (size_t i = 0; i < held.size(); ++i) target.vertices_m.row(cloud.rows() + static_cast<Eigen::Index>(i)) = x.row(held[i]);
  } else {
    target.vertices_m = std::move(cloud);
  }
  pipeline.setTarget(target);
  res.field_s = since(t0);
  t0 = std::chrono::steady_clock::now();
  for (int i = 0; i < options_.iterations_per_frame; ++i) {
    res.last = pipeline.iterate();
    ++res.iterations;
    res.reversals += res.last.reversals;
  }
  res.iterate_s = since(t0);
  res.tracked = true;
  return res;
}

}  // namespace breast_sim::ros_interface
