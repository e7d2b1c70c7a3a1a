#include "breast_sim/core/sliding/chest_wall_sliding.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include <Eigen/Geometry>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/model/model_case.h"
#include "../util/closest_point.h"

namespace breast_sim::core {

namespace {

// Accepted calls in a row a contact node must pull off the wall before it is freed: one call's
// reaction carries inertia (a node caught while falling, a bounce), which is no lift-off.
constexpr int kReleaseCalls = 3;

double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

[[noreturn]] void bad(const char* name, double v, const char* range) {
  std::ostringstream s;
  s << "sliding '" << name << "' = " << v << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

double tetVolume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                 const Eigen::Vector3d& d) {
  return (b - a).dot((c - a).cross(d - a)) / 6.0;
}


}  // namespace

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

  // Rest distance to the wall; nodes too far are held.
  h0_.resize(n);
  held_flag_.assign(n, 0);
  for (int i = 0; i < n; ++i) {
    const double h = surface_->signedDistance(rest_.row(i).transpose());
    if (h > settings_.max_wall_distance_m) {
      held_flag_[i] = 1;
      ++held_;
    }
    h0_[i] = std::clamp(h, 0.0, settings_.max_wall_distance_m);
  }

  // Thickness: ray marching from the rest position along the rest normal through tissue.
  thickness_factor_ = Eigen::VectorXd::Ones(n);
  thickness_m_ = Eigen::VectorXd::Zero(n);
  if (settings_.thickness_limit) {
    const double step = 0.5 * labels->spacing_m.minCoeff();
    const double reach = (labels->spacing_m.cwiseProduct(labels->size.cast<double>())).norm();
    const double wall_skip = 3.0 * labels->spacing_m.maxCoeff();
#pragma omp parallel for schedule(dynamic, 64)
    for (int i = 0; i < n; ++i) {
      const Eigen::Vector3d x = rest_.row(i).transpose();
      const Eigen::Vector3d nrm = surface_->normal(x);
      if (nrm.isZero()) continue;
      double t = step;
      for (; t < reach; t += step) {
        const std::uint16_t l = labels->labelAt(x + t * nrm, 0);
        if (tissue.isTissue(l)) continue;
        if (t < wall_skip && tissue.classify(l) == TissueClass::kChestWall) continue;
        break;
      }
      thickness_m_[i] = t - 0.5 * step;
    }
    const double tmax = thickness_m_.maxCoeff();
    if (tmax > 0) thickness_factor_ = thickness_m_ / tmax;
  }

