#pragma once
/// @file label_lookup.h
/// Nearest-voxel label lookups for the per-voxel loops of src/core/mri (private): the same rule as
/// LabelImage::labelAt (the voxel whose centre is nearest, `outside` beyond the grid), with the grid's
/// inverse taken once (the direction's transpose: the label image must have passed validate()).

#include <cmath>
#include <cstdint>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"

namespace breast_sim::core {

class LabelLookup {
 public:
  explicit LabelLookup(const LabelImage& labels) : labels_(labels), geometry_(ImageGeometry::of(labels)) {}
  std::uint16_t operator()(const Eigen::Vector3d& p_m, std::uint16_t outside = 0) const {
    const Eigen::Vector3d q = geometry_.physicalToIndex(p_m);
    if (!q.allFinite()) return outside;
    const Eigen::Vector3d r = (q.array() + 0.5).floor().matrix();
    if ((r.array() < 0.0).any() || r.x() >= labels_.size.x() || r.y() >= labels_.size.y() || r.z() >= labels_.size.z())
      return outside;
    return labels_.at(static_cast<int>(r.x()), static_cast<int>(r.y()), static_cast<int>(r.z()));
  }

 private:
  const LabelImage& labels_;
  ImageGeometry geometry_;
};

}  // namespace breast_sim::core
