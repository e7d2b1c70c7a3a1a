#pragma once
// Shared by the MRI tests (test_mri_*.cpp): the VICTRE phantom in LPS, small synthetic T1 images
// rendered from it, and the message of a thrown exception.

#include <functional>
#include <stdexcept>
#include <string>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/synthetic_mri.h"

namespace breast_sim::test {

/// The 1 mm VICTRE phantom of test/data, turned into LPS patient space (read once).
inline const core::LabelImage& victreLps() {
  static const core::LabelImage phantom =
      core::victrePhantomInLps(core::readLabelImage(std::string(BREAST_SIM_TEST_DATA_DIR) + "/victre_labels_1mm.nrrd"));
  return phantom;
}

/// Image parameters with a tight field of view (5 mm of air, 25 mm of thorax), so a test's image is
/// about 1.7 million voxels.
inline core::SyntheticMriParams smallImageParams(std::uint64_t seed) {
  core::SyntheticMriParams p;
  p.margin_mm = 5.0;
  p.thorax_depth_mm = 25.0;
  p.seed = seed;
  return p;
}

/// what() of the exception of type E that `f` throws, or "" if it throws none.
template <typename E = std::runtime_error>
std::string messageOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const E& e) {
    return e.what();
  }
  return "";
}

}  // namespace breast_sim::test
