// A recorded tracking scene with sensor models of its own (see scene_recording.h).
#include "breast_sim/ros_interface/scene_recording.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <random>
#include <sstream>
#include <stdexcept>

#include <boost/make_shared.hpp>
#include <geometry_msgs/PoseStamped.h>
#include <rosbag/bag.h>
#include <sensor_msgs/PointCloud2.h>
#include <tf2_msgs/TFMessage.h>

#include "breast_sim/core/model/phantom.h"
#include "breast_sim/ros_interface/conversions.h"

namespace breast_sim::ros_interface {

namespace {

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();

/// A pinhole camera: pixel (u, v) [px, continuous, (0, 0) the image's corner] looks along
/// ((u − cx) / f, (v − cy) / f, 1) in its optical frame.
struct Pinhole {
  int width = 0, height = 0;
  double f = 0, cx = 0, cy = 0;
  static Pinhole fromFov(int w, int h, double hfov_deg) {
    Pinhole p;
    p.width = w;
    p.height = h;
    p.f = 0.5 * w / std::tan(0.5 * hfov_deg * M_PI / 180.0);
    p.cx = 0.5 * w;
    p.cy = 0.5 * h;
    return p;
  }
  Eigen::Vector3d ray(double u, double v) const { return Eigen::Vector3d((u - cx) / f, (v - cy) / f, 1.0); }
};

/// An ellipsoid: centre, axes (columns, unit, orthogonal) and semi-axes [m], in the model frame.
struct Ellipsoid {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  Eigen::Matrix3d axes = Eigen::Matrix3d::Identity();
  Eigen::Vector3d semi_axes = Eigen::Vector3d::Ones();
};

enum class Hit { kNone, kSkin, kTorso, kHand };

/// The torso: the plane y = y of the skin's rim, over [x0, x1] × [z0, z1] (model frame) [m].
struct Torso {
  double y = 0, x0 = 0, x1 = 0, z0 = 0, z1 = 0;
};

/// What one camera sees of the scene at one instant: the skin's triangles binned by the cells of the
/// image they cover (projected bounding boxes), so that a ray tests only the triangles of its cell.
class FrameCaster {
 public:
  static constexpr int kCell = 4;  // [px]

  FrameCaster(const Pinhole& cam, const Eigen::Isometry3d& camera_from_model, const core::Points& skin_m,
              const core::Triangles& tris, const Torso& torso, const Ellipsoid* hand)
      : cam_(cam), camera_from_model_(camera_from_model), model_from_camera_(camera_from_model.inverse()),
        torso_(torso), hand_(hand) {
    cells_x_ = (cam.width + kCell - 1) / kCell;
    cells_y_ = (cam.height + kCell - 1) / kCell;
    cells_.assign(static_cast<size_t>(cells_x_ * cells_y_), {});
    vc_.resize(skin_m.rows(), 3);
    for (Eigen::Index i = 0; i < skin_m.rows(); ++i) vc_.row(i) = (camera_from_model * Eigen::Vector3d(skin_m.row(i))).transpose();
    tris_ = &tris;
    for (Eigen::Index t = 0; t < tris.rows(); ++t) {
      double u0 = 1e30, u1 = -1e30, v0 = 1e30, v1 = -1e30;
      bool in_front = true;
      for (int k = 0; k < 3; ++k) {
        const Eigen::Vector3d p = vc_.row(tris(t, k));
        if (p.z() < 1e-3) {
          in_front = false;
          break;
        }
        const double u = cam.f * p.x() / p.z() + cam.cx, v = cam.f * p.y() / p.z() + cam.cy;
        u0 = std::min(u0, u), u1 = std::max(u1, u), v0 = std::min(v0, v), v1 = std::max(v1, v);
      }
      if (!in_front || u1 < 0 || v1 < 0 || u0 >= cam.width || v0 >= cam.height) continue;
      const int cx0 = std::max(0, static_cast<int>(std::floor(u0)) / kCell), cx1 = std::min(cells_x_ - 1, static_cast<int>(std::floor(u1)) / kCell);
      const int cy0 = std::max(0, static_cast<int>(std::floor(v0)) / kCell), cy1 = std::min(cells_y_ - 1, static_cast<int>(std::floor(v1)) / kCell);
      for (int cy = cy0; cy <= cy1; ++cy)
        for (int cx = cx0; cx <= cx1; ++cx) cells_[static_cast<size_t>(cy * cells_x_ + cx)].push_back(static_cast<int>(t));
    }
    // The torso plane and the hand in the camera frame.
    plane_n_ = camera_from_model.linear() * Eigen::Vector3d::UnitY();
    plane_d_ = plane_n_.dot(camera_from_model * Eigen::Vector3d(0, torso.y, 0));
    if (hand_) {
      // camera point p → unit-sphere coordinates of the hand: S⁻¹ Aᵀ (model_from_camera p − c)
      const Eigen::Matrix3d to_unit = hand_->semi_axes.cwiseInverse().asDiagonal() * hand_->axes.transpose();
      hand_linear_ = to_unit * model_from_camera_.linear();
      hand_origin_ = to_unit * (model_from_camera_.translation() - hand_->centre);
    }
  }