  // Chest-wall plane frame and the bimodal Gaussian.
  gaussian_factor_ = Eigen::VectorXd::Ones(n);
  const Eigen::Vector3d a = anterior.normalized();
  auto inPlane = [&](const Eigen::Vector3d& v) { return Eigen::Vector3d(v - v.dot(a) * a); };
  if (nipples_m.size() == 2 && inPlane(nipples_m[0] - nipples_m[1]).norm() > 1e-6) {
    plane_u_ = inPlane(nipples_m[0] - nipples_m[1]).normalized();
    plane_origin_ = 0.5 * (nipples_m[0] + nipples_m[1]);
  } else {
    // One nipple (or none): u along the patient x axis (or y, z if x is anterior) in the plane.
    for (const Eigen::Vector3d e : {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ()})
      if (inPlane(e).norm() > 0.5) {
        plane_u_ = inPlane(e).normalized();
        break;
      }
    if (!nipples_m.empty()) plane_origin_ = nipples_m[0];
  }
  plane_v_ = a.cross(plane_u_).normalized();
  if (settings_.gaussian_limit) {
    // Each mode is centred at the nipple's foot point on the wall: the closest point of the
    // all-sliding boundary triangles (or, without any, the closest sliding node).
    for (const Eigen::Vector3d& p : nipples_m) {
      Eigen::Vector3d best = rest_.row(0).transpose();
      double best_d = std::numeric_limits<double>::infinity();
      bool any_triangle = false;
      for (Eigen::Index f = 0; f < b.triangles.rows(); ++f) {
        const int a0 = b.triangles(f, 0), a1 = b.triangles(f, 1), a2 = b.triangles(f, 2);
        if (slot[a0] < 0 || slot[a1] < 0 || slot[a2] < 0) continue;
        any_triangle = true;
        const Eigen::Vector3d q = closestPointOnTriangle(p, mesh.nodes().row(a0).transpose(), mesh.nodes().row(a1).transpose(),
                                                    mesh.nodes().row(a2).transpose());
        const double d = (q - p).squaredNorm();
        if (d < best_d) {
          best_d = d;
          best = q;
        }
      }
      if (!any_triangle)
        for (int i = 0; i < n; ++i) {
          const double d = (rest_.row(i).transpose() - p).squaredNorm();
          if (d < best_d) {
            best_d = d;
            best = rest_.row(i).transpose();
          }
        }
      centre_points_.push_back(best);
      centres_.emplace_back((best - plane_origin_).dot(plane_u_), (best - plane_origin_).dot(plane_v_));
    }
    if (settings_.gaussian_sigma_m > 0) {
      gaussian_sigma_ = Eigen::Vector2d::Constant(settings_.gaussian_sigma_m);
    } else {
      // Extent of the sliding nodes closest to each nipple, along u and v (a breast's diameter).
      std::vector<Eigen::Vector2d> lo(centres_.size(), Eigen::Vector2d::Constant(1e300)),
          hi(centres_.size(), Eigen::Vector2d::Constant(-1e300));
      for (int i = 0; i < n; ++i) {
        const Eigen::Vector3d d = rest_.row(i).transpose() - plane_origin_;
        const Eigen::Vector2d uv(d.dot(plane_u_), d.dot(plane_v_));
        size_t best = 0;
        for (size_t k = 1; k < centres_.size(); ++k)
          if ((uv - centres_[k]).squaredNorm() < (uv - centres_[best]).squaredNorm()) best = k;
        lo[best] = lo[best].cwiseMin(uv);
        hi[best] = hi[best].cwiseMax(uv);
      }
      Eigen::Vector2d ext = Eigen::Vector2d::Zero();
      int count = 0;
      for (size_t k = 0; k < centres_.size(); ++k)
        if (hi[k].x() >= lo[k].x()) {
          ext += hi[k] - lo[k];
          ++count;
        }
      if (count == 0 || !(ext.minCoeff() > 0))
        throw std::invalid_argument("ChestWallSliding: cannot measure the breasts' extent for the Gaussian sigma; "
                                    "give gaussian_sigma_m > 0");
      gaussian_sigma_ = settings_.gaussian_sigma_fraction * ext / count;
    }
    for (int i = 0; i < n; ++i) gaussian_factor_[i] = gaussianWeight(rest_.row(i).transpose());
  }
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

double ChestWallSliding::gaussianWeight(const Eigen::Vector3d& p_m) const {
  if (centres_.empty()) return 1.0;
  const Eigen::Vector3d d = p_m - plane_origin_;
  const double u = d.dot(plane_u_), v = d.dot(plane_v_);
  double z = 0;
  for (const Eigen::Vector2d& c : centres_) {
    const double du = (u - c.x()) / gaussian_sigma_.x(), dv = (v - c.y()) / gaussian_sigma_.y();
    z += settings_.gaussian_amplitude * std::exp(-0.5 * (du * du + dv * dv));
  }
  return std::min(1.0, z);
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

SlidingStepStats ChestWallSliding::update(DynamicSimulator& sim, const Eigen::VectorXd* external_forces) {
  const auto t0 = std::chrono::steady_clock::now();
  const Eigen::VectorXd& f = sim.elasticForces();
  const double tf = since(t0);
  SlidingStepStats st = update(sim.state().displacement_m, f, sim.lumpedMass(), sim.params().gravity_mps2,
                               sim.params().time_step_s, external_forces);
  st.force_seconds = tf;
  sim.setNodeTargets(nodes_, targets_);
  return st;
}

SlidingStepStats ChestWallSliding::update(const Eigen::VectorXd& u, const Eigen::VectorXd& f_el,
                                          const Eigen::VectorXd& mass, const Eigen::Vector3d& g, double dt,
                                          const Eigen::VectorXd* f_ext) {
  const long n3 = 3L * num_mesh_nodes_;
  if (u.size() != n3 || f_el.size() != n3 || mass.size() != num_mesh_nodes_ || (f_ext && f_ext->size() != n3))
    throw std::invalid_argument("ChestWallSliding::update: vectors do not match the mesh's " +
                                std::to_string(num_mesh_nodes_) + " nodes");
  // Applied load on each sliding node (the reaction is its negative), quasi-static.
  Eigen::VectorXd load = Eigen::VectorXd::Zero(n3);
  for (int v : nodes_) {
    Eigen::Vector3d l = f_el.segment<3>(3 * v) + mass[v] * g;
    if (f_ext) l += f_ext->segment<3>(3 * v);
    load.segment<3>(3 * v) = l;
  }
  return updateFromLoads(u, load, dt, 1.0);
}

SlidingStepStats ChestWallSliding::updateFromLoads(const Eigen::VectorXd& u, const Eigen::VectorXd& load, double dt,
                                                   double scale) {
  const auto t0 = std::chrono::steady_clock::now();
  const long n3 = 3L * num_mesh_nodes_;
  if (u.size() != n3 || load.size() != n3)
    throw std::invalid_argument("ChestWallSliding::updateFromLoads: vectors do not match the mesh's " +
                                std::to_string(num_mesh_nodes_) + " nodes");
  if (!(dt > 0) || !std::isfinite(dt)) bad("update dt_s", dt, "a finite time step > 0 [s]");
  if (!(scale > 0 && scale <= 1)) bad("updateFromLoads move_scale", scale, "(0, 1]");
  const SlidingSettings& s = settings_;
  const int n = static_cast<int>(nodes_.size());
  const Eigen::Index k_slots = stiffness_.size() / 9;  // slots with a measured stiffness block
  auto movable = [&](int i) { return !held_flag_[i] && weight_[i] > 0; };

  // 1. Traction per node [Pa]: the load of the node and its ring(s) of wall neighbours over their area.
  Points F(n, 3);
  Eigen::VectorXd A = area_;
  for (int i = 0; i < n; ++i) F.row(i) = load.segment<3>(3 * nodes_[i]).transpose();
  for (int ring = 0; ring < s.traction_smoothing_rings; ++ring) {
    Points F2 = F;
    Eigen::VectorXd A2 = A;
    for (int i = 0; i < n; ++i)
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) {
        F2.row(i) += F.row(nbr_[k]);
        A2[i] += A[nbr_[k]];
      }
    F.swap(F2);
    A.swap(A2);
  }

  // 2. Per-node move from friction and mobility (stability-capped), plus inertia.
  Points move = Points::Zero(n, 3), normal = Points::Zero(n, 3);
  int limited = 0;
  for (int i = 0; i < n; ++i) {
    if (!movable(i)) continue;
    const Eigen::Vector3d x = rest_.row(i).transpose() + u.segment<3>(3 * nodes_[i]);
    const Eigen::Vector3d nrm = surface_->normal(x);
    if (nrm.isZero()) continue;
    normal.row(i) = nrm.transpose();
    const Eigen::Vector3d tau = F.row(i).transpose() / A[i];
    const double tn = tau.dot(nrm);
    const Eigen::Vector3d tt = tau - tn * nrm;
    const double tau_n = std::abs(tn), tau_t = tt.norm();
    const Eigen::Vector3d v_prev = velocity_.row(i).transpose();
    const Eigen::Vector3d v_prev_t = v_prev - v_prev.dot(nrm) * nrm;
    const bool was_moving = v_prev_t.squaredNorm() > 0;
    if (!(was_moving || tau_t > s.static_friction * tau_n + s.static_threshold_pa)) continue;
    Eigen::Vector3d m = Eigen::Vector3d::Zero();
    const double drive = std::max(0.0, tau_t - s.kinetic_friction * tau_n - s.static_threshold_pa);
    if (tau_t > 0 && drive > 0) {
      const Eigen::Vector3d t = tt / tau_t;
      double len = dt * (1.0 - s.inertia) * weight_[i] * s.mobility_m_per_pa_s * drive;
      // Stiffness of the node along its driving direction: tᵀ K_ii t [N/m].
      const double kt = i < k_slots ? t.dot(Eigen::Map<const Eigen::Matrix3d>(&stiffness_[9 * i]).transpose() * t) : 0.0;
      if (kt > 0 && s.stiffness_safety > 0) {
        const double stable = drive * area_[i] / (s.stiffness_safety * kt);
        if (len > stable) {
          len = stable;
          ++limited;
        }
      }
      m = len * t;
    }
    m += dt * s.inertia * v_prev_t;
    move.row(i) = m.transpose();
  }

  // 3. Rim and rim-band nodes follow their neighbours of a lower level (the rim follows the wall
  //    nodes next to it, the band the rim), level by level.
  int rim = 0;
  if (s.rim_follows_neighbours) {
    const int max_level = n > 0 ? *std::max_element(rim_level_.begin(), rim_level_.end()) : 0;
    for (int lv = 1; lv <= max_level; ++lv)
      for (int i = 0; i < n; ++i) {
        if (rim_level_[i] != lv || !movable(i) || normal.row(i).isZero()) continue;
        Eigen::Vector3d sum = Eigen::Vector3d::Zero();
        double wsum = 0.0;
        int cnt = 0;
        for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k)
          if (rim_level_[nbr_[k]] < lv) {
            sum += move.row(nbr_[k]).transpose();
            wsum += weight_[nbr_[k]];
            ++cnt;
          }
        if (cnt == 0) continue;
        const Eigen::Vector3d nrm = normal.row(i).transpose();
        sum /= cnt;
        // The node's own limiting weight still applies: scaled by it relative to its neighbours'
        // (a rim node near the sternum does not take the full move of livelier neighbours).
        if (wsum > 0) sum *= std::min(1.0, weight_[i] * cnt / wsum);
        move.row(i) = (sum - sum.dot(nrm) * nrm).transpose();
        ++rim;
      }
  }

