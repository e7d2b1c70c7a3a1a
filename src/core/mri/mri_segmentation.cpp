#include "breast_sim/core/mri/mri_segmentation.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

#include "breast_sim/core/image/distance_transform.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "chest_wall_boundary.h"
#include "grid_conversion.h"
#include "label_lookup.h"

namespace breast_sim::core {

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

std::string mm(const Eigen::Vector3d& p_m) {
  std::ostringstream s;
  s.precision(1);
  s << std::fixed << "(" << 1e3 * p_m.x() << ", " << 1e3 * p_m.y() << ", " << 1e3 * p_m.z() << ") mm";
  return s.str();
}

// The voxels of one grid axis seen as columns running from anterior to posterior: scan position s = 0
// is the most anterior voxel of a column.
struct Columns {
  ImageGeometry g;
  int axis = 1, u_axis = 0, v_axis = 2, sign = -1, n = 0;
  long stride[3] = {1, 0, 0};

  Columns(const ImageGeometry& geometry, int axis_, int sign_) : g(geometry), axis(axis_), sign(sign_) {
    u_axis = axis == 0 ? 1 : 0;
    v_axis = axis == 2 ? 1 : 2;
    n = g.size[axis];
    stride[0] = 1;
    stride[1] = g.size.x();
    stride[2] = static_cast<long>(g.size.x()) * g.size.y();
  }
  int nu() const { return g.size[u_axis]; }
  int nv() const { return g.size[v_axis]; }
  // The grid index along `axis` of scan position s (fractional allowed).
  double gridIndex(double s) const { return sign > 0 ? (n - 1) - s : s; }
  // Memory index of scan position s in column (u, v), and the step between scan positions.
  long first(int u, int v) const {
    return u * stride[u_axis] + v * stride[v_axis] + (sign > 0 ? (n - 1) * stride[axis] : 0);
  }
  long step() const { return sign > 0 ? -stride[axis] : stride[axis]; }
};

// A percentile of a strided sample of the values (deterministic, linear time).
double samplePercentile(const std::vector<float>& values, double q) {
  std::vector<float> sample;
  const long n = static_cast<long>(values.size());
  const long stride = std::max(1L, n / 2000000);
  sample.reserve(static_cast<std::size_t>(n / stride + 1));
  for (long v = 0; v < n; v += stride) sample.push_back(values[v]);
  const auto at = sample.begin() + static_cast<long>(q * static_cast<double>(sample.size() - 1));
  std::nth_element(sample.begin(), at, sample.end());
  return *at;
}

std::vector<std::uint8_t> above(const std::vector<float>& values, double threshold) {
  std::vector<std::uint8_t> m(values.size());
#pragma omp parallel for schedule(static)
  for (long v = 0; v < static_cast<long>(values.size()); ++v) m[v] = values[v] >= threshold;
  return m;
}

// Components of `mask` with at least `share` of the largest's voxels; the others are cleared. With
// `component`, each kept voxel's component (1 = largest) goes there, 0 elsewhere.
std::vector<std::uint8_t> largeComponents(const itk_bridge::Grid& grid, const std::vector<std::uint8_t>& mask, double share,
                                          std::vector<std::int32_t>* component = nullptr, int* kept = nullptr) {
  std::vector<long> sizes;
  std::vector<std::int32_t> cc = itk_bridge::connectedComponents(grid, mask, false, &sizes);
  std::vector<std::uint8_t> out(mask.size(), 0);
  int keep = 0;
  while (keep < static_cast<int>(sizes.size()) && static_cast<double>(sizes[keep]) >= share * static_cast<double>(sizes[0])) ++keep;
#pragma omp parallel for schedule(static)
  for (long v = 0; v < static_cast<long>(mask.size()); ++v) {
    out[v] = cc[v] >= 1 && cc[v] <= keep;
    if (!out[v]) cc[v] = 0;
  }
  if (component) component->swap(cc);
  if (kept) *kept = keep;
  return out;
}

// Calls f(index) for each of the (up to six) face neighbours of voxel (i, j, k) inside the grid.
template <typename F>
void forEachFaceNeighbour(const ImageGeometry& g, int i, int j, int k, F&& f) {
  for (int a = 0; a < 3; ++a)
    for (int d : {-1, 1}) {
      Eigen::Vector3i q(i, j, k);
      q[a] += d;
      if (q[a] >= 0 && q[a] < g.size[a]) f(g.index(q.x(), q.y(), q.z()));
    }
}

std::uint16_t firstLabel(const std::set<std::uint16_t>& s) { return *s.begin(); }

}  // namespace

