#pragma once
/// @file box_mesh.h
/// Structured tetrahedral meshes of boxes, for verification cases (patch test, cantilever, blocks).

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// A box [0, size.x] × [0, size.y] × [0, size.z] [m] split into cells.x × cells.y × cells.z cubes of
/// six tetrahedra each (Kuhn subdivision around each cube's main diagonal, conforming across cubes).
/// Node sets: "x_min", "x_max", "y_min", "y_max", "z_min", "z_max" (the six faces) and "boundary".
/// @throws std::invalid_argument for a non-positive cell count or size.
TetMesh makeBoxMesh(const Eigen::Vector3i& cells, const Eigen::Vector3d& size_m);

}  // namespace breast_sim::core