  // 4. Smoothing of the move field (held nodes take part with 0), back into each tangent plane.
  for (int it = 0; it < s.move_smoothing_iterations; ++it) {
    Points next = move;
    for (int i = 0; i < n; ++i) {
      if (!movable(i) || normal.row(i).isZero()) continue;
      const int deg = nbr_start_[i + 1] - nbr_start_[i];
      if (deg == 0) continue;
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) mean += move.row(nbr_[k]).transpose();
      mean /= deg;
      double wmean = 0.0;
      for (int k = nbr_start_[i]; k < nbr_start_[i + 1]; ++k) wmean += weight_[nbr_[k]];
      wmean /= deg;
      // Smoothing blends the neighbours' moves in, but not beyond the node's own limiting weight.
      if (wmean > 0) mean *= std::min(1.0, weight_[i] / wmean);
      const Eigen::Vector3d nrm = normal.row(i).transpose();
      Eigen::Vector3d m = 0.5 * (move.row(i).transpose() + mean);
      m -= m.dot(nrm) * nrm;
      next.row(i) = m.transpose();
    }
    move.swap(next);
  }

  // 5. Scale, step cap, permissible shift, projection onto the node's rest level of the wall.
  Points proposed(n, 3), current(n, 3);
  std::vector<char> ok(n, 0), cap(n, 0);
  int failures = 0;
