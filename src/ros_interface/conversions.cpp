#include "breast_sim/ros_interface/conversions.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <unordered_map>
#include <unordered_set>
#include <array>
#include <sstream>

namespace breast_sim::ros_interface {

namespace {
// The skin marker's look: skin tone, seen-through alpha, and the light of its face shading (model
// frame; anterior of the phantom is −y, z up).
constexpr float kSkinColour[3] = {0.96f, 0.76f, 0.64f};
constexpr float kSkinAlpha = 0.45f;
constexpr double kSkinLight[3] = {-0.3, -1.0, 0.6};
// A clustered triangle within ~80° of edge-on to the surface's normal over its cells is a fold.
constexpr double kFinCosine = 0.17;
}  // namespace

breast_sim::TetrahedralMesh toMessage(const core::TetMesh& mesh, const core::Points& displacement_m,
                                      const std::string& frame_id, const ros::Time& stamp) {
  breast_sim::TetrahedralMesh msg;
  msg.header.frame_id = frame_id;
  msg.header.stamp = stamp;
  const core::Points& x = mesh.nodes();
  msg.rest_positions.assign(x.data(), x.data() + x.size());  // row-major: x0 y0 z0 x1 …
  if (displacement_m.rows() > 0) {
    if (displacement_m.rows() != mesh.numNodes())
      throw std::invalid_argument("toMessage: displacement has " + std::to_string(displacement_m.rows()) +
                                  " rows for a mesh of " + std::to_string(mesh.numNodes()) + " nodes");
    msg.displacements.assign(displacement_m.data(), displacement_m.data() + displacement_m.size());
  }
  msg.tetrahedra.assign(mesh.tets().data(), mesh.tets().data() + mesh.tets().size());
  msg.region_labels.assign(mesh.regionLabels().begin(), mesh.regionLabels().end());
  if (mesh.hasNodeSet(core::node_sets::kChestWall)) {
    const auto& s = mesh.nodeSet(core::node_sets::kChestWall);
    msg.chest_wall_nodes.assign(s.begin(), s.end());
  }
  if (mesh.hasNodeSet(core::node_sets::kSkin)) {
    const auto& s = mesh.nodeSet(core::node_sets::kSkin);
    msg.skin_nodes.assign(s.begin(), s.end());
  }
  return msg;
}

core::TetMesh meshFromMessage(const breast_sim::TetrahedralMesh& msg) {
  if (msg.rest_positions.size() % 3 != 0)
    throw std::invalid_argument("TetrahedralMesh: rest_positions has " + std::to_string(msg.rest_positions.size()) +
                                " values, not a multiple of 3 (x, y, z per node)");
  if (msg.tetrahedra.size() % 4 != 0)
    throw std::invalid_argument("TetrahedralMesh: tetrahedra has " + std::to_string(msg.tetrahedra.size()) +
                                " indices, not a multiple of 4");
  const Eigen::Index n = static_cast<Eigen::Index>(msg.rest_positions.size() / 3);
  const Eigen::Index t = static_cast<Eigen::Index>(msg.tetrahedra.size() / 4);
  if (!msg.region_labels.empty() && static_cast<Eigen::Index>(msg.region_labels.size()) != t)
    throw std::invalid_argument("TetrahedralMesh: " + std::to_string(msg.region_labels.size()) +
                                " region_labels for " + std::to_string(t) + " tetrahedra; give one each or none");
  core::Points x = Eigen::Map<const core::Points>(msg.rest_positions.data(), n, 3);
  core::Tets tets(t, 4);
  for (Eigen::Index i = 0; i < t * 4; ++i) {
    const uint32_t v = msg.tetrahedra[static_cast<size_t>(i)];
    if (v >= static_cast<uint32_t>(n))
      throw std::invalid_argument("TetrahedralMesh: tetrahedron " + std::to_string(i / 4) + " refers to node " +
                                  std::to_string(v) + " of " + std::to_string(n));
    tets.data()[i] = static_cast<int>(v);
  }
  core::TetMesh mesh(std::move(x), std::move(tets), std::vector<int>(msg.region_labels.begin(), msg.region_labels.end()));
  mesh.setNodeSet(core::node_sets::kChestWall, std::vector<int>(msg.chest_wall_nodes.begin(), msg.chest_wall_nodes.end()));
  mesh.setNodeSet(core::node_sets::kSkin, std::vector<int>(msg.skin_nodes.begin(), msg.skin_nodes.end()));
  return mesh;
}

core::Points displacementFromMessage(const breast_sim::TetrahedralMesh& msg) {
  const Eigen::Index n = static_cast<Eigen::Index>(msg.rest_positions.size() / 3);
  if (msg.displacements.empty()) return core::Points::Zero(n, 3);
  if (msg.displacements.size() != msg.rest_positions.size())
    throw std::invalid_argument("TetrahedralMesh: displacements has " + std::to_string(msg.displacements.size()) +
                                " values for " + std::to_string(n) + " nodes; expected 3 per node or none");
  return Eigen::Map<const core::Points>(msg.displacements.data(), n, 3);
}

namespace {

void checkRegionCount(const char* what, const std::vector<core::LesionRegion>* regions, size_t lesions) {
  if (regions && regions->size() != lesions)
    throw std::invalid_argument(std::string(what) + ": " + std::to_string(regions->size()) + " regions for " +
                                std::to_string(lesions) + " lesions");
}

}  // namespace

breast_sim::LesionArray lesionsMessage(const std::vector<core::Lesion>& lesions, const core::Points& positions_m,
                                       const std::string& frame_id, const ros::Time& stamp, bool valid,
                                       const std::string& status, const std::vector<core::LesionRegion>* regions) {
  if (positions_m.rows() != static_cast<Eigen::Index>(lesions.size()))
    throw std::invalid_argument("lesionsMessage: " + std::to_string(positions_m.rows()) + " positions for " +
                                std::to_string(lesions.size()) + " lesions");
  checkRegionCount("lesionsMessage", regions, lesions.size());
  breast_sim::LesionArray msg;
  msg.header.frame_id = frame_id;
  msg.header.stamp = stamp;
  msg.valid = valid;
  msg.status = status;
  for (size_t i = 0; i < lesions.size(); ++i) {
    breast_sim::Lesion l;
    l.id = lesions[i].name;
    l.prone_position.x = lesions[i].position_m.x();
    l.prone_position.y = lesions[i].position_m.y();
    l.prone_position.z = lesions[i].position_m.z();
    const auto r = static_cast<Eigen::Index>(i);
    l.position.x = positions_m(r, 0);
    l.position.y = positions_m(r, 1);
    l.position.z = positions_m(r, 2);
    l.valid = valid;
    l.position_covariance.fill(0.0);
    l.position_covariance_type = breast_sim::Lesion::COVARIANCE_UNKNOWN;
    if (regions) {
      const core::LesionRegion& g = (*regions)[i];
      for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) l.position_covariance[static_cast<size_t>(3 * a + b)] = g.covariance_m2(a, b);
      l.position_covariance_type = breast_sim::Lesion::COVARIANCE_ENSEMBLE;
      l.region_confidence = g.confidence;
      l.region_scale = g.scale;
    }
    msg.lesions.push_back(l);
  }
  return msg;
}

