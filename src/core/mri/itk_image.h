#pragma once
/// @file itk_image.h
/// An ITK image on a bridge grid (private to the two ITK sources of src/core/mri; includes ITK).

#include <itkImage.h>

#include "itk_bridge.h"

namespace breast_sim::core::itk_bridge {

/// A new, allocated ITK image with the grid's size, spacing, origin and direction (mm).
template <typename ImageType>
typename ImageType::Pointer makeImage(const Grid& g) {
  auto out = ImageType::New();
  typename ImageType::RegionType region;
  typename ImageType::SpacingType spacing;
  typename ImageType::PointType origin;
  typename ImageType::DirectionType direction;
  for (int d = 0; d < 3; ++d) {
    region.SetSize(d, static_cast<itk::SizeValueType>(g.size[d]));
    spacing[d] = g.spacing_mm[d];
    origin[d] = g.origin_mm[d];
    for (int r = 0; r < 3; ++r) direction[r][d] = g.direction[3 * r + d];
  }
  out->SetRegions(region);
  out->SetSpacing(spacing);
  out->SetOrigin(origin);
  out->SetDirection(direction);
  out->Allocate();
  return out;
}

}  // namespace breast_sim::core::itk_bridge