#pragma omp parallel for schedule(static) reduction(+ : failures)
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d X = rest_.row(i).transpose();
    const Eigen::Vector3d x = X + u.segment<3>(3 * nodes_[i]);
    current.row(i) = x.transpose();
    proposed.row(i) = x.transpose();
    Eigen::Vector3d m = scale * move.row(i).transpose();
    const double len = m.norm();
    if (len > s.max_step_m) m *= s.max_step_m / len;
    // Contact nodes are projected even without a move: their level may have changed.
    const bool relevel = i >= num_base_;
    if (!movable(i) || !(m.squaredNorm() > 0 || relevel)) continue;
    Eigen::Vector3d y = x + m;
    if (s.max_slide_m > 0) {
      const Eigen::Vector3d O = origin_.row(i).transpose();
      const double limit = weight_[i] * s.max_slide_m;
      const Eigen::Vector3d d = y - O;
      if (d.norm() > limit) {
        y = O + d * (limit / d.norm());
        cap[i] = 1;
      }
    }
    const WallProjection p = surface_->project(y, h0_[i], s.projection_iterations, s.projection_tolerance_m);
    if (!p.converged && p.residual_m > 1e-5) {  // keep the old constraint rather than a bad point
      ++failures;
      continue;
    }
    proposed.row(i) = p.point_m.transpose();
    ok[i] = 1;
  }

  // 6. Volume guard on the wall elements: halve the moves of an element's sliding nodes while it
  //    would shrink below min_volume_fraction of its rest volume (or invert); six halvings, then hold.
  std::vector<double> factor(n, 1.0);
  std::vector<char> guarded(n, 0);
  int guard_held = 0;
  const int m_tets = static_cast<int>(wall_tets_.size());
  for (int round = 0; round <= 6; ++round) {
    std::vector<char> shrink(n, 0);
    bool any = false;
    for (int e = 0; e < m_tets; ++e) {
      const Eigen::Vector4i& tv = wall_tets_[e];
      const Eigen::Vector4i& sl = wall_slots_[e];
      bool moves = false;
      for (int c = 0; c < 4; ++c) moves = moves || (sl[c] >= 0 && ok[sl[c]] && factor[sl[c]] > 0);
      if (!moves) continue;
      Eigen::Vector3d pc[4], pt[4];
      for (int c = 0; c < 4; ++c) {
        const int i = sl[c];
        if (i < 0) {
          pc[c] = pt[c] = mesh_rest_.row(tv[c]).transpose() + u.segment<3>(3 * tv[c]);
        } else {
          pc[c] = current.row(i).transpose();
          pt[c] = ok[i] ? Eigen::Vector3d(pc[c] + factor[i] * (proposed.row(i) - current.row(i)).transpose()) : pc[c];
        }
      }
      const double v_new = tetVolume(pt[0], pt[1], pt[2], pt[3]);
      const double v_now = tetVolume(pc[0], pc[1], pc[2], pc[3]);
      if (v_new >= s.min_volume_fraction * wall_rest_volume_[e] && v_new > 0) continue;
      if (v_new >= v_now && v_new > 0) continue;  // the move does not shrink it
      any = true;
      for (int c = 0; c < 4; ++c)
        if (sl[c] >= 0 && ok[sl[c]]) shrink[sl[c]] = 1;
    }
    if (!any) break;
    for (int i = 0; i < n; ++i)
      if (shrink[i]) {
        guarded[i] = 1;
        factor[i] = round < 6 ? 0.5 * factor[i] : 0.0;
      }
  }

  // 7. The new targets.
  int moving = 0, stuck = 0, capped = 0, guard_limited = 0;
  double max_move = 0, max_slide = 0, max_pen = 0;
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d X = rest_.row(i).transpose();
    const Eigen::Vector3d x = current.row(i).transpose();
    if (guarded[i]) {
      ++guard_limited;
      if (factor[i] == 0) ++guard_held;
    }
    if (!ok[i] || factor[i] == 0) {
      targets_.row(i) = (x - X).transpose();
      velocity_.row(i).setZero();
      ++stuck;
      continue;
    }
    const Eigen::Vector3d y = x + factor[i] * (proposed.row(i).transpose() - x);
    const Eigen::Vector3d moved = y - x;
    targets_.row(i) = (y - X).transpose();
    velocity_.row(i) = cap[i] || guarded[i] ? Eigen::RowVector3d::Zero() : Eigen::RowVector3d((moved / dt).transpose());
    ++moving;
    capped += cap[i];
    max_move = std::max(max_move, moved.norm());
    max_pen = std::max(max_pen, -surface_->signedDistance(y));
  }
  for (int i = 0; i < n; ++i)
    max_slide = std::max(max_slide, (rest_.row(i) + targets_.row(i) - origin_.row(i)).norm());
  base_targets_ = targets_.topRows(num_base_);
  SlidingStepStats st;
  st.moving = moving;
  st.stuck = stuck;
  st.capped = capped;
  st.stiffness_limited = limited;
  st.projection_failures = failures;
  st.guard_limited = guard_limited;
  st.guard_held = guard_held;
  st.rim_nodes = rim;
  st.move_scale = scale;
  st.max_move_m = max_move;
  st.max_slide_m = max_slide;
  st.max_penetration_m = std::max(0.0, max_pen);
  st.seconds = since(t0);
  return st;
}

