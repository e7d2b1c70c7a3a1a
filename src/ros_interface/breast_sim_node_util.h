#pragma once
/// @file breast_sim_node_util.h
/// Clock and formatting functions shared by the files that implement BreastSimNode (private to the ROS layer).

#include <chrono>
#include <sstream>
#include <string>

namespace breast_sim::ros_interface::node_util {

using Clock = std::chrono::steady_clock;

/// A duration in seconds.
inline double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

/// A length given in [m] as text in millimetres ("1.23 mm").
inline std::string mm(double m, int precision = 2) {
  std::ostringstream s;
  s.setf(std::ios::fixed);
  s.precision(precision);
  s << 1e3 * m << " mm";
  return s.str();
}

}  // namespace breast_sim::ros_interface::node_util
