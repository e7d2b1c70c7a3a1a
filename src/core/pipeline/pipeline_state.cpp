// Snapshots of the pipeline: state(), restore() and the binary state file (saveState, loadState).
#include <algorithm>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <stdexcept>
#include <string>

#include "breast_sim/core/pipeline/prone_to_supine.h"
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
  if (s.morphing_forces_n.rows() > 0 && !field_)
    throw std::invalid_argument("pipeline state has morphing forces, but no target surface is set");
  if (!s.gravity_load_mps2.allFinite())
    throw std::invalid_argument("pipeline state has a gravity load that is not finite (norm " +
                                std::to_string(s.gravity_load_mps2.norm()) + " m/s²)");
  simulator().restore(s.simulation);
  // Directly, not through setGravityLoad: the α controller's state below is the snapshot's, not a
  // restarted search.
  simulator().setGravity(s.gravity_load_mps2 + gravity_offset_mps2_);
  simulator().elements().setModulusFactors(s.modulus_factors);
  stiff_->controller().setState(s.alpha);
  stiff_->resync();  // the stress the next moduli come from is this state's
  if (slip_ && s.sliding_targets_m.rows() > 0) {
    slip_->setStickPoints(s.sliding_targets_m, s.sliding_slip_directions);
    slip_->attach(simulator());
    sliding_attached_ = true;
  }
  if (sliding_ && s.sliding_targets_m.rows() > 0) {
    attachSliding();
    sliding_->setTargets(simulator(), s.sliding_targets_m);
  }
  simulator().clearExternalForces();
  if (s.morphing_forces_n.rows() > 0) ensureMorphing().restoreForces(simulator(), s.morphing_forces_n);
  last_advanced_ = true;
  coarse_ahead_ = false;  // this state is the one to go on from
  stage_ = s.stage;
}

namespace {
constexpr char kMagic[8] = {'B', 'S', 'S', 'T', 'A', 'T', 'E', '1'};

void writeVector(std::ofstream& out, const double* data, std::int64_t n) {
  out.write(reinterpret_cast<const char*>(&n), sizeof n);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(n * sizeof(double)));
}

Eigen::VectorXd readVector(std::ifstream& in, const std::string& path) {
  std::int64_t n = 0;
  in.read(reinterpret_cast<char*>(&n), sizeof n);
  if (!in || n < 0 || n > (std::int64_t{1} << 34)) throw std::runtime_error(path + ": truncated or corrupt state file");
  Eigen::VectorXd v(n);
  in.read(reinterpret_cast<char*>(v.data()), static_cast<std::streamsize>(n * sizeof(double)));
  if (!in) throw std::runtime_error(path + ": truncated state file");
  return v;
}

Points toPoints(const Eigen::VectorXd& v) {
  Points p(v.size() / 3, 3);
  for (Eigen::Index i = 0; i < p.rows(); ++i) p.row(i) = v.segment<3>(3 * i).transpose();
  return p;
}

Eigen::VectorXd flatten(const Points& p) {
  Eigen::VectorXd v(3 * p.rows());
  for (Eigen::Index i = 0; i < p.rows(); ++i) v.segment<3>(3 * i) = p.row(i).transpose();
  return v;
}
}  // namespace

void ProneToSupinePipeline::saveState(const std::string& path) const {
  const PipelineState s = state();
  std::ofstream out(path, std::ios::binary);
  if (!out) throw std::runtime_error(path + ": cannot write the state file (check the folder exists and is writable)");
  out.write(kMagic, sizeof kMagic);
  const double header[10] = {static_cast<double>(model_.mesh.numNodes()), static_cast<double>(model_.mesh.numTets()),
                             s.simulation.time_s, static_cast<double>(s.simulation.step), s.alpha.alpha_per_pa,
                             static_cast<double>(s.alpha.phase == AlphaController::Phase::kSettling), s.alpha.rate,
                             static_cast<double>(s.alpha.oscillations), static_cast<double>(s.stage),
                             meshFingerprint(prone_model_.mesh)};
  writeVector(out, header, 10);
  const double runs[3] = {static_cast<double>(s.alpha.runs[0]), static_cast<double>(s.alpha.runs[1]), static_cast<double>(s.alpha.runs[2])};
  writeVector(out, runs, 3);
  writeVector(out, s.simulation.displacement_m.data(), s.simulation.displacement_m.size());
  writeVector(out, s.simulation.velocity_mps.data(), s.simulation.velocity_mps.size());
  writeVector(out, s.modulus_factors.data(), s.modulus_factors.size());
  const Eigen::VectorXd st = flatten(s.sliding_targets_m), mf = flatten(s.morphing_forces_n);
  writeVector(out, st.data(), st.size());
  writeVector(out, mf.data(), mf.size());
  // Appended after the first format (a file without it loads with every wall node sticking).
  const Eigen::VectorXd sd = flatten(s.sliding_slip_directions);
  writeVector(out, sd.data(), sd.size());
  // Appended after the second (a file without it loads under the supine gravity load).
  writeVector(out, s.gravity_load_mps2.data(), 3);
  // ... and after the third: the rest shape (a file without it is of the prone shape as rest shape).
  const Eigen::VectorXd rest = flatten(model_.mesh.nodes());
  writeVector(out, rest.data(), rest.size());
  if (!out) throw std::runtime_error(path + ": writing the state file failed (disk full?)");
}

