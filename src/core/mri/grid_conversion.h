#pragma once
/// @file grid_conversion.h
/// ImageGeometry (m) to and from the ITK bridge's Grid (mm), for the sources of src/core/mri that
/// call the ITK bridge (private to src/core/mri).

#include "breast_sim/core/image/gaussian_filter.h"
#include "itk_bridge.h"

namespace breast_sim::core {

inline itk_bridge::Grid bridgeGrid(const ImageGeometry& g) {
  itk_bridge::Grid out;
  for (int d = 0; d < 3; ++d) {
    out.size[d] = g.size[d];
    out.spacing_mm[d] = g.spacing_m[d] * 1e3;
    out.origin_mm[d] = g.origin_m[d] * 1e3;
    for (int r = 0; r < 3; ++r) out.direction[3 * r + d] = g.direction(r, d);
  }
  return out;
}

/// The geometry of a bridge grid, taken as it is (no orthonormality check).
inline ImageGeometry geometryOf(const itk_bridge::Grid& g) {
  ImageGeometry out;
  for (int d = 0; d < 3; ++d) {
    out.size[d] = static_cast<int>(g.size[d]);
    out.spacing_m[d] = g.spacing_mm[d] * 1e-3;
    out.origin_m[d] = g.origin_mm[d] * 1e-3;
    for (int r = 0; r < 3; ++r) out.direction(r, d) = g.direction[3 * r + d];
  }
  return out;
}

}  // namespace breast_sim::core
