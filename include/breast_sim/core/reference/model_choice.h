#pragma once
/// @file model_choice.h
/// "Model no more than a scene needs": from a measured error curve (error against element count for
/// one method, bench_speed_accuracy's sweep against the CalculiX reference) and an accuracy target,
/// the coarsest mesh size that meets the target, with the error and time measured there.
///
/// Only measured points are used (no extrapolation): the choice is the smallest element count n such
/// that the point at n and every measured point finer than n meet the target, so a coarse point
/// that meets it by chance while a finer one does not is not chosen. When no point meets the target
/// the finest is returned with met = false.

#include <string>
#include <vector>

namespace breast_sim::core {

/// One measured point of an error curve.
struct ErrorCurvePoint {
  int target_elements = 0;  ///< the meshing target that produced it (MeshingOptions::target_elements)
  int elements = 0;         ///< tetrahedra the mesh had
  double error_mm = 0.0;    ///< the error measure chosen (e.g. lesion error, mean nodal error) [mm]
  double seconds = 0.0;     ///< compute time to the settled state [s]
};

/// Which error measure of a sweep row a curve uses.
enum class ErrorMeasure { kMeanNodal, kP95Nodal, kMaxNodal, kLesionMax, kSurfaceMean };

/// "mean", "p95", "max", "lesion", "surface". @throws std::invalid_argument naming the choices.
ErrorMeasure errorMeasureFromName(const std::string& name);
std::string errorMeasureName(ErrorMeasure m);

/// The choice.
struct ModelChoice {
  bool met = false;           ///< a measured point meets the target
  int target_elements = 0;    ///< what to put in MeshingOptions::target_elements
  int elements = 0;           ///< elements of the measured mesh
  double expected_error_mm = 0.0;  ///< measured error there [mm]
  double expected_seconds = 0.0;   ///< measured time there [s]
  std::string explanation;    ///< one sentence for a log or a summary
};

/// The coarsest measured point that meets max_error_mm (see the file comment).
/// @throws std::invalid_argument for an empty curve, a non-positive or non-finite target, or a point
///         with a negative or non-finite error.
ModelChoice chooseCoarsestModel(std::vector<ErrorCurvePoint> curve, double max_error_mm);

/// Reads an error curve from bench_speed_accuracy's JSON (`--json FILE`): the rows of `method`
/// (e.g. "corotated+stiffening/multigrid") with the chosen measure.
/// @throws std::runtime_error naming the file and the methods it has when it cannot be read or has
///         no row of that method.
std::vector<ErrorCurvePoint> loadErrorCurve(const std::string& json_path, const std::string& method,
                                            ErrorMeasure measure);

}  // namespace breast_sim::core
