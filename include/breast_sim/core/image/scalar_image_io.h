#pragma once
/// @file scalar_image_io.h
/// NRRD and MetaImage files of any voxel type read as float values (intensity images such as an MRI),
/// by the same parsers as the label images of label_image.h: one parser per format, whose limits and
/// errors are those of readLabelImage.

#include <functional>
#include <string>
#include <vector>

#include "breast_sim/core/image/gaussian_filter.h"  // ScalarImage

namespace breast_sim::core {

/// What a NRRD or MetaImage header says about an image's shape.
struct ImageFileShape {
  /// Voxels along each of the image's axes, in the file's order (NRRD `sizes` without the axes of a
  /// range kind, MetaImage `DimSize`).
  std::vector<long> sizes;
  /// Values per voxel: the product of the sizes of NRRD axes of a range kind (`vector`, `RGB-color`,
  /// `complex`, …), MetaImage `ElementNumberOfChannels`.
  long components = 1;
};

/// An intensity image and what its file stored.
struct ScalarImageFile {
  ScalarImage image;       ///< values as float, geometry in m and LPS (as readLabelImage)
  std::string format;      ///< "NRRD" or "MetaImage"
  std::string value_type;  ///< the stored type: "uint8", "int8", "uint16", "int16", "uint32", "int32",
                           ///< "uint64", "int64", "float" or "double"
};

/// Reads a 3-D image of one value per voxel from NRRD (`.nrrd`, `.nhdr`) or MetaImage (`.mha`, `.mhd`)
/// (case-insensitive extension): the encodings, byte orders, geometry conventions and limits listed at
/// readLabelImage (label_image.h), every value type converted to float (64-bit integers and doubles
/// rounded to float; values that are not finite are kept for the caller to judge).
/// @param check  called with the header's shape once the header is read, before anything the header
///               claims is allocated; it throws to refuse the file (a caller's own cap on the voxels,
///               its message for a 2-D image, …). May be empty.
/// @throws std::runtime_error whose message starts with the path: an unknown extension; whatever
///         `check` throws; a shape other than 3-D with one value per voxel; more than 2^31 voxels; the
///         readers' errors (malformed field and its value, truncated or corrupt data with the byte
///         counts, …).
ScalarImageFile readScalarImageFile(const std::string& path,
                                    const std::function<void(const ImageFileShape&)>& check = {});

}  // namespace breast_sim::core
