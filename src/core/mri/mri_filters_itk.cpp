// The ITK filters of the MRI segmentation behind plain types (itk_bridge.h). One of the two sources
// that compile ITK's headers (mri_volume_itk.cpp is the other); it includes no Eigen (see itk_bridge.h).
#include "itk_image.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <itkBSplineControlPointImageFilter.h>
#include <itkBinaryFillholeImageFilter.h>
#include <itkConnectedComponentImageFilter.h>
#include <itkImage.h>
#include <itkN4BiasFieldCorrectionImageFilter.h>
#include <itkOtsuThresholdImageFilter.h>
#include <itkRelabelComponentImageFilter.h>
#include <itkShrinkImageFilter.h>

namespace breast_sim::core::itk_bridge {

namespace {

using FloatImage = itk::Image<float, 3>;
using MaskImage = itk::Image<std::uint8_t, 3>;
using LabelImage32 = itk::Image<std::int32_t, 3>;

Grid gridOf(const itk::ImageBase<3>& image) {
  Grid g;
  for (int d = 0; d < 3; ++d) {
    g.size[d] = static_cast<long>(image.GetLargestPossibleRegion().GetSize()[d]);
    g.spacing_mm[d] = image.GetSpacing()[d];
    g.origin_mm[d] = image.GetOrigin()[d];
    for (int r = 0; r < 3; ++r) g.direction[3 * r + d] = image.GetDirection()[r][d];
  }
  return g;
}

FloatImage::Pointer floatImage(const Grid& g, const std::vector<float>& values) {
  auto out = makeImage<FloatImage>(g);
  std::copy(values.begin(), values.end(), out->GetBufferPointer());
  return out;
}

MaskImage::Pointer maskImage(const Grid& g, const std::vector<std::uint8_t>& mask) {
  auto out = makeImage<MaskImage>(g);
  std::copy(mask.begin(), mask.end(), out->GetBufferPointer());
  return out;
}

std::vector<std::uint8_t> maskValues(const MaskImage& image) {
  const std::uint8_t* p = image.GetBufferPointer();
  return std::vector<std::uint8_t>(p, p + image.GetLargestPossibleRegion().GetNumberOfPixels());
}

}  // namespace

std::vector<float> n4BiasField(const Grid& grid, const std::vector<float>& values, const N4Options& options, Grid* field_grid) {
  using Shrink = itk::ShrinkImageFilter<FloatImage, FloatImage>;
  using N4 = itk::N4BiasFieldCorrectionImageFilter<FloatImage, MaskImage, FloatImage>;
  const unsigned factor = static_cast<unsigned>(std::max(1, options.shrink_factor));
  const auto work_units = static_cast<itk::ThreadIdType>(std::max(1, options.work_units));
  auto shrink = Shrink::New();
  shrink->SetInput(floatImage(grid, values));
  shrink->SetShrinkFactors(factor);
  shrink->Update();
  // The tissue of the shrunk image: above its Otsu threshold.
  auto otsu = itk::OtsuThresholdImageFilter<FloatImage, MaskImage>::New();
  otsu->SetInput(shrink->GetOutput());
  otsu->SetNumberOfHistogramBins(256);
  otsu->SetInsideValue(0);
  otsu->SetOutsideValue(1);
  otsu->Update();
  auto n4 = N4::New();
  n4->SetInput(shrink->GetOutput());
  n4->SetMaskImage(otsu->GetOutput());
  n4->SetMaskLabel(1);
  n4->SetNumberOfWorkUnits(work_units);
  N4::VariableSizeArrayType iterations(static_cast<unsigned>(options.fitting_levels));
  iterations.Fill(static_cast<unsigned>(options.iterations_per_level));
  n4->SetMaximumNumberOfIterations(iterations);
  n4->SetNumberOfFittingLevels(static_cast<unsigned>(options.fitting_levels));
  n4->SetConvergenceThreshold(options.convergence_threshold);
  // Control points of the first level: the extent over the spline distance, plus the spline order.
  N4::ArrayType control_points;
  for (int d = 0; d < 3; ++d) {
    const double extent = static_cast<double>(grid.size[d]) * grid.spacing_mm[d];
    control_points[d] =
        static_cast<unsigned>(std::max(1.0, std::ceil(extent / options.spline_distance_mm))) + n4->GetSplineOrder();
  }
  n4->SetNumberOfControlPoints(control_points);
  try {
    n4->Update();
  } catch (const itk::ExceptionObject& e) {
    throw std::runtime_error(std::string("N4 bias-field correction failed: ") + e.GetDescription());
  }
  // The log bias field from its B-spline lattice, on the shrunk grid.
  const FloatImage* shrunk = shrink->GetOutput();
  using Lattice = N4::BiasFieldControlPointLatticeType;
  using Reconstruct = itk::BSplineControlPointImageFilter<Lattice, N4::ScalarImageType>;
  auto reconstruct = Reconstruct::New();
  reconstruct->SetInput(n4->GetLogBiasFieldControlPointLattice());
  reconstruct->SetSplineOrder(n4->GetSplineOrder());
  reconstruct->SetSize(shrunk->GetLargestPossibleRegion().GetSize());
  reconstruct->SetOrigin(shrunk->GetOrigin());
  reconstruct->SetSpacing(shrunk->GetSpacing());
  reconstruct->SetDirection(shrunk->GetDirection());
  reconstruct->SetNumberOfWorkUnits(work_units);
  reconstruct->Update();
  const auto* field = reconstruct->GetOutput();
  *field_grid = gridOf(*field);
  std::vector<float> out(static_cast<std::size_t>(field_grid->count()));
  const auto* src = field->GetBufferPointer();
  for (std::size_t v = 0; v < out.size(); ++v) out[v] = static_cast<float>(std::exp(src[v][0]));
  return out;
}

double otsuThreshold(const Grid& grid, const std::vector<float>& values, const std::vector<std::uint8_t>& mask, int bins) {
  using Otsu = itk::OtsuThresholdImageFilter<FloatImage, MaskImage, MaskImage>;
  if (!mask.empty() && std::none_of(mask.begin(), mask.end(), [](std::uint8_t m) { return m != 0; }))
    throw std::runtime_error("Otsu threshold: the mask selects no voxel");
  auto otsu = Otsu::New();
  otsu->SetInput(floatImage(grid, values));
  if (!mask.empty()) {
    otsu->SetMaskImage(maskImage(grid, mask));
    otsu->SetMaskValue(1);
  }
  otsu->SetNumberOfHistogramBins(static_cast<unsigned>(std::max(2, bins)));
  try {
    otsu->Update();
  } catch (const itk::ExceptionObject& e) {
    throw std::runtime_error(std::string("Otsu threshold failed: ") + e.GetDescription());
  }
  return otsu->GetThreshold();
}

std::vector<std::int32_t> connectedComponents(const Grid& grid, const std::vector<std::uint8_t>& mask, bool full_connectivity,
                                              std::vector<long>* sizes) {
  using Components = itk::ConnectedComponentImageFilter<MaskImage, LabelImage32>;
  using Relabel = itk::RelabelComponentImageFilter<LabelImage32, LabelImage32>;
  auto components = Components::New();
  components->SetInput(maskImage(grid, mask));
  components->SetFullyConnected(full_connectivity);
  auto relabel = Relabel::New();
  relabel->SetInput(components->GetOutput());
  relabel->SetSortByObjectSize(true);
  relabel->Update();
  const std::int32_t* p = relabel->GetOutput()->GetBufferPointer();
  if (sizes) {
    sizes->clear();
    for (const auto s : relabel->GetSizeOfObjectsInPixels()) sizes->push_back(static_cast<long>(s));
  }
  return std::vector<std::int32_t>(p, p + mask.size());
}

std::vector<std::uint8_t> fillHoles(const Grid& grid, const std::vector<std::uint8_t>& mask) {
  using Fill = itk::BinaryFillholeImageFilter<MaskImage>;
  auto fill = Fill::New();
  fill->SetInput(maskImage(grid, mask));
  fill->SetForegroundValue(1);
  fill->SetFullyConnected(false);
  fill->Update();
  return maskValues(*fill->GetOutput());
}

}  // namespace breast_sim::core::itk_bridge