  /// The nearest hit of the ray through pixel (u, v): its depth (optical z) [m] and what it hit.
  Hit cast(double u, double v, double max_depth, double* depth) const {
    const Eigen::Vector3d d = cam_.ray(u, v);  // z = 1: the ray parameter is the depth
    double best = max_depth;
    Hit what = Hit::kNone;
    const int cx = std::clamp(static_cast<int>(u) / kCell, 0, cells_x_ - 1), cy = std::clamp(static_cast<int>(v) / kCell, 0, cells_y_ - 1);
    for (int t : cells_[static_cast<size_t>(cy * cells_x_ + cx)]) {
      const Eigen::Vector3d a = vc_.row((*tris_)(t, 0)), b = vc_.row((*tris_)(t, 1)), c = vc_.row((*tris_)(t, 2));
      // Möller–Trumbore from the origin.
      const Eigen::Vector3d e1 = b - a, e2 = c - a, p = d.cross(e2);
      const double det = e1.dot(p);
      if (std::abs(det) < 1e-14) continue;
      const Eigen::Vector3d s = -a;
      const double bu = s.dot(p) / det;
      if (bu < 0 || bu > 1) continue;
      const Eigen::Vector3d q = s.cross(e1);
      const double bv = d.dot(q) / det;
      if (bv < 0 || bu + bv > 1) continue;
      const double z = e2.dot(q) / det;
      if (z > 1e-4 && z < best) {
        best = z;
        what = Hit::kSkin;
      }
    }
    const double nd = plane_n_.dot(d);
    if (std::abs(nd) > 1e-9) {
      const double z = plane_d_ / nd;
      if (z > 1e-4 && z < best) {
        const Eigen::Vector3d m = model_from_camera_ * (z * d);
        if (m.x() >= torso_.x0 && m.x() <= torso_.x1 && m.z() >= torso_.z0 && m.z() <= torso_.z1) {
          best = z;
          what = Hit::kTorso;
        }
      }
    }
    if (hand_) {
      const Eigen::Vector3d o = hand_origin_, w = hand_linear_ * d;
      const double qa = w.squaredNorm(), qb = 2 * o.dot(w), qc = o.squaredNorm() - 1;
      const double disc = qb * qb - 4 * qa * qc;
      if (disc >= 0) {
        const double z = (-qb - std::sqrt(disc)) / (2 * qa);
        if (z > 1e-4 && z < best) {
          best = z;
          what = Hit::kHand;
        }
      }
    }
    *depth = best;
    return what;
  }

