// Orthogonal cross-sections of MRI volumes with outlined labels, drawn with OpenCV; see
// mri_cross_sections.h.
#include "breast_sim/core/mri/mri_cross_sections.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <stdexcept>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "label_lookup.h"

namespace breast_sim::core {

namespace {

// A view: the patient axis cut, the patient axes of the image's columns and rows, and the sign of each
// (+1: the coordinate grows to the right / downwards).
struct View {
  const char* name;
  int axis, col_axis, row_axis, col_sign, row_sign;
};
constexpr View kViews[3] = {{"axial", 2, 0, 1, +1, +1}, {"coronal", 1, 0, 2, +1, -1}, {"sagittal", 0, 1, 2, +1, -1}};

Eigen::AlignedBox3d boxOf(const ImageGeometry& g) {
  Eigen::AlignedBox3d box;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d ijk((c & 1) ? g.size.x() - 0.5 : -0.5, (c & 2) ? g.size.y() - 0.5 : -0.5,
                              (c & 4) ? g.size.z() - 0.5 : -0.5);
    box.extend(g.indexToPhysical(ijk));
  }
  return box;
}

// Value of a voxel index, 0 outside.
double sampleOrZero(const ScalarImage& image, const Eigen::Vector3d& p) {
  const Eigen::Vector3d x = image.geometry.physicalToIndex(p);
  const Eigen::Vector3i& n = image.geometry.size;
  for (int a = 0; a < 3; ++a)
    if (x[a] < -0.5 || x[a] > n[a] - 0.5) return 0.0;
  return sampleTrilinear(image, p);
}

cv::Vec3b classColour(TissueClass c) {  // BGR
  switch (c) {
    case TissueClass::kFat: return {0, 220, 255};
    case TissueClass::kFibroglandular: return {255, 0, 255};
    case TissueClass::kSkin: return {0, 140, 255};
    case TissueClass::kLesion: return {0, 0, 255};
    case TissueClass::kChestWall: return {255, 255, 0};
    case TissueClass::kAir: break;
  }
  return {0, 0, 0};
}

// Drawing priority at a border between two classes: the chest wall first, then lesion, gland, skin, fat.
int priority(TissueClass c) {
  switch (c) {
    case TissueClass::kChestWall: return 5;
    case TissueClass::kLesion: return 4;
    case TissueClass::kFibroglandular: return 3;
    case TissueClass::kSkin: return 2;
    case TissueClass::kFat: return 1;
    case TissueClass::kAir: break;
  }
  return 0;
}

// The 1st and 99.5th percentile of a strided sample.
std::pair<double, double> window(const std::vector<float>& v) {
  std::vector<float> s;
  const std::size_t stride = std::max<std::size_t>(1, v.size() / 500000);
  for (std::size_t i = 0; i < v.size(); i += stride) s.push_back(v[i]);
  const auto at = [&](double q) {
    auto it = s.begin() + static_cast<long>(q * (s.size() - 1));
    std::nth_element(s.begin(), it, s.end());
    return static_cast<double>(*it);
  };
  const double lo = at(0.01), hi = at(0.995);
  return {lo, hi > lo ? hi : lo + 1.0};
}

}  // namespace

