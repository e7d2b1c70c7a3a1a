#pragma once
/// @file node_checkpoint.h
/// Which checkpoint belongs to which case: the node checkpoints its state into ~state_folder after
/// each precomputation, after a loaded state and periodically while tracking, and on start resumes
/// from the newest checkpoint of the case it loaded (docs/ros.md, "Checkpoints and restart").
/// A checkpoint is a state file (pipeline/state_file.h) named after the case's fingerprint.

#include <cstdint>
#include <string>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::ros_interface {

/// The fingerprint a checkpoint must match: 64-bit FNV-1a over the prone mesh's node coordinates
/// (#N×3 doubles [m]) and element indices (#T×4, as the pipeline numbers them) and the case's
/// effective settings (core::effectiveCaseYaml: tissue source, lesions, meshing, material,
/// simulation, sliding, morphing, ...). The same bits on every machine; a different mesh (another
/// meshing, a moved node), material or setting gives another fingerprint. Never 0.
std::uint64_t caseFingerprint(const core::TetMesh& mesh, const std::string& effective_settings);

/// The checkpoint file name of a fingerprint: "checkpoint-" + 16 lower-case hex digits + ".state".
std::string checkpointName(std::uint64_t fingerprint);
/// The parts around the fingerprint, to list a folder's checkpoints of one case.
std::string checkpointPrefix(std::uint64_t fingerprint);
inline constexpr const char* kCheckpointSuffix = ".state";

}  // namespace breast_sim::ros_interface