sensor_msgs::PointCloud2 cloudToMessage(const core::Points& points_m, const std::string& frame_id,
                                        const ros::Time& stamp) {
  sensor_msgs::PointCloud2 msg;
  msg.header.frame_id = frame_id;
  msg.header.stamp = stamp;
  msg.height = 1;
  msg.width = static_cast<uint32_t>(points_m.rows());
  const char* names[3] = {"x", "y", "z"};
  for (int k = 0; k < 3; ++k) {
    sensor_msgs::PointField f;
    f.name = names[k];
    f.offset = static_cast<uint32_t>(4 * k);
    f.datatype = sensor_msgs::PointField::FLOAT32;
    f.count = 1;
    msg.fields.push_back(f);
  }
  msg.is_bigendian = false;
  msg.point_step = 12;
  msg.row_step = msg.point_step * msg.width;
  msg.is_dense = points_m.allFinite();
  msg.data.resize(msg.row_step);
  for (Eigen::Index i = 0; i < points_m.rows(); ++i)
    for (int k = 0; k < 3; ++k) {
      const float v = static_cast<float>(points_m(i, k));
      std::memcpy(msg.data.data() + 12 * i + 4 * k, &v, 4);
    }
  return msg;
}

Eigen::Isometry3d isometryFromPose(const geometry_msgs::Pose& pose) {
  const Eigen::Vector3d p(pose.position.x, pose.position.y, pose.position.z);
  Eigen::Quaterniond q(pose.orientation.w, pose.orientation.x, pose.orientation.y, pose.orientation.z);
  if (!p.allFinite() || !q.coeffs().allFinite())
    throw std::invalid_argument("pose: a position or orientation value is not finite");
  if (!(std::abs(q.norm() - 1.0) <= 1e-3)) {
    std::ostringstream s;
    s << "pose: the orientation quaternion (w " << q.w() << ", x " << q.x() << ", y " << q.y() << ", z " << q.z()
      << ") has norm " << q.norm() << "; a rotation needs a unit quaternion (norm within 1 ± 0.001; w = 1 for none)";
    throw std::invalid_argument(s.str());
  }
  q.normalize();
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = q.toRotationMatrix();
  t.translation() = p;
  return t;
}

