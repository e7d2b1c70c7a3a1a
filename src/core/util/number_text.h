#pragma once
// A double as error messages give it (private to src/core): all 17 significant digits, so that a
// value a check refused is shown as it was (1e-07 stays 1e-07, not 0.000000).

#include <sstream>
#include <string>

namespace breast_sim::core::util {

inline std::string numberText(double v) {
  std::ostringstream s;
  s.precision(17);
  s << v;
  return s.str();
}

}  // namespace breast_sim::core::util
