// Load cases of the speed–accuracy study (reference/reference_case.h).

#include "breast_sim/core/reference/reference_case.h"

#include <stdexcept>

#include "breast_sim/core/model/phantom.h"

namespace breast_sim::core {

std::string gravityLoadCaseName(GravityLoadCase c) { return c == GravityLoadCase::kProneHanging ? "hanging" : "supine"; }

GravityLoadCase gravityLoadCaseFromName(const std::string& name) {
  if (name == "supine") return GravityLoadCase::kProneToSupine;
  if (name == "hanging") return GravityLoadCase::kProneHanging;
  throw std::invalid_argument("gravity load '" + name + "': expected supine (g_supine - g_prone) or hanging (g_prone)");
}

Eigen::Vector3d gravityLoad(const ModelCase& c, GravityLoadCase which, double g) {
  if (!(g > 0)) throw std::invalid_argument("gravityLoad: magnitude " + std::to_string(g) + " m/s^2: expected > 0");
  if (!(c.prone_gravity_direction.norm() > 0))
    throw std::invalid_argument("gravityLoad: case '" + c.name + "' has a zero prone_gravity_direction");
  const Eigen::Vector3d prone = g * c.prone_gravity_direction.normalized();
  if (which == GravityLoadCase::kProneHanging) return prone;
  const Eigen::Vector3d supine = c.phantom ? Eigen::Vector3d(c.phantom->gravity_supine_mps2) : Eigen::Vector3d(-prone);
  return supine - prone;
}

CalculixLoadCase referenceLoadCase(const SimulationSettings& s, const Eigen::Vector3d& g, ReferenceElement element) {
  CalculixLoadCase l;
  l.material = s.material;
  l.gravity_mps2 = g;
  l.fixed_node_set = s.fixed_node_set;
  l.element = element;
  return l;
}

}  // namespace breast_sim::core
