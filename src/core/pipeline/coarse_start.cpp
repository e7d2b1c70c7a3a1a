// Nested iteration: a pipeline on a coarser mesh of the same case hands its state to this model
// (startFrom; runGravity and runMorphing call it with coarse_start).
#include <algorithm>
#include <cstddef>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "pipeline_internal.h"

namespace breast_sim::core {

using pipeline_detail::meshFingerprint;

void ProneToSupinePipeline::startFrom(const ProneToSupinePipeline& coarse, double snap_tolerance_m) {
  if (static_cast<bool>(slip_) != static_cast<bool>(coarse.slip_) || static_cast<bool>(sliding_) != static_cast<bool>(coarse.sliding_))
    throw std::invalid_argument(std::string("startFrom: sliding differs (coarse: ") +
                                (coarse.slip_ ? "implicit" : coarse.sliding_ ? "explicit" : "off") + ", this model: " +
                                (slip_ ? "implicit" : sliding_ ? "explicit" : "off") + "); use the same settings for both");
  if (static_cast<bool>(unloaded_model_) != static_cast<bool>(coarse.unloaded_model_))
    throw std::invalid_argument(std::string("startFrom: the reference states differ (coarse: ") +
                                (coarse.unloaded_model_ ? "unloaded" : "prone") + ", this model: " +
                                (unloaded_model_ ? "unloaded" : "prone") + "); use the same settings for both");
  if (coarse.morphing_forces_ && !field_)
    throw std::invalid_argument("startFrom: the coarse run has morphing forces, but this model has no target surface (setTarget first)");
  // The two models meet in the prone domain, the shape both mesh: a material point is where the
  // MRI shows it. With reference_state unloaded each rest shape is its own model's X0, and the
  // coarser model sags less (on the phantom X0 lies 2.3 mm mean from prone at 4.8k elements, 3.1 mm
  // at 48.8k), so the two X0 are not one shape. With the prone reference the prone meshes are the
  // rest meshes.
  const TetMesh& cm = coarse.prone_model_.mesh;
  const Points& prone = prone_model_.mesh.nodes();
  const Points& rest = model_.mesh.nodes();
  const Points& crest = coarse.model_.mesh.nodes();
  // Prone nodes and element centroids of this model in the coarse prone mesh (everything is
  // validated before this pipeline changes).
  // They depend on the two prone meshes alone: kept for the next start from the same coarse mesh
  // (runGravity and runMorphing both start from the coarse model).
  const double fingerprint = meshFingerprint(cm);
  if (!coarse_embedding_ || coarse_embedding_->fingerprint != fingerprint ||
      coarse_embedding_->snap_tolerance_m != snap_tolerance_m) {
    auto e = std::make_unique<CoarseEmbedding>();
    e->nodes = PointEmbedding(cm, prone, {}, snap_tolerance_m);
    Points centroids(model_.mesh.numTets(), 3);
    const Tets& T = model_.mesh.tets();
    for (int t = 0; t < model_.mesh.numTets(); ++t)
      centroids.row(t) = 0.25 * (prone.row(T(t, 0)) + prone.row(T(t, 1)) + prone.row(T(t, 2)) + prone.row(T(t, 3)));
    e->centroids = PointEmbedding(cm, centroids, {}, snap_tolerance_m);
    e->fingerprint = fingerprint;
    e->snap_tolerance_m = snap_tolerance_m;
    coarse_embedding_ = std::move(e);
  }
  const PointEmbedding& at_nodes = coarse_embedding_->nodes;
  const PointEmbedding& at_centroids = coarse_embedding_->centroids;

  const SimulationState& cs = coarse.simulator().state();
  auto asPoints = [](const Eigen::VectorXd& v) {
    return Points(Eigen::Map<const Points>(v.data(), v.size() / 3, 3));
  };
  auto asVector = [](const Points& p) { return Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(p.data(), p.size())); };
  PipelineState s;
  // The coarse move from prone, interpolated, is this model's move from prone; displacements are
  // from each model's rest shape (the same as the prone one with the prone reference).
  Points coarse_move = asPoints(cs.displacement_m);
  if (coarse.unloaded_model_) coarse_move += crest - cm.nodes();
  Points u = at_nodes.interpolate(coarse_move);
  if (unloaded_model_) u += prone - rest;
  s.simulation.displacement_m = asVector(u);
  s.simulation.velocity_mps = asVector(at_nodes.interpolate(asPoints(cs.velocity_mps)));
  s.simulation.time_s = cs.time_s;
  s.simulation.step = cs.step;
  const Eigen::VectorXd coarse_factors = coarse.modulusFactors();
  s.modulus_factors.resize(model_.mesh.numTets());
  // Local α's as the moduli: a fine element takes those of the coarse element its centroid lies in.
  const Eigen::VectorXd& coarse_local = coarse.stiff_->elementAlpha();
  s.element_alpha_per_pa.resize(model_.mesh.numTets());
  for (int t = 0; t < model_.mesh.numTets(); ++t) {
    const int ct = at_centroids.points()[t].tet;
    s.modulus_factors[t] = coarse_factors[ct];
    s.element_alpha_per_pa[t] = coarse_local[ct];
  }
  s.alpha = coarse.stiff_->controller().state();
  s.stage = coarse.stage_;
  if (coarse.sliding_attached_) {
    // Each wall node takes the friction state of the nearest coarse wall node (prone positions): its
    // stick point's (or explicit target's) offset from where that node is now, and its slip direction.
    const std::vector<int>& wall = slip_ ? slip_->nodes() : sliding_->nodes();
    const std::vector<int>& cwall = slip_ ? coarse.slip_->nodes() : coarse.sliding_->nodes();
    const Points& ctargets = slip_ ? coarse.slip_->stickPoints() : coarse.sliding_->targets();
    const Points cdirections = slip_ ? coarse.slip_->slipDirections() : Points();
    const Points cu = asPoints(cs.displacement_m);
    s.sliding_targets_m.resize(static_cast<Eigen::Index>(wall.size()), 3);
    if (slip_) s.sliding_slip_directions = Points::Zero(s.sliding_targets_m.rows(), 3);
    for (size_t i = 0; i < wall.size(); ++i) {
      const Eigen::Index row = static_cast<Eigen::Index>(i);
      size_t nearest = 0;
      double best = std::numeric_limits<double>::infinity();
      for (size_t j = 0; j < cwall.size(); ++j) {
        const double d2 = (cm.nodes().row(cwall[j]) - prone.row(wall[i])).squaredNorm();
        if (d2 < best) best = d2, nearest = j;
      }
      const Eigen::Index crow = static_cast<Eigen::Index>(nearest);
      // Stick points are positions, explicit targets displacements.
      Eigen::RowVector3d cnow = cu.row(cwall[nearest]), now = u.row(wall[i]);
      if (slip_) cnow += crest.row(cwall[nearest]), now += rest.row(wall[i]);
      s.sliding_targets_m.row(row) = now + (ctargets.row(crow) - cnow);
      if (slip_) s.sliding_slip_directions.row(row) = cdirections.row(crow);
    }
  }
  // The gravity load before the α state: a direction change would restart the α search.
  s.gravity_load_mps2 = coarse.gravityLoad();
  stiff_->setGravity(s.gravity_load_mps2 + gravity_offset_mps2_);
  restore(s);

