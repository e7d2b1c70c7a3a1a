#pragma once
/// @file case_file.h
/// The settings a case runs with, written back as a case file: every key the case readers accept
/// (model_case.h, phantom.h, mri_case.h, mri_segmentation.h, simulation_settings.h, prone_to_supine.h),
/// each with the value the run uses, in the file's units (mm, degrees, Pa, s). A run's output holds
/// it, so the run can be repeated and every default it took can be read; loading the text again
/// gives the same settings.

#include <string>

#include "breast_sim/core/model/image_mesher.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::core {

/// The case file `case_path` (with its `base:` files) with every setting filled in: `phantom:` (all
/// parameters), `image:` or `mesh:` (as given, its path made absolute) or `mri:` (every key, paths
/// absolute) with the complete `segmentation:` map, `lesions:` as given, and the complete
/// `meshing:`, `simulation:`, `stiffening:`, `sliding:`, `morphing:`, `coarse_start:` and `uncertainty:` maps. Numbers
/// carry 12 significant digits. Does not read the image (nor segment the MRI) or build a model.
/// @throws std::runtime_error as the case readers do for a case they reject.
std::string effectiveCaseYaml(const std::string& case_path);

/// The same with the settings maps taken from the given settings (e.g. after command-line
/// overrides) instead of the file; the tissue source, `segmentation:` and `lesions:` still come from the file.
/// @throws std::invalid_argument for settings a case file cannot express.
std::string effectiveCaseYaml(const std::string& case_path, const MeshingOptions& meshing,
                              double lesion_snap_tolerance_m, const PipelineSettings& settings);

}  // namespace breast_sim::core