bool ChestWallSliding::updateContacts(DynamicSimulator& sim, const Eigen::VectorXd& load, SlidingStepStats& st) {
  const SlidingSettings& s = settings_;
  st.min_free_skin_distance_m = std::numeric_limits<double>::infinity();
  if (!s.contact || skin_candidates_.empty()) return false;
  const Eigen::VectorXd& u = sim.state().displacement_m;
  const Eigen::VectorXd& vel = sim.state().velocity_mps;
  const double dt = sim.params().time_step_s;
  auto position = [&](int v) { return Eigen::Vector3d(mesh_rest_.row(v).transpose() + u.segment<3>(3 * v)); };

  // 1. Contact nodes: freed when their load pulls them off the wall (unilateral), else their level
  //    descends half way to the gap while they press on it.
  int n = static_cast<int>(nodes_.size());
  std::vector<char> keep(n, 1);
  int released = 0;
  for (int i = num_base_; i < n; ++i) {
    const int v = nodes_[i];
    const Eigen::Vector3d nrm = surface_->normal(position(v));
    if (nrm.isZero()) continue;
    const double fn = load.segment<3>(3 * v).dot(nrm);  // > 0: the node pulls away from the wall
    const bool pulled = fn > s.contact_release_pa * area_[i];
    tension_calls_[v] = pulled ? tension_calls_[v] + 1 : 0;
    if (s.contact_release && tension_calls_[v] >= kReleaseCalls) {
      keep[i] = 0;
      released_[v] = 1;
      tension_calls_[v] = 0;
      ++released;
    } else if (fn < 0) {
      h0_[i] = std::max(s.contact_gap_m, h0_[i] - 0.5 * (h0_[i] - s.contact_gap_m));
    }
  }
  if (released > 0) {
    compactSlots(keep);
    // No call frees single nodes: clear, then re-impose the others' constraints (file comment);
    // the caller re-imposes the slots' targets.
    sim.clearConstraints();
    sim.fixNodes(foreign_fixed_);
    contacts_released_ += released;
    n = static_cast<int>(nodes_.size());
  }

  // 2. Free skin nodes that touch the wall, now or one step ahead along their velocity.
  const int m = static_cast<int>(skin_candidates_.size());
  std::vector<double> level(m, -1.0);
  double min_h = std::numeric_limits<double>::infinity();
#pragma omp parallel for schedule(static) reduction(min : min_h)
  for (int q = 0; q < m; ++q) {
    const int v = skin_candidates_[q];
    if (slot_of_[v] >= 0) continue;
    Eigen::Vector3d grad;
    const Eigen::Vector3d x = position(v);
    const double h = surface_->signedDistance(x, grad);
    // Look two steps ahead along the approach: a node falling onto the wall still accelerates.
    const double h_pred = h + 2.0 * dt * std::min(0.0, grad.dot(vel.segment<3>(3 * v)));
    // A freed node was let go at the gap or above: it is caught again only below half of it.
    const double threshold = released_[v] ? 0.5 * s.contact_gap_m : s.contact_tolerance_m;
    if (std::min(h, h_pred) <= threshold) level[q] = std::max(s.contact_gap_m, h);
    else min_h = std::min(min_h, h);
  }
  std::vector<int> add_v;
  std::vector<Eigen::Vector3d> add_y;
  std::vector<double> add_l;
  for (int q = 0; q < m; ++q) {
    if (level[q] < 0) continue;
    const int v = skin_candidates_[q];
    const WallProjection p = surface_->project(position(v), level[q], s.projection_iterations, s.projection_tolerance_m);
    if (!p.converged && p.residual_m > 1e-5) {  // no usable wall point: stays free this call
      min_h = std::min(min_h, surface_->signedDistance(position(v)));
      continue;
    }
    add_v.push_back(v);
    add_y.push_back(p.point_m);
    add_l.push_back(level[q]);
  }
  st.min_free_skin_distance_m = min_h;
  st.contacts_released = released;
  st.contacts_added = static_cast<int>(add_v.size());
  if (!add_v.empty()) {
    const int k = static_cast<int>(add_v.size());
    const int n2 = n + k;
    rest_.conservativeResize(n2, 3);
    origin_.conservativeResize(n2, 3);
    targets_.conservativeResize(n2, 3);
    velocity_.conservativeResize(n2, 3);
    for (Eigen::VectorXd* vec : {&h0_, &area_, &weight_, &thickness_factor_, &gaussian_factor_, &thickness_m_})
      vec->conservativeResize(n2);
    held_flag_.resize(n2, 0);
    rim_level_.resize(n2, 0);
    // The median wall area of the sliding set: a contact node's share of the contact surface.
    std::vector<double> areas(area_.data(), area_.data() + num_base_);
    std::nth_element(areas.begin(), areas.begin() + areas.size() / 2, areas.end());
    const double median_area = areas.empty() ? 1e-6 : areas[areas.size() / 2];
    for (int j = 0; j < k; ++j) {
      const int i = n + j, v = add_v[j];
      nodes_.push_back(v);
      rest_.row(i) = mesh_rest_.row(v);
      origin_.row(i) = add_y[j].transpose();
      targets_.row(i) = (add_y[j] - mesh_rest_.row(v).transpose()).transpose();
      velocity_.row(i).setZero();
      h0_[i] = add_l[j];
      area_[i] = median_area;
      // Limiting weight of the touch-down point's foot on the wall.
      const WallProjection foot = surface_->project(add_y[j], 0.0, s.projection_iterations, s.projection_tolerance_m);
      gaussian_factor_[i] = s.gaussian_limit ? gaussianWeight(foot.point_m) : 1.0;
      thickness_factor_[i] = 1.0;
      thickness_m_[i] = 0.0;
      held_flag_[i] = 0;
    }
    contacts_made_ += k;
    buildGraph();
    // Thickness factor and stiffness block (when attach() measured them): the means of the node's
    // constrained neighbours.
    const bool have_k = stiffness_.size() == 9L * n;
    if (have_k) stiffness_.conservativeResize(9L * n2);
    for (int i = n; i < n2; ++i) {
      double tf = 0;
      Eigen::Matrix<double, 9, 1> kb = Eigen::Matrix<double, 9, 1>::Zero();
      int cnt = 0, kcnt = 0;
      for (int q = nbr_start_[i]; q < nbr_start_[i + 1]; ++q) {
        const int j = nbr_[q];
        if (j >= n) continue;
        tf += thickness_factor_[j];
        ++cnt;
        if (have_k) {
          kb += stiffness_.segment<9>(9L * j);
          ++kcnt;
        }
      }
      if (s.thickness_limit && cnt > 0) thickness_factor_[i] = tf / cnt;
      if (have_k) stiffness_.segment<9>(9L * i) = kcnt > 0 ? Eigen::Matrix<double, 9, 1>(kb / kcnt) : kb;
      weight_[i] = thickness_factor_[i] * gaussian_factor_[i];
    }
  }
  st.contacts = static_cast<int>(nodes_.size()) - num_base_;
  return released > 0;
}

