// Snapshots of the pipeline: state(), restore() and the binary state file (saveState, loadState).
#include <algorithm>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/pipeline/state_file.h"
#include "../util/number_text.h"
#include "pipeline_internal.h"

namespace breast_sim::core {

using pipeline_detail::meshFingerprint;

PipelineState ProneToSupinePipeline::state() const {
  PipelineState s;
  fillState(s);
  return s;
}

void ProneToSupinePipeline::fillState(PipelineState& s) const {
  // Assignments into s's vectors reuse their storage when the sizes match.
  s.simulation = simulator().state();
  s.modulus_factors = simulator().elements().modulusFactors();
  s.alpha = stiff_->controller().state();
  s.element_alpha_per_pa = stiff_->elementAlpha();
  if (sliding_) s.sliding_targets_m = sliding_->targets();
  if (slip_ && sliding_attached_) {
    s.sliding_targets_m = slip_->stickPoints();  // positions, not displacements
    s.sliding_slip_directions = slip_->slipDirections();
  }
  if (!sliding_ && !(slip_ && sliding_attached_)) {
    s.sliding_targets_m.resize(0, 3);
    s.sliding_slip_directions.resize(0, 3);
  }
  if (morphing_forces_) s.morphing_forces_n = morphing_forces_->accumulatedForces();
  else s.morphing_forces_n.resize(0, 3);
  s.stage = stage_;
  s.gravity_load_mps2 = gravityLoad();
}

void ProneToSupinePipeline::restore(const PipelineState& s) {
  const Eigen::Index n3 = 3 * static_cast<Eigen::Index>(model_.mesh.numNodes());
  if (s.simulation.displacement_m.size() != n3 || s.simulation.velocity_mps.size() != n3 ||
      s.modulus_factors.size() != model_.mesh.numTets())
    throw std::invalid_argument("pipeline state of another model: " + std::to_string(s.simulation.displacement_m.size() / 3) +
                                " nodes and " + std::to_string(s.modulus_factors.size()) + " elements, this model has " +
                                std::to_string(model_.mesh.numNodes()) + " and " + std::to_string(model_.mesh.numTets()));
  const size_t sliding_nodes = slip_ ? slip_->nodes().size() : sliding_ ? sliding_->nodes().size() : 0;
  if (s.sliding_targets_m.rows() > 0 && (!hasSliding() || s.sliding_targets_m.rows() != static_cast<Eigen::Index>(sliding_nodes)))
    throw std::invalid_argument("pipeline state has sliding targets for " + std::to_string(s.sliding_targets_m.rows()) +
                                " nodes, but sliding is " + (hasSliding() ? "on for " + std::to_string(sliding_nodes) + " nodes" : "off"));
  if (slip_ && s.sliding_targets_m.rows() > 0 && s.sliding_slip_directions.rows() != 0 &&
      s.sliding_slip_directions.rows() != s.sliding_targets_m.rows())
    throw std::invalid_argument("pipeline state has " + std::to_string(s.sliding_slip_directions.rows()) +
                                " slip directions for " + std::to_string(s.sliding_targets_m.rows()) + " sliding targets");
  // The morphing forces pull the skin nodes that are free once the state's wall is attached: with no
  // force generator yet, one is made here for those nodes (implicit sliding frees every node,
  // explicit sliding adds the wall's moving constraints) and kept only if the whole state applies.
  std::unique_ptr<SurfaceMorphing> made;
  if (s.morphing_forces_n.rows() > 0) {
    if (!field_) throw std::invalid_argument("pipeline state has morphing forces, but no target surface is set");
    if (!morphing_forces_) {
      std::vector<char> fixed;
      simulator().constrainedNodes(fixed);
      if (slip_ && s.sliding_targets_m.rows() > 0) std::fill(fixed.begin(), fixed.end(), 0);
      if (sliding_ && s.sliding_targets_m.rows() > 0)
        for (const int v : sliding_->nodes()) fixed[static_cast<size_t>(v)] = 1;
      made = makeMorphing(fixed);
    }
    const size_t pulled = (made ? made : morphing_forces_)->vertices().size();
    if (s.morphing_forces_n.rows() != static_cast<Eigen::Index>(pulled))
      throw std::invalid_argument("pipeline state has morphing forces for " + std::to_string(s.morphing_forces_n.rows()) +
                                  " skin vertices, this model pulls " + std::to_string(pulled));
    if (!s.morphing_forces_n.allFinite())
      throw std::invalid_argument("pipeline state has morphing forces that are not finite; they are forces [N] on the "
                                  "pulled skin vertices");
  }
  // The values the model takes over: checked before anything changes (a refused restore keeps the
  // state).
  for (Eigen::Index e = 0; e < s.modulus_factors.size(); ++e)
    if (!(s.modulus_factors[e] > 0.0) || !std::isfinite(s.modulus_factors[e]))
      throw std::invalid_argument("pipeline state has the modulus factor " + util::numberText(s.modulus_factors[e]) +
                                  " at element " + std::to_string(e) + "; modulus factors are finite and > 0");
  if (!s.gravity_load_mps2.allFinite())
    throw std::invalid_argument("pipeline state has a gravity load that is not finite (norm " +
                                util::numberText(s.gravity_load_mps2.norm()) + " m/s²)");
  // Positions and the wall's points enter the springs and constraints set below, which refuse
  // values that are not finite: refused here, before anything changed.
  const std::pair<const char*, bool> finite[] = {
      {"displacements that are not finite", s.simulation.displacement_m.allFinite()},
      {"velocities that are not finite", s.simulation.velocity_mps.allFinite()},
      {"sliding targets that are not finite", s.sliding_targets_m.allFinite()},
      {"slip directions that are not finite", s.sliding_slip_directions.allFinite()},
      {"an alpha that is not finite and positive",
       std::isfinite(s.alpha.alpha_per_pa) && s.alpha.alpha_per_pa > 0.0 && std::isfinite(s.alpha.rate)}};
  for (const auto& [what, ok] : finite)
    if (!ok) throw std::invalid_argument(std::string("pipeline state has ") + what);
  // The first change: restoreSnapshot checks the local α's before it applies anything; resync()
  // inside gives the stress the next moduli come from at this state.
  try {
    stiff_->restoreSnapshot(s.simulation, s.modulus_factors, s.alpha, s.element_alpha_per_pa);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("pipeline state has ") + e.what());
  }
  // Directly, not through setGravityLoad: the α controller's state is the snapshot's, not a
  // restarted search.
  simulator().setGravity(s.gravity_load_mps2 + gravity_offset_mps2_);
  if (slip_ && s.sliding_targets_m.rows() > 0) {
    slip_->setStickPoints(s.sliding_targets_m, s.sliding_slip_directions);
    slip_->attach(simulator());
    sliding_attached_ = true;
  }
  if (sliding_ && s.sliding_targets_m.rows() > 0) {
    sliding_->attach(simulator());  // not attachSliding(): the α controller's state is the snapshot's
    sliding_attached_ = true;
    sliding_->setTargets(simulator(), s.sliding_targets_m);
  }
  simulator().clearExternalForces();
  if (made) morphing_forces_ = std::move(made);
  if (s.morphing_forces_n.rows() > 0) morphing_forces_->restoreForces(simulator(), s.morphing_forces_n);
  // A state from before the morphing: no forces accumulated, as when the generator did not exist yet
  // (it is made again, for the nodes then free, at the next morphing step).
  else morphing_forces_.reset();
  last_advanced_ = true;
  coarse_ahead_ = false;  // this state is the one to go on from
  stage_ = s.stage;
}

