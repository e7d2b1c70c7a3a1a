#pragma once
/// @file node_checkpoint.h
/// Which checkpoint belongs to which case: the node checkpoints its state into ~state_folder after
/// each precomputation, after a loaded state and periodically while tracking, and on start resumes
/// from the newest checkpoint of the case it loaded (docs/ros.md, "Checkpoints and restart").
/// A checkpoint is a state file (pipeline/state_file.h) named after the case's fingerprint. Beside
/// it lie the multigrid's coarse levels of the case, so that a restarted node reads them instead of
/// meshing them (meshing them is most of the build of a 20k-element model).

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/ros_interface/confined_folder.h"

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

/// The file of coarse level `level` (1 = the finest coarse level) of `levels`: "multigrid-" + 16 hex
/// digits of the fingerprint + "-" + level + "of" + levels + ".msh", a Gmsh 2.2 binary file (its
/// doubles written and read back exactly, so that a restarted node solves to the same bits).
std::string multigridLevelName(std::uint64_t fingerprint, int level, int levels);

/// Writes the coarse levels (coarsest last) into `folder`, each atomically, replacing older files of
/// the same names. Nothing for an empty list.
/// @throws as ConfinedFolder::writeFile (a refused name, a failed system call, naming the file).
void writeMultigridLevels(const ConfinedFolder& folder, std::uint64_t fingerprint,
                          const std::vector<core::TetMesh>& levels);

/// The coarse levels of `fingerprint` in `folder` when it holds a complete set (levels 1 … n of the
/// same n, at most 16), coarsest last; nullopt when it holds none.
/// @throws std::runtime_error naming the file for an incomplete set or a file that does not read
///         (the caller then meshes the levels again).
std::optional<std::vector<core::TetMesh>> readMultigridLevels(const ConfinedFolder& folder, std::uint64_t fingerprint);

/// The file of the unloaded (gravity-free) rest shape X0 of a case (reference_state unloaded):
/// "unloaded-" + 16 hex digits of the fingerprint + ".msh", the model's mesh with X0's nodes as a
/// Gmsh 2.2 binary file (its doubles exact). A restarted node starts the recovery of X0 there and
/// confirms it in one loading.
std::string unloadedShapeName(std::uint64_t fingerprint);

/// Writes `mesh` (the model's elements at X0's nodes) into `folder` atomically, replacing an older
/// file of the same name.
/// @throws as ConfinedFolder::writeFile.
void writeUnloadedShape(const ConfinedFolder& folder, std::uint64_t fingerprint, const core::TetMesh& mesh);

/// X0's nodes (#N×3 [m]) kept for `fingerprint` in `folder`; nullopt when there are none.
/// @throws std::runtime_error naming the file when it does not read (the caller recovers X0 anew).
std::optional<core::Points> readUnloadedShape(const ConfinedFolder& folder, std::uint64_t fingerprint);

}  // namespace breast_sim::ros_interface