geometry_msgs::Pose poseFromIsometry(const Eigen::Isometry3d& t) {
  geometry_msgs::Pose pose;
  pose.position.x = t.translation().x();
  pose.position.y = t.translation().y();
  pose.position.z = t.translation().z();
  const Eigen::Quaterniond q(t.linear());
  pose.orientation.w = q.w();
  pose.orientation.x = q.x();
  pose.orientation.y = q.y();
  pose.orientation.z = q.z();
  return pose;
}

Eigen::Isometry3d isometryFromTransform(const geometry_msgs::Transform& t) {
  geometry_msgs::Pose p;
  p.position.x = t.translation.x;
  p.position.y = t.translation.y;
  p.position.z = t.translation.z;
  p.orientation = t.rotation;
  return isometryFromPose(p);
}

geometry_msgs::Transform transformFromIsometry(const Eigen::Isometry3d& t) {
  const geometry_msgs::Pose p = poseFromIsometry(t);
  geometry_msgs::Transform out;
  out.translation.x = p.position.x;
  out.translation.y = p.position.y;
  out.translation.z = p.position.z;
  out.rotation = p.orientation;
  return out;
}

core::Points transformPoints(const Eigen::Isometry3d& t, const core::Points& points_m) {
  core::Points out(points_m.rows(), 3);
  const Eigen::Matrix3d r = t.linear();
  const Eigen::RowVector3d c = t.translation().transpose();
  out.noalias() = points_m * r.transpose();
  out.rowwise() += c;
  return out;
}

Eigen::Vector3d gravityLoad(const Eigen::Matrix3d& model_from_gravity, double g_mps2,
                            const Eigen::Vector3d& prone_gravity_mps2) {
  return model_from_gravity * Eigen::Vector3d(0.0, 0.0, -g_mps2) - prone_gravity_mps2;
}

double angleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  const double na = a.norm(), nb = b.norm();
  if (na == 0.0 || nb == 0.0) return 0.0;
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / M_PI;
}

bool gravityLoadChanged(const Eigen::Vector3d& load, const Eigen::Vector3d& current, double threshold_deg, double g_mps2) {
  return angleDeg(load, current) > threshold_deg || (load - current).norm() > 0.01 * g_mps2;
}

