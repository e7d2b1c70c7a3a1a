#include "breast_sim/core/mri/synthetic_mri.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

#include <Eigen/Geometry>

#include "breast_sim/core/mri/mri_volume.h"
#include "label_lookup.h"

namespace breast_sim::core {

namespace {

[[noreturn]] void bad(const std::string& field, double value, const std::string& range) {
  std::ostringstream s;
  s << "synthetic MRI: " << field << " = " << value << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

void inRange(const std::string& field, double v, double lo, double hi, const std::string& unit = "") {
  if (!(v >= lo && v <= hi) || !std::isfinite(v)) {
    std::ostringstream r;
    r << "[" << lo << ", " << hi << "]" << (unit.empty() ? "" : " " + unit);
    bad(field, v, r.str());
  }
}

// splitmix64: a counter-based generator, so each voxel's noise depends on (seed, voxel) alone.
std::uint64_t mix(std::uint64_t z) {
  z += 0x9E3779B97F4A7C15ULL;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}

// A uniform number in (0, 1).
double uniform(std::uint64_t bits) { return (static_cast<double>(bits >> 11) + 0.5) * (1.0 / 9007199254740992.0); }

// The thorax behind the chest wall's posterior plane y = wall_y: intercostal muscle with ribs that run
// along x (left-right), then lung.
struct Thorax {
  double wall_y = 0, depth = 0, intercostal = 0, rib_spacing = 1, rib_radius = 0, rib_cortex = 0, rib_z0 = 0;
  bool contains(const Eigen::Vector3d& p) const { return depth > 0 && p.y() > wall_y; }
  double signal(const Eigen::Vector3d& p, const T1Signal& s) const {
    const double d = p.y() - wall_y;
    if (d > intercostal) return s.lung;
    if (rib_radius > 0) {
      const double dz = p.z() - rib_z0 - rib_spacing * std::round((p.z() - rib_z0) / rib_spacing);
      const double dy = d - 0.5 * intercostal;
      const double r = std::hypot(dy, dz);
      if (r <= rib_radius - rib_cortex) return s.rib_marrow;
      if (r <= rib_radius) return s.rib_cortex;
    }
    return s.muscle;
  }
};

double tissueSignal(TissueClass c, const T1Signal& s) {
  switch (c) {
    case TissueClass::kFat: return s.fat;
    case TissueClass::kFibroglandular: return s.fibroglandular;
    case TissueClass::kSkin: return s.skin;
    case TissueClass::kLesion: return s.lesion;
    case TissueClass::kChestWall: return s.muscle;
    case TissueClass::kAir: break;
  }
  return s.air;
}

// Half the extent of a voxel along each patient axis [m].
Eigen::Vector3d halfVoxelExtent(const LabelImage& image) {
  return 0.5 * (image.direction.cwiseAbs() * image.spacing_m);
}

// An axis-aligned LPS grid covering [lo, hi] with spacing h, its origin on the lattice of the
// phantom's voxel centres where the phantom's axes are the patient axes (so a grid of the phantom's
// spacing samples its voxels exactly, without ties).
ImageGeometry alignedGrid(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, double h, const LabelImage& phantom,
                          const Eigen::Vector3i& forced_size) {
  ImageGeometry g;
  g.spacing_m = Eigen::Vector3d::Constant(h);
  const Eigen::Vector3d centre = 0.5 * (lo + hi);
  for (int a = 0; a < 3; ++a) {
    const int n = forced_size[a] > 0 ? forced_size[a] : static_cast<int>(std::ceil((hi[a] - lo[a]) / h - 1e-9)) + 1;
    g.size[a] = n;
    g.origin_m[a] = centre[a] - 0.5 * (n - 1) * h;
    // The phantom axis along patient axis a, if any: snap to its voxel centres.
    for (int b = 0; b < 3; ++b) {
      if (std::abs(std::abs(phantom.direction(a, b)) - 1.0) < 1e-9) {
        const double step = phantom.spacing_m[b];
        g.origin_m[a] = phantom.origin_m[a] + step * std::round((g.origin_m[a] - phantom.origin_m[a]) / step);
      }
    }
  }
  return g;
}

constexpr long kMaxVoxels = 1L << 28;

void checkSize(const ImageGeometry& g, const char* what) {
  long n = 1;
  for (int a = 0; a < 3; ++a) {
    if (g.size[a] < 1 || n > kMaxVoxels / g.size[a]) {
      std::ostringstream s;
      s << "synthetic MRI: the " << what << " would have " << g.size.transpose() << " voxels, more than 2^28; use larger "
        << "voxels or a smaller size_voxels";
      throw std::invalid_argument(s.str());
    }
    n *= g.size[a];
  }
}

}  // namespace

void SyntheticMriParams::validate() const {
  for (const auto& [name, v] : {std::pair<const char*, double>{"signal.fat", signal.fat},
                                {"signal.fibroglandular", signal.fibroglandular},
                                {"signal.skin", signal.skin},
                                {"signal.lesion", signal.lesion},
                                {"signal.muscle", signal.muscle},
                                {"signal.rib_marrow", signal.rib_marrow},
                                {"signal.rib_cortex", signal.rib_cortex},
                                {"signal.lung", signal.lung},
                                {"signal.air", signal.air}})
    inRange(name, v, 0.0, 30000.0, "a.u.");
  inRange("voxel_size_mm", voxel_size_mm, 0.2, 5.0, "mm");
  inRange("blur_fwhm_mm", blur_fwhm_mm, 0.0, 20.0, "mm");
  inRange("bias_amplitude", bias_amplitude, 0.0, 1.0);
  inRange("bias_wavelength_mm", bias_wavelength_mm, 20.0, 1e5, "mm");
  inRange("noise_sigma", noise_sigma, 0.0, 30000.0, "a.u.");
  inRange("margin_mm", margin_mm, 0.0, 500.0, "mm");
  inRange("thorax_depth_mm", thorax_depth_mm, 0.0, 500.0, "mm");
  inRange("intercostal_depth_mm", intercostal_depth_mm, 0.0, thorax_depth_mm, "mm (at most thorax_depth_mm)");
  inRange("rib_spacing_mm", rib_spacing_mm, 1.0, 1000.0, "mm");
  inRange("rib_radius_mm", rib_radius_mm, 0.0, 0.5 * rib_spacing_mm, "mm (at most half the rib spacing)");
  inRange("rib_cortex_mm", rib_cortex_mm, 0.0, std::max(rib_radius_mm, 0.0), "mm (at most the rib radius)");
  for (int a = 0; a < 3; ++a) inRange("size_voxels", size_voxels[a], 0, 4096, "voxels");
}

Eigen::Matrix3d victreToLpsRotation() {
  Eigen::Matrix3d r;
  r << 0, 1, 0,
      -1, 0, 0,
       0, 0, 1;
  return r;
}

LabelImage victrePhantomInLps(const LabelImage& victre) {
  victre.validate();
  LabelImage out = victre;
  const Eigen::Matrix3d r = victreToLpsRotation();
  out.direction = r * victre.direction;
  out.origin_m = r * victre.origin_m;
  return out;
}

SyntheticMri renderSyntheticT1(const LabelImage& phantom, const TissueLabels& labels, const SyntheticMriParams& params) {
  params.validate();
  phantom.validate();
  labels.validate();
  const T1Signal& sig = params.signal;

  // The tissue's box and the chest wall's posterior plane, from the voxels' extents.
  const Eigen::Vector3d half = halfVoxelExtent(phantom);
  Eigen::AlignedBox3d tissue_box;
  double wall_y = -std::numeric_limits<double>::infinity();
  for (int k = 0; k < phantom.size.z(); ++k)
    for (int j = 0; j < phantom.size.y(); ++j)
      for (int i = 0; i < phantom.size.x(); ++i) {
        const TissueClass c = labels.classify(phantom.at(i, j, k));
        if (c == TissueClass::kAir) continue;
        const Eigen::Vector3d p = phantom.indexToPhysical(Eigen::Vector3d(i, j, k));
        tissue_box.extend(p - half);
        tissue_box.extend(p + half);
        if (c == TissueClass::kChestWall) wall_y = std::max(wall_y, p.y() + half.y());
      }
  if (tissue_box.isEmpty()) throw std::invalid_argument("synthetic MRI: the phantom has no tissue (every label is air)");
  if (!std::isfinite(wall_y))
    throw std::invalid_argument("synthetic MRI: the phantom has no chest-wall voxel (labels " +
                                std::to_string(labels.chest_wall.empty() ? 0 : *labels.chest_wall.begin()) +
                                "…); the thorax is placed behind it");
  const double margin = params.margin_mm * 1e-3;
  const double h = params.voxel_size_mm * 1e-3;
  Eigen::Vector3d lo = tissue_box.min() - Eigen::Vector3d::Constant(margin);
  Eigen::Vector3d hi = tissue_box.max() + Eigen::Vector3d::Constant(margin);
  Thorax thorax;
  thorax.wall_y = wall_y;
  thorax.depth = params.thorax_depth_mm * 1e-3;
  thorax.intercostal = params.intercostal_depth_mm * 1e-3;
  thorax.rib_spacing = params.rib_spacing_mm * 1e-3;
  thorax.rib_radius = params.rib_radius_mm * 1e-3;
  thorax.rib_cortex = params.rib_cortex_mm * 1e-3;
  thorax.rib_z0 = tissue_box.center().z();
  if (thorax.depth > 0) hi.y() = wall_y + thorax.depth;  // the field of view cuts through the thorax
  const ImageGeometry out_grid = alignedGrid(lo, hi, h, phantom, params.size_voxels);
  checkSize(out_grid, "output grid");

  // The signal map on a grid at the phantom's resolution (at most 4 samples per output voxel and axis),
  // covering the output grid and the point-spread function's reach.
  const double sigma_psf = params.blur_fwhm_mm * 1e-3 / (2.0 * std::sqrt(2.0 * std::log(2.0)));
  double fine_h = std::max(phantom.spacing_m.minCoeff(), h / 4.0);
  const Eigen::Vector3d out_lo = out_grid.origin_m, out_hi = out_grid.indexToPhysical((out_grid.size.cast<double>().array() - 1.0).matrix());
  const Eigen::Vector3d pad = Eigen::Vector3d::Constant(4.0 * sigma_psf + h);
  ImageGeometry fine_grid = alignedGrid(out_lo - pad, out_hi + pad, fine_h, phantom, Eigen::Vector3i::Zero());
  if (fine_grid.numVoxels() > (1L << 26)) {  // a fine phantom in a large field of view: render at the output voxel
    fine_h = h;
    fine_grid = alignedGrid(out_lo - pad, out_hi + pad, fine_h, phantom, Eigen::Vector3i::Zero());
  }
  checkSize(fine_grid, "rendering grid");
  // The signal of each label value (a table: the label sets are searched once, not per voxel).
  std::vector<float> signal_of(65536);
  for (int l = 0; l < 65536; ++l) signal_of[l] = static_cast<float>(tissueSignal(labels.classify(static_cast<std::uint16_t>(l)), sig));
  const LabelLookup label_at(phantom);
  ScalarImage fine;
  fine.geometry = fine_grid;
  fine.values.resize(static_cast<std::size_t>(fine_grid.numVoxels()));
#pragma omp parallel for schedule(static)
  for (int k = 0; k < fine_grid.size.z(); ++k)
    for (int j = 0; j < fine_grid.size.y(); ++j)
      for (int i = 0; i < fine_grid.size.x(); ++i) {
        const Eigen::Vector3d p = fine_grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        const double s = thorax.contains(p) ? thorax.signal(p, sig) : signal_of[label_at(p)];
        fine.values[fine_grid.index(i, j, k)] = static_cast<float>(s);
      }
  if (sigma_psf > 0) fine = gaussianFilter(fine, sigma_psf);

  // The bias field's plane waves, drawn from the seed.
  struct Wave {
    Eigen::Vector3d k;
    double phase, amplitude;
  };
  std::vector<Wave> waves;
  std::uint64_t state = mix(params.seed ^ 0xB1A5F1E1DULL);
  const auto next = [&] { return uniform(state = mix(state)); };
  for (int w = 0; w < 8; ++w) {
    const double cos_t = 2.0 * next() - 1.0, phi = 2.0 * M_PI * next();
    const double sin_t = std::sqrt(std::max(0.0, 1.0 - cos_t * cos_t));
    const Eigen::Vector3d dir(sin_t * std::cos(phi), sin_t * std::sin(phi), cos_t);
    const double wavelength = params.bias_wavelength_mm * 1e-3 * (1.0 + 2.0 * next());
    waves.push_back({2.0 * M_PI / wavelength * dir, 2.0 * M_PI * next(), 0.5 + 0.5 * next()});
  }

  SyntheticMri out;
  out.image.geometry = out_grid;
  out.image.values.resize(static_cast<std::size_t>(out_grid.numVoxels()));
  out.bias_field.geometry = out_grid;
  out.bias_field.values.resize(out.image.values.size());
  out.truth = labelImageLike(out.image);
  const std::uint16_t wall_label = *labels.chest_wall.begin();
  const Eigen::Vector3d centre = out_grid.indexToPhysical(0.5 * (out_grid.size.cast<double>().array() - 1.0).matrix());
  std::vector<double> f(out.image.values.size());
  double f_max = 0.0;
#pragma omp parallel for schedule(static) reduction(max : f_max)
  for (int k = 0; k < out_grid.size.z(); ++k)
    for (int j = 0; j < out_grid.size.y(); ++j)
      for (int i = 0; i < out_grid.size.x(); ++i) {
        const long v = out_grid.index(i, j, k);
        const Eigen::Vector3d p = out_grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        double s = 0.0;
        for (const Wave& w : waves) s += w.amplitude * std::cos(w.k.dot(p - centre) + w.phase);
        f[v] = s;
        f_max = std::max(f_max, std::abs(s));
        out.truth.labels[v] = thorax.contains(p) ? wall_label : label_at(p);
      }
  const double scale = f_max > 0 ? params.bias_amplitude / f_max : 0.0;
  const double sigma = params.noise_sigma;
#pragma omp parallel for schedule(static)
  for (int k = 0; k < out_grid.size.z(); ++k)
    for (int j = 0; j < out_grid.size.y(); ++j)
      for (int i = 0; i < out_grid.size.x(); ++i) {
        const long v = out_grid.index(i, j, k);
        const double clean = sampleTrilinear(fine, out_grid.indexToPhysical(Eigen::Vector3d(i, j, k)));
        const double b = std::exp(scale * f[v]);
        double value = clean * b;
        if (sigma > 0) {
          const std::uint64_t key = mix(params.seed) ^ static_cast<std::uint64_t>(v);
          const double u1 = uniform(mix(2 * key)), u2 = uniform(mix(2 * key + 1));
          const double r = sigma * std::sqrt(-2.0 * std::log(u1));
          value = std::hypot(value + r * std::cos(2.0 * M_PI * u2), r * std::sin(2.0 * M_PI * u2));
        }
        out.image.values[v] = static_cast<float>(value);
        out.bias_field.values[v] = static_cast<float>(b);
      }
  return out;
}

}  // namespace breast_sim::core
