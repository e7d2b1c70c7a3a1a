#pragma once
/// @file conversions.h
/// Pure conversions between core types and ROS messages. Messages are validated before anything is
/// built from them; a malformed message raises std::invalid_argument naming the field and the fix.

#include <string>

#include <ros/time.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/TetrahedralMesh.h>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/point_embedding.h"

namespace breast_sim::ros_interface {

/// A TetrahedralMesh message of `mesh` with an optional displacement (#N×3 [m], or empty).
breast_sim::TetrahedralMesh toMessage(const core::TetMesh& mesh, const core::Points& displacement_m,
                                      const std::string& frame_id, const ros::Time& stamp);

/// The mesh (rest positions, tetrahedra, labels, chest-wall and skin node sets) of a message.
/// @throws std::invalid_argument when array lengths disagree, an index is out of range or a
///         tetrahedron is degenerate (the message says which).
core::TetMesh meshFromMessage(const breast_sim::TetrahedralMesh& msg);

/// Displacements of a message as #N×3 [m] (zeros when the message carries none).
/// @throws std::invalid_argument when the length is not 3 × #nodes.
core::Points displacementFromMessage(const breast_sim::TetrahedralMesh& msg);

/// Lesions at their prone positions and at the positions given by the mesh displacement.
breast_sim::LesionArray toMessage(const std::vector<core::Lesion>& lesions,
                                  const core::PointEmbedding& embedding,
                                  const core::Points& displacement_m, const std::string& frame_id,
                                  const ros::Time& stamp);

}  // namespace breast_sim::ros_interface
