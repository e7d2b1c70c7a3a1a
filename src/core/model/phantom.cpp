#include "breast_sim/core/model/phantom.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <utility>

#include <Eigen/Geometry>

#include "breast_sim/core/model/tissue_labels.h"

namespace breast_sim::core {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kMm = 1e-3;
constexpr double kDeg = kPi / 180.0;

// Generous caps that only protect against typos (a voxel size of 0.001 mm, say).
constexpr double kMaxVoxels = 4e8;
constexpr double kMaxTriangles = 2e7;

std::string fmt(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

std::string mmString(double v_m) { return fmt(v_m / kMm); }

[[noreturn]] void fail(const std::string& key, const std::string& value, const std::string& expected) {
  throw std::invalid_argument("key 'phantom." + key + "' = " + value + ": expected " + expected);
}

// ---------------------------------------------------------------------------------------------------
// Geometry of one half-ellipsoid on the wall.

// Sag of the cylindrical wall behind the tangent plane at lateral offset u: R − sqrt(R² − u²),
// written without cancellation. 0 for the planar wall (R = 0).
double wallSag(double u, double R) {
  if (R <= 0.0) return 0.0;
  const double d = std::max(0.0, R * R - u * u);
  return u * u / (R + std::sqrt(d));
}

// ∫ min(c·sqrt(q² − v²/b²), s) dv over |v| ≤ b·q: the part of the slice of the ellipsoid at lateral
// offset u (q = sqrt(1 − u²/a²)) that lies between the base plane and the curved wall (sag s).
double sliverSlice(double b, double c, double q, double s) {
  if (q <= 0.0 || s <= 0.0) return 0.0;
  if (s >= c * q) return 0.5 * kPi * b * c * q * q;
  const double t0 = std::sqrt(std::max(0.0, q * q - (s / c) * (s / c)));
  // Antiderivative of sqrt(q² − t²).
  const auto F = [q](double t) {
    const double r = std::clamp(t / q, -1.0, 1.0);
    return 0.5 * (t * std::sqrt(std::max(0.0, q * q - t * t)) + q * q * std::asin(r));
  };
  return 2.0 * s * b * t0 + 2.0 * c * b * (F(q) - F(t0));
}

// Volume between the base plane of a half-ellipsoid (a, b, c) and a cylindrical wall of radius R
// (the part of the ellipsoid's posterior half in front of the wall). The slice integral is closed
// form; the lateral integral is split where the whole slice becomes sliver (s(u) = c·q(u)): beyond,
// it is a polynomial integrated exactly; before, the integrand has a (u* − u)^{3/2} term, removed by
// u = u*·(1 − σ²), and composite 5-point Gauss–Legendre is refined until it changes < 1e-13.
double cylinderSliverVolume(double a, double b, double c, double R) {
  if (R <= 0.0) return 0.0;
  const auto q = [a](double u) { return std::sqrt(std::max(0.0, 1.0 - (u / a) * (u / a))); };
  double lo = 0.0, hi = a;
  for (int it = 0; it < 200 && hi - lo > 1e-16 * a; ++it) {
    const double mid = 0.5 * (lo + hi);
    (wallSag(mid, R) < c * q(mid) ? lo : hi) = mid;
  }
  const double us = 0.5 * (lo + hi);
  const auto prim = [a](double u) { return u - u * u * u / (3.0 * a * a); };
  const double tail = 0.5 * kPi * b * c * (prim(a) - prim(us));

  static const std::array<double, 5> x{0.0, -0.5384693101056831, 0.5384693101056831,
                                       -0.9061798459386640, 0.9061798459386640};
  static const std::array<double, 5> w{0.5688888888888889, 0.4786286704993665, 0.4786286704993665,
                                       0.2369268850561891, 0.2369268850561891};
  const auto integrate = [&](int panels) {
    double sum = 0.0;
    const double h = 1.0 / panels;
    for (int p = 0; p < panels; ++p) {
      const double mid = (p + 0.5) * h;
      for (int g = 0; g < 5; ++g) {
        const double sigma = mid + 0.5 * h * x[g];
        const double u = us * (1.0 - sigma * sigma);
        sum += 0.5 * h * w[g] * sliverSlice(b, c, q(u), wallSag(u, R)) * 2.0 * us * sigma;
      }
    }
    return sum;
  };
  const double scale = 2.0 / 3.0 * kPi * a * b * c;
  double prev = integrate(4), cur = prev;
  for (int panels = 8; panels <= 8192; panels *= 2) {
    cur = integrate(panels);
    if (std::abs(cur - prev) <= 1e-13 * scale) break;
    prev = cur;
  }
  return 2.0 * (cur + tail);  // both lateral sides
}

// Polar angle θ ∈ [π/2, π] of the rim at azimuth α, where the ellipsoid point
// (a sinθ cosα, b sinθ sinα, c cosθ) meets the wall: c·cosθ + sag(a·sinθ·cosα) = 0. The left side
// decreases monotonically in θ on [π/2, π], so bisection is safe.
double rimPolarAngle(const HalfEllipsoid& e, double alpha) {
  if (e.wall_radius_m <= 0.0) return 0.5 * kPi;
  const auto f = [&](double theta) {
    return e.depth_m * std::cos(theta) + wallSag(e.lateral_m * std::sin(theta) * std::cos(alpha), e.wall_radius_m);
  };
  double lo = 0.5 * kPi, hi = kPi;
  if (f(lo) <= 0.0) return lo;
  for (int it = 0; it < 100 && hi - lo > 1e-15; ++it) {
    const double mid = 0.5 * (lo + hi);
    (f(mid) > 0.0 ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

// A shape attached to the wall at arc-length position `arc_m` from the sternum (signed along x).
HalfEllipsoid shapeOnWall(const PhantomParams& p, double arc_m, double a, double b, double c) {
  HalfEllipsoid e;
  e.lateral_m = a;
  e.si_m = b;
  e.depth_m = c;
  if (p.chest_wall_shape == ChestWallShape::kPlanar) {
    e.base_centre_m = Eigen::Vector3d(arc_m, 0.0, 0.0);
    return e;
  }
  const double R = p.chest_wall_radius_m;
  const double phi = arc_m / R;
  e.wall_radius_m = R;
  e.base_centre_m = Eigen::Vector3d(R * std::sin(phi), R - R * std::cos(phi), 0.0);
  e.lateral_axis = Eigen::Vector3d(std::cos(phi), std::sin(phi), 0.0);
  e.depth_axis = Eigen::Vector3d(std::sin(phi), -std::cos(phi), 0.0);
  return e;
}

// Arc-length position of each breast centre and its lateral sign (+1: lateral is +x), left first.
std::vector<std::pair<double, double>> breastPlacements(const PhantomParams& p) {
  if (p.num_breasts == 1) return {{0.0, p.side == BreastSide::kLeft ? 1.0 : -1.0}};
  const double x = 0.5 * p.breast_separation_m;
  // Two breasts are centred at x = ±separation/2; on the cylinder that is arc R·asin(x/R).
  const double arc = p.chest_wall_shape == ChestWallShape::kPlanar
                         ? x
                         : p.chest_wall_radius_m * std::asin(std::min(1.0, x / p.chest_wall_radius_m));
  return {{arc, 1.0}, {-arc, -1.0}};
}

// Depth c of `e` such that its volume is `target` (cylindrical wall: the sliver grows with the
// base). Secant iteration on a monotone, nearly linear function of c.
void matchVolumeByDepth(HalfEllipsoid& e, double target) {
  double c0 = e.depth_m;
  e.depth_m = c0;
  double f0 = e.volume() - target;
  double c1 = c0 * target / (f0 + target);
  for (int it = 0; it < 60; ++it) {
    e.depth_m = c1;
    const double f1 = e.volume() - target;
    if (std::abs(f1) <= 1e-13 * target || f1 == f0) break;
    const double c2 = c1 - f1 * (c1 - c0) / (f1 - f0);
    c0 = c1;
    f0 = f1;
    c1 = std::max(0.05 * c1, c2);
  }
}

struct Shapes {
  std::vector<HalfEllipsoid> prone, supine;
  std::vector<double> lateral_sign;
};

Shapes makeShapes(const PhantomParams& p) {
  Shapes s;
  const double a = p.lateral_semi_axis_m, b = p.si_semi_axis_m, c = p.depth_m;
  const double k = p.supine_depth_scale;
  const double a_sup = a * std::pow(k, -p.supine_lateral_share);
  const double b_sup = b * std::pow(k, -(1.0 - p.supine_lateral_share));
  const double c_sup = c * k;
  for (const auto& [arc, sign] : breastPlacements(p)) {
    s.prone.push_back(shapeOnWall(p, arc, a, b, c));
    HalfEllipsoid sup = shapeOnWall(p, arc + sign * p.supine_lateral_shift_m, a_sup, b_sup, c_sup);
    if (p.chest_wall_shape == ChestWallShape::kCylindrical) matchVolumeByDepth(sup, s.prone.back().volume());
    s.supine.push_back(sup);
    s.lateral_sign.push_back(sign);
  }
  return s;
}

// Half-extents of the full ellipsoid along x and y (support function), for bounds and clearances.
Eigen::Vector3d ellipsoidHalfExtent(const HalfEllipsoid& e) {
  const Eigen::Vector3d& t = e.lateral_axis;
  const Eigen::Vector3d& n = e.depth_axis;
  return Eigen::Vector3d(std::hypot(e.lateral_m * t.x(), e.depth_m * n.x()),
                         std::hypot(e.lateral_m * t.y(), e.depth_m * n.y()), e.si_m);
}

// Voxel-face index range [lo, hi) per axis of the label image; voxel faces lie on multiples of the
// voxel size, so the planar wall y = 0 never passes through a voxel centre.
struct Grid {
  Eigen::Vector3i lo, hi;
  double h;
};

Grid imageGrid(const PhantomParams& p, const std::vector<HalfEllipsoid>& prone) {
  const double h = p.voxel_size_m;
  const int m = std::max(3, static_cast<int>(std::ceil(p.margin_m / h - 1e-9)));
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  for (const auto& e : prone) {
    const Eigen::Vector3d ext = ellipsoidHalfExtent(e);
    lo = lo.cwiseMin(e.base_centre_m - ext);
    hi = hi.cwiseMax(e.base_centre_m + ext);
  }
  Grid g;
  g.h = h;
  const auto down = [h](double v) { return static_cast<int>(std::floor(v / h + 1e-9)); };
  const auto up = [h](double v) { return static_cast<int>(std::ceil(v / h - 1e-9)); };
  g.lo = Eigen::Vector3i(down(lo.x()) - m, down(lo.y()) - m, down(lo.z()) - m);
  g.hi.x() = up(hi.x()) + m;
  g.hi.z() = up(hi.z()) + m;
  // Posterior end: the back of the chest slab at the image's lateral edges, then the margin.
  double back = p.chest_wall_thickness_m;
  if (p.chest_wall_shape == ChestWallShape::kCylindrical) {
    const double R = p.chest_wall_radius_m, ri = R - p.chest_wall_thickness_m;
    const double xm = h * std::max(std::abs(g.lo.x()), std::abs(g.hi.x()));
    back = R - std::sqrt(std::max(0.0, ri * ri - xm * xm));
  }
  g.hi.y() = up(back) + m;
  return g;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------
// PhantomParams

std::vector<Lesion> PhantomParams::defaultLesions() {
  Lesion a;
  a.name = "upper_outer";
  a.position_m = Eigen::Vector3d(0.020, -0.035, 0.015);
  a.radius_m = 0.005;
  Lesion b;
  b.name = "lower_inner";
  b.position_m = Eigen::Vector3d(-0.015, -0.020, -0.020);
  b.radius_m = 0.003;
  return {a, b};
}

void PhantomParams::validate() const {
  const auto positive = [](const char* key, double v_m) {
    if (!(v_m > 0.0) || !std::isfinite(v_m)) fail(key, mmString(v_m) + " mm", "a positive length in mm");
  };
  if (num_breasts != 1 && num_breasts != 2) fail("num_breasts", std::to_string(num_breasts), "1 or 2");
  positive("breast_separation_mm", breast_separation_m);
  positive("chest_wall_radius_mm", chest_wall_radius_m);
  positive("chest_wall_thickness_mm", chest_wall_thickness_m);
  positive("lateral_semi_axis_mm", lateral_semi_axis_m);
  positive("si_semi_axis_mm", si_semi_axis_m);
  positive("depth_mm", depth_m);
  positive("voxel_size_mm", voxel_size_m);
  positive("surface_edge_mm", surface_edge_m);
  if (!(gland_scale >= 0.0 && gland_scale < 1.0))
    fail("gland_scale", fmt(gland_scale), "a fraction in [0, 1) (0 = no fibroglandular core)");
  const double min_axis = std::min({lateral_semi_axis_m, si_semi_axis_m, depth_m});
  if (!(skin_thickness_m >= 0.0 && skin_thickness_m < 0.5 * min_axis))
    fail("skin_thickness_mm", mmString(skin_thickness_m) + " mm",
         "a length in [0, " + mmString(0.5 * min_axis) + ") mm (less than half the smallest semi-axis)");
  if (!(supine_depth_scale > 0.0 && supine_depth_scale <= 1.0))
    fail("supine_depth_scale", fmt(supine_depth_scale), "a factor in (0, 1]");
  if (!(supine_lateral_share >= 0.0 && supine_lateral_share <= 1.0))
    fail("supine_lateral_share", fmt(supine_lateral_share), "a fraction in [0, 1]");
  if (!std::isfinite(supine_lateral_shift_m))
    fail("supine_lateral_shift_mm", mmString(supine_lateral_shift_m) + " mm", "a finite length in mm");
  if (!(std::abs(supine_gravity_tilt_rad) < 0.5 * kPi))
    fail("supine_gravity_tilt_deg", fmt(supine_gravity_tilt_rad / kDeg) + " deg", "an angle in (-90, 90) degrees");
  if (!(gravity_mps2 > 0.0) || !std::isfinite(gravity_mps2))
    fail("gravity_mps2", fmt(gravity_mps2) + " m/s^2", "a positive acceleration in m/s^2");
  if (!(margin_m >= 0.0) || !std::isfinite(margin_m)) fail("margin_mm", mmString(margin_m) + " mm", "a length >= 0 in mm");
  if (supersampling < 1 || supersampling > 4)
    fail("supersampling", std::to_string(supersampling), "an integer in [1, 4] (sub-samples per axis)");

  // Cylindrical wall: every shape (and the image) within the front of the cylinder.
  if (chest_wall_shape == ChestWallShape::kCylindrical) {
    const double R = chest_wall_radius_m;
    const double a_sup = lateral_semi_axis_m * std::pow(supine_depth_scale, -supine_lateral_share);
    const double need = std::max({depth_m, lateral_semi_axis_m, a_sup}) + chest_wall_thickness_m;
    if (!(R > need))
      fail("chest_wall_radius_mm", mmString(R) + " mm",
           "a radius > " + mmString(need) + " mm (the largest semi-axis plus the wall thickness)");
    if (num_breasts == 2 && !(breast_separation_m < 2.0 * R))
      fail("breast_separation_mm", mmString(breast_separation_m) + " mm",
           "less than the chest-wall diameter, " + mmString(2.0 * R) + " mm");
  }
  const Shapes shapes = makeShapes(*this);
  if (chest_wall_shape == ChestWallShape::kCylindrical) {
    const double R = chest_wall_radius_m;
    const double lim = R - chest_wall_thickness_m - std::max(3.0 * voxel_size_m, margin_m) - voxel_size_m;
    for (const auto* set : {&shapes.prone, &shapes.supine}) {
      for (const auto& e : *set) {
        const double reach = std::abs(e.base_centre_m.x()) + ellipsoidHalfExtent(e).x();
        if (!(reach < lim))
          fail("chest_wall_radius_mm", mmString(R) + " mm",
               "a larger radius: a breast shape reaches x = " + mmString(reach) + " mm, beyond the front of the "
               "wall (usable |x| < " + mmString(lim) + " mm); or a smaller separation, shift or size");
        if (!(e.depth_m < R - chest_wall_thickness_m))
          fail("chest_wall_radius_mm", mmString(R) + " mm", "a radius larger than the depth plus the wall thickness");
      }
    }
  }
  // Two breasts must not touch: the left one (+x) stays in x > 0 (the layout is mirror-symmetric).
  if (num_breasts == 2) {
    for (const auto* set : {&shapes.prone, &shapes.supine}) {
      const HalfEllipsoid& left = set->front();
      const double medial = left.base_centre_m.x() - ellipsoidHalfExtent(left).x();
      if (!(medial > 0.0))
        fail("breast_separation_mm", mmString(breast_separation_m) + " mm",
             std::string("a larger separation: the ") + (set == &shapes.prone ? "prone" : "supine") +
                 " breasts would overlap by " + mmString(-2.0 * medial) + " mm at the sternum");
    }
  }
  // Image and surface sizes (typo guards).
  const Grid g = imageGrid(*this, shapes.prone);
  const Eigen::Vector3d n = (g.hi - g.lo).cast<double>();
  if (n.prod() > kMaxVoxels)
    fail("voxel_size_mm", mmString(voxel_size_m) + " mm",
         "a larger voxel size: the image would have " + fmt(n.prod()) + " voxels (limit " + fmt(kMaxVoxels) + ")");
  for (const auto& e : shapes.supine) {
    const double r = std::max({e.lateral_m, e.si_m, e.depth_m});
    const double est = 2.0 * (2.0 * kPi * r / surface_edge_m) * (2.5 * r / surface_edge_m);
    if (est * num_breasts > kMaxTriangles)
      fail("surface_edge_mm", mmString(surface_edge_m) + " mm",
           "a larger edge length: the surfaces would have about " + fmt(est * num_breasts) + " triangles");
  }
  // Lesions.
  for (std::size_t i = 0; i < lesions.size(); ++i) {
    const Lesion& l = lesions[i];
    const std::string key = "lesions[" + std::to_string(i) + "]";
    if (l.name.empty()) fail(key + ".name", "''", "a non-empty name");
    for (std::size_t j = 0; j < i; ++j)
      if (lesions[j].name == l.name) fail(key + ".name", "'" + l.name + "'", "a name not used by another lesion");
    if (!l.position_m.allFinite()) fail(key + ".position_mm", "(non-finite)", "three finite coordinates in mm");
    if (!(l.radius_m >= 0.0) || !std::isfinite(l.radius_m))
      fail(key + ".radius_mm", mmString(l.radius_m) + " mm", "a radius >= 0 in mm");
    bool inside = false;
    for (const auto& e : shapes.prone) inside = inside || e.contains(l.position_m);
    if (!inside) {
      std::ostringstream pos;
      pos << "[" << mmString(l.position_m.x()) << ", " << mmString(l.position_m.y()) << ", "
          << mmString(l.position_m.z()) << "] mm";
      fail(key + ".position_mm", pos.str() + " ('" + l.name + "')",
           "a point inside the prone breast tissue (LPS, mm; breasts protrude towards -y)");
    }
  }
}

// ---------------------------------------------------------------------------------------------------
// HalfEllipsoid

Eigen::Vector3d HalfEllipsoid::localCoordinates(const Eigen::Vector3d& p_m) const {
  const Eigen::Vector3d d = p_m - base_centre_m;
  return Eigen::Vector3d(d.dot(lateral_axis), d.z(), d.dot(depth_axis));
}

bool HalfEllipsoid::contains(const Eigen::Vector3d& p_m) const {
  const Eigen::Vector3d l = localCoordinates(p_m);
  const double e = (l.x() / lateral_m) * (l.x() / lateral_m) + (l.y() / si_m) * (l.y() / si_m) +
                   (l.z() / depth_m) * (l.z() / depth_m);
  if (!(e < 1.0)) return false;
  if (wall_radius_m <= 0.0) return l.z() > 0.0;
  // Anterior to the wall: farther from the cylinder axis (at base_centre − R·n) than R.
  const double wr = l.z() + wall_radius_m;
  return l.x() * l.x() + wr * wr > wall_radius_m * wall_radius_m && wr > 0.0;
}

double HalfEllipsoid::volume() const {
  return 2.0 / 3.0 * kPi * lateral_m * si_m * depth_m +
         cylinderSliverVolume(lateral_m, si_m, depth_m, wall_radius_m);
}

void HalfEllipsoid::appendSurface(double edge_m, Points& vertices_m, Triangles& triangles,
                                  std::vector<bool>& is_skin) const {
  const double a = lateral_m, b = si_m, c = depth_m;
  const int n_alpha = std::max(24, static_cast<int>(std::ceil(2.0 * kPi * std::max(a, b) / edge_m)));
  std::vector<double> theta_rim(n_alpha);
  double theta_max = 0.0;
  for (int k = 0; k < n_alpha; ++k) {
    theta_rim[k] = rimPolarAngle(*this, 2.0 * kPi * k / n_alpha);
    theta_max = std::max(theta_max, theta_rim[k]);
  }
  // Rings of constant τ = θ / θ_rim(α) on the skin (apex τ = 0, rim τ = 1) and of constant
  // τ = ρ / ρ_rim(α) on the base (rim τ = 1, base centre τ = 0), sharing the rim ring.
  const int m_skin = std::max(8, static_cast<int>(std::ceil(theta_max * std::max({a, b, c}) / edge_m)));
  const int m_base = std::max(4, static_cast<int>(std::ceil(std::max(a, b) / edge_m)));

  const auto toWorld = [this](double u, double v, double w) -> Eigen::Vector3d {
    return base_centre_m + u * lateral_axis + v * Eigen::Vector3d::UnitZ() + w * depth_axis;
  };
  std::vector<Eigen::Vector3d> verts;
  verts.reserve(2 + static_cast<std::size_t>(n_alpha) * (m_skin + m_base));
  const int apex_id = 0;
  verts.push_back(apex());
  // ring(i, k): skin ring i = 1..m_skin (m_skin is the rim), then base rings m_skin + 1 .. m_skin +
  // m_base − 1 going inward; the base centre last.
  for (int i = 1; i <= m_skin; ++i) {
    const double tau = static_cast<double>(i) / m_skin;
    for (int k = 0; k < n_alpha; ++k) {
      const double alpha = 2.0 * kPi * k / n_alpha;
      const double theta = tau * theta_rim[k];
      verts.push_back(toWorld(a * std::sin(theta) * std::cos(alpha), b * std::sin(theta) * std::sin(alpha),
                              c * std::cos(theta)));
    }
  }
  for (int j = m_base - 1; j >= 1; --j) {
    const double tau = static_cast<double>(j) / m_base;
    for (int k = 0; k < n_alpha; ++k) {
      const double alpha = 2.0 * kPi * k / n_alpha;
      const double u = tau * a * std::sin(theta_rim[k]) * std::cos(alpha);
      const double v = tau * b * std::sin(theta_rim[k]) * std::sin(alpha);
      verts.push_back(toWorld(u, v, -wallSag(u, wall_radius_m)));
    }
  }
  const int centre_id = static_cast<int>(verts.size());
  verts.push_back(base_centre_m);

  const int offset = static_cast<int>(vertices_m.rows());
  const auto ring = [&](int r, int k) { return offset + 1 + (r - 1) * n_alpha + (k % n_alpha); };
  std::vector<std::array<int, 3>> tris;
  std::vector<bool> skin;
  const auto add = [&](int i0, int i1, int i2, bool on_skin) {
    tris.push_back({i0, i1, i2});
    skin.push_back(on_skin);
  };
  // Skin: apex fan, then quads (ordered θ then α, so that t × z = n gives the outward normal).
  for (int k = 0; k < n_alpha; ++k) add(offset + apex_id, ring(1, k), ring(1, k + 1), true);
  for (int i = 1; i < m_skin; ++i)
    for (int k = 0; k < n_alpha; ++k) {
      add(ring(i, k), ring(i + 1, k), ring(i + 1, k + 1), true);
      add(ring(i, k), ring(i + 1, k + 1), ring(i, k + 1), true);
    }
  // Base: from the rim (ring m_skin) inward, reversed so that the normal points into the wall.
  const int last = m_skin + m_base - 1;
  for (int r = m_skin; r < last; ++r)
    for (int k = 0; k < n_alpha; ++k) {
      add(ring(r + 1, k), ring(r, k + 1), ring(r, k), false);
      add(ring(r + 1, k), ring(r + 1, k + 1), ring(r, k + 1), false);
    }
  for (int k = 0; k < n_alpha; ++k) add(offset + centre_id, ring(last, k + 1), ring(last, k), false);

  vertices_m.conservativeResize(offset + static_cast<Eigen::Index>(verts.size()), 3);
  for (std::size_t i = 0; i < verts.size(); ++i) vertices_m.row(offset + static_cast<Eigen::Index>(i)) = verts[i].transpose();
  const Eigen::Index t0 = triangles.rows();
  triangles.conservativeResize(t0 + static_cast<Eigen::Index>(tris.size()), 3);
  for (std::size_t i = 0; i < tris.size(); ++i)
    triangles.row(t0 + static_cast<Eigen::Index>(i)) << tris[i][0], tris[i][1], tris[i][2];
  is_skin.insert(is_skin.end(), skin.begin(), skin.end());
}

// ---------------------------------------------------------------------------------------------------
// ChestWall

double ChestWall::surfaceY(double x_m) const {
  if (shape == ChestWallShape::kPlanar) return 0.0;
  return radius_m - std::sqrt(std::max(0.0, radius_m * radius_m - x_m * x_m));
}

bool ChestWall::slabContains(const Eigen::Vector3d& p_m) const {
  if (shape == ChestWallShape::kPlanar) return p_m.y() >= 0.0 && p_m.y() <= thickness_m;
  const double dy = p_m.y() - radius_m;
  const double r2 = p_m.x() * p_m.x() + dy * dy;
  const double ri = radius_m - thickness_m;
  return dy < 0.0 && r2 <= radius_m * radius_m && r2 >= ri * ri;
}

// ---------------------------------------------------------------------------------------------------
// Phantom

bool Phantom::insideProne(const Eigen::Vector3d& p_m) const {
  return std::any_of(prone_breasts.begin(), prone_breasts.end(), [&](const HalfEllipsoid& e) { return e.contains(p_m); });
}

bool Phantom::insideSupine(const Eigen::Vector3d& p_m) const {
  return std::any_of(supine_breasts.begin(), supine_breasts.end(), [&](const HalfEllipsoid& e) { return e.contains(p_m); });
}

std::uint16_t Phantom::analyticLabel(const Eigen::Vector3d& p_m) const {
  for (const HalfEllipsoid& e : prone_breasts) {
    if (!e.contains(p_m)) continue;
    const Eigen::Vector3d l = e.localCoordinates(p_m);
    std::uint16_t label = phantom_labels::kFat;
    const auto value = [&l](double a, double b, double c) {
      return (l.x() / a) * (l.x() / a) + (l.y() / b) * (l.y() / b) + (l.z() / c) * (l.z() / c);
    };
    const double g = params.gland_scale;
    if (g > 0.0 && value(g * e.lateral_m, g * e.si_m, g * e.depth_m) < 1.0) label = phantom_labels::kGland;
    const double t = params.skin_thickness_m;
    if (t > 0.0 && !(value(e.lateral_m - t, e.si_m - t, e.depth_m - t) < 1.0)) label = phantom_labels::kSkin;
    for (const Lesion& les : lesions)
      if (les.radius_m > 0.0 && (p_m - les.position_m).squaredNorm() < les.radius_m * les.radius_m)
        label = phantom_labels::kLesion;
    return label;
  }
  return chest_wall.slabContains(p_m) ? phantom_labels::kChestWall : phantom_labels::kAir;
}


namespace {

// Label of one voxel: the centre sample, or the majority of n³ sub-samples (ties keep the centre's
// label, so a sub-sampled image never differs from the centre-sampled one by a coin flip). Because
// the sub-samples are symmetric about the centre, a locally planar boundary gives the centre's label
// anyway: the volume is not closer to the analytic one with n > 1 (numbers in phantom.h), which is why
// the default is 1. The grid puts voxel faces on the planar wall, so the base is not staircased.
std::uint16_t voxelLabel(const Phantom& ph, const Eigen::Vector3d& centre, int n, double h) {
  const std::uint16_t centre_label = ph.analyticLabel(centre);
  if (n == 1) return centre_label;
  std::array<std::pair<std::uint16_t, int>, 8> counts{};
  int used = 0;
  for (int a = 0; a < n; ++a)
    for (int b = 0; b < n; ++b)
      for (int c = 0; c < n; ++c) {
        const Eigen::Vector3d off = (Eigen::Vector3d(a, b, c).array() + 0.5) / n - 0.5;
        const std::uint16_t l = ph.analyticLabel(centre + h * off);
        int s = 0;
        while (s < used && counts[s].first != l) ++s;
        if (s == used) counts[used++] = {l, 0};
        ++counts[s].second;
      }
  int centre_count = 0;
  for (int s = 0; s < used; ++s)
    if (counts[s].first == centre_label) centre_count = counts[s].second;
  std::uint16_t best = centre_label;
  int best_count = centre_count;
  for (int s = 0; s < used; ++s)
    if (counts[s].second > best_count) {
      best = counts[s].first;
      best_count = counts[s].second;
    }
  return best;
}

}  // namespace

Phantom generatePhantom(const PhantomParams& params) {
  params.validate();
  Phantom ph;
  ph.params = params;
  ph.chest_wall.shape = params.chest_wall_shape;
  ph.chest_wall.radius_m = params.chest_wall_shape == ChestWallShape::kCylindrical ? params.chest_wall_radius_m : 0.0;
  ph.chest_wall.thickness_m = params.chest_wall_thickness_m;

  const Shapes shapes = makeShapes(params);
  ph.prone_breasts = shapes.prone;
  ph.supine_breasts = shapes.supine;
  for (const auto& e : ph.prone_breasts) {
    ph.prone_volume_m3 += e.volume();
    ph.nipples_m.push_back(e.apex());
  }
  for (const auto& e : ph.supine_breasts) ph.supine_volume_m3 += e.volume();
  ph.lesions = params.lesions;
  const double g = params.gravity_mps2, tilt = params.supine_gravity_tilt_rad;
  ph.gravity_prone_mps2 = Eigen::Vector3d(0.0, -g, 0.0);
  ph.gravity_supine_mps2 = Eigen::Vector3d(g * std::sin(tilt), g * std::cos(tilt), 0.0);

  for (const auto& e : ph.prone_breasts)
    e.appendSurface(params.surface_edge_m, ph.prone_surface.vertices_m, ph.prone_surface.triangles,
                    ph.prone_surface.is_skin);
  for (const auto& e : ph.supine_breasts)
    e.appendSurface(params.surface_edge_m, ph.supine_surface.vertices_m, ph.supine_surface.triangles,
                    ph.supine_surface.is_skin);

  const Grid grid = imageGrid(params, ph.prone_breasts);
  const double h = grid.h;
  ph.labels = LabelImage(grid.hi - grid.lo, Eigen::Vector3d::Constant(h), (grid.lo.cast<double>().array() + 0.5) * h,
                         phantom_labels::kAir);
  LabelImage& img = ph.labels;
  const int nx = img.size.x(), ny = img.size.y(), nz = img.size.z();
  const int n = params.supersampling;
  // Each voxel depends on its own position only, so the image is identical for any thread count.
#pragma omp parallel for schedule(dynamic, 1)
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const Eigen::Vector3d p = img.origin_m + h * Eigen::Vector3d(i, j, k);
        img.labels[static_cast<std::size_t>(img.index(i, j, k))] = voxelLabel(ph, p, n, h);
      }
  return ph;
}

}  // namespace breast_sim::core