DisplaySurface decimateSurface(const core::Points& positions_m, const core::Triangles& triangles, int max_triangles) {
  const Eigen::Index nv = positions_m.rows();
  for (Eigen::Index i = 0; i < triangles.size(); ++i)
    if (triangles.data()[i] < 0 || triangles.data()[i] >= nv)
      throw std::invalid_argument("decimateSurface: triangle index " + std::to_string(triangles.data()[i]) +
                                  " out of range for " + std::to_string(nv) + " vertices");
  // Collapse vertices cell by cell; representative = the first vertex met in a cell.
  auto cluster = [&](double cell, std::vector<int>& rep) {
    rep.assign(static_cast<size_t>(nv), -1);
    std::unordered_map<long long, int> first;
    for (Eigen::Index t = 0; t < triangles.rows(); ++t)
      for (int k = 0; k < 3; ++k) {
        const int v = triangles(t, k);
        if (rep[static_cast<size_t>(v)] >= 0) continue;
        if (cell <= 0) {
          rep[static_cast<size_t>(v)] = v;
          continue;
        }
        const Eigen::RowVector3d p = positions_m.row(v) / cell;
        const long long key = (static_cast<long long>(std::floor(p.x())) & 0x1FFFFF) |
                              ((static_cast<long long>(std::floor(p.y())) & 0x1FFFFF) << 21) |
                              ((static_cast<long long>(std::floor(p.z())) & 0x1FFFFF) << 42);
        rep[static_cast<size_t>(v)] = first.emplace(key, v).first->second;
      }
  };
  auto collapse = [&](const std::vector<int>& rep, DisplaySurface& out, bool clustered) {
    // Area-weighted normal of the input surface over each cell (indexed by the cell's representative).
    std::vector<Eigen::RowVector3d> cell_normal;
    if (clustered) {
      cell_normal.assign(static_cast<size_t>(nv), Eigen::RowVector3d::Zero());
      for (Eigen::Index t = 0; t < triangles.rows(); ++t) {
        const Eigen::RowVector3d n = (positions_m.row(triangles(t, 1)) - positions_m.row(triangles(t, 0)))
                                         .cross(positions_m.row(triangles(t, 2)) - positions_m.row(triangles(t, 0)));
        for (int k = 0; k < 3; ++k) cell_normal[static_cast<size_t>(rep[static_cast<size_t>(triangles(t, k))])] += n;
      }
    }
    std::unordered_map<int, int> index;
    std::unordered_set<std::string> seen;
    std::vector<Eigen::Vector3i> tris;
    for (Eigen::Index t = 0; t < triangles.rows(); ++t) {
      const int a = rep[static_cast<size_t>(triangles(t, 0))], b = rep[static_cast<size_t>(triangles(t, 1))],
                c = rep[static_cast<size_t>(triangles(t, 2))];
      if (a == b || b == c || a == c) continue;
      std::array<int, 3> key{a, b, c};
      std::sort(key.begin(), key.end());
      if (!seen.insert(std::to_string(key[0]) + ',' + std::to_string(key[1]) + ',' + std::to_string(key[2])).second) continue;
      Eigen::Vector3i tri;
      // A clustered triangle may have turned over: wind it with the surface's own normal over its
      // three cells (the input winding where nothing was clustered). One standing edge-on to that
      // normal is a fin clustering folded out of the surface (e.g. across a meridian of a sphere): it
      // faces neither way and is dropped.
      bool flip = false;
      if (!cell_normal.empty()) {
        const Eigen::RowVector3d n = (positions_m.row(b) - positions_m.row(a)).cross(positions_m.row(c) - positions_m.row(a));
        const Eigen::RowVector3d s = cell_normal[static_cast<size_t>(a)] + cell_normal[static_cast<size_t>(b)] +
                                     cell_normal[static_cast<size_t>(c)];
        const double d = n.dot(s), ns = n.norm() * s.norm();
        if (std::abs(d) < kFinCosine * ns) continue;
        flip = d < 0.0;
      }
      const int abc[3] = {a, flip ? c : b, flip ? b : c};
      for (int k = 0; k < 3; ++k) {
        auto it = index.find(abc[k]);
        if (it == index.end()) {
          it = index.emplace(abc[k], static_cast<int>(out.vertices.size())).first;
          out.vertices.push_back(abc[k]);
        }
        tri[k] = it->second;
      }
      tris.push_back(tri);
    }
    out.triangles.resize(static_cast<Eigen::Index>(tris.size()), 3);
    for (size_t i = 0; i < tris.size(); ++i) out.triangles.row(static_cast<Eigen::Index>(i)) = tris[i].transpose();
  };
  DisplaySurface out;
  std::vector<int> rep;
  if (max_triangles <= 0 || triangles.rows() <= max_triangles) {
    cluster(0.0, rep);
    collapse(rep, out, false);
    return out;
  }
  double edge = 0.0;
  for (Eigen::Index t = 0; t < triangles.rows(); ++t)
    edge += (positions_m.row(triangles(t, 0)) - positions_m.row(triangles(t, 1))).norm();
  double cell = edge / static_cast<double>(triangles.rows());
  for (int attempt = 0; attempt < 30; ++attempt, cell *= 1.5) {
    out = DisplaySurface();
    cluster(cell, rep);
    collapse(rep, out, true);
    out.cell_m = cell;
    if (out.triangles.rows() <= max_triangles) break;
  }
  return out;
}

