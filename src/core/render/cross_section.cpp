// Orthogonal cross-sections of tetrahedral meshes drawn with OpenCV; see cross_section.h.
#include "breast_sim/core/render/cross_section.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace breast_sim::core {

void CrossSectionOptions::validate() const {
  if (!(pixel_size_m > 0) || !std::isfinite(pixel_size_m) || pixel_size_m > 0.01)
    throw std::invalid_argument("cross-section pixel_size_m = " + std::to_string(pixel_size_m) + " is invalid: expected (0, 0.01] m");
  if (!(margin_m >= 0) || !std::isfinite(margin_m))
    throw std::invalid_argument("cross-section margin_m = " + std::to_string(margin_m) + " is invalid: expected ≥ 0 m");
}

std::vector<Eigen::Vector3d> tetPlaneSection(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                             const Eigen::Vector3d& d, int axis, double value) {
  const Eigen::Vector3d* v[4] = {&a, &b, &c, &d};
  double s[4];
  for (int i = 0; i < 4; ++i) s[i] = (*v[i])[axis] - value;
  std::vector<Eigen::Vector3d> pts;
  // Points where an edge crosses the plane (a vertex exactly on it counts once, via its edges with
  // the strictly positive side).
  for (int i = 0; i < 4; ++i)
    for (int j = i + 1; j < 4; ++j) {
      const bool cross = (s[i] < 0 && s[j] >= 0) || (s[j] < 0 && s[i] >= 0);
      if (!cross) continue;
      const double t = s[i] / (s[i] - s[j]);
      const Eigen::Vector3d p = *v[i] + t * (*v[j] - *v[i]);
      bool dup = false;
      for (const auto& q : pts) dup = dup || (q - p).squaredNorm() < 1e-24;
      if (!dup) pts.push_back(p);
    }
  if (pts.size() < 3) return {};
  // Order around the centroid in the plane's two other coordinates.
  const int u = (axis + 1) % 3, w = (axis + 2) % 3;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const auto& p : pts) centre += p;
  centre /= static_cast<double>(pts.size());
  std::sort(pts.begin(), pts.end(), [&](const Eigen::Vector3d& p, const Eigen::Vector3d& q) {
    return std::atan2(p[w] - centre[w], p[u] - centre[u]) < std::atan2(q[w] - centre[w], q[u] - centre[u]);
  });
  return pts;
}

namespace {

/// A view: which axis is cut, which patient axes map to image columns and rows, and their signs
/// (+1: the coordinate grows to the right / downwards).
struct View {
  const char* name;
  int axis;
  int col_axis, row_axis;
  double col_sign, row_sign;
};
// LPS: x left, y posterior, z superior. Radiological: patient's left on the image's right
// (+x to the right), superior up (−z down), anterior up in axial (−y up, so +y grows downwards).
constexpr View kViews[3] = {{"axial", 2, 0, 1, +1.0, +1.0},
                            {"coronal", 1, 0, 2, +1.0, -1.0},
                            {"sagittal", 0, 1, 2, +1.0, -1.0}};

cv::Scalar regionColour(int label) {
  switch (label) {
    case 1: return {120, 200, 245};   // fat: light orange (BGR)
    case 2: return {90, 120, 220};    // fibroglandular: red-brown
    case 3: return {170, 170, 170};   // skin: grey
    case 4: return {40, 40, 40};      // lesion: near black
    default: return {200, 200, 200};
  }
}

}  // namespace

