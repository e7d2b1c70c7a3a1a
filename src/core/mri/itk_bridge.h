#pragma once
/// @file itk_bridge.h
/// What the ITK sources (mri_volume_itk.cpp, mri_filters_itk.cpp) offer the rest of src/core/mri, in
/// plain types (private to src/core/mri). Those two sources include ITK's headers and no Eigen: ITK 5.2
/// ships its own Eigen, and the two cannot meet in one translation unit. Lengths in mm, as ITK's files
/// keep them; masks are one byte per voxel, 0 or 1; voxels i fastest.

#include <cstdint>
#include <string>
#include <vector>

namespace breast_sim::core::itk_bridge {

/// A voxel grid: p = origin + direction · diag(spacing) · (i, j, k) [mm]; direction row-major
/// (direction[3 r + c] is row r of column c, column c the unit vector of axis c).
struct Grid {
  long size[3] = {0, 0, 0};
  double spacing_mm[3] = {1, 1, 1};
  double origin_mm[3] = {0, 0, 0};
  double direction[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  long count() const { return size[0] * size[1] * size[2]; }
};

struct Volume {
  Grid grid;
  std::vector<float> values;
  std::string format;              ///< "NIfTI"
  std::string pixel_type;          ///< ITK's name of the stored type, e.g. "short"
};

// ---- mri_volume.cpp, for the ITK sources ----
/// readMriVolume's check of the sizes a header gives (all its axes), before anything is allocated: 3-D
/// (a 2-D image, a volume of one slice or several volumes are errors) and at most `max_voxels`.
/// @throws std::runtime_error naming `path` and the fix.
void checkVolumeSize(const std::string& path, const std::vector<long>& sizes, long max_voxels);

// ---- mri_volume_itk.cpp ----
/// Whether ITK's NIfTI ImageIO takes the file (by its name and header).
bool isNifti(const std::string& path);
/// A NIfTI file, its header checked first (see readMriVolume, mri_volume.h).
Volume readNifti(const std::string& path, long max_voxels);

/// Writes float voxels; format by extension (.nii, .nii.gz, .nrrd, .mha), atomically (rename).
void writeVolume(const std::string& path, const Grid& grid, const std::vector<float>& values);

struct DicomTags {
  std::string study_uid, series_uid, frame_uid, description, patient_name, patient_id;
  int series_number = 1;
};
/// One MR Image Storage file per k-slice of int16 voxels (rounded, clamped) into an empty folder.
void writeDicom(const std::string& folder, const Grid& grid, const std::vector<float>& values, const DicomTags& tags);

// ---- mri_filters_itk.cpp ----
/// N4 bias-field estimation [Tustison et al. 2010, IEEE TMI 29(6)] on a shrunk copy of the image.
struct N4Options {
  int shrink_factor = 4;          ///< the image is shrunk by this per axis first (speed)
  int fitting_levels = 3;         ///< B-spline fitting levels
  int iterations_per_level = 50;  ///< at most this many iterations per level
  double convergence_threshold = 1e-3;
  double spline_distance_mm = 100.0;  ///< control-point spacing of the first level [mm]
  /// ITK work units: fixed, so the result does not depend on the machine's core count.
  int work_units = 4;
};
/// The bias field b (I = b · I_true) on the shrunk grid `field_grid` (smooth: sample it trilinearly),
/// fitted within the shrunk image's voxels above its Otsu threshold (the tissue; air and lung carry
/// no bias information).
/// @throws std::runtime_error with ITK's message when N4 fails.
std::vector<float> n4BiasField(const Grid& grid, const std::vector<float>& values, const N4Options& options, Grid* field_grid);

/// Otsu's threshold [Otsu 1979] of the values within `mask` (all voxels if empty), from `bins` bins
/// over the masked range; values above it are the upper class.
/// @throws std::runtime_error when the mask selects no voxel.
double otsuThreshold(const Grid& grid, const std::vector<float>& values, const std::vector<std::uint8_t>& mask, int bins = 256);

/// Connected components of a mask: per voxel its component (1 = largest, 2 = next, …) or 0 off the
/// mask; sizes[c − 1] voxels in component c. `full_connectivity`: 26-neighbourhood, else 6.
std::vector<std::int32_t> connectedComponents(const Grid& grid, const std::vector<std::uint8_t>& mask, bool full_connectivity,
                                              std::vector<long>* sizes);

/// The mask with its holes filled: background not connected (6-neighbourhood) to the grid's border.
std::vector<std::uint8_t> fillHoles(const Grid& grid, const std::vector<std::uint8_t>& mask);

}  // namespace breast_sim::core::itk_bridge