 private:
  Pinhole cam_;
  Eigen::Isometry3d camera_from_model_, model_from_camera_;
  Torso torso_;
  const Ellipsoid* hand_;
  core::Points vc_;
  const core::Triangles* tris_ = nullptr;
  int cells_x_ = 0, cells_y_ = 0;
  std::vector<std::vector<int>> cells_;
  Eigen::Vector3d plane_n_;
  double plane_d_ = 0;
  Eigen::Matrix3d hand_linear_ = Eigen::Matrix3d::Identity();
  Eigen::Vector3d hand_origin_ = Eigen::Vector3d::Zero();
};

float packedRgb(Hit h) {
  uint32_t rgb = 0;
  switch (h) {
    case Hit::kSkin: rgb = (230u << 16) | (180u << 8) | 160u; break;
    case Hit::kTorso: rgb = (200u << 16) | (150u << 8) | 130u; break;
    case Hit::kHand: rgb = (120u << 16) | (170u << 8) | 230u; break;  // a blue glove
    case Hit::kNone: break;
  }
  float f;
  std::memcpy(&f, &rgb, 4);
  return f;
}

sensor_msgs::PointField field(const std::string& name, uint32_t offset, uint8_t type) {
  sensor_msgs::PointField f;
  f.name = name;
  f.offset = offset;
  f.datatype = type;
  f.count = 1;
  return f;
}

/// Smallest (first) intersection of a ray with the triangles, brute force (a few rays per scene).
bool firstSkinHit(const core::Points& x, const core::Triangles& tris, const Eigen::Vector3d& o, const Eigen::Vector3d& d,
                  Eigen::Vector3d* point, Eigen::Vector3d* normal) {
  double best = std::numeric_limits<double>::infinity();
  for (Eigen::Index t = 0; t < tris.rows(); ++t) {
    const Eigen::Vector3d a = x.row(tris(t, 0)), b = x.row(tris(t, 1)), c = x.row(tris(t, 2));
    const Eigen::Vector3d e1 = b - a, e2 = c - a, p = d.cross(e2);
    const double det = e1.dot(p);
    if (std::abs(det) < 1e-14) continue;
    const Eigen::Vector3d s = o - a;
    const double bu = s.dot(p) / det;
    if (bu < 0 || bu > 1) continue;
    const Eigen::Vector3d q = s.cross(e1);
    const double bv = d.dot(q) / det;
    if (bv < 0 || bu + bv > 1) continue;
    const double r = e2.dot(q) / det;
    if (r > 0 && r < best) {
      best = r;
      *point = o + r * d;
      *normal = e1.cross(e2).normalized();
    }
  }
  return std::isfinite(best);
}

void require(bool ok, const std::string& what, const std::string& range) {
  if (!ok) throw std::invalid_argument("SceneOptions: " + what + " must be " + range);
}

}  // namespace

const char* sceneBadKindName(SceneBadKind kind) {
  switch (kind) {
    case SceneBadKind::kPoseNearZeroQuaternion: return "pose near-zero quaternion";
    case SceneBadKind::kPoseFlipped: return "pose flipped 180 deg";
    case SceneBadKind::kPoseFuture: return "pose stamped an hour ahead";
    case SceneBadKind::kCloudFuture: return "cloud stamped an hour ahead";
    case SceneBadKind::kCloudPast: return "cloud stamped 10 s in the past";
    case SceneBadKind::kCloudTruncated: return "cloud truncated";
    case SceneBadKind::kCloudAllNan: return "cloud all NaN";
    case SceneBadKind::kCloudUnknownFrame: return "cloud in an unknown frame";
  }
  return "?";
}

void SceneOptions::validate() const {
  require(duration_s > 0, "duration_s", "> 0");
  require(start_s > bad_past_s + 1.0, "start_s", "> bad_past_s + 1 (no stamp may reach 0)");
  require(sensor_latency_s >= 0, "sensor_latency_s", ">= 0");
  require(gravity_in_model.norm() > 0 && gravity_in_model.allFinite(), "gravity_in_model", "a non-zero vector");
  require(tf_rate_hz > 0 && camera_rate_hz > 0 && burst_rate_hz > 0 && scanner_rate_hz > 0, "every rate", "> 0 Hz");
  require(camera_width >= 8 && camera_height >= 8, "camera_width, camera_height", ">= 8");
  require(camera_hfov_deg > 1 && camera_hfov_deg < 170 && scanner_hfov_deg > 1 && scanner_hfov_deg < 170, "the fields of view", "in (1, 170) deg");
  require(camera_distance_m > 0 && scanner_distance_m > 0 && camera_max_range_m > camera_distance_m, "the sensor distances",
          "> 0, camera_max_range_m beyond camera_distance_m");
  require(depth_noise_m >= 0 && scanner_noise_m >= 0, "the noise", ">= 0");
  require(hand_semi_axes_m.minCoeff() > 0 && hand_gap_min_m > 0 && hand_gap_max_m >= hand_gap_min_m, "the hand",
          "positive semi-axes, 0 < hand_gap_min_m <= hand_gap_max_m");
  require(scanner_points > 0, "scanner_points", "> 0");
  require(drift_ramp_s > 0 && drift_start_s + drift_ramp_s <= duration_s, "drift_start_s + drift_ramp_s", "within duration_s");
  require(bad_burst_size > 0 && bad_burst_spacing_s >= 0, "bad_burst_size, bad_burst_spacing_s", "> 0, >= 0");
  for (const auto& b : bad_bursts)
    require(b.offset_s >= camera_start_s && b.offset_s + bad_burst_size * bad_burst_spacing_s < duration_s, "bad_bursts",
            "within [camera_start_s, duration_s)");
}

int SceneDescription::bursts(SceneBadKind kind) const {
  return static_cast<int>(std::count_if(bad_bursts.begin(), bad_bursts.end(), [&](const SceneBadBurst& b) { return b.kind == kind; }));
}

std::string SceneDescription::toYaml() const {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(3);
  s << "# What the scene bag holds (scene_recording.h); times on the scene clock [s].\n";
  s << "start_s: " << start_s << "\nend_s: " << end_s << "\n";
  s << "drift: {begin_s: " << drift_begin_s << ", full_s: " << drift_full_s << ", end_s: " << drift_end_s
    << ", slide_mm: " << 1e3 * drift_m << "}\n";
  s << "segments:\n";
  for (const auto& g : segments) s << "  - {name: \"" << g.name << "\", begin_s: " << g.begin_s << ", end_s: " << g.end_s << "}\n";
  int depth = 0, scanner = 0, hand = 0;
  for (const auto& c : clouds) (c.depth_camera ? depth : scanner) += 1, hand += c.hand;
  s << "clouds: {depth_camera: " << depth << ", handheld_scanner: " << scanner << ", with_hand: " << hand << "}\n";
  s << "bad_inputs:\n";
  for (const auto& b : bad_inputs)
    s << "  - {kind: \"" << sceneBadKindName(b.kind) << "\", time_s: " << b.time_s << ", stamp_s: " << b.stamp_s
      << ", topic: \"" << b.topic << "\"}\n";
  return s.str();
}

Eigen::Vector3d supineGravityDirection(const core::ModelCase& c) {
  if (c.phantom && c.phantom->gravity_supine_mps2.norm() > 0) return c.phantom->gravity_supine_mps2.normalized();
  return -c.prone_gravity_direction.normalized();
}

SceneDescription writeSceneBag(const std::string& bag_path, const core::Points& x, const core::Triangles& tris,
                               const SceneOptions& o) {
  o.validate();
  if (x.rows() == 0 || tris.rows() == 0) throw std::invalid_argument("writeSceneBag: no skin (no positions or triangles)");
  if (tris.minCoeff() < 0 || tris.maxCoeff() >= x.rows())
    throw std::invalid_argument("writeSceneBag: a skin triangle refers to a node out of range");

  // --- The skin's extent, the rim plane (the torso) and the frames.
  Eigen::AlignedBox3d box;
  for (Eigen::Index t = 0; t < tris.rows(); ++t)
    for (int k = 0; k < 3; ++k) box.extend(Eigen::Vector3d(x.row(tris(t, k))));
  std::map<std::pair<int, int>, int> edges;
  for (Eigen::Index t = 0; t < tris.rows(); ++t)
    for (int k = 0; k < 3; ++k) {
      const int a = tris(t, k), b = tris(t, (k + 1) % 3);
      ++edges[{std::min(a, b), std::max(a, b)}];
    }
  double rim_y = 0;
  int rim_n = 0;
  for (const auto& [e, n] : edges)
    if (n == 1) rim_y += x(e.first, 1) + x(e.second, 1), rim_n += 2;
  rim_y = rim_n ? rim_y / rim_n : box.max().y();
  const double cx = box.center().x(), cz = box.center().z(), apex_y = box.min().y();
  Torso torso{rim_y, cx - o.torso_half_width_m, cx + 0.7 * o.torso_half_width_m, cz - o.torso_half_length_m,
              cz + o.torso_half_length_m};
  if (!o.with_torso) torso.x0 = torso.x1 = torso.z0 = torso.z1 = kNan;  // no ray lands in it

  // World axes in the model frame at the mean roll: z against gravity, x along the table (model z).
  const Eigen::Vector3d g = o.gravity_in_model.normalized();
  Eigen::Vector3d wx = Eigen::Vector3d::UnitZ() - Eigen::Vector3d::UnitZ().dot(g) * g;
  if (wx.norm() < 1e-6) throw std::invalid_argument("SceneOptions: gravity_in_model along the model's z axis leaves the table undefined");
  wx.normalize();
  const Eigen::Vector3d wz = -g, wy = wz.cross(wx);
  Eigen::Matrix3d model_from_world0;
  model_from_world0.col(0) = wx;
  model_from_world0.col(1) = wy;
  model_from_world0.col(2) = wz;
  auto worldFromModel = [&](double t_rel, bool roll) {
    Eigen::Isometry3d w = Eigen::Isometry3d::Identity();
    const double a = roll ? o.roll_amplitude_deg * M_PI / 180.0 * std::sin(2 * M_PI * t_rel / o.roll_period_s) : 0.0;
    w.linear() = Eigen::AngleAxisd(a, Eigen::Vector3d::UnitX()).toRotationMatrix() * model_from_world0.transpose();
    w.translation() = o.table_origin_m;
    return w;
  };
  const Eigen::Isometry3d world_from_model_mean = worldFromModel(0.0, false);
  // Depth camera: anterior of the apex, looking posterior; image x = model x, image y = model −z.
  Eigen::Isometry3d model_from_camera = Eigen::Isometry3d::Identity();
  model_from_camera.linear().col(0) = Eigen::Vector3d::UnitX();
  model_from_camera.linear().col(1) = -Eigen::Vector3d::UnitZ();
  model_from_camera.linear().col(2) = Eigen::Vector3d::UnitY();
  model_from_camera.translation() = Eigen::Vector3d(cx, apex_y - o.camera_distance_m, cz);
  const Eigen::Isometry3d world_from_camera = world_from_model_mean * model_from_camera;
  const Pinhole depth_cam = Pinhole::fromFov(o.camera_width, o.camera_height, o.camera_hfov_deg);
  const Pinhole scan_cam = Pinhole::fromFov(64, 64, o.scanner_hfov_deg);
  const double scanner_end = o.scanner_start_s + o.scanner_duration_s;
  // Hand-held scanner: a sweep above the breast, aimed at the skin's centre (in world: the patient
  // rolls under it).
  const Eigen::Vector3d aim(cx, 0.5 * (apex_y + rim_y), cz);
  auto worldFromScanner = [&](double t_rel) {
    const double tau = t_rel - o.scanner_start_s;
    const Eigen::Vector3d p(cx + o.scanner_sweep_m * std::sin(2 * M_PI * tau / o.scanner_duration_s),
                            apex_y - o.scanner_distance_m,
                            cz + 0.75 * o.scanner_sweep_m * std::sin(2 * M_PI * tau / (0.6 * o.scanner_duration_s)));
    const Eigen::Vector3d z = (aim - p).normalized();
    const Eigen::Vector3d xa = (Eigen::Vector3d::UnitX() - Eigen::Vector3d::UnitX().dot(z) * z).normalized();
    Eigen::Isometry3d m = Eigen::Isometry3d::Identity();
    m.linear().col(0) = xa;
    m.linear().col(1) = z.cross(xa);
    m.linear().col(2) = z;
    m.translation() = p;
    return world_from_model_mean * m;
  };
  auto driftAt = [&](double t_rel) {
    if (t_rel < o.drift_start_s) return 0.0;
    return o.drift_m * std::min(1.0, (t_rel - o.drift_start_s) / o.drift_ramp_s);
  };
  auto handAt = [&](double t_rel, Ellipsoid* hand) {
    if (!o.with_hand || t_rel < o.hand_start_s || t_rel > o.hand_end_s) return false;
    const double s = (t_rel - o.hand_start_s) / (o.hand_end_s - o.hand_start_s);
    const double hx = cx - 0.35 * box.sizes().x() + 0.7 * box.sizes().x() * s, hz = cz + 0.15 * box.sizes().z() * std::sin(2 * M_PI * s);
    Eigen::Vector3d p = Eigen::Vector3d::Zero(), n = -Eigen::Vector3d::UnitY();
    if (!firstSkinHit(x, tris, Eigen::Vector3d(hx, apex_y - 0.2, hz), Eigen::Vector3d::UnitY(), &p, &n)) {
      p = Eigen::Vector3d(hx, rim_y, hz);
      n = -Eigen::Vector3d::UnitY();
    }
    if (n.y() > 0) n = -n;  // towards the camera
    const double gap = o.hand_gap_min_m + (o.hand_gap_max_m - o.hand_gap_min_m) * (0.5 + 0.5 * std::sin(2 * M_PI * 1.5 * s));
    hand->semi_axes = o.hand_semi_axes_m;
    hand->centre = p + n * (gap + o.hand_semi_axes_m.y());
    const Eigen::Vector3d lateral = (Eigen::Vector3d::UnitX() - Eigen::Vector3d::UnitX().dot(n) * n).normalized();
    hand->axes.col(0) = lateral;
    hand->axes.col(1) = n;
    hand->axes.col(2) = lateral.cross(n);
    return true;
  };

  std::mt19937 rng(o.seed);
  std::normal_distribution<double> unit_normal(0.0, 1.0);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const double t0 = o.start_s;

  // Depth camera frame (good content) at t_rel: the organized cloud, and what it held.
  auto depthCloud = [&](double t_rel, const ros::Time& stamp, const std::string& frame, SceneCloud* info) {
    const double drift = driftAt(t_rel);
    core::Points skin = x;
    skin.col(0).array() += drift;
    Ellipsoid hand;
    const bool with_hand = handAt(t_rel, &hand);
    const Eigen::Isometry3d camera_from_model = world_from_camera.inverse() * worldFromModel(t_rel, true);
    const FrameCaster caster(depth_cam, camera_from_model, skin, tris, torso, with_hand ? &hand : nullptr);
    sensor_msgs::PointCloud2 m;
    m.header.stamp = stamp;
    m.header.frame_id = frame;
    m.height = static_cast<uint32_t>(depth_cam.height);
    m.width = static_cast<uint32_t>(depth_cam.width);
    m.fields = {field("x", 0, sensor_msgs::PointField::FLOAT32), field("y", 4, sensor_msgs::PointField::FLOAT32),
                field("z", 8, sensor_msgs::PointField::FLOAT32), field("rgb", 16, sensor_msgs::PointField::FLOAT32)};
    m.is_bigendian = false;
    m.point_step = 32;
    m.row_step = m.point_step * m.width;
    m.is_dense = false;
    m.data.assign(static_cast<size_t>(m.row_step) * m.height, 0);
    int finite = 0;
    for (int v = 0; v < depth_cam.height; ++v)
      for (int u = 0; u < depth_cam.width; ++u) {
        double z;
        const Hit h = caster.cast(u + 0.5, v + 0.5, o.camera_max_range_m, &z);
        float p[4] = {static_cast<float>(kNan), static_cast<float>(kNan), static_cast<float>(kNan), packedRgb(h)};
        if (h != Hit::kNone) {
          const double zn = z + o.depth_noise_m * unit_normal(rng);
          const Eigen::Vector3d q = zn * depth_cam.ray(u + 0.5, v + 0.5);
          p[0] = static_cast<float>(q.x()), p[1] = static_cast<float>(q.y()), p[2] = static_cast<float>(q.z());
          ++finite;
        }
        uint8_t* dst = m.data.data() + static_cast<size_t>(v) * m.row_step + static_cast<size_t>(u) * m.point_step;
        std::memcpy(dst, p, 12);
        std::memcpy(dst + 16, &p[3], 4);
      }
    if (info) *info = SceneCloud{stamp.toSec(), true, with_hand, drift, finite};
    return m;
  };
  auto scannerCloud = [&](double t_rel, const ros::Time& stamp, SceneCloud* info) {
    const Eigen::Isometry3d scanner_from_model = worldFromScanner(t_rel).inverse() * worldFromModel(t_rel, true);
    const FrameCaster caster(scan_cam, scanner_from_model, x, tris, torso, nullptr);
    std::vector<Eigen::Vector3d> pts;
    std::vector<float> intensity;
    pts.reserve(static_cast<size_t>(o.scanner_points));
    for (int i = 0; i < o.scanner_points; ++i) {
      const double u = u01(rng) * scan_cam.width, v = u01(rng) * scan_cam.height;
      double z;
      const Hit h = caster.cast(u, v, 2.0, &z);
      const double noise = o.scanner_noise_m * unit_normal(rng);
      if (h == Hit::kNone) continue;
      const Eigen::Vector3d d = scan_cam.ray(u, v);
      const Eigen::Vector3d q = (z * d.norm() + noise) * d.normalized();
      pts.push_back(q);
      intensity.push_back(static_cast<float>(h == Hit::kSkin ? 0.8 : 0.5) * static_cast<float>(std::exp(-q.norm())));
    }
    sensor_msgs::PointCloud2 m;
    m.header.stamp = stamp;
    m.header.frame_id = o.scanner_frame;
    m.height = 1;
    m.width = static_cast<uint32_t>(pts.size());
    m.fields = {field("x", 0, sensor_msgs::PointField::FLOAT64), field("y", 8, sensor_msgs::PointField::FLOAT64),
                field("z", 16, sensor_msgs::PointField::FLOAT64), field("intensity", 24, sensor_msgs::PointField::FLOAT32)};
    m.is_bigendian = false;
    m.point_step = 32;
    m.row_step = m.point_step * m.width;
    m.is_dense = true;
    m.data.assign(static_cast<size_t>(m.row_step), 0);
    for (size_t i = 0; i < pts.size(); ++i) {
      uint8_t* dst = m.data.data() + i * m.point_step;
      const double xyz[3] = {pts[i].x(), pts[i].y(), pts[i].z()};
      std::memcpy(dst, xyz, 24);
      std::memcpy(dst + 24, &intensity[i], 4);
    }
    if (info) *info = SceneCloud{stamp.toSec(), false, false, 0.0, static_cast<int>(pts.size())};
    return m;
  };

  // --- The schedule: every message as an event at its write time, written in time order.
  enum class Ev { kTf, kDepth, kScanner, kBad };
  struct Event {
    double time_rel;  // written at
    double stamp_rel;
    Ev type;
    SceneBadKind bad = SceneBadKind::kCloudFuture;
    size_t seq = 0;
  };
  std::vector<Event> events;
  const int tf_n = static_cast<int>(std::floor(o.duration_s * o.tf_rate_hz + 1e-9));
  for (int k = 0; k <= tf_n; ++k) events.push_back({k / o.tf_rate_hz, k / o.tf_rate_hz, Ev::kTf});
  // The bad messages first: the sensors are quiet around each bad cloud.
  SceneDescription desc;
  auto isPose = [](SceneBadKind k) {
    return k == SceneBadKind::kPoseNearZeroQuaternion || k == SceneBadKind::kPoseFlipped || k == SceneBadKind::kPoseFuture;
  };
  std::vector<double> bad_cloud_times;
  for (const auto& b : o.bad_bursts) {
    desc.bad_bursts.push_back({b.kind, t0 + b.offset_s});
    for (int i = 0; i < o.bad_burst_size; ++i) {
      const double t = b.offset_s + i * o.bad_burst_spacing_s;
      events.push_back({t, t, Ev::kBad, b.kind});
      if (!isPose(b.kind)) bad_cloud_times.push_back(t);
    }
  }
  auto quiet = [&](double stamp) {
    for (double t : bad_cloud_times)
      if (stamp > t - o.bad_quiet_before_s && stamp < t + o.bad_quiet_after_s) return true;
    return false;
  };
  auto addClouds = [&](double from, double to, double rate, Ev type) {
    for (int k = 0;; ++k) {
      const double t = from + k / rate;
      if (t >= to - 1e-9) break;
      if (!quiet(t)) events.push_back({t + o.sensor_latency_s, t, type});
    }
  };
  addClouds(o.camera_start_s, std::min(o.burst_start_s, o.duration_s), o.camera_rate_hz, Ev::kDepth);
  addClouds(o.burst_start_s, std::min(o.burst_start_s + o.burst_duration_s, o.duration_s), o.burst_rate_hz, Ev::kDepth);
  addClouds(o.burst_start_s + o.burst_duration_s, o.duration_s, o.camera_rate_hz, Ev::kDepth);
  addClouds(o.scanner_start_s, std::min(scanner_end, o.duration_s), o.scanner_rate_hz, Ev::kScanner);
  for (size_t i = 0; i < events.size(); ++i) events[i].seq = i;
  std::stable_sort(events.begin(), events.end(), [](const Event& a, const Event& b) { return a.time_rel < b.time_rel; });

  // --- Write.
  rosbag::Bag bag(bag_path, rosbag::bagmode::Write);
  bag.setCompression(rosbag::compression::Uncompressed);
  auto at = [&](double t_rel) { return ros::Time(t0 + t_rel); };
  {
    tf2_msgs::TFMessage statics;
    geometry_msgs::TransformStamped ts;
    ts.header.stamp = at(0);
    ts.header.frame_id = o.world_frame;
    ts.child_frame_id = o.camera_frame;
    ts.transform = transformFromIsometry(world_from_camera);
    statics.transforms.push_back(ts);
    // Latched, as tf2's static broadcaster publishes it: rosbag play keeps it for late subscribers.
    auto latched = boost::make_shared<ros::M_string>();
    (*latched)["latching"] = "1";
    (*latched)["callerid"] = "/scene_recording";
    // A connection header given to rosbag replaces the one it would write: it needs the type too.
    (*latched)["type"] = ros::message_traits::datatype(statics);
    (*latched)["md5sum"] = ros::message_traits::md5sum(statics);
    (*latched)["message_definition"] = ros::message_traits::definition(statics);
    bag.write("/tf_static", at(0), statics, latched);
  }
  for (const Event& e : events) {
    const ros::Time when = at(e.time_rel), stamp = at(e.stamp_rel);
    switch (e.type) {
      case Ev::kTf: {
        tf2_msgs::TFMessage tf;
        geometry_msgs::TransformStamped ts;
        ts.header.stamp = stamp;
        ts.header.frame_id = o.world_frame;
        ts.child_frame_id = o.model_frame;
        ts.transform = transformFromIsometry(worldFromModel(e.stamp_rel, true));
        tf.transforms.push_back(ts);
        if (e.stamp_rel >= o.scanner_start_s - 0.2 && e.stamp_rel <= scanner_end + 0.2) {
          ts.child_frame_id = o.scanner_frame;
          ts.transform = transformFromIsometry(worldFromScanner(e.stamp_rel));
          tf.transforms.push_back(ts);
        }
        bag.write("/tf", when, tf);
        break;
      }
      case Ev::kDepth: {
        SceneCloud info;
        bag.write(o.cloud_topic, when, depthCloud(e.stamp_rel, stamp, o.camera_frame, &info));
        desc.clouds.push_back(info);
        break;
      }
      case Ev::kScanner: {
        SceneCloud info;
        bag.write(o.cloud_topic, when, scannerCloud(e.stamp_rel, stamp, &info));
        desc.clouds.push_back(info);
        break;
      }
      case Ev::kBad: {
        SceneBadInput bad{e.bad, t0 + e.time_rel, t0 + e.time_rel, ""};
        if (e.bad == SceneBadKind::kPoseNearZeroQuaternion || e.bad == SceneBadKind::kPoseFlipped ||
            e.bad == SceneBadKind::kPoseFuture) {
          geometry_msgs::PoseStamped pose;
          pose.header.frame_id = o.world_frame;
          pose.header.stamp = stamp;
          Eigen::Isometry3d w = worldFromModel(e.stamp_rel, true);
          if (e.bad == SceneBadKind::kPoseFlipped) w = w * Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX());
          if (e.bad == SceneBadKind::kPoseFuture) pose.header.stamp = at(e.stamp_rel + o.bad_future_s);
          pose.pose = poseFromIsometry(w);
          if (e.bad == SceneBadKind::kPoseNearZeroQuaternion) {
            pose.pose.orientation.w = 1e-5;
            pose.pose.orientation.x = pose.pose.orientation.y = pose.pose.orientation.z = 0.0;
          }
          bad.stamp_s = pose.header.stamp.toSec();
          bad.topic = o.pose_topic;
          bag.write(o.pose_topic, when, pose);
        } else {
          sensor_msgs::PointCloud2 m;
          if (e.bad == SceneBadKind::kCloudAllNan) {
            m = depthCloud(e.stamp_rel, stamp, o.camera_frame, nullptr);
            for (size_t i = 0; i < m.data.size(); i += m.point_step) {
              const float nan[3] = {static_cast<float>(kNan), static_cast<float>(kNan), static_cast<float>(kNan)};
              std::memcpy(m.data.data() + i, nan, 12);
            }
          } else {
            m = depthCloud(e.stamp_rel, stamp, e.bad == SceneBadKind::kCloudUnknownFrame ? o.unknown_frame : o.camera_frame, nullptr);
            if (e.bad == SceneBadKind::kCloudFuture) m.header.stamp = at(e.stamp_rel + o.bad_future_s);
            if (e.bad == SceneBadKind::kCloudPast) m.header.stamp = at(e.stamp_rel - o.bad_past_s);
            if (e.bad == SceneBadKind::kCloudTruncated) m.data.resize(m.data.size() / 2);
          }
          bad.stamp_s = m.header.stamp.toSec();
          bad.topic = o.cloud_topic;
          bag.write(o.cloud_topic, when, m);
        }
        desc.bad_inputs.push_back(bad);
        break;
      }
    }
  }
  bag.close();

  desc.start_s = t0;
  desc.end_s = t0 + o.duration_s;
  desc.drift_begin_s = t0 + o.drift_start_s;
  desc.drift_full_s = t0 + o.drift_start_s + o.drift_ramp_s;
  desc.drift_end_s = t0 + o.duration_s;
  desc.drift_m = o.drift_m;
  desc.segments = {{"depth camera 15 Hz", t0 + o.camera_start_s, t0 + o.duration_s},
                   {"depth camera burst", t0 + o.burst_start_s, t0 + o.burst_start_s + o.burst_duration_s},
                   {"hand in view", t0 + o.hand_start_s, t0 + o.hand_end_s},
                   {"hand-held scanner", t0 + o.scanner_start_s, t0 + std::min(scanner_end, o.duration_s)},
                   {"drift ramp", desc.drift_begin_s, desc.drift_full_s},
                   {"drift held", desc.drift_full_s, desc.drift_end_s}};
  std::sort(desc.clouds.begin(), desc.clouds.end(), [](const SceneCloud& a, const SceneCloud& b) { return a.stamp_s < b.stamp_s; });
  return desc;
}

}  // namespace breast_sim::ros_interface
