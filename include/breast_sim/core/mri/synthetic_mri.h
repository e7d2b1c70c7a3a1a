#pragma once
/// @file synthetic_mri.h
/// A synthetic T1-weighted prone breast MRI rendered from a label phantom, with the label image it was
/// rendered from as ground truth: test data with known answers for the MRI path (reading, segmentation,
/// the simulated supine MRI).
///
/// The model of the image, in order:
///  1. tissue: each label of the phantom takes its tissue's T1 signal (fat bright, fibroglandular and
///     muscle darker, air 0); posterior to the phantom's chest wall a thorax is added (intercostal
///     muscle with ribs of fatty marrow in a dark cortex, then lung), since a breast MRI shows the chest
///     behind the pectoral muscle, not air;
///  2. partial volume: the signal map on the phantom's own grid is blurred by a Gaussian point-spread
///     function of the given FWHM and sampled at the centres of the output grid (isotropic voxels, LPS
///     axes: i → left, j → posterior, k → superior, as an axial DICOM series);
///  3. a smooth multiplicative bias field b = exp(a f), f a sum of random plane waves whose wavelengths
///     are at least `bias_wavelength_mm`, scaled so |f| ≤ 1 on the grid (so b is in [e^−a, e^a]);
///  4. Rician noise: |s b + n₁ + i n₂| with n₁, n₂ ~ N(0, σ²) per voxel.
/// The noise comes from a counter-based generator (voxel index and seed), so the image is the same for
/// a seed whatever the thread count.

#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/gaussian_filter.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

/// T1-weighted signal of each tissue [arbitrary units; fat = 1000 by default]. Defaults: a non-fat-
/// suppressed T1 gradient echo at 1.5–3 T, where muscle and fibroglandular tissue are both dark.
struct T1Signal {
  double fat = 1000.0;
  double fibroglandular = 420.0;
  double skin = 550.0;
  double lesion = 450.0;
  double muscle = 330.0;       ///< the phantom's chest wall (pectoral muscle) and the intercostal muscle
  double rib_marrow = 750.0;   ///< fatty marrow inside the ribs
  double rib_cortex = 80.0;    ///< cortical bone (signal void)
  double lung = 40.0;
  double air = 0.0;
};

/// Every knob of the synthetic image, with its unit.
struct SyntheticMriParams {
  T1Signal signal;
  double voxel_size_mm = 1.0;        ///< isotropic output voxel [mm], in [0.2, 5]
  double blur_fwhm_mm = 1.2;         ///< FWHM of the Gaussian point-spread function [mm], ≥ 0 (0 = none)
  double bias_amplitude = 0.25;      ///< a: the bias field lies in [e^−a, e^a], in [0, 1]
  double bias_wavelength_mm = 200.0; ///< shortest wavelength of the bias field [mm], ≥ 20
  double noise_sigma = 20.0;         ///< σ of each quadrature channel of the Rician noise [a.u.], ≥ 0
  double margin_mm = 10.0;           ///< air around the phantom's tissue in the output grid [mm], ≥ 0
  double thorax_depth_mm = 40.0;     ///< thorax behind the chest wall's posterior face [mm], ≥ 0
  double intercostal_depth_mm = 14.0;  ///< intercostal muscle and ribs, then lung [mm], ≤ thorax depth
  double rib_spacing_mm = 24.0;      ///< ribs run left-right, one every this along z [mm], > 0
  double rib_radius_mm = 5.0;        ///< outer radius of a rib [mm], ≥ 0 (0 = no ribs)
  double rib_cortex_mm = 1.0;        ///< thickness of the rib's cortex [mm]
  /// Output grid size [voxels]; 0 in a component = fit the tissue plus margins (and the thorax) along
  /// that axis; a larger size adds air (and thorax) around the same centre.
  Eigen::Vector3i size_voxels = Eigen::Vector3i::Zero();
  std::uint64_t seed = 1;            ///< bias field and noise
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// A rendered image and its truth.
struct SyntheticMri {
  ScalarImage image;        ///< the T1 image [a.u.], geometry in m, LPS, identity direction
  /// The label at each output voxel centre (nearest phantom voxel; the thorax and lung behind the
  /// chest wall carry the first chest-wall label, everything else the phantom's labels).
  LabelImage truth;
  ScalarImage bias_field;   ///< b on the output grid (the image is ≈ b × the clean image)
};

/// Renders the synthetic T1 image of a phantom given in LPS patient space (anterior = −y: the
/// breast hangs towards −y, the chest wall is at its +y side). The thorax fills the output grid
/// posterior to the plane y = y_w through the most posterior face of the chest-wall voxels.
/// @param labels  which phantom labels are which tissue (labels in no set are air)
/// @throws std::invalid_argument for invalid params, an invalid phantom, a phantom without tissue or
///         without chest-wall voxels, or an output grid of more than 2^28 voxels.
SyntheticMri renderSyntheticT1(const LabelImage& phantom_lps, const TissueLabels& labels, const SyntheticMriParams& params);

/// The VICTRE phantom (shared/data/victre-phantom) placed in LPS patient space as a prone left breast.
/// Its file's axes are not anatomical: x runs chest wall → nipple (anterior), z inferior → superior,
/// and y, in the generator's right-handed frame, z × x = towards the patient's left (lateral for this
/// left breast). The rotation R = [[0, 1, 0], [−1, 0, 0], [0, 0, 1]] (det 1) takes those axes to LPS:
/// LPS x = y_victre, y = −x_victre, z = z_victre. The labels are not resampled: only the origin and the
/// direction change (direction ← R · direction, origin ← R · origin), so every voxel keeps its tissue.
LabelImage victrePhantomInLps(const LabelImage& victre);

/// The VICTRE rotation of victrePhantomInLps (a point of the phantom's file → LPS).
Eigen::Matrix3d victreToLpsRotation();

}  // namespace breast_sim::core
