#pragma once
/// @file sliding_internal.h
/// Functions shared by the translation units of ChestWallSliding (chest_wall_sliding.h); private to
/// src/core/sliding.
#include <chrono>
#include <sstream>
#include <stdexcept>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace breast_sim::core::sliding_internal {

/// Wall time since t [s].
inline double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

/// @throws std::invalid_argument "sliding 'NAME' = V is invalid: expected RANGE".
[[noreturn]] inline void bad(const char* name, double v, const char* range) {
  std::ostringstream s;
  s << "sliding '" << name << "' = " << v << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

/// Signed volume of the tetrahedron (a, b, c, d) [m³]; > 0 for positive orientation.
inline double tetVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                        const Eigen::Vector3d& d) {
  return (b - a).dot((c - a).cross(d - a)) / 6.0;
}

}  // namespace breast_sim::core::sliding_internal
