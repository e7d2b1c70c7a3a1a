#include "breast_sim/core/mri/segmentation_metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <unordered_map>

#include <Eigen/Core>

namespace breast_sim::core {

namespace {

// Centres of the faces between a chest-wall voxel and a breast-tissue voxel [m].
std::vector<Eigen::Vector3d> boundaryFaces(const LabelImage& image, const TissueLabels& labels) {
  std::vector<Eigen::Vector3d> faces;
  std::vector<std::uint8_t> cls(image.labels.size());
  for (std::size_t v = 0; v < cls.size(); ++v) {
    const TissueClass c = labels.classify(image.labels[v]);
    cls[v] = c == TissueClass::kChestWall ? 2 : (c == TissueClass::kAir ? 0 : 1);
  }
  for (int k = 0; k < image.size.z(); ++k)
    for (int j = 0; j < image.size.y(); ++j)
      for (int i = 0; i < image.size.x(); ++i) {
        const std::uint8_t a = cls[image.index(i, j, k)];
        if (a == 0) continue;
        const Eigen::Vector3i here(i, j, k);
        for (int axis = 0; axis < 3; ++axis) {
          Eigen::Vector3i next = here;
          ++next[axis];
          if (next[axis] >= image.size[axis]) continue;
          const std::uint8_t b = cls[image.index(next.x(), next.y(), next.z())];
          if (a + b == 3)
            faces.push_back(image.indexToPhysical(0.5 * (here.cast<double>() + next.cast<double>())));
        }
      }
  return faces;
}

// Nearest-point queries over a fixed set of points, by a uniform grid of buckets.
class NearestPoint {
 public:
  NearestPoint(const std::vector<Eigen::Vector3d>& points, double cell) : points_(points), cell_(cell) {
    for (std::size_t p = 0; p < points.size(); ++p) buckets_[key(cellOf(points[p]))].push_back(static_cast<int>(p));
  }
  double distance(const Eigen::Vector3d& q) const {
    const Eigen::Vector3i c = cellOf(q);
    double best = std::numeric_limits<double>::infinity();
    for (int r = 0;; ++r) {
      // Shell r of cells; a point in it is at least (r - 1) cells away.
      if (std::isfinite(best) && (r - 1) * cell_ > best) break;
      if (r > 100000) break;
      for (int dz = -r; dz <= r; ++dz)
        for (int dy = -r; dy <= r; ++dy)
          for (int dx = -r; dx <= r; ++dx) {
            if (std::max({std::abs(dx), std::abs(dy), std::abs(dz)}) != r) continue;
            const auto it = buckets_.find(key(c + Eigen::Vector3i(dx, dy, dz)));
            if (it == buckets_.end()) continue;
            for (int p : it->second) best = std::min(best, (points_[p] - q).norm());
          }
    }
    return best;
  }

 private:
  Eigen::Vector3i cellOf(const Eigen::Vector3d& p) const { return (p / cell_).array().floor().cast<int>(); }
  static long long key(const Eigen::Vector3i& c) {
    return (static_cast<long long>(c.x() + (1 << 20)) << 42) ^ (static_cast<long long>(c.y() + (1 << 20)) << 21) ^
           static_cast<long long>(c.z() + (1 << 20));
  }
  const std::vector<Eigen::Vector3d>& points_;
  double cell_;
  std::unordered_map<long long, std::vector<int>> buckets_;
};

}  // namespace

const ClassScore& SegmentationScores::score(const std::string& name) const {
  for (const ClassScore& c : classes)
    if (c.name == name) return c;
  throw std::out_of_range("no segmentation score named '" + name + "'");
}

SegmentationScores scoreSegmentation(const LabelImage& result, const TissueLabels& result_labels, const LabelImage& truth,
                                     const TissueLabels& truth_labels) {
  result.validate();
  truth.validate();
  if (result.size != truth.size || (result.spacing_m - truth.spacing_m).cwiseAbs().maxCoeff() > 1e-6 ||
      (result.origin_m - truth.origin_m).cwiseAbs().maxCoeff() > 1e-6 ||
      (result.direction - truth.direction).cwiseAbs().maxCoeff() > 1e-6)
    throw std::invalid_argument("scoreSegmentation: the segmentation and the truth lie on different grids");
  SegmentationScores out;
  const std::pair<const char*, std::vector<TissueClass>> classes[] = {
      {"breast", {TissueClass::kFat, TissueClass::kFibroglandular, TissueClass::kSkin, TissueClass::kLesion}},
      {"fat", {TissueClass::kFat}},
      {"fibroglandular", {TissueClass::kFibroglandular}},
      {"skin", {TissueClass::kSkin}},
      {"lesion", {TissueClass::kLesion}},
      {"chest_wall", {TissueClass::kChestWall}}};
  for (const auto& [name, set] : classes) {
    ClassScore s;
    s.name = name;
    const auto in = [&](TissueClass c) { return std::find(set.begin(), set.end(), c) != set.end(); };
    for (std::size_t v = 0; v < truth.labels.size(); ++v) {
      const bool a = in(result_labels.classify(result.labels[v])), b = in(truth_labels.classify(truth.labels[v]));
      s.result_voxels += a;
      s.truth_voxels += b;
      s.overlap_voxels += a && b;
    }
    s.dice = s.result_voxels + s.truth_voxels == 0 ? 1.0 : 2.0 * s.overlap_voxels / double(s.result_voxels + s.truth_voxels);
    out.classes.push_back(s);
  }
  const std::vector<Eigen::Vector3d> a = boundaryFaces(result, result_labels), b = boundaryFaces(truth, truth_labels);
  if (a.empty() || b.empty())
    throw std::invalid_argument(std::string("scoreSegmentation: the ") + (a.empty() ? "segmentation" : "truth") +
                                " has no face between chest wall and breast tissue");
  const double cell = 4.0 * truth.spacing_m.maxCoeff();
  const NearestPoint to_b(b, cell), to_a(a, cell);
  std::vector<double> d(a.size() + b.size());
#pragma omp parallel for schedule(dynamic, 256)
  for (long p = 0; p < static_cast<long>(a.size()); ++p) d[p] = to_b.distance(a[p]);
#pragma omp parallel for schedule(dynamic, 256)
  for (long p = 0; p < static_cast<long>(b.size()); ++p) d[a.size() + p] = to_a.distance(b[p]);
  BoundaryDistance& bd = out.boundary;
  bd.result_faces = static_cast<long>(a.size());
  bd.truth_faces = static_cast<long>(b.size());
  double sa = 0, sb = 0;
  for (std::size_t p = 0; p < a.size(); ++p) sa += d[p];
  for (std::size_t p = 0; p < b.size(); ++p) sb += d[a.size() + p];
  bd.result_to_truth_mean_mm = 1e3 * sa / a.size();
  bd.truth_to_result_mean_mm = 1e3 * sb / b.size();
  bd.mean_mm = 1e3 * (sa + sb) / d.size();
  std::vector<double> sorted = d;
  const auto at = sorted.begin() + static_cast<long>(0.95 * (sorted.size() - 1));
  std::nth_element(sorted.begin(), at, sorted.end());
  bd.p95_mm = 1e3 * *at;
  bd.max_mm = 1e3 * *std::max_element(d.begin(), d.end());
  return out;
}

}  // namespace breast_sim::core