SlidingStepStats ChestWallSliding::afterStep(StiffeningSimulation& stiff, const StiffeningStepResult& r) {
  const auto t0 = std::chrono::steady_clock::now();
  DynamicSimulator& sim = stiff.simulator();
  if (sim.numNodes() != num_mesh_nodes_)
    throw std::invalid_argument("ChestWallSliding::afterStep: the simulator has " + std::to_string(sim.numNodes()) +
                                " nodes, the mesh " + std::to_string(num_mesh_nodes_));
  const Eigen::VectorXd& u = sim.state().displacement_m;
  SlidingStepStats st;
  if (!r.advanced) {
    // The call could not advance: the state is where it started.
    const int n = static_cast<int>(nodes_.size());
    st.taken_back = true;
    if (last_moved_) {
      // The pending move is the suspect: no α saves an inversion that the targets force. Undo the
      // α escalation of the failed call (state, moduli, controller of the last accepted step) and
      // take half the move back; hold the wall once the scale is exhausted. Contact nodes are part
      // of it: their constraints were made at that same state.
      if (stiff.historySize() > 0) stiff.revertTo(0);
      move_scale_ *= 0.25;
      const bool hold = move_scale_ < settings_.min_move_scale;
      for (int i = 0; i < n; ++i) {
        const Eigen::RowVector3d now = u.segment<3>(3 * nodes_[i]).transpose();
        targets_.row(i) = hold ? now : Eigen::RowVector3d(now + 0.5 * (targets_.row(i) - now));
        st.max_move_m = std::max(st.max_move_m, (targets_.row(i) - now).norm());
      }
      velocity_.setZero();
      if (hold) {
        move_scale_ = settings_.min_move_scale;
        last_moved_ = false;
        st.held_wall = true;
      }
      base_targets_ = targets_.topRows(num_base_);
      sim.setNodeTargets(nodes_, targets_);
    }
    for (int i = 0; i < n; ++i)
      st.max_slide_m = std::max(st.max_slide_m, (rest_.row(i) + targets_.row(i) - origin_.row(i)).norm());
    st.move_scale = move_scale_;
    st.contacts = n - num_base_;
    st.min_free_skin_distance_m = std::numeric_limits<double>::quiet_NaN();
    st.seconds = since(t0);
    return st;
  }
  move_scale_ = r.reversals > 0 && last_moved_ ? std::max(settings_.min_move_scale, 0.5 * move_scale_)
                                               : std::min(1.0, 1.25 * move_scale_);
  Eigen::VectorXd load = -sim.constraintForces();
  SlidingStepStats cs;
  updateContacts(sim, load, cs);
  st = updateFromLoads(u, load, sim.params().time_step_s, move_scale_);
  st.contacts = cs.contacts;
  st.contacts_added = cs.contacts_added;
  st.contacts_released = cs.contacts_released;
  st.min_free_skin_distance_m = cs.min_free_skin_distance_m;
  last_moved_ = st.max_move_m > 0 || cs.contacts_added > 0 || cs.contacts_released > 0;
  sim.setNodeTargets(nodes_, targets_);
  st.seconds = since(t0);
  return st;
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

StiffSlidingSettleResult settleWithSlidingAndStiffening(
    StiffeningSimulation& stiff, ChestWallSliding& sliding, int max_calls, double increment_tolerance_m,
    int consecutive_steps, const std::function<void(int, const StiffeningStepResult&, const SlidingStepStats&)>& progress) {
  if (max_calls < 1) bad("settleWithSlidingAndStiffening max_calls", max_calls, "≥ 1");
  if (!(increment_tolerance_m > 0))
    bad("settleWithSlidingAndStiffening increment_tolerance_m", increment_tolerance_m, "> 0 [m]");
  if (consecutive_steps < 1) bad("settleWithSlidingAndStiffening consecutive_steps", consecutive_steps, "≥ 1");
  StiffSlidingSettleResult out;
  const auto t0 = std::chrono::steady_clock::now();
  int quiet = 0;
  while (out.calls < max_calls) {
    const StiffeningStepResult r = stiff.step();
    ++out.calls;
    const SlidingStepStats st = sliding.afterStep(stiff, r);
    out.sliding_seconds += st.seconds;
    out.take_backs += st.taken_back ? 1 : 0;
    out.max_slide_m = st.max_slide_m;
    if (progress) progress(out.calls, r, st);
    quiet = r.advanced && stiff.stats().settled && st.max_move_m <= increment_tolerance_m ? quiet + 1 : 0;
    if (quiet >= consecutive_steps) {
      out.settled = true;
      break;
    }
  }
  out.seconds = since(t0);
  return out;
}

SlidingSettleResult settleWithSliding(DynamicSimulator& sim, ChestWallSliding& sliding, int max_steps,
                                      double increment_tolerance_m, int consecutive_steps,
                                      const std::function<void(int, double, const SlidingStepStats&)>& progress) {
  if (max_steps < 1) bad("settleWithSliding max_steps", max_steps, "≥ 1");
  if (!(increment_tolerance_m > 0)) bad("settleWithSliding increment_tolerance_m", increment_tolerance_m, "> 0 [m]");
  if (consecutive_steps < 1) bad("settleWithSliding consecutive_steps", consecutive_steps, "≥ 1");
  SlidingSettleResult r;
  const auto t0 = std::chrono::steady_clock::now();
  int quiet = 0;
  Eigen::VectorXd before;
  while (r.steps < max_steps) {
    before = sim.state().displacement_m;
    sim.step();
    ++r.steps;
    const SlidingStepStats st = sliding.update(sim);
    r.sliding_seconds += st.seconds;
    r.force_seconds += st.force_seconds;
    r.last_increment_m = std::max(maxNodalNorm(sim.state().displacement_m - before), st.max_move_m);
    r.max_slide_m = st.max_slide_m;
    if (progress) progress(r.steps, r.last_increment_m, st);
    quiet = r.last_increment_m <= increment_tolerance_m ? quiet + 1 : 0;
    if (quiet >= consecutive_steps) {
      r.settled = true;
      break;
    }
  }
  r.seconds = since(t0);
  return r;
}

}  // namespace breast_sim::core