void ProneToSupinePipeline::loadState(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot open the state file");
  char magic[8];
  in.read(magic, sizeof magic);
  if (!in || std::memcmp(magic, kMagic, sizeof kMagic) != 0)
    throw std::runtime_error(path + ": not a breast_sim state file (written by saveState / the node's save_state)");
  const Eigen::VectorXd h = readVector(in, path);
  const Eigen::VectorXd runs = readVector(in, path);
  if (h.size() != 10 || runs.size() != 3) throw std::runtime_error(path + ": corrupt state file header");
  if (static_cast<int>(h[0]) != model_.mesh.numNodes() || static_cast<int>(h[1]) != model_.mesh.numTets())
    throw std::runtime_error(path + ": the state is of a model with " + std::to_string(static_cast<long>(h[0])) + " nodes and " +
                             std::to_string(static_cast<long>(h[1])) + " elements; this model has " +
                             std::to_string(model_.mesh.numNodes()) + " and " + std::to_string(model_.mesh.numTets()) +
                             " (load the same case with the same meshing first)");
  if (h[9] != meshFingerprint(prone_model_.mesh))
    throw std::runtime_error(path + (h[9] == 0.0 ? ": the state file was written by an older breast_sim, whose mesh "
                                                    "nodes were numbered differently; precompute the state again"
                                                  : ": the state is of a mesh with the same size but other nodes (another "
                                                    "case, meshing option or breast_sim version); load the case it was "
                                                    "saved with, or precompute again"));
  PipelineState s;
  s.simulation.time_s = h[2];
  s.simulation.step = static_cast<long>(h[3]);
  s.alpha.alpha_per_pa = h[4];
  s.alpha.phase = h[5] != 0.0 ? AlphaController::Phase::kSettling : AlphaController::Phase::kSearch;
  s.alpha.rate = h[6];
  s.alpha.oscillations = static_cast<int>(h[7]);
  s.stage = static_cast<PipelineStage>(std::clamp(static_cast<int>(h[8]), 0, static_cast<int>(PipelineStage::kDone)));
  for (int k = 0; k < 3; ++k) s.alpha.runs[k] = static_cast<int>(runs[k]);
  s.simulation.displacement_m = readVector(in, path);
  s.simulation.velocity_mps = readVector(in, path);
  s.modulus_factors = readVector(in, path);
  s.sliding_targets_m = toPoints(readVector(in, path));
  s.morphing_forces_n = toPoints(readVector(in, path));
  if (in.peek() != std::char_traits<char>::eof()) s.sliding_slip_directions = toPoints(readVector(in, path));
  s.gravity_load_mps2 = supineGravityLoad();
  if (in.peek() != std::char_traits<char>::eof()) {
    const Eigen::VectorXd g = readVector(in, path);
    if (g.size() != 3) throw std::runtime_error(path + ": corrupt state file (a gravity load of " + std::to_string(g.size()) + " values)");
    s.gravity_load_mps2 = g;
  }
  // The rest shape: the same within the recovery's tolerance (a recovery is repeatable to far less).
  const Points& own_rest = model_.mesh.nodes();
  Points rest = prone_model_.mesh.nodes();
  if (in.peek() != std::char_traits<char>::eof()) {
    const Eigen::VectorXd r = readVector(in, path);
    if (r.size() != 3 * own_rest.rows())
      throw std::runtime_error(path + ": corrupt state file (a rest shape of " + std::to_string(r.size()) + " values)");
    rest = toPoints(r);
  }
  const double rest_gap_m = (rest - own_rest).rowwise().norm().maxCoeff();
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
