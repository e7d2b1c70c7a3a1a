// ChestWallSliding: settings validation, construction of the sliding set (rim band, wall areas, rest
// distances), the slot state (wall graph, compaction), attach() and the targets. The limiting weights
// are in sliding_limits.cpp, the constraint update in sliding_update.cpp, skin–wall contact in
// sliding_contact.cpp, afterStep() and the settle loops in sliding_stepping.cpp.
#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "breast_sim/core/model/model_case.h"
#include "sliding_internal.h"

namespace breast_sim::core {

using sliding_internal::bad;
using sliding_internal::tetVolume;

void SlidingSettings::validate() const {
  field.validate();
  auto finite = [](double v) { return std::isfinite(v); };
  if (!(mobility_m_per_pa_s >= 0) || !finite(mobility_m_per_pa_s))
    bad("mobility_m_per_pa_s", mobility_m_per_pa_s, "a finite value ≥ 0 [m/(Pa·s)], e.g. 5e-5");
  if (!(static_friction >= 0) || !finite(static_friction)) bad("static_friction", static_friction, "a finite μ_s ≥ 0");
  if (!(kinetic_friction >= 0 && kinetic_friction <= static_friction))
    bad("kinetic_friction", kinetic_friction, "μ_k in [0, static_friction]");
  if (!(static_threshold_pa >= 0) || !finite(static_threshold_pa))
    bad("static_threshold_pa", static_threshold_pa, "a finite traction ≥ 0 [Pa]");
  if (!(stiffness_safety >= 0 && stiffness_safety <= 100))
    bad("stiffness_safety", stiffness_safety, "κ in [0, 100] (0 = no stability cap)");
  if (!(inertia >= 0 && inertia < 1)) bad("inertia", inertia, "β in [0, 1)");
  if (!(max_step_m > 0) || !finite(max_step_m)) bad("max_step_m", max_step_m, "a finite length > 0 [m], e.g. 0.001");
  if (!(max_wall_distance_m > 0 && max_wall_distance_m <= 3 * field.sigma_m))
    bad("max_wall_distance_m", max_wall_distance_m, "(0, 3·sigma] [m] (the field saturates beyond)");
  if (!(projection_iterations >= 1 && projection_iterations <= 50))
    bad("projection_iterations", projection_iterations, "[1, 50]");
  if (!(projection_tolerance_m > 0) || !finite(projection_tolerance_m))
    bad("projection_tolerance_m", projection_tolerance_m, "a finite length > 0 [m], e.g. 1e-7");
  if (!(gaussian_amplitude > 0) || !finite(gaussian_amplitude))
    bad("gaussian_amplitude", gaussian_amplitude, "a finite A > 0");
  if (!(gaussian_sigma_m >= 0) || !finite(gaussian_sigma_m))
    bad("gaussian_sigma_m", gaussian_sigma_m, "0 (automatic) or a length > 0 [m]");
  if (!(gaussian_sigma_fraction > 0 && gaussian_sigma_fraction <= 2))
    bad("gaussian_sigma_fraction", gaussian_sigma_fraction, "(0, 2] of a breast's extent");
  if (!(max_slide_m >= 0) || !finite(max_slide_m)) bad("max_slide_m", max_slide_m, "0 (no cap) or a length > 0 [m]");
  if (!(traction_smoothing_rings >= 0 && traction_smoothing_rings <= 20))
    bad("traction_smoothing_rings", traction_smoothing_rings, "[0, 20]");
  if (!(move_smoothing_iterations >= 0 && move_smoothing_iterations <= 50))
    bad("move_smoothing_iterations", move_smoothing_iterations, "[0, 50]");
  if (!(min_volume_fraction >= 0 && min_volume_fraction < 1))
    bad("min_volume_fraction", min_volume_fraction, "[0, 1) of the rest volume");
  if (!(min_move_scale > 0 && min_move_scale <= 1)) bad("min_move_scale", min_move_scale, "(0, 1]");
  if (!(contact_gap_m >= 0) || !finite(contact_gap_m))
    bad("contact_gap_m", contact_gap_m, "a finite length ≥ 0 [m], below contact_tolerance_m, e.g. 0.0002");
  if (!(contact_tolerance_m > contact_gap_m && contact_tolerance_m <= 3 * field.sigma_m))
    bad("contact_tolerance_m", contact_tolerance_m, "(contact_gap_m, 3·sigma] [m], e.g. 0.0005");
  if (!(contact_release_pa >= 0) || !finite(contact_release_pa))
    bad("contact_release_pa", contact_release_pa, "a finite traction ≥ 0 [Pa], e.g. 50");
}

ChestWallSliding::ChestWallSliding(const TetMesh& mesh, std::vector<int> nodes,
                                   std::shared_ptr<const ChestWallSurface> surface, const SlidingSettings& settings,
                                   const LabelImage* labels, const TissueLabels& tissue,
                                   const std::vector<Eigen::Vector3d>& nipples_m, const Eigen::Vector3d& anterior)
    : settings_(settings), surface_(std::move(surface)), nodes_(std::move(nodes)), num_mesh_nodes_(mesh.numNodes()) {
  settings_.validate();
  if (!surface_) throw std::invalid_argument("ChestWallSliding: no chest-wall surface given");
  if (nodes_.empty()) throw std::invalid_argument("ChestWallSliding: the sliding node set is empty");
  int n = static_cast<int>(nodes_.size());
  std::vector<int> slot(mesh.numNodes(), -1);
  for (int i = 0; i < n; ++i) {
    const int v = nodes_[i];
    if (v < 0 || v >= mesh.numNodes())
      throw std::invalid_argument("ChestWallSliding: node " + std::to_string(v) + " is not in [0, " +
                                  std::to_string(mesh.numNodes()) + ")");
    if (slot[v] >= 0) throw std::invalid_argument("ChestWallSliding: node " + std::to_string(v) + " is given twice");
    slot[v] = i;
  }
  // Rim band: skin nodes within max_wall_distance_m of the wall, joined to the rim through skin
  // nodes (shared tetrahedra), join the set, level by level (see rim_band in the header).
  std::vector<int> level(nodes_.size(), 0);
  std::vector<char> skin(mesh.numNodes(), 0);
  if (mesh.nodeSets().count(node_sets::kSkin))
    for (int v : mesh.nodeSet(node_sets::kSkin))
      if (v >= 0 && v < mesh.numNodes()) skin[v] = 1;
  for (int i = 0; i < n; ++i)
    if (skin[nodes_[i]]) level[i] = 1;
  if (settings_.rim_band) {
    const Tets& tt = mesh.tets();
    for (int pass = 2; pass < 22; ++pass) {
      std::vector<int> add;
      for (Eigen::Index t = 0; t < tt.rows(); ++t) {
        bool touches = false;
        for (int c = 0; c < 4; ++c) {
          const int sv = slot[tt(t, c)];
          touches = touches || (sv >= 0 && level[sv] > 0);
        }
        if (!touches) continue;
        for (int c = 0; c < 4; ++c) {
          const int v = tt(t, c);
          if (!skin[v] || slot[v] != -1) continue;
          slot[v] = -2;  // looked at
          if (surface_->signedDistance(mesh.nodes().row(v).transpose()) <= settings_.max_wall_distance_m) add.push_back(v);
        }
      }
      for (int& sv : slot)
        if (sv == -2) sv = -1;
      if (add.empty()) break;
      for (int v : add) {
        slot[v] = static_cast<int>(nodes_.size());
        nodes_.push_back(v);
        level.push_back(pass);
      }
    }
  }
  n = static_cast<int>(nodes_.size());
  rim_level_ = level;
  base_nodes_ = nodes_;
  num_base_ = n;
  mesh_tets_ = mesh.tets();
  released_.assign(mesh.numNodes(), 0);
  tension_calls_.assign(mesh.numNodes(), 0);
  for (int v = 0; v < mesh.numNodes(); ++v)
    if (skin[v] && slot[v] < 0) skin_candidates_.push_back(v);
  if (settings_.thickness_limit && !labels)
    throw std::invalid_argument("ChestWallSliding: the thickness limit needs the label image");
  if (settings_.gaussian_limit && (nipples_m.empty() || nipples_m.size() > 2))
    throw std::invalid_argument("ChestWallSliding: the Gaussian limit needs 1 or 2 nipple points, the case has " +
                                std::to_string(nipples_m.size()));
  if (!anterior.allFinite() || anterior.norm() < 1e-9)
    throw std::invalid_argument("ChestWallSliding: the anterior direction must be a non-zero vector");

  rest_.resize(n, 3);
  for (int i = 0; i < n; ++i) rest_.row(i) = mesh.nodes().row(nodes_[i]);
  origin_ = rest_;
  mesh_rest_ = mesh.nodes();
  targets_ = Points::Zero(n, 3);
  base_targets_ = targets_;
  velocity_ = Points::Zero(n, 3);

  // Wall area per node: a third of each boundary triangle whose three nodes all slide.
  area_ = Eigen::VectorXd::Zero(n);
  const BoundarySurface& b = mesh.boundary();
  for (Eigen::Index f = 0; f < b.triangles.rows(); ++f) {
    const int a = b.triangles(f, 0), c = b.triangles(f, 1), d = b.triangles(f, 2);
    if (slot[a] < 0 || slot[c] < 0 || slot[d] < 0) continue;
    const Eigen::Vector3d pa = mesh.nodes().row(a), pc = mesh.nodes().row(c), pd = mesh.nodes().row(d);
    const double third = (pc - pa).cross(pd - pa).norm() / 6.0;
    area_[slot[a]] += third;
    area_[slot[c]] += third;
    area_[slot[d]] += third;
  }
  {  // Nodes in no all-sliding triangle get the median share.
    std::vector<double> pos;
    for (int i = 0; i < n; ++i)
      if (area_[i] > 0) pos.push_back(area_[i]);
    double median = 1e-6;
    if (!pos.empty()) {
      std::nth_element(pos.begin(), pos.begin() + pos.size() / 2, pos.end());
      median = pos[pos.size() / 2];
    }
    for (int i = 0; i < n; ++i)
      if (!(area_[i] > 0)) area_[i] = median;
  }

  // Rest distance to the wall. Held: nodes too far from the wall, deeper than σ inside the wall mask
  // (tissue the segmentation encloses in the wall: its level is a tube, not the wall), and within σ
  // of the image border (the levels there run straight out of the image).
  h0_.resize(n);
  held_flag_.assign(n, 0);
  const double sigma = surface_->options().sigma_m;
  for (int i = 0; i < n; ++i) {
    const double h = surface_->signedDistance(rest_.row(i).transpose());
    if (h > settings_.max_wall_distance_m || h < -sigma || surface_->borderDistance(rest_.row(i).transpose()) < sigma) {
      held_flag_[i] = 1;
      ++held_;
    }
    h0_[i] = std::clamp(h, 0.0, settings_.max_wall_distance_m);
  }


  // Limiting factors (sliding_limits.cpp).
  measureThickness(labels, tissue);
  placeGaussian(mesh, slot, nipples_m, anterior);
  weight_ = thickness_factor_.cwiseProduct(gaussian_factor_);
  for (int i = 0; i < n; ++i)
    if (held_flag_[i]) weight_[i] = 0.0;

  buildGraph();
}

void ChestWallSliding::buildGraph() {
  const int n = static_cast<int>(nodes_.size());
  slot_of_.assign(num_mesh_nodes_, -1);
  for (int i = 0; i < n; ++i) slot_of_[nodes_[i]] = i;
  std::vector<std::vector<int>> adj(n);
  static constexpr int kEdges[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};
  wall_tets_.clear();
  wall_slots_.clear();
  wall_rest_volume_.clear();
  for (Eigen::Index t = 0; t < mesh_tets_.rows(); ++t) {
    Eigen::Vector4i sl;
    bool any = false;
    for (int c = 0; c < 4; ++c) {
      sl[c] = slot_of_[mesh_tets_(t, c)];
      any = any || sl[c] >= 0;
    }
    if (!any) continue;
    const Eigen::Vector4i tv(mesh_tets_(t, 0), mesh_tets_(t, 1), mesh_tets_(t, 2), mesh_tets_(t, 3));
    wall_tets_.push_back(tv);
    wall_slots_.push_back(sl);
    wall_rest_volume_.push_back(tetVolume(mesh_rest_.row(tv[0]).transpose(), mesh_rest_.row(tv[1]).transpose(),
                                          mesh_rest_.row(tv[2]).transpose(), mesh_rest_.row(tv[3]).transpose()));
    for (const auto& e : kEdges)
      if (sl[e[0]] >= 0 && sl[e[1]] >= 0) {
        adj[sl[e[0]]].push_back(sl[e[1]]);
        adj[sl[e[1]]].push_back(sl[e[0]]);
      }
  }
  nbr_start_.assign(n + 1, 0);
  for (int i = 0; i < n; ++i) {
    std::sort(adj[i].begin(), adj[i].end());
    adj[i].erase(std::unique(adj[i].begin(), adj[i].end()), adj[i].end());
    nbr_start_[i + 1] = nbr_start_[i] + static_cast<int>(adj[i].size());
  }
  nbr_.clear();
  nbr_.reserve(nbr_start_[n]);
  for (int i = 0; i < n; ++i) nbr_.insert(nbr_.end(), adj[i].begin(), adj[i].end());
  // Levels of the contact slots: graph distance from the sliding set (its levels kept), so a
  // contact node follows the constrained neighbours closer to the wall; unreached: one above all.
  rim_level_.resize(n);
  const int unset = std::numeric_limits<int>::max();
  for (int i = num_base_; i < n; ++i) rim_level_[i] = unset;
  for (bool changed = n > num_base_; changed;) {
    changed = false;
    for (int i = num_base_; i < n; ++i)
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) {
        const int l = rim_level_[nbr_[k]];
        if (l != unset && l + 1 < rim_level_[i]) {
          rim_level_[i] = l + 1;
          changed = true;
        }
      }
  }
  int top = 0;
  for (int i = 0; i < n; ++i)
    if (rim_level_[i] != unset) top = std::max(top, rim_level_[i]);
  for (int i = num_base_; i < n; ++i)
    if (rim_level_[i] == unset) rim_level_[i] = top + 1;
  rim_flag_.assign(n, 0);
  for (int i = 0; i < n; ++i) rim_flag_[i] = rim_level_[i] > 0 ? 1 : 0;
}

