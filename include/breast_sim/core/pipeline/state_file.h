#pragma once
/// @file state_file.h
/// The binary state file behind ProneToSupinePipeline::saveState / loadState, read and written
/// without a pipeline: the reader checks a whole file (every count against the bytes present, every
/// value finite and in range) before anything of it reaches a model, and it can be tested and
/// fuzzed on its own.
///
/// Layout (host byte order: little-endian on every machine breast_sim builds for): the 8 bytes
/// "BSSTATE1", then sections, each an int64 count n followed by n float64 values:
///   1. header (10): nodes, tets, simulated time [s], step, α [1/Pa], phase (0 search, 1 settling),
///      settling rate, oscillations, stage (PipelineStage), mesh fingerprint
///   2. runs (3): the α controller's last three runs, each −1, 0 or +1
///   3. displacement (3·nodes) [m]     4. velocity (3·nodes) [m/s]     5. modulus factors (tets)
///   6. sliding targets (3·k) [m]      7. morphing forces (3·m) [N]
/// and, each optional in this order (files of earlier versions end before them):
///   8. slip directions (0 or 3·k)     9. gravity load (3) [m/s²]      10. rest shape (3·nodes) [m]
///  11. local α's (0 or tets) [1/Pa]

#include <string>

#include "breast_sim/core/pipeline/prone_to_supine.h"

namespace breast_sim::core {

/// What a state file holds.
struct StateFile {
  int nodes = 0;                  ///< of the model the state belongs to
  int tets = 0;
  double mesh_fingerprint = 0.0;  ///< of the prone mesh; 0 in files of versions before it
  PipelineState state;            ///< gravity_load_mps2 is meaningful only when has_gravity_load
  bool has_gravity_load = false;
  bool has_rest_shape = false;
  Points rest_m;                  ///< #nodes×3 when has_rest_shape, else empty
};

/// Reads and checks a state file. Checked before anything is allocated: each section's count
/// against the bytes left in the file. Checked after: the header's counts are whole numbers in
/// [0, 2^31), the section sizes match them (3·nodes, tets, multiples of 3, slip directions as many
/// as sliding targets or none, local α's as many as tets or none), every value is finite, modulus
/// factors are > 0, local α's ≥ 0, the phase, stage and runs are valid codes, and nothing follows
/// the last section.
/// @throws std::runtime_error whose message starts with the path and names the section and value.
StateFile readStateFile(const std::string& path);

/// Writes a state file (all eleven sections; has_gravity_load and has_rest_shape must be set) through
/// a temporary file in the same folder, flushed (fsync), renamed over `path` once complete and the
/// folder flushed, so that a failed write or a crash never leaves half a state.
/// @throws std::invalid_argument when sizes do not match nodes and tets, or for a local α that is
///         negative or not finite (the reader would refuse the file);
///         std::runtime_error naming the file when it cannot be written.
void writeStateFile(const std::string& path, const StateFile& file);

}  // namespace breast_sim::core
