#include "breast_sim/ros_interface/conversions.h"

#include <stdexcept>

namespace breast_sim::ros_interface {

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

breast_sim::LesionArray toMessage(const std::vector<core::Lesion>& lesions,
                                  const core::PointEmbedding& embedding,
                                  const core::Points& displacement_m, const std::string& frame_id,
                                  const ros::Time& stamp) {
  if (static_cast<int>(lesions.size()) != embedding.size())
    throw std::invalid_argument("toMessage: " + std::to_string(lesions.size()) + " lesions but " +
                                std::to_string(embedding.size()) + " embedded points");
  breast_sim::LesionArray msg;
  msg.header.frame_id = frame_id;
  msg.header.stamp = stamp;
  // interpolate() checks that the field has a row per mesh node.
  const core::Points u = displacement_m.rows() > 0 ? embedding.interpolate(displacement_m)
                                                   : core::Points::Zero(embedding.size(), 3);
  for (size_t i = 0; i < lesions.size(); ++i) {
    breast_sim::Lesion l;
    l.id = lesions[i].name;
    l.prone_position.x = lesions[i].position_m.x();
    l.prone_position.y = lesions[i].position_m.y();
    l.prone_position.z = lesions[i].position_m.z();
    l.position.x = l.prone_position.x + u(static_cast<Eigen::Index>(i), 0);
    l.position.y = l.prone_position.y + u(static_cast<Eigen::Index>(i), 1);
    l.position.z = l.prone_position.z + u(static_cast<Eigen::Index>(i), 2);
    msg.lesions.push_back(l);
  }
  return msg;
}

}  // namespace breast_sim::ros_interface