void ChestWallSliding::compactSlots(const std::vector<char>& keep) {
  const int n = static_cast<int>(nodes_.size());
  int w = 0;
  for (int i = 0; i < n; ++i) {
    if (!keep[i]) continue;
    if (w != i) {
      nodes_[w] = nodes_[i];
      rest_.row(w) = rest_.row(i);
      origin_.row(w) = origin_.row(i);
      targets_.row(w) = targets_.row(i);
      velocity_.row(w) = velocity_.row(i);
      if (stiffness_.size() >= 9L * (i + 1)) stiffness_.segment<9>(9L * w) = stiffness_.segment<9>(9L * i);
      h0_[w] = h0_[i];
      area_[w] = area_[i];
      weight_[w] = weight_[i];
      thickness_factor_[w] = thickness_factor_[i];
      gaussian_factor_[w] = gaussian_factor_[i];
      thickness_m_[w] = thickness_m_[i];
      held_flag_[w] = held_flag_[i];
      rim_level_[w] = rim_level_[i];
    }
    ++w;
  }
  nodes_.resize(w);
  rest_.conservativeResize(w, 3);
  origin_.conservativeResize(w, 3);
  targets_.conservativeResize(w, 3);
  velocity_.conservativeResize(w, 3);
  if (stiffness_.size() > 9L * w) stiffness_.conservativeResize(9L * w);
  for (Eigen::VectorXd* v : {&h0_, &area_, &weight_, &thickness_factor_, &gaussian_factor_, &thickness_m_})
    v->conservativeResize(w);
  held_flag_.resize(w);
  rim_level_.resize(w);
  buildGraph();
}