std::uint16_t segmentationLabel(TissueClass c) {
  static const TissueLabels defaults;
  switch (c) {
    case TissueClass::kFat: return firstLabel(defaults.fat);
    case TissueClass::kFibroglandular: return firstLabel(defaults.fibroglandular);
    case TissueClass::kSkin: return firstLabel(defaults.skin);
    case TissueClass::kLesion: return firstLabel(defaults.lesion);
    case TissueClass::kChestWall: return firstLabel(defaults.chest_wall);
    case TissueClass::kAir: break;
  }
  return 0;
}

bool ChestWallBoundary::posterior(const Eigen::Vector3i& ijk) const {
  const double b = index[ijk[u_axis] + static_cast<long>(size.x()) * ijk[v_axis]];
  return anterior_sign > 0 ? ijk[axis] < b : ijk[axis] > b;
}

MriSegmentation segmentProneMri(const ScalarImage& image, const SegmentationSettings& settings, const LesionMarks& lesions) {
  const auto t_start = Clock::now();
  settings.validate();
  const ImageGeometry& g = image.geometry;
  g.validate();
  const long nvox = g.numVoxels();
  if (static_cast<long>(image.values.size()) != nvox)
    throw std::invalid_argument("segmentProneMri: the image has " + std::to_string(image.values.size()) +
                                " values for a grid of " + std::to_string(nvox) + " voxels");
  for (int a = 0; a < 3; ++a)
    if (g.size[a] < 3)
      throw std::invalid_argument("segmentProneMri: the image has " + std::to_string(g.size[a]) + " voxels along axis " +
                                  std::to_string(a) + "; a breast MRI is a 3-D volume");
  const itk_bridge::Grid grid = bridgeGrid(g);
  MriSegmentation out;
  SegmentationReport& report = out.report;

  // The grid axis along which the chest wall is searched: the one nearest the anterior direction.
  const Eigen::Vector3d anterior = settings.prone_gravity_direction.normalized();
  int axis = 0;
  for (int a = 1; a < 3; ++a)
    if (std::abs(g.direction.col(a).dot(anterior)) > std::abs(g.direction.col(axis).dot(anterior))) axis = a;
  const double cosine = g.direction.col(axis).dot(anterior);
  if (std::abs(cosine) < std::cos(M_PI / 4)) {
    std::ostringstream s;
    s << "no grid axis of the image is within 45 deg of the anterior direction (" << anterior.transpose()
      << ", segmentation.prone_gravity_direction; the nearest is axis " << axis << " at "
      << std::acos(std::min(1.0, std::abs(cosine))) * 180.0 / M_PI
      << " deg): the chest wall is searched along a grid axis; resample the image or correct the direction";
    throw std::runtime_error(s.str());
  }
  const Columns cols(g, axis, cosine > 0 ? +1 : -1);

  // 1. Bias correction (N4 within the voxels above Otsu's threshold of the whole image).
  auto t0 = Clock::now();
  ScalarImage corrected = image;
  std::vector<float> bias;
  if (settings.bias_correction) {
    itk_bridge::N4Options n4;
    n4.shrink_factor = settings.n4_shrink_factor;
    n4.fitting_levels = settings.n4_fitting_levels;
    n4.iterations_per_level = settings.n4_iterations;
    n4.spline_distance_mm = settings.n4_spline_distance_mm;
    itk_bridge::Grid field_grid;
    ScalarImage field;
    field.values = itk_bridge::n4BiasField(grid, image.values, n4, &field_grid);
    field.geometry = geometryOf(field_grid);
    bias.resize(static_cast<std::size_t>(nvox));
#pragma omp parallel for schedule(static)
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const long v = g.index(i, j, k);
          bias[v] = static_cast<float>(sampleTrilinear(field, g.indexToPhysical(Eigen::Vector3d(i, j, k))));
          corrected.values[v] = image.values[v] / bias[v];
        }
  }
  report.seconds_bias = since(t0);

  // 2. Levels, body and fat.
  t0 = Clock::now();
  const ScalarImage smooth = settings.smoothing_sigma_mm > 0 ? gaussianFilter(corrected, settings.smoothing_sigma_mm * 1e-3) : corrected;
  const std::vector<float>& I = smooth.values;
  const double bright = 0.6 * samplePercentile(I, 0.995);
  std::vector<float> fat_sample;
  for (long v = 0; v < nvox; v += std::max(1L, nvox / 2000000))
    if (I[v] >= bright) fat_sample.push_back(I[v]);
  if (!(bright > 0) || fat_sample.size() < 100)
    throw std::runtime_error("no bright tissue in the image (99.5th percentile " + std::to_string(bright / 0.6) +
                             "): a T1-weighted breast MRI shows fat brightest; is the image empty or fat-suppressed?");
  std::nth_element(fat_sample.begin(), fat_sample.begin() + fat_sample.size() / 2, fat_sample.end());
  const double F = fat_sample[fat_sample.size() / 2];
  report.fat_level = F;
  report.body_threshold = settings.body_threshold * F;
  // The background (air and lung: Rician noise) must stay below the body threshold: its level is the
  // most frequent value below the threshold, its spread that of the values below that level (the
  // noise's lower flank, which no tissue reaches), and the threshold rises to the level plus
  // body_noise_margin spreads when the noise is strong.
  {
    constexpr int kBins = 400;
    std::vector<long> histogram(kBins, 0);
    const double width = report.body_threshold / kBins;
    for (long v = 0; v < nvox; v += std::max(1L, nvox / 4000000))
      if (I[v] >= 0 && I[v] < report.body_threshold) ++histogram[std::min(kBins - 1, static_cast<int>(I[v] / width))];
    const int mode = static_cast<int>(std::max_element(histogram.begin(), histogram.end()) - histogram.begin());
    const double level = (mode + 0.5) * width;
    double sum = 0.0;
    long count = 0;
    for (int b = 0; b < mode; ++b) {
      const double d = level - (b + 0.5) * width;
      sum += histogram[b] * d * d;
      count += histogram[b];
    }
    const double spread = count ? std::sqrt(sum / count) : 0.0;
    report.noise_level = level;
    report.noise_spread = spread;
    report.body_threshold = std::max(report.body_threshold, level + settings.body_noise_margin * spread);
  }
  const std::vector<std::uint8_t> body = above(I, report.body_threshold);
  double t_fat = itk_bridge::otsuThreshold(grid, I, body);
  if (!(t_fat > report.body_threshold && t_fat < F)) t_fat = 0.5 * (report.body_threshold + F);
  std::vector<std::uint8_t> fat(static_cast<std::size_t>(nvox));
