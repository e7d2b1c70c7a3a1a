#pragma once
// Shared by the pipeline's translation units (prone_to_supine.cpp, gravity_stage.cpp,
// sliding_stage.cpp, morphing_stage.cpp, coarse_start.cpp, pipeline_state.cpp); not installed.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::core::pipeline_detail {

/// A stage stops after this many stiffening calls in a row that could not advance (each already
/// tried max_reversals_per_step α increases): the state cannot go on without inverting elements.
inline constexpr int kMaxStuckCalls = 5;

/// Implicit sliding: a step is repeated at most this many times with the wall nodes that reversed
/// against their kinetic friction set sticking (WallSlip::stickReversed); a node set sticking cannot
/// reverse again, so the passes only catch nodes that reverse because others stopped.
inline constexpr int kMaxFrictionPasses = 3;

/// Tracking mode: the step matrix is assembled at every this-many-th frame and reused in between
/// (DynamicSimulator::setMatrixReuse; measured in docs/tracking.md, "Latency").
inline constexpr int kTrackingMatrixReuse = 10;

/// FNV-1a hash of a mesh (node coordinates and connectivity; the callers give a prone mesh), cut to
/// 52 bits so that a double holds it exactly (never 0): which mesh a saved state (its nodes must be
/// numbered the same way) or a kept embedding belongs to.
inline double meshFingerprint(const TetMesh& mesh) {
  std::uint64_t h = 1469598103934665603ULL;
  auto mix = [&](const void* data, size_t bytes) {
    const auto* c = static_cast<const unsigned char*>(data);
    for (size_t k = 0; k < bytes; ++k) h = (h ^ c[k]) * 1099511628211ULL;
  };
  mix(mesh.nodes().data(), sizeof(double) * static_cast<size_t>(mesh.nodes().size()));
  mix(mesh.tets().data(), sizeof(int) * static_cast<size_t>(mesh.tets().size()));
  return static_cast<double>(h & ((std::uint64_t{1} << 52) - 1)) + 1.0;  // never 0 (0: older files)
}

/// Wall time since t0 [s].
inline double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// Completion estimate: how far the increment came down from the first one towards the tolerance,
/// on a log scale.
inline double logFraction(double first, double now, double tolerance) {
  if (!(first > tolerance) || !(now > 0)) return now <= tolerance ? 1.0 : 0.0;
  return std::clamp(std::log(first / now) / std::log(first / tolerance), 0.0, 1.0);
}

}  // namespace breast_sim::core::pipeline_detail