visualization_msgs::Marker surfaceMarker(const DisplaySurface& surface, const core::Points& positions_m,
                                         const std::string& frame_id, const ros::Time& stamp) {
  visualization_msgs::Marker m;
  m.header.frame_id = frame_id;
  m.header.stamp = stamp;
  m.ns = "skin";
  m.id = 0;
  m.type = visualization_msgs::Marker::TRIANGLE_LIST;
  m.action = visualization_msgs::Marker::ADD;
  m.pose.orientation.w = 1.0;
  m.scale.x = m.scale.y = m.scale.z = 1.0;
  m.color.r = kSkinColour[0];
  m.color.g = kSkinColour[1];
  m.color.b = kSkinColour[2];
  m.color.a = kSkinAlpha;
  const Eigen::Vector3d light = Eigen::Vector3d(kSkinLight[0], kSkinLight[1], kSkinLight[2]).normalized();
  m.points.resize(static_cast<size_t>(3 * surface.triangles.rows()));
  m.colors.resize(static_cast<size_t>(surface.triangles.rows()));
  for (Eigen::Index t = 0; t < surface.triangles.rows(); ++t) {
    Eigen::Vector3d c[3];
    for (int k = 0; k < 3; ++k) {
      const int node = surface.vertices[static_cast<size_t>(surface.triangles(t, k))];
      c[k] = positions_m.row(node).transpose();
      auto& p = m.points[static_cast<size_t>(3 * t + k)];
      p.x = c[k].x();
      p.y = c[k].y();
      p.z = c[k].z();
    }
    // Two-sided shading: the same shade seen from outside or inside.
    const Eigen::Vector3d n = (c[1] - c[0]).cross(c[2] - c[0]);
    const double nn = n.norm();
    const double shade = 0.55 + 0.45 * (nn > 0 ? std::abs(n.dot(light)) / nn : 0.0);
    auto& col = m.colors[static_cast<size_t>(t)];
    col.r = static_cast<float>(shade * kSkinColour[0]);
    col.g = static_cast<float>(shade * kSkinColour[1]);
    col.b = static_cast<float>(shade * kSkinColour[2]);
    col.a = 1.0f;  // rviz multiplies by color.a
  }
  return m;
}

visualization_msgs::MarkerArray lesionMarkers(const std::vector<core::Lesion>& lesions, const core::Points& positions_m,
                                              const std::string& frame_id, const ros::Time& stamp,
                                              const std::vector<core::LesionRegion>* regions) {
  if (positions_m.rows() != static_cast<Eigen::Index>(lesions.size()))
    throw std::invalid_argument("lesionMarkers: " + std::to_string(positions_m.rows()) + " positions for " +
                                std::to_string(lesions.size()) + " lesions");
  checkRegionCount("lesionMarkers", regions, lesions.size());
  visualization_msgs::MarkerArray out;
  for (size_t i = 0; i < lesions.size(); ++i) {
    const auto r = static_cast<Eigen::Index>(i);
    visualization_msgs::Marker s;
    s.header.frame_id = frame_id;
    s.header.stamp = stamp;
    s.ns = "lesions";
    s.id = static_cast<int>(i);
    s.type = visualization_msgs::Marker::SPHERE;
    s.action = visualization_msgs::Marker::ADD;
    s.pose.position.x = positions_m(r, 0);
    s.pose.position.y = positions_m(r, 1);
    s.pose.position.z = positions_m(r, 2);
    s.pose.orientation.w = 1.0;
    s.scale.x = s.scale.y = s.scale.z = 2.0 * std::max(lesions[i].radius_m, 2e-3);
    s.color.r = 0.9f;
    s.color.g = 0.1f;
    s.color.b = 0.1f;
    s.color.a = 1.0f;
    out.markers.push_back(s);
    visualization_msgs::Marker t = s;
    t.ns = "lesion_labels";
    t.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
    t.text = lesions[i].name;
    t.pose.position.z += s.scale.z;
    t.scale.x = t.scale.y = 0.0;
    t.scale.z = 0.008;
    t.color.r = t.color.g = t.color.b = 1.0f;
    out.markers.push_back(t);
    visualization_msgs::Marker e = s;
    e.ns = "lesion_regions";
    if (regions) {
      const core::LesionRegion& g = (*regions)[i];
      const Eigen::Quaterniond q(g.axes);  // the ellipsoid's x, y, z along semi-axes 1, 2, 3
      e.pose.orientation.x = q.x();
      e.pose.orientation.y = q.y();
      e.pose.orientation.z = q.z();
      e.pose.orientation.w = q.w();
      // rviz cannot draw a zero-width sphere: a degenerate axis is drawn 0.1 mm wide.
      e.scale.x = std::max(2.0 * g.semi_axes_m.x(), 1e-4);
      e.scale.y = std::max(2.0 * g.semi_axes_m.y(), 1e-4);
      e.scale.z = std::max(2.0 * g.semi_axes_m.z(), 1e-4);
      e.color.r = 1.0f;
      e.color.g = 0.6f;
      e.color.b = 0.1f;
      e.color.a = 0.35f;
    } else {
      e.action = visualization_msgs::Marker::DELETE;
    }
    out.markers.push_back(e);
  }
  return out;
}