#pragma omp parallel for schedule(static)
  for (long v = 0; v < nvox; ++v) fat[v] = body[v] && I[v] >= t_fat;
  const std::vector<std::uint8_t> breast_fat =
      largeComponents(grid, fat, settings.min_fat_component_share);
  report.seconds_tissue = since(t0);

  // 3. The chest-wall boundary: a candidate per column, then the robust smooth fit.
  t0 = Clock::now();
  const int nu = cols.nu(), nv = cols.nv(), n = cols.n;
  const double h_axis_mm = g.spacing_m[axis] * 1e3;
  const int run = std::max(1, static_cast<int>(std::ceil(settings.chest_wall_min_thickness_mm / h_axis_mm - 1e-9)));
  std::vector<float> height(static_cast<std::size_t>(nu) * nv, 0.0f);
  std::vector<std::uint8_t> candidate(height.size(), 0), has_fat(height.size(), 0);
  const long step = cols.step();
#pragma omp parallel for schedule(dynamic, 4)
  for (int v = 0; v < nv; ++v)
    for (int u = 0; u < nu; ++u) {
      const long c = u + static_cast<long>(nu) * v, base = cols.first(u, v);
      int last_fat = -1;
      for (int s = 0; s < n; ++s)
        if (breast_fat[base + s * step]) last_fat = s;
      has_fat[c] = last_fat >= 0;
      // The first run of at least `run` body voxels without breast fat behind the last breast fat.
      int length = 0, start = -1;
      for (int s = last_fat + 1; s < n; ++s) {
        const long idx = base + s * step;
        if (body[idx] && !breast_fat[idx]) {
          if (length++ == 0) start = s;
          if (length >= run) break;
        } else {
          length = 0;
        }
      }
      if (length < run) continue;
      double pos = start - 0.5;  // at the anterior edge of the grid
      if (start > 0) {
        const long prev = base + (start - 1) * step, here = base + start * step;
        const double t = breast_fat[prev] ? t_fat : report.body_threshold;
        const double a = I[prev], b = I[here];
        const double frac = a > b ? std::clamp((a - t) / (a - b), 0.0, 1.0) : 0.5;
        pos = (start - 1) + frac;
      }
      height[c] = static_cast<float>(pos);
      candidate[c] = 1;
    }
  boundary_fit::ColumnGrid column_grid{nu, nv, g.spacing_m[cols.u_axis] * 1e3, g.spacing_m[cols.v_axis] * 1e3};
  boundary_fit::FitOptions fit_options;
  fit_options.median_window_mm = settings.boundary_median_window_mm;
  fit_options.sigma_mm = settings.boundary_smoothing_mm;
  fit_options.outlier_mm = settings.boundary_outlier_mm;
  fit_options.height_mm = h_axis_mm;
  std::vector<std::uint8_t> accepted = candidate;
  const std::vector<float> fitted = boundary_fit::robustSmoothFit(column_grid, height, accepted, fit_options, &report.rejected_candidates);
  // Coverage: the breast's columns with an accepted candidate, per slice along v.
  std::vector<int> row_fat(nv, 0), row_ok(nv, 0);
  for (int v = 0; v < nv; ++v)
    for (int u = 0; u < nu; ++u) {
      const long c = u + static_cast<long>(nu) * v;
      row_fat[v] += has_fat[c];
      row_ok[v] += has_fat[c] && accepted[c];
    }
  for (int v = 0; v < nv; ++v) report.breast_columns += row_fat[v], report.measured_columns += row_ok[v];
  if (report.breast_columns == 0)
    throw std::runtime_error("no breast tissue found: no bright (fat) region of the image lies anterior of a chest wall "
                             "(fat level " + std::to_string(F) + "); is this a T1-weighted breast MRI without fat suppression?");
  report.boundary_coverage = static_cast<double>(report.measured_columns) / report.breast_columns;
  if (report.boundary_coverage < settings.min_boundary_coverage) {
    // The widest run of slices whose breast columns gave too few boundaries, for the message.
    int best_lo = 0, best_hi = nv - 1, lo = -1, best_len = 0;
    for (int v = 0; v <= nv; ++v) {
      const bool bad = v < nv && row_fat[v] > 0 && row_ok[v] < settings.min_boundary_coverage * row_fat[v];
      if (bad && lo < 0) lo = v;
      if (!bad && lo >= 0) {
        if (v - lo > best_len) best_len = v - lo, best_lo = lo, best_hi = v - 1;
        lo = -1;
      }
    }
    std::ostringstream s;
    s.precision(0);
    s << std::fixed << "no chest-wall boundary found in slices " << best_lo << "–" << best_hi << " (grid axis " << cols.v_axis
      << "): of the " << report.breast_columns << " columns holding breast fat only " << 100.0 * report.boundary_coverage
      << " % show a chest wall (at least " << settings.chest_wall_min_thickness_mm << " mm of non-fat tissue posterior "
      << "of the breast) where " << 100.0 * settings.min_boundary_coverage
      << " % are needed (segmentation.min_boundary_coverage): is this a breast MRI in prone position, with the chest wall "
         "in the field of view and the breasts anterior along segmentation.prone_gravity_direction?";
    throw std::runtime_error(s.str());
  }
  ChestWallBoundary& boundary = out.boundary;
  boundary.axis = axis;
  boundary.anterior_sign = cols.sign;
  boundary.u_axis = cols.u_axis;
  boundary.v_axis = cols.v_axis;
  boundary.size = Eigen::Vector2i(nu, nv);
  boundary.index.resize(fitted.size());
  for (std::size_t c = 0; c < fitted.size(); ++c) boundary.index[c] = static_cast<float>(cols.gridIndex(fitted[c]));
  boundary.measured = accepted;
  report.seconds_boundary = since(t0);

  // 4. Labels: chest wall posterior of the surface; anterior, the body's large components, holes filled.
  t0 = Clock::now();
  std::vector<std::uint8_t> wall(static_cast<std::size_t>(nvox)), breast(static_cast<std::size_t>(nvox));
