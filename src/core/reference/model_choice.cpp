// The coarsest model that meets an accuracy target (reference/model_choice.h).

#include "breast_sim/core/reference/model_choice.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <set>
#include <stdexcept>

#include <nlohmann/json.hpp>

namespace breast_sim::core {

ErrorMeasure errorMeasureFromName(const std::string& name) {
  if (name == "mean") return ErrorMeasure::kMeanNodal;
  if (name == "p95") return ErrorMeasure::kP95Nodal;
  if (name == "max") return ErrorMeasure::kMaxNodal;
  if (name == "lesion") return ErrorMeasure::kLesionMax;
  if (name == "surface") return ErrorMeasure::kSurfaceMean;
  throw std::invalid_argument("error measure '" + name + "': expected mean, p95, max, lesion or surface");
}

std::string errorMeasureName(ErrorMeasure m) {
  switch (m) {
    case ErrorMeasure::kMeanNodal: return "mean";
    case ErrorMeasure::kP95Nodal: return "p95";
    case ErrorMeasure::kMaxNodal: return "max";
    case ErrorMeasure::kLesionMax: return "lesion";
    case ErrorMeasure::kSurfaceMean: return "surface";
  }
  return "mean";
}

ModelChoice chooseCoarsestModel(std::vector<ErrorCurvePoint> curve, double max_error_mm) {
  if (curve.empty()) throw std::invalid_argument("chooseCoarsestModel: the error curve is empty (run the sweep first)");
  if (!(max_error_mm > 0 && std::isfinite(max_error_mm)))
    throw std::invalid_argument("chooseCoarsestModel: target " + std::to_string(max_error_mm) +
                                " mm: expected a positive error bound in mm");
  for (const auto& p : curve)
    if (!(p.error_mm >= 0 && std::isfinite(p.error_mm)))
      throw std::invalid_argument("chooseCoarsestModel: the point at " + std::to_string(p.elements) +
                                  " elements has error " + std::to_string(p.error_mm) + " mm (expected ≥ 0, finite)");
  std::sort(curve.begin(), curve.end(), [](const auto& a, const auto& b) { return a.elements < b.elements; });
  // From the finest down: the run of points that all meet the target.
  int chosen = -1;
  for (int i = static_cast<int>(curve.size()) - 1; i >= 0 && curve[i].error_mm <= max_error_mm; --i) chosen = i;
  ModelChoice c;
  const ErrorCurvePoint& p = curve[chosen >= 0 ? chosen : curve.size() - 1];
  c.met = chosen >= 0;
  c.target_elements = p.target_elements;
  c.elements = p.elements;
  c.expected_error_mm = p.error_mm;
  c.expected_seconds = p.seconds;
  char buf[256];
  if (c.met)
    std::snprintf(buf, sizeof buf, "target_elements %d (%d elements): measured error %.2f mm <= %.2f mm in %.2f s",
                  c.target_elements, c.elements, c.expected_error_mm, max_error_mm, c.expected_seconds);
  else
    std::snprintf(buf, sizeof buf,
                  "no measured model meets %.2f mm; the finest, target_elements %d (%d elements), has %.2f mm in %.2f s",
                  max_error_mm, c.target_elements, c.elements, c.expected_error_mm, c.expected_seconds);
  c.explanation = buf;
  return c;
}

std::vector<ErrorCurvePoint> loadErrorCurve(const std::string& json_path, const std::string& method,
                                            ErrorMeasure measure) {
  std::ifstream f(json_path);
  if (!f) throw std::runtime_error("cannot read the error curve " + json_path);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(f);
  } catch (const std::exception& e) {
    throw std::runtime_error(json_path + ": " + e.what());
  }
  if (!j.contains("sweep") || !j["sweep"].contains("rows"))
    throw std::runtime_error(json_path + ": no sweep.rows (write it with bench_speed_accuracy --json)");
  static const char* kKey[] = {"error_mean_mm", "error_p95_mm", "error_max_mm", "lesion_error_max_mm", "surface_distance_mean_mm"};
  std::vector<ErrorCurvePoint> out;
  std::set<std::string> methods;
  for (const auto& r : j["sweep"]["rows"]) {
    const std::string m = r.value("method", "");
    methods.insert(m);
    if (m != method) continue;
    ErrorCurvePoint p;
    p.target_elements = r.value("target_elements", 0);
    p.elements = r.value("elements", 0);
    p.error_mm = r.value(kKey[static_cast<int>(measure)], -1.0);
    p.seconds = r.value("settle_seconds", 0.0);
    out.push_back(p);
  }
  if (out.empty()) {
    std::string have;
    for (const auto& m : methods) have += (have.empty() ? "" : ", ") + m;
    throw std::runtime_error(json_path + ": no sweep row of method '" + method + "' (it has: " + have + ")");
  }
  return out;
}

}  // namespace breast_sim::core