void writeMriCrossSections(const std::string& png_path, const std::vector<MriSectionRow>& rows, const MriSectionOptions& options) {
  if (rows.empty()) throw std::invalid_argument("writeMriCrossSections: no rows to draw");
  if (!(options.pixel_size_m > 0) || !std::isfinite(options.pixel_size_m))
    throw std::invalid_argument("writeMriCrossSections: pixel_size_m = " + std::to_string(options.pixel_size_m) +
                                " is invalid: expected > 0 [m]");
  Eigen::AlignedBox3d box;
  for (const MriSectionRow& r : rows) {
    if (!r.image) throw std::invalid_argument("writeMriCrossSections: row '" + r.title + "' has no image");
    r.image->geometry.validate();
    if (static_cast<long>(r.image->values.size()) != r.image->geometry.numVoxels())
      throw std::invalid_argument("writeMriCrossSections: row '" + r.title + "': value count does not match its grid");
    if (r.labels) r.labels->validate();
    box.extend(boxOf(r.image->geometry));
  }
  Eigen::Vector3d centre = options.centre_m;
  if (!centre.allFinite()) {
    const MriSectionRow& first = rows.front();
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    long count = 0;
    if (first.labels) {
      const LabelImage& l = *first.labels;
      for (int k = 0; k < l.size.z(); ++k)
        for (int j = 0; j < l.size.y(); ++j)
          for (int i = 0; i < l.size.x(); ++i) {
            const TissueClass c = first.label_map.classify(l.at(i, j, k));
            if (c == TissueClass::kAir || c == TissueClass::kChestWall) continue;
            sum += l.indexToPhysical(Eigen::Vector3d(i, j, k));
            ++count;
          }
    }
    const Eigen::Vector3d fallback = boxOf(first.image->geometry).center();
    for (int a = 0; a < 3; ++a)
      if (!std::isfinite(centre[a])) centre[a] = count ? sum[a] / static_cast<double>(count) : fallback[a];
  }
  const double px = options.pixel_size_m;
  int panel_w[3], panel_h[3];
  for (int v = 0; v < 3; ++v) {
    const View& view = kViews[v];
    panel_w[v] = static_cast<int>(std::ceil(box.sizes()[view.col_axis] / px));
    panel_h[v] = static_cast<int>(std::ceil(box.sizes()[view.row_axis] / px));
    if (panel_w[v] > 4096 || panel_h[v] > 4096)
      throw std::invalid_argument("writeMriCrossSections: a panel would be " + std::to_string(panel_w[v]) + " x " +
                                  std::to_string(panel_h[v]) + " pixels; choose a larger pixel_size_m");
  }
  const int gap = 10, title_h = 28, footer_h = 24;
  const int row_h = title_h + std::max({panel_h[0], panel_h[1], panel_h[2]}) + footer_h;
  const int width = gap + panel_w[0] + gap + panel_w[1] + gap + panel_w[2] + gap;
  cv::Mat img(static_cast<int>(rows.size()) * row_h, width, CV_8UC3, cv::Scalar(255, 255, 255));
  for (std::size_t r = 0; r < rows.size(); ++r) {
    const MriSectionRow& row = rows[r];
    const auto [lo, hi] = window(row.image->values);
    const int y0 = static_cast<int>(r) * row_h;
    cv::putText(img, row.title, {gap, y0 + 20}, cv::FONT_HERSHEY_SIMPLEX, 0.6, {0, 0, 0}, 1, cv::LINE_AA);
    std::vector<int> class_of;
    std::unique_ptr<LabelLookup> label_at;
    if (row.labels) {
      class_of.resize(65536);
      for (int l = 0; l < 65536; ++l) class_of[l] = static_cast<int>(row.label_map.classify(static_cast<std::uint16_t>(l)));
      label_at = std::make_unique<LabelLookup>(*row.labels);
    }
    int x0 = gap;
    for (int v = 0; v < 3; ++v) {
      const View& view = kViews[v];
      const int w = panel_w[v], h = panel_h[v];
      std::vector<int> cls(static_cast<std::size_t>(w) * h, -1);
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) {
          Eigen::Vector3d p = centre;
          p[view.col_axis] = view.col_sign > 0 ? box.min()[view.col_axis] + (x + 0.5) * px : box.max()[view.col_axis] - (x + 0.5) * px;
          p[view.row_axis] = view.row_sign > 0 ? box.min()[view.row_axis] + (y + 0.5) * px : box.max()[view.row_axis] - (y + 0.5) * px;
          const double g = std::clamp((sampleOrZero(*row.image, p) - lo) / (hi - lo), 0.0, 1.0);
          const auto grey = static_cast<unsigned char>(std::lround(255.0 * g));
          img.at<cv::Vec3b>(y0 + title_h + y, x0 + x) = cv::Vec3b(grey, grey, grey);
          if (row.labels) cls[static_cast<std::size_t>(y) * w + x] = class_of[(*label_at)(p)];
        }
      if (row.labels) {
        for (int y = 0; y < h; ++y)
          for (int x = 0; x < w; ++x) {
            const int c = cls[static_cast<std::size_t>(y) * w + x];
            int best = 0;
            TissueClass colour = TissueClass::kAir;
            for (const auto& [dx, dy] : {std::pair{1, 0}, {-1, 0}, {0, 1}, {0, -1}}) {
              const int xx = x + dx, yy = y + dy;
              if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
              const int d = cls[static_cast<std::size_t>(yy) * w + xx];
              if (d == c) continue;
              // A border pixel on the side of the class that wins the priority.
              const auto mine = static_cast<TissueClass>(c);
              if (priority(mine) > priority(static_cast<TissueClass>(d)) && priority(mine) > best) {
                best = priority(mine);
                colour = mine;
              }
            }
            if (best > 0) img.at<cv::Vec3b>(y0 + title_h + y, x0 + x) = classColour(colour);
          }
      }
      char label[96];
      std::snprintf(label, sizeof label, "%s  %c = %.1f mm", view.name, "xyz"[view.axis], 1e3 * centre[view.axis]);
      cv::putText(img, label, {x0, y0 + title_h + panel_h[v] + 16}, cv::FONT_HERSHEY_SIMPLEX, 0.45, {0, 0, 0}, 1, cv::LINE_AA);
      // 1 cm scale bar in the panel's lower left corner.
      const int bar = static_cast<int>(std::lround(0.01 / px));
      const int by = y0 + title_h + panel_h[v] - 8;
      cv::line(img, {x0 + 6, by}, {x0 + 6 + bar, by}, {0, 255, 0}, 2);
      x0 += w + gap;
    }
  }
  if (!cv::imwrite(png_path, img)) throw std::runtime_error(png_path + ": cannot write the PNG");
}

}  // namespace breast_sim::core
