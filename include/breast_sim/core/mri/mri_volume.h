#pragma once
/// @file mri_volume.h
/// Intensity MRI volumes: reading NIfTI, NRRD, MetaImage files and DICOM series into a ScalarImage in
/// LPS patient space, and writing volumes and DICOM series. ITK reads NIfTI and does the writing (GDCM
/// for DICOM); NRRD and MetaImage are read by the core's parsers (image/scalar_image_io.h), which are
/// memory-safe on malformed files where ITK's leak, and DICOM by the core's reader (dicom_scan.h), as
/// GDCM allocates what a damaged file claims and aborts on values out of its range. No ITK type appears
/// here.
///
/// Geometry: the ScalarImage's origin, spacing and direction are in metres and LPS (x towards the
/// patient's left, y posterior, z superior), as ITK gives them: NIfTI's RAS sform/qform is converted by
/// ITK; NRRD in "right-anterior-superior" likewise; DICOM is LPS by definition. Images whose space is
/// not anatomical (MetaImage, NRRD "3D-right-handed") are taken as they are, as readLabelImage does.

#include <cstdint>
#include <string>
#include <vector>

#include "breast_sim/core/image/gaussian_filter.h"  // ScalarImage, ImageGeometry
#include "breast_sim/core/image/label_image.h"

namespace breast_sim::core {

/// How to read an MRI volume.
struct MriReadOptions {
  /// DICOM folder holding more than one series: the SeriesInstanceUID (0020,000E) to read. Empty: the
  /// folder must hold exactly one series.
  std::string series_uid;
  /// Largest volume accepted [voxels], checked against the header before anything is allocated
  /// (2^28 voxels = 1 GiB of float; a breast MRI at 0.5 mm of 40 cm x 40 cm x 20 cm is 2.6e8).
  long max_voxels = 1L << 28;
  /// DICOM: slices whose spacing along the slice normal differs from the median spacing by more than
  /// this share are a gap (a missing slice) or an uneven series, an error.
  double slice_spacing_tolerance = 0.05;
};

/// What was read besides the voxels.
struct MriVolumeInfo {
  std::string path;            ///< the file or DICOM folder as given
  std::string format;          ///< "NIfTI", "NRRD", "MetaImage" or "DICOM"
  std::string series_uid;      ///< DICOM: the series read
  std::string series_description;  ///< DICOM (0008,103E), when present
  int files = 1;               ///< DICOM: slice files read
  std::string pixel_type;      ///< the file's voxel type, e.g. "short", "float"
};

/// An intensity volume and where it came from.
struct MriVolume {
  /// Voxel values as stored (after DICOM rescale slope/intercept), geometry in m and LPS.
  ScalarImage image;
  MriVolumeInfo info;
};

/// Reads a 3-D scalar MRI volume. `path` is a file (`.nii`, `.nii.gz`, `.nrrd`, `.nhdr`, `.mha`, `.mhd`,
/// or one DICOM file of a series, whose folder is read) or a folder of DICOM files (one series, or the
/// one `options.series_uid` names). DICOM slices are sorted along their normal and must be evenly
/// spaced (a missing slice is an error, not a silent stretch). DICOM files are DICOM Part 10 files (a
/// 128-byte preamble, then "DICM") of uncompressed single-frame greyscale images (dicom_scan.h lists
/// what is read); every file of the folder is walked by scanDicomFile: other files and DICOM files
/// without an image are skipped, and a damaged DICOM file (an element claiming more than the file
/// holds, …) is an error naming it, not skipped, since a skipped slice would silently change the volume.
/// @throws std::runtime_error whose message starts with the path and names the fix, for: a path that
///         does not exist; a file that is no image of these formats; a 2-D image (or a volume of one
///         slice); a non-scalar image (RGB, vector, complex, tensor); more than `max_voxels` voxels
///         (NRRD and MetaImage: also more than 2^31); a damaged or unreadable file (the readers' errors:
///         truncated or corrupt data, a DICOM element and its claimed length); a DICOM file that is
///         compressed or multi-frame, or lacks the attributes that place a slice; a DICOM folder without
///         DICOM images, with several series and no UID given, or whose UID is not there (the message
///         lists the series); slices of different sizes or orientations; unevenly spaced slices (names
///         the gap and its neighbours); non-finite voxel values.
MriVolume readMriVolume(const std::string& path, const MriReadOptions& options = {});

/// Writes an intensity volume as float: `.nii`, `.nii.gz` (NIfTI-1, RAS on disk as ITK writes it),
/// `.nrrd` (gzip, LPS) or `.mha` (compressed): single files, written to a temporary name beside the
/// target and then renamed, so a reader never sees half a file (two-file formats, `.nhdr` and `.mhd`,
/// cannot be renamed as one and are not written).
/// @throws std::invalid_argument for an invalid image (geometry, value count);
///         std::runtime_error naming the file for an unknown extension or a write error.
void writeMriVolume(const std::string& path, const ScalarImage& image);

/// DICOM series attributes for writeDicomSeries.
struct DicomSeriesOptions {
  std::string series_uid;          ///< SeriesInstanceUID; empty = derived from `uid_seed`
  std::string study_uid;           ///< StudyInstanceUID; empty = derived from `uid_seed`
  std::uint64_t uid_seed = 1;      ///< UIDs "2.25.<number>" derived from this, so a series repeats
  std::string series_description = "breast_sim synthetic T1";
  std::string patient_name = "SYNTHETIC^PHANTOM";
  std::string patient_id = "BREAST_SIM";
  int series_number = 1;
};

/// Writes a volume as a DICOM MR series, one file per slice along the grid's k axis
/// (`folder/IM00001.dcm`, …), 16-bit signed voxels (values rounded and clamped to [-32768, 32767]),
/// ImagePositionPatient, ImageOrientationPatient, PixelSpacing, SliceThickness and SpacingBetweenSlices
/// from the geometry (mm, LPS). The folder is created; files of another series already in it are an
/// error (a folder holds one series).
/// @throws std::invalid_argument for an invalid image; std::runtime_error naming the folder when it
///         cannot be created or written, or already holds DICOM files.
void writeDicomSeries(const std::string& folder, const ScalarImage& image, const DicomSeriesOptions& options = {});

/// The label image on the geometry of `image` (for label maps that follow an MRI volume).
LabelImage labelImageLike(const ScalarImage& image, std::uint16_t fill = 0);
/// The geometry of a label image as a ScalarImage with zero values (the inverse of labelImageLike).
ScalarImage scalarImageLike(const LabelImage& labels, float fill = 0.0f);

}  // namespace breast_sim::core