#pragma omp parallel for schedule(static)
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) {
        const long v = g.index(i, j, k);
        wall[v] = boundary.posterior(Eigen::Vector3i(i, j, k));
        breast[v] = body[v] || wall[v];
      }
  breast = itk_bridge::fillHoles(grid, breast);
#pragma omp parallel for schedule(static)
  for (long v = 0; v < nvox; ++v) breast[v] = breast[v] && !wall[v];
  std::vector<std::int32_t> component;
  int pieces = 0;
  breast = largeComponents(grid, breast, settings.min_component_share, &component, &pieces);
  // The nipple of each breast: the centroid of its voxels within 2 mm of its most anterior one.
  {
    std::vector<double> apex(static_cast<std::size_t>(pieces), -1e300);
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const std::int32_t c = component[g.index(i, j, k)];
          if (c > 0) apex[c - 1] = std::max(apex[c - 1], anterior.dot(g.indexToPhysical(Eigen::Vector3d(i, j, k))));
        }
    std::vector<Eigen::Vector3d> sum(static_cast<std::size_t>(pieces), Eigen::Vector3d::Zero());
    std::vector<long> count(static_cast<std::size_t>(pieces), 0);
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const std::int32_t c = component[g.index(i, j, k)];
          if (c <= 0) continue;
          const Eigen::Vector3d p = g.indexToPhysical(Eigen::Vector3d(i, j, k));
          if (anterior.dot(p) >= apex[c - 1] - 2e-3) sum[c - 1] += p, ++count[c - 1];
        }
    for (int c = 0; c < pieces; ++c) report.nipples_m.push_back(sum[c] / static_cast<double>(count[c]));
  }
  double t_breast = t_fat;
  if (std::any_of(breast.begin(), breast.end(), [](std::uint8_t b) { return b != 0; })) {
    const double t = itk_bridge::otsuThreshold(grid, I, breast);
    if (t > report.body_threshold && t < F) t_breast = t;
  }
  report.fat_threshold = t_breast;
  LabelImage& labels = out.labels;
  labels = labelImageLike(image, segmentationLabel(TissueClass::kAir));
  const std::uint16_t l_fat = segmentationLabel(TissueClass::kFat), l_gland = segmentationLabel(TissueClass::kFibroglandular),
                      l_wall = segmentationLabel(TissueClass::kChestWall), l_skin = segmentationLabel(TissueClass::kSkin),
                      l_lesion = segmentationLabel(TissueClass::kLesion);