std::vector<geometry_msgs::TransformStamped> lesionTransforms(const std::vector<core::Lesion>& lesions,
                                                              const core::Points& positions_m,
                                                              const std::string& frame_id, const std::string& prefix,
                                                              const ros::Time& stamp) {
  if (positions_m.rows() != static_cast<Eigen::Index>(lesions.size()))
    throw std::invalid_argument("lesionTransforms: " + std::to_string(positions_m.rows()) + " positions for " +
                                std::to_string(lesions.size()) + " lesions");
  std::vector<geometry_msgs::TransformStamped> out;
  for (size_t i = 0; i < lesions.size(); ++i) {
    geometry_msgs::TransformStamped t;
    t.header.frame_id = frame_id;
    t.header.stamp = stamp;
    t.child_frame_id = prefix + lesions[i].name;
    const auto r = static_cast<Eigen::Index>(i);
    t.transform.translation.x = positions_m(r, 0);
    t.transform.translation.y = positions_m(r, 1);
    t.transform.translation.z = positions_m(r, 2);
    t.transform.rotation.w = 1.0;
    out.push_back(t);
  }
  return out;
}

visualization_msgs::MarkerArray slidingMarkers(const core::Points& positions_m, const core::Points& vectors_m,
                                               const std::vector<int>& nodes, double scale, double min_length_m,
                                               int max_arrows, const std::string& frame_id, const ros::Time& stamp) {
  if (vectors_m.rows() != positions_m.rows())
    throw std::invalid_argument("slidingMarkers: " + std::to_string(vectors_m.rows()) + " vectors for " +
                                std::to_string(positions_m.rows()) + " nodes");
  visualization_msgs::MarkerArray out;
  visualization_msgs::Marker clear;
  clear.header.frame_id = frame_id;
  clear.header.stamp = stamp;
  clear.ns = "sliding";
  clear.action = visualization_msgs::Marker::DELETEALL;
  out.markers.push_back(clear);
  std::vector<int> moving;
  for (int n : nodes) {
    if (n < 0 || n >= positions_m.rows())
      throw std::invalid_argument("slidingMarkers: node " + std::to_string(n) + " out of range");
    if (vectors_m.row(n).norm() > min_length_m) moving.push_back(n);
  }
  const size_t step = (max_arrows > 0 && moving.size() > static_cast<size_t>(max_arrows))
                          ? (moving.size() + static_cast<size_t>(max_arrows) - 1) / static_cast<size_t>(max_arrows)
                          : 1;
  int id = 0;
  for (size_t i = 0; i < moving.size(); i += step) {
    const int n = moving[i];
    visualization_msgs::Marker a;
    a.header.frame_id = frame_id;
    a.header.stamp = stamp;
    a.ns = "sliding";
    a.id = id++;
    a.type = visualization_msgs::Marker::ARROW;
    a.action = visualization_msgs::Marker::ADD;
    a.pose.orientation.w = 1.0;
    geometry_msgs::Point p0, p1;
    p0.x = positions_m(n, 0);
    p0.y = positions_m(n, 1);
    p0.z = positions_m(n, 2);
    p1.x = p0.x + scale * vectors_m(n, 0);
    p1.y = p0.y + scale * vectors_m(n, 1);
    p1.z = p0.z + scale * vectors_m(n, 2);
    a.points = {p0, p1};
    a.scale.x = 0.0010;  // shaft diameter [m]
    a.scale.y = 0.0022;  // head diameter [m]
    a.scale.z = 0.0030;  // head length [m]
    a.color.r = 0.2f;    // yellow-green: apart from the skin, the red lesions and a blue tracker cloud
    a.color.g = 0.95f;
    a.color.b = 0.2f;
    a.color.a = 1.0f;
    out.markers.push_back(a);
  }
  return out;
}

}  // namespace breast_sim::ros_interface
