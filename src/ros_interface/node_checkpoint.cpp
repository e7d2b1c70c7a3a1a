// Case fingerprints, checkpoint names and the multigrid level files beside them (node_checkpoint.h).
#include "breast_sim/ros_interface/node_checkpoint.h"

#include <cstdio>
#include <stdexcept>

#include "breast_sim/core/mesh/mesh_io.h"

namespace breast_sim::ros_interface {

namespace {

constexpr int kMaxMultigridLevels = 16;

std::string hex16(std::uint64_t fingerprint) {
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(fingerprint));
  return hex;
}

std::uint64_t fnv1a(const void* data, std::size_t bytes, std::uint64_t h) {
  const auto* c = static_cast<const unsigned char*>(data);
  for (std::size_t k = 0; k < bytes; ++k) h = (h ^ c[k]) * 1099511628211ULL;
  return h;
}

// `mesh` as a Gmsh 2.2 binary file (its doubles exact) named `name` in `folder`, atomically.
void writeExactMesh(const ConfinedFolder& folder, const std::string& name, const core::TetMesh& mesh) {
  core::GmshOptions binary;
  binary.binary = true;
  folder.writeFile(name, true, [&](const std::string& temp) { core::writeGmsh(temp, mesh, binary); });
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

std::string checkpointPrefix(std::uint64_t fingerprint) { return "checkpoint-" + hex16(fingerprint); }

std::string checkpointName(std::uint64_t fingerprint) { return checkpointPrefix(fingerprint) + kCheckpointSuffix; }

std::string multigridLevelName(std::uint64_t fingerprint, int level, int levels) {
  return "multigrid-" + hex16(fingerprint) + "-" + std::to_string(level) + "of" + std::to_string(levels) + ".msh";
}

void writeMultigridLevels(const ConfinedFolder& folder, std::uint64_t fingerprint,
                          const std::vector<core::TetMesh>& levels) {
  const int n = static_cast<int>(levels.size());
  for (int l = 0; l < n; ++l) writeExactMesh(folder, multigridLevelName(fingerprint, l + 1, n), levels[static_cast<size_t>(l)]);
}

std::string unloadedShapeName(std::uint64_t fingerprint) { return "unloaded-" + hex16(fingerprint) + ".msh"; }

void writeUnloadedShape(const ConfinedFolder& folder, std::uint64_t fingerprint, const core::TetMesh& mesh) {
  writeExactMesh(folder, unloadedShapeName(fingerprint), mesh);
}

std::optional<core::Points> readUnloadedShape(const ConfinedFolder& folder, std::uint64_t fingerprint) {
  const std::string name = unloadedShapeName(fingerprint);
  if (folder.newestFirst(name.substr(0, name.size() - 4), ".msh").empty()) return std::nullopt;
  std::string path;
  try {
    path = folder.existingFile(name);
    return core::readGmsh(path).nodes();
  } catch (const std::exception& e) {
    throw std::runtime_error("the unloaded shape kept in " + (path.empty() ? name : path) + " does not read: " + e.what());
  }
}

std::optional<std::vector<core::TetMesh>> readMultigridLevels(const ConfinedFolder& folder, std::uint64_t fingerprint) {
  const std::string prefix = "multigrid-" + hex16(fingerprint) + "-";
  const std::vector<std::string> files = folder.newestFirst(prefix, ".msh");
  if (files.empty()) return std::nullopt;
  // The level count of the newest file; every level of that count must be there.
  const std::string newest = files.front().substr(files.front().find_last_of('/') + 1);
  int level = 0, levels = 0;
  char end = 0;
  if (std::sscanf(newest.c_str() + prefix.size(), "%dof%d.ms%c", &level, &levels, &end) != 3 || end != 'h' ||
      levels < 1 || levels > kMaxMultigridLevels || level < 1 || level > levels || newest != multigridLevelName(fingerprint, level, levels))
    throw std::runtime_error("multigrid level file " + files.front() + " is not named '" + prefix +
                             "<level>of<levels>.msh' with 1 <= level <= levels <= " + std::to_string(kMaxMultigridLevels));
  std::vector<core::TetMesh> out;
  for (int l = 1; l <= levels; ++l) {
    std::string path;
    try {
      path = folder.existingFile(multigridLevelName(fingerprint, l, levels));
    } catch (const ConfinementError& e) {
      throw std::runtime_error("the multigrid levels of " + files.front() + " are incomplete: " + e.what());
    }
    try {
      out.push_back(core::readGmsh(path));
    } catch (const std::exception& e) {
      throw std::runtime_error("multigrid level file " + path + " does not read: " + e.what());
    }
  }
  return out;
}

}  // namespace breast_sim::ros_interface
