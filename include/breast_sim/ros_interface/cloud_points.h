#pragma once
/// @file cloud_points.h
/// The points of a sensor_msgs/PointCloud2: the one conversion that reads bytes a tracker sends, kept
/// apart from the other conversions so the fuzz build (fuzz/fuzz_cloud.cpp) compiles it alone.
/// Units: metres, in the message's frame.

#include <cstddef>

#include <sensor_msgs/PointCloud2.h>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::ros_interface {

/// The points of a PointCloud2 and what was left out.
struct CloudPoints {
  core::Points points_m;     ///< finite points [m], in the message's frame
  size_t total = 0;          ///< points in the message (width × height)
  size_t non_finite = 0;     ///< points dropped for a NaN or infinite coordinate
  size_t stride = 1;         ///< every stride-th point was read (1 = all)
};

/// Reads the x, y, z fields (FLOAT32 or FLOAT64, any offsets, either endianness of this machine only)
/// of a cloud. Clouds with more than `max_points` points (0 = no limit) are read with a stride so at
/// most `max_points` are taken. Non-finite points are dropped and counted.
/// @throws std::invalid_argument naming the field when x/y/z are missing or not floating point, or
///         when point_step, row_step and the data size disagree (a truncated or malformed message).
CloudPoints pointsFromCloud(const sensor_msgs::PointCloud2& msg, size_t max_points = 0);

}  // namespace breast_sim::ros_interface
