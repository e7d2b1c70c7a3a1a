// breast_sim_make_mri: renders a synthetic T1-weighted prone breast MRI from a label phantom (by
// default the VICTRE phantom of test/data) with its ground-truth labels (mri/synthetic_mri.h), and
// writes it as NIfTI / NRRD / MetaImage and optionally as a DICOM series.
#include <chrono>
#include <cstdio>
#include <iostream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/mri/synthetic_mri.h"
#include "mri_tool_args.h"

using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_make_mri PHANTOM --out IMAGE [--truth LABELS] [--dicom FOLDER] [options]

Renders a synthetic T1-weighted prone breast MRI from a label phantom (include/breast_sim/core/mri/synthetic_mri.h).
  PHANTOM                 label image (NRRD, NIfTI, MetaImage), e.g. test/data/victre_labels_1mm.nrrd
  --phantom-space S       victre (default: the VICTRE file's axes, x chest wall -> nipple, turned into LPS)
                          or lps (the phantom is already in LPS patient space, anterior = -y)
  --out IMAGE             the image: .nii, .nii.gz, .nrrd or .mha (float, LPS geometry)
  --truth LABELS          the labels it was rendered from, on the image's grid (.nrrd, .nii.gz, .mha)
  --dicom FOLDER          also a DICOM MR series (int16), one file per axial slice, into a new folder
Signal of each tissue [a.u.] (defaults: a T1 gradient echo without fat suppression):
  --fat 1000 --fibroglandular 420 --skin 550 --lesion 450 --muscle 330 --rib-marrow 750 --rib-cortex 80
  --lung 40 --air 0
Image:
  --voxel-size-mm 1       isotropic output voxel [mm]
  --blur-fwhm-mm 1.2      point-spread function (partial volume) [mm]
  --bias-amplitude 0.25   bias field within [e^-a, e^a]
  --bias-wavelength-mm 200  shortest wavelength of the bias field [mm]
  --noise-sigma 20        Rician noise, sigma per channel [a.u.]
  --margin-mm 10          air around the tissue [mm]
  --thorax-depth-mm 40    thorax behind the chest wall [mm] (0 = none)
  --intercostal-depth-mm 14  intercostal muscle and ribs, then lung [mm]
  --rib-spacing-mm 24 --rib-radius-mm 5 --rib-cortex-mm 1   ribs [mm] (radius 0 = none)
  --size X,Y,Z            output grid [voxels] (0 = fit), e.g. 256,256,160
  --seed N                bias field and noise (default 1)
)";

Eigen::Vector3i parseSize(const std::string& text) {
  Eigen::Vector3i s;
  char c1 = 0, c2 = 0;
  std::istringstream in(text);
  if (!(in >> s.x() >> c1 >> s.y() >> c2 >> s.z()) || c1 != ',' || c2 != ',')
    throw std::invalid_argument("--size needs X,Y,Z in voxels, got '" + text + "'");
  return s;
}

}  // namespace

int main(int argc, char** argv) try {
  SyntheticMriParams p;
  std::string phantom_path;
  std::string space = "victre", out, truth, dicom;
  std::map<std::string, double*> numbers = {
      {"--fat", &p.signal.fat}, {"--fibroglandular", &p.signal.fibroglandular}, {"--skin", &p.signal.skin},
      {"--lesion", &p.signal.lesion}, {"--muscle", &p.signal.muscle}, {"--rib-marrow", &p.signal.rib_marrow},
      {"--rib-cortex", &p.signal.rib_cortex}, {"--lung", &p.signal.lung}, {"--air", &p.signal.air},
      {"--voxel-size-mm", &p.voxel_size_mm}, {"--blur-fwhm-mm", &p.blur_fwhm_mm}, {"--bias-amplitude", &p.bias_amplitude},
      {"--bias-wavelength-mm", &p.bias_wavelength_mm}, {"--noise-sigma", &p.noise_sigma}, {"--margin-mm", &p.margin_mm},
      {"--thorax-depth-mm", &p.thorax_depth_mm}, {"--intercostal-depth-mm", &p.intercostal_depth_mm},
      {"--rib-spacing-mm", &p.rib_spacing_mm}, {"--rib-radius-mm", &p.rib_radius_mm}, {"--rib-cortex-mm", &p.rib_cortex_mm}};
  breast_sim::tools::Arguments args(argc, argv, kUsage);
  while (args.next()) {
    const std::string& a = args.option();
    if (args.help()) return 0;
    if (a == "--out") out = args.value();
    else if (a == "--truth") truth = args.value();
    else if (a == "--dicom") dicom = args.value();
    else if (a == "--phantom-space") space = args.value();
    else if (a == "--size") p.size_voxels = parseSize(args.value());
    else if (a == "--seed") p.seed = std::stoull(args.value());
    else if (numbers.count(a)) {
      const std::string v = args.value();
      std::size_t used = 0;
      *numbers[a] = std::stod(v, &used);
      if (used != v.size()) throw std::invalid_argument(a + " needs a number, got '" + v + "'");
    } else if (args.positional() && phantom_path.empty()) {
      phantom_path = a;
    } else {
      args.unknown();
    }
  }
  if (phantom_path.empty()) throw std::invalid_argument(std::string("give the PHANTOM label image\n") + kUsage);
  if (out.empty()) throw std::invalid_argument(std::string("--out IMAGE is required\n") + kUsage);
  if (space != "victre" && space != "lps") throw std::invalid_argument("--phantom-space must be victre or lps, got '" + space + "'");
  const auto t0 = std::chrono::steady_clock::now();
  LabelImage phantom = readLabelImage(phantom_path);
  if (space == "victre") phantom = victrePhantomInLps(phantom);
  const SyntheticMri mri = renderSyntheticT1(phantom, TissueLabels{}, p);
  const double render_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  writeMriVolume(out, mri.image);
  if (!truth.empty()) writeLabelImage(truth, mri.truth);
  if (!dicom.empty()) {
    DicomSeriesOptions o;
    o.uid_seed = p.seed;
    writeDicomSeries(dicom, mri.image, o);
  }
  const ImageGeometry& g = mri.image.geometry;
  std::printf("synthetic T1 MRI of %s: %d x %d x %d voxels of %.2f mm, origin (%.2f, %.2f, %.2f) mm (LPS), rendered in %.2f s\n",
              phantom_path.c_str(), g.size.x(), g.size.y(), g.size.z(), 1e3 * g.spacing_m.x(), 1e3 * g.origin_m.x(),
              1e3 * g.origin_m.y(), 1e3 * g.origin_m.z(), render_s);
  std::printf("  fat %.0f, fibroglandular %.0f, muscle %.0f, skin %.0f; bias amplitude %.2f (wavelength >= %.0f mm), noise "
              "sigma %.1f, PSF FWHM %.2f mm, seed %llu\n",
              p.signal.fat, p.signal.fibroglandular, p.signal.muscle, p.signal.skin, p.bias_amplitude, p.bias_wavelength_mm,
              p.noise_sigma, p.blur_fwhm_mm, static_cast<unsigned long long>(p.seed));
  std::printf("  wrote %s%s%s%s%s\n", out.c_str(), truth.empty() ? "" : ", ", truth.c_str(), dicom.empty() ? "" : ", DICOM series in ",
              dicom.c_str());
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "breast_sim_make_mri: %s\n", e.what());
  return 2;
}
