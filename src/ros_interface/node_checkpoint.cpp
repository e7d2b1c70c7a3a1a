// Case fingerprints and checkpoint names (node_checkpoint.h).
#include "breast_sim/ros_interface/node_checkpoint.h"

#include <cstdio>

namespace breast_sim::ros_interface {

namespace {

std::uint64_t fnv1a(const void* data, std::size_t bytes, std::uint64_t h) {
  const auto* c = static_cast<const unsigned char*>(data);
  for (std::size_t k = 0; k < bytes; ++k) h = (h ^ c[k]) * 1099511628211ULL;
  return h;
}

}  // namespace

std::uint64_t caseFingerprint(const core::TetMesh& mesh, const std::string& effective_settings) {
  std::uint64_t h = 14695981039346656037ULL;
  // Sizes first: a mesh cannot pass for another whose arrays concatenate to the same bytes.
  const std::int64_t sizes[3] = {mesh.numNodes(), mesh.numTets(), static_cast<std::int64_t>(effective_settings.size())};
  h = fnv1a(sizes, sizeof sizes, h);
  h = fnv1a(mesh.nodes().data(), sizeof(double) * static_cast<std::size_t>(mesh.nodes().size()), h);
  h = fnv1a(mesh.tets().data(), sizeof(int) * static_cast<std::size_t>(mesh.tets().size()), h);
  h = fnv1a(effective_settings.data(), effective_settings.size(), h);
  return h == 0 ? 1 : h;
}

std::string checkpointPrefix(std::uint64_t fingerprint) {
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(fingerprint));
  return std::string("checkpoint-") + hex;
}

std::string checkpointName(std::uint64_t fingerprint) { return checkpointPrefix(fingerprint) + kCheckpointSuffix; }

}  // namespace breast_sim::ros_interface