void ProneToSupinePipeline::saveState(const std::string& path) const {
  StateFile f;
  f.nodes = model_.mesh.numNodes();
  f.tets = model_.mesh.numTets();
  f.mesh_fingerprint = meshFingerprint(prone_model_.mesh);
  f.state = state();
  f.has_gravity_load = true;
  f.has_rest_shape = true;
  f.rest_m = model_.mesh.nodes();
  writeStateFile(path, f);
}

void ProneToSupinePipeline::loadState(const std::string& path) {
  // The whole file is read and checked first; the model is touched only by restore() at the end.
  StateFile f = readStateFile(path);
  if (f.nodes != model_.mesh.numNodes() || f.tets != model_.mesh.numTets())
    throw std::runtime_error(path + ": the state is of a model with " + std::to_string(f.nodes) + " nodes and " +
                             std::to_string(f.tets) + " elements; this model has " +
                             std::to_string(model_.mesh.numNodes()) + " and " + std::to_string(model_.mesh.numTets()) +
                             " (load the same case with the same meshing first)");
  if (f.mesh_fingerprint != meshFingerprint(prone_model_.mesh))
    throw std::runtime_error(path + (f.mesh_fingerprint == 0.0
                                         ? ": the state file was written by an older breast_sim, whose mesh "
                                           "nodes were numbered differently; precompute the state again"
                                         : ": the state is of a mesh with the same size but other nodes (another "
                                           "case, meshing option or breast_sim version); load the case it was "
                                           "saved with, or precompute again"));
  PipelineState& s = f.state;
  if (!f.has_gravity_load) s.gravity_load_mps2 = supineGravityLoad();
  // The rest shape: the same within the recovery's tolerance (a recovery is repeatable to far less).
  const Points& own_rest = model_.mesh.nodes();
  const Points rest = f.has_rest_shape ? f.rest_m : prone_model_.mesh.nodes();
  const double rest_gap_m = own_rest.rows() == 0 ? 0.0 : (rest - own_rest).rowwise().norm().maxCoeff();
  if (!(rest_gap_m <= UnloadedStateOptions{}.tolerance_m)) {
    const bool file_prone = (rest - prone_model_.mesh.nodes()).rowwise().norm().maxCoeff() == 0.0;
    throw std::runtime_error(path + ": the state was computed from another rest shape (" +
                             (file_prone ? std::string("the prone shape, simulation.reference_state: prone")
                                         : std::string("an unloaded shape ") + std::to_string(1e3 * rest_gap_m) +
                                               " mm from this model's")  +
                             "); load it with the case and settings it was saved with, or precompute again");
  }
  try {
    restore(s);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
}

}  // namespace breast_sim::core