  if (!coarse.morphing_forces_) return;
  // Morphing forces as tractions, carried to this model's pulled vertices.
  const SurfaceMorphing& cmorph = *coarse.morphing_forces_;
  const std::vector<int>& cv = cmorph.vertices();
  const Points& cf = cmorph.accumulatedForces();
  const Eigen::VectorXd& ca = cmorph.vertexAreas();
  SurfaceMorphing& morph = ensureMorphing();
  const std::vector<int>& fv = morph.vertices();
  Points forces = Points::Zero(static_cast<Eigen::Index>(fv.size()), 3);
  constexpr int kNearest = 4;
  std::vector<std::pair<double, int>> d2(cv.size());
  for (size_t j = 0; j < fv.size(); ++j) {
    const Eigen::RowVector3d p = prone.row(fv[j]);
    for (size_t i = 0; i < cv.size(); ++i) d2[i] = {(cm.nodes().row(cv[i]) - p).squaredNorm(), static_cast<int>(i)};
    const size_t k = std::min<size_t>(kNearest, d2.size());
    std::partial_sort(d2.begin(), d2.begin() + static_cast<std::ptrdiff_t>(k), d2.end());
    Eigen::RowVector3d traction = Eigen::RowVector3d::Zero();
    double wsum = 0.0;
    for (size_t q = 0; q < k; ++q) {
      const int i = d2[q].second;
      // 1/d² weights; a coincident vertex (within 1 nm) gives its own traction.
      if (d2[q].first <= 1e-18) {
        traction = cf.row(i) / ca[i];
        wsum = 1.0;
        break;
      }
      const double w = 1.0 / d2[q].first;
      traction += w * cf.row(i) / ca[i];
      wsum += w;
    }
    if (wsum > 0) forces.row(static_cast<Eigen::Index>(j)) = traction / wsum * morph.vertexAreas()[static_cast<Eigen::Index>(j)];
  }
  morph.restoreForces(simulator(), forces);
}

}  // namespace breast_sim::core