ChestWallSliding ChestWallSliding::fromCase(const ModelCase& model_case, const TetMesh& mesh,
                                            const SlidingSettings& settings) {
  settings.validate();
  auto surface = std::make_shared<const ChestWallSurface>(model_case.image, model_case.labels.chest_wall, settings.field);
  return ChestWallSliding(mesh, mesh.nodeSet(node_sets::kChestWall), surface, settings, &model_case.image,
                          model_case.labels, model_case.nipples_m, model_case.prone_gravity_direction);
}

void ChestWallSliding::attach(DynamicSimulator& sim) {
  if (sim.numNodes() != num_mesh_nodes_)
    throw std::invalid_argument("ChestWallSliding::attach: the simulator has " + std::to_string(sim.numNodes()) +
                                " nodes, the mesh " + std::to_string(num_mesh_nodes_));
  const Eigen::VectorXd& u = sim.state().displacement_m;
  if (static_cast<int>(nodes_.size()) > num_base_) {  // contacts of an earlier run
    std::vector<char> keep(nodes_.size(), 0);
    std::fill(keep.begin(), keep.begin() + num_base_, 1);
    compactSlots(keep);
  }
  std::fill(released_.begin(), released_.end(), 0);
  tension_calls_.assign(num_mesh_nodes_, 0);
  contacts_made_ = contacts_released_ = 0;
  // Nodes constrained by others (re-imposed as fixed when a contact is released).
  foreign_fixed_.clear();
  for (int v = 0; v < num_mesh_nodes_; ++v)
    if (slot_of_[v] < 0 && (sim.constrainedDofs()[3 * v] || sim.constrainedDofs()[3 * v + 1] ||
                            sim.constrainedDofs()[3 * v + 2]))
      foreign_fixed_.push_back(v);
  for (size_t i = 0; i < nodes_.size(); ++i) targets_.row(i) = u.segment<3>(3 * nodes_[i]).transpose();
  base_targets_ = targets_;
  velocity_.setZero();
  move_scale_ = 1.0;
  last_moved_ = false;
  // Stiffness diagonal at the current state: K from one assembly.
  sim.elasticForces();  // updates the element linearisation
  SparseMatrix K = sim.elements().pattern().matrix();
  std::fill(K.valuePtr(), K.valuePtr() + K.nonZeros(), 0.0);
  sim.elements().addStiffness(1.0, K);
  stiffness_.resize(9 * static_cast<Eigen::Index>(nodes_.size()));
  for (size_t i = 0; i < nodes_.size(); ++i) {
    const int r = 3 * nodes_[i];
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) stiffness_[9 * i + 3 * a + b] = K.coeff(r + a, r + b);
  }
  sim.setNodeTargets(nodes_, targets_);
}

void ChestWallSliding::setTargets(DynamicSimulator& sim, const Points& targets_m) {
  if (targets_m.rows() != static_cast<Eigen::Index>(num_base_) || !targets_m.allFinite())
    throw std::invalid_argument("ChestWallSliding::setTargets: " + std::to_string(targets_m.rows()) +
                                " rows given; expected " + std::to_string(num_base_) +
                                " finite rows, one per node of nodes()");
  targets_.topRows(num_base_) = targets_m;
  base_targets_ = targets_m;
  velocity_.setZero();
  last_moved_ = true;
  sim.setNodeTargets(nodes_, targets_);
}

Points ChestWallSliding::slidingVectors() const {
  Points out = Points::Zero(num_mesh_nodes_, 3);
  for (size_t i = 0; i < nodes_.size(); ++i) out.row(nodes_[i]) = rest_.row(i) + targets_.row(i) - origin_.row(i);
  return out;
}

}  // namespace breast_sim::core