void writeCrossSections(const std::string& png_path, const TetMesh& mesh,
                        const std::vector<CrossSectionConfiguration>& rows, const CrossSectionOptions& options) {
  options.validate();
  if (rows.empty()) throw std::invalid_argument("writeCrossSections: no configuration to draw");
  const Points& rest = mesh.nodes();
  auto positions = [&](const CrossSectionConfiguration& r) -> const Points& { return r.positions_m ? *r.positions_m : rest; };
  Eigen::AlignedBox3d box, first_box;
  for (size_t k = 0; k < rows.size(); ++k) {
    const Points& x = positions(rows[k]);
    if (x.rows() != rest.rows() || x.cols() != 3)
      throw std::invalid_argument("writeCrossSections: configuration '" + rows[k].title + "' has " + std::to_string(x.rows()) +
                                  " positions, the mesh " + std::to_string(rest.rows()) + " nodes");
    for (Eigen::Index i = 0; i < x.rows(); ++i) {
      box.extend(x.row(i).transpose());
      if (k == 0) first_box.extend(x.row(i).transpose());
    }
    const Points& ov = rows[k].outline_vertices_m;
    for (Eigen::Index f = 0; f < rows[k].outline_triangles.rows(); ++f)
      for (int c = 0; c < 3; ++c) {
        const Eigen::Index v = rows[k].outline_triangles(f, c);
        if (v < 0 || v >= ov.rows())
          throw std::invalid_argument("writeCrossSections: outline triangle " + std::to_string(f) + " of '" + rows[k].title +
                                      "' uses vertex " + std::to_string(v) + " of " + std::to_string(ov.rows()));
        box.extend(ov.row(v).transpose());
      }
  }
  Eigen::Vector3d centre = options.centre_m;
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(centre[a])) centre[a] = first_box.center()[a];
  const Eigen::Vector3d lo = box.min().array() - options.margin_m, hi = box.max().array() + options.margin_m;
  const double h = options.pixel_size_m;
  const int title_h = 28, label_h = 22;
  // Panel sizes per view.
  int panel_w[3], panel_h[3];
  for (int v = 0; v < 3; ++v) {
    panel_w[v] = static_cast<int>(std::ceil((hi[kViews[v].col_axis] - lo[kViews[v].col_axis]) / h));
    panel_h[v] = static_cast<int>(std::ceil((hi[kViews[v].row_axis] - lo[kViews[v].row_axis]) / h));
  }
  const int row_h = *std::max_element(panel_h, panel_h + 3) + title_h + label_h;
  const int width = panel_w[0] + panel_w[1] + panel_w[2] + 40;
  cv::Mat img(static_cast<int>(rows.size()) * row_h + 10, width, CV_8UC3, cv::Scalar(255, 255, 255));
  const Tets& T = mesh.tets();
  const std::vector<int>& labels = mesh.regionLabels();

  for (size_t k = 0; k < rows.size(); ++k) {
    const Points& x = positions(rows[k]);
    const int y0 = static_cast<int>(k) * row_h;
    cv::putText(img, rows[k].title, {10, y0 + 20}, cv::FONT_HERSHEY_SIMPLEX, 0.6, {0, 0, 0}, 1, cv::LINE_AA);
    int x0 = 10;
    for (int v = 0; v < 3; ++v) {
      const View& view = kViews[v];
      const double value = centre[view.axis];
      const cv::Rect roi(x0, y0 + title_h, panel_w[v], panel_h[v]);
      cv::Mat panel = img(roi);
      panel.setTo(cv::Scalar(245, 245, 245));
      auto toPixel = [&](const Eigen::Vector3d& p) {
        const double cu = view.col_sign > 0 ? p[view.col_axis] - lo[view.col_axis] : hi[view.col_axis] - p[view.col_axis];
        const double rv = view.row_sign > 0 ? p[view.row_axis] - lo[view.row_axis] : hi[view.row_axis] - p[view.row_axis];
        // Fixed point with 4 fractional bits for sub-pixel accurate polygons.
        return cv::Point(static_cast<int>(std::lround(cu / h * 16.0)), static_cast<int>(std::lround(rv / h * 16.0)));
      };
      for (Eigen::Index t = 0; t < T.rows(); ++t) {
        double mn = 1e300, mx = -1e300;
        for (int c = 0; c < 4; ++c) {
          const double s = x(T(t, c), view.axis);
          mn = std::min(mn, s);
          mx = std::max(mx, s);
        }
        if (mn > value || mx < value) continue;
        const auto poly = tetPlaneSection(x.row(T(t, 0)).transpose(), x.row(T(t, 1)).transpose(),
                                          x.row(T(t, 2)).transpose(), x.row(T(t, 3)).transpose(), view.axis, value);
        if (poly.empty()) continue;
        std::vector<cv::Point> pts;
        for (const auto& p : poly) pts.push_back(toPixel(p));
        cv::fillConvexPoly(panel, pts, regionColour(labels.empty() ? 0 : labels[static_cast<size_t>(t)]), cv::LINE_8, 4);
      }
      // The outline of a surface (e.g. the target) cut by the plane.
      const Points& ov = rows[k].outline_vertices_m;
      const Triangles& ot = rows[k].outline_triangles;
      for (Eigen::Index f = 0; f < ot.rows(); ++f) {
        Eigen::Vector3d p[3];
        double s[3];
        for (int c = 0; c < 3; ++c) {
          p[c] = ov.row(ot(f, c)).transpose();
          s[c] = p[c][view.axis] - value;
        }
        std::vector<Eigen::Vector3d> seg;
        for (int i = 0; i < 3; ++i) {
          const int j = (i + 1) % 3;
          if ((s[i] < 0) != (s[j] < 0)) seg.push_back(p[i] + s[i] / (s[i] - s[j]) * (p[j] - p[i]));
        }
        if (seg.size() == 2) cv::line(panel, toPixel(seg[0]), toPixel(seg[1]), {0, 0, 230}, 2, cv::LINE_AA, 4);
      }
      // Lesions within 5 mm of the plane.
      for (Eigen::Index l = 0; l < rows[k].lesions_m.rows(); ++l) {
        const Eigen::Vector3d p = rows[k].lesions_m.row(l).transpose();
        if (std::abs(p[view.axis] - value) > 5e-3) continue;
        cv::circle(panel, toPixel(p), 5 * 16, {200, 60, 0}, 2, cv::LINE_AA, 4);
      }
      char label[96];
      std::snprintf(label, sizeof label, "%s, %c = %.1f mm", view.name, "xyz"[view.axis], value * 1e3);
      cv::putText(img, label, {x0, y0 + title_h + panel_h[v] + 16}, cv::FONT_HERSHEY_SIMPLEX, 0.45, {0, 0, 0}, 1, cv::LINE_AA);
      // 1 cm scale bar, bottom right of the panel.
      const int bar = static_cast<int>(std::lround(0.01 / h));
      cv::line(panel, {panel_w[v] - bar - 8, panel_h[v] - 8}, {panel_w[v] - 8, panel_h[v] - 8}, {0, 0, 0}, 2);
      x0 += panel_w[v] + 10;
    }
  }
  if (!cv::imwrite(png_path, img))
    throw std::runtime_error(png_path + ": cannot write the cross-section image (check the folder exists and the name ends in .png)");
}

}  // namespace breast_sim::core