#pragma omp parallel for schedule(static)
  for (long v = 0; v < nvox; ++v) {
    if (wall[v]) labels.labels[v] = l_wall;
    else if (breast[v]) labels.labels[v] = I[v] >= t_breast ? l_fat : l_gland;
  }
  // The outermost voxels share their signal with the air: darker than their tissue, they would read as
  // dense tissue. They take fat unless every tissue voxel behind them (6-neighbours not on the surface)
  // is dense.
  {
    std::vector<std::uint8_t> surface(static_cast<std::size_t>(nvox), 0);
#pragma omp parallel for schedule(static)
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const long v = g.index(i, j, k);
          if (!breast[v]) continue;
          forEachFaceNeighbour(g, i, j, k, [&](long w) { surface[v] = surface[v] || (!breast[w] && !wall[w]); });
        }
    std::vector<std::uint16_t> relabel(labels.labels);
#pragma omp parallel for schedule(static)
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const long v = g.index(i, j, k);
          if (!surface[v] || labels.labels[v] != l_gland) continue;
          bool any_fat = false, any_inner = false;
          forEachFaceNeighbour(g, i, j, k, [&](long w) {
            if (!breast[w] || surface[w]) return;
            any_inner = true;
            any_fat = any_fat || labels.labels[w] == l_fat;
          });
          if (any_fat || !any_inner) relabel[v] = l_fat;
        }
    labels.labels.swap(relabel);
  }
  if (settings.skin_thickness_mm > 0) {
    std::vector<std::uint8_t> air(static_cast<std::size_t>(nvox));
    for (long v = 0; v < nvox; ++v) air[v] = !breast[v] && !wall[v];
    const std::vector<float> d = euclideanDistanceTransform(air, g.size, g.spacing_m * 1e3);
    const double limit = settings.skin_thickness_mm + 0.5 * g.spacing_m.minCoeff() * 1e3;
    for (long v = 0; v < nvox; ++v)
      if (breast[v] && d[v] <= limit) labels.labels[v] = l_skin;
  }
  // Lesions: points (spheres) and the user's label image, only onto breast tissue.
  for (const Lesion& l : lesions.points) {
    const Eigen::Vector3d c = g.physicalToIndex(l.position_m);
    const Eigen::Vector3i ci = c.array().round().cast<int>();
    if ((ci.array() < 0).any() || (ci.array() >= g.size.array()).any())
      throw std::runtime_error("lesion " + l.name + " at " + mm(l.position_m) +
                               " lies outside the image; give its position in the MRI's patient space (LPS, mm)");
    if (!breast[g.index(ci.x(), ci.y(), ci.z())])
      throw std::runtime_error("lesion " + l.name + " at " + mm(l.position_m) + " lies in the " +
                               (wall[g.index(ci.x(), ci.y(), ci.z())] ? "chest wall" : "air") +
                               ", not in the breast; check its position (the MRI's patient space, LPS, mm)");
    if (l.radius_m <= 0) continue;
    const Eigen::Vector3d r = (l.radius_m / g.spacing_m.array()).matrix();
    const Eigen::Vector3i lo = (c - r).array().floor().cast<int>().max(0), hi = (c + r).array().ceil().cast<int>().min(g.size.array() - 1);
    for (int k = lo.z(); k <= hi.z(); ++k)
      for (int j = lo.y(); j <= hi.y(); ++j)
        for (int i = lo.x(); i <= hi.x(); ++i) {
          const long v = g.index(i, j, k);
          if (breast[v] && (g.indexToPhysical(Eigen::Vector3d(i, j, k)) - l.position_m).norm() <= l.radius_m) labels.labels[v] = l_lesion;
        }
  }
  if (lesions.label_image.size.prod() > 0) {
    const LabelImage& li = lesions.label_image;
    li.validate();
    const LabelLookup label_at(li);
    long inside = 0, outside = 0;
    for (int k = 0; k < g.size.z(); ++k)
      for (int j = 0; j < g.size.y(); ++j)
        for (int i = 0; i < g.size.x(); ++i) {
          const long v = g.index(i, j, k);
          if (label_at(g.indexToPhysical(Eigen::Vector3d(i, j, k))) == 0) continue;
          if (breast[v]) labels.labels[v] = l_lesion, ++inside;
          else ++outside;
        }
    if (inside == 0)
      throw std::runtime_error("the lesion label image has " + std::string(outside ? std::to_string(outside) + " lesion voxels, all outside the breast"
                                                                                : "no non-zero voxel within the MRI") +
                               "; check that it lies in the MRI's patient space (LPS) and marks the lesion with non-zero labels");
  }
  // Volumes per class, and the bias field's range within the body.
  long counts[6] = {0, 0, 0, 0, 0, 0};
  static const TissueLabels defaults;
  for (long v = 0; v < nvox; ++v) ++counts[static_cast<int>(defaults.classify(labels.labels[v]))];
  for (int c = 0; c < 6; ++c) report.volume_ml[c] = static_cast<double>(counts[c]) * g.spacing_m.prod() * 1e6;
  if (!bias.empty()) {
    double lo = 1e30, hi = -1e30;
    for (long v = 0; v < nvox; ++v)
      if (breast[v]) lo = std::min<double>(lo, bias[v]), hi = std::max<double>(hi, bias[v]);
    if (lo <= hi) report.bias_min = lo, report.bias_max = hi;
  }
  report.seconds_labels = since(t0);
  report.seconds_total = since(t_start);
  return out;
}

}  // namespace breast_sim::core
