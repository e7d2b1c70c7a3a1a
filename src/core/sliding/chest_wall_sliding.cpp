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

namespace breast_sim::core {

namespace {

double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

[[noreturn]] void bad(const char* name, double v, const char* range) {
  std::ostringstream s;
  s << "sliding '" << name << "' = " << v << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
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
}

ChestWallSliding::ChestWallSliding(const TetMesh& mesh, std::vector<int> nodes,
                                   std::shared_ptr<const ChestWallSurface> surface, const SlidingSettings& settings,
                                   const LabelImage* labels, const TissueLabels& tissue,
                                   const std::vector<Eigen::Vector3d>& nipples_m, const Eigen::Vector3d& anterior)
    : settings_(settings), surface_(std::move(surface)), nodes_(std::move(nodes)), num_mesh_nodes_(mesh.numNodes()) {
  settings_.validate();
  if (!surface_) throw std::invalid_argument("ChestWallSliding: no chest-wall surface given");
  if (nodes_.empty()) throw std::invalid_argument("ChestWallSliding: the sliding node set is empty");
  const int n = static_cast<int>(nodes_.size());
  std::vector<int> slot(mesh.numNodes(), -1);
  for (int i = 0; i < n; ++i) {
    const int v = nodes_[i];
    if (v < 0 || v >= mesh.numNodes())
      throw std::invalid_argument("ChestWallSliding: node " + std::to_string(v) + " is not in [0, " +
                                  std::to_string(mesh.numNodes()) + ")");
    if (slot[v] >= 0) throw std::invalid_argument("ChestWallSliding: node " + std::to_string(v) + " is given twice");
    slot[v] = i;
  }
  if (settings_.thickness_limit && !labels)
    throw std::invalid_argument("ChestWallSliding: the thickness limit needs the label image");
  if (settings_.gaussian_limit && (nipples_m.empty() || nipples_m.size() > 2))
    throw std::invalid_argument("ChestWallSliding: the Gaussian limit needs 1 or 2 nipple points, the case has " +
                                std::to_string(nipples_m.size()));
  if (!anterior.allFinite() || anterior.norm() < 1e-9)
    throw std::invalid_argument("ChestWallSliding: the anterior direction must be a non-zero vector");

  rest_.resize(n, 3);
  for (int i = 0; i < n; ++i) rest_.row(i) = mesh.nodes().row(nodes_[i]);
  targets_ = Points::Zero(n, 3);
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
    for (const Eigen::Vector3d& p : nipples_m)
      centres_.emplace_back((p - plane_origin_).dot(plane_u_), (p - plane_origin_).dot(plane_v_));
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
  for (size_t i = 0; i < nodes_.size(); ++i) targets_.row(i) = u.segment<3>(3 * nodes_[i]).transpose();
  velocity_.setZero();
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
  const auto t0 = std::chrono::steady_clock::now();
  const long n3 = 3L * num_mesh_nodes_;
  if (u.size() != n3 || f_el.size() != n3 || mass.size() != num_mesh_nodes_ || (f_ext && f_ext->size() != n3))
    throw std::invalid_argument("ChestWallSliding::update: vectors do not match the mesh's " +
                                std::to_string(num_mesh_nodes_) + " nodes");
  if (!(dt > 0) || !std::isfinite(dt)) bad("update dt_s", dt, "a finite time step > 0 [s]");
  const SlidingSettings& s = settings_;
  const int n = static_cast<int>(nodes_.size());
  int moving = 0, stuck = 0, capped = 0, failures = 0, limited = 0;
  const bool have_k = stiffness_.size() == 9L * n;
  double max_move = 0, max_slide = 0, max_pen = 0;
#pragma omp parallel for schedule(static) reduction(+ : moving, stuck, capped, failures, limited) \
    reduction(max : max_move, max_slide, max_pen)
  for (int i = 0; i < n; ++i) {
    const int v = nodes_[i];
    const Eigen::Vector3d X = rest_.row(i).transpose();
    const Eigen::Vector3d ui = u.segment<3>(3 * v);
    const Eigen::Vector3d x = X + ui;
    if (held_flag_[i] || !(weight_[i] > 0)) {
      targets_.row(i) = ui.transpose();
      velocity_.row(i).setZero();
      ++stuck;
      continue;
    }
    // Applied load on the node (the reaction is its negative).
    Eigen::Vector3d load = f_el.segment<3>(3 * v) + mass[v] * g;
    if (f_ext) load += f_ext->segment<3>(3 * v);
    const Eigen::Vector3d nrm = surface_->normal(x);
    if (nrm.isZero()) {
      targets_.row(i) = ui.transpose();
      ++stuck;
      continue;
    }
    const double fn = load.dot(nrm);
    const Eigen::Vector3d ft = load - fn * nrm;
    const double tau_n = std::abs(fn) / area_[i], tau_t = ft.norm() / area_[i];
    const Eigen::Vector3d v_prev = velocity_.row(i).transpose();
    const Eigen::Vector3d v_prev_t = v_prev - v_prev.dot(nrm) * nrm;
    const bool was_moving = v_prev_t.squaredNorm() > 0;
    // Force-driven move (stability-capped), plus the share of the last velocity kept (inertia).
    Eigen::Vector3d move = Eigen::Vector3d::Zero();
    if (was_moving || tau_t > s.static_friction * tau_n + s.static_threshold_pa) {
      const double drive = std::max(0.0, tau_t - s.kinetic_friction * tau_n - s.static_threshold_pa);
      if (tau_t > 0 && drive > 0) {
        double len = dt * (1.0 - s.inertia) * weight_[i] * s.mobility_m_per_pa_s * drive;
        // Stiffness of the node along its driving direction t: tᵀ K_ii t [N/m].
        const double kt = have_k ? Eigen::Map<const Eigen::Matrix3d>(&stiffness_[9 * i]).transpose()
                                       .operator*(ft / ft.norm()).dot(ft / ft.norm())
                                 : 0.0;
        if (kt > 0 && s.stiffness_safety > 0) {
          const double stable = drive * area_[i] / (s.stiffness_safety * kt);
          if (len > stable) {
            len = stable;
            ++limited;
          }
        }
        move = (len / ft.norm()) * ft;
      }
      move += dt * s.inertia * v_prev_t;
    }
    const double len = move.norm();
    if (len > s.max_step_m) move *= s.max_step_m / len;
    if (!(move.squaredNorm() > 0)) {
      targets_.row(i) = ui.transpose();
      velocity_.row(i).setZero();
      ++stuck;
      continue;
    }
    Eigen::Vector3d y = x + move;
    bool cap = false;
    if (s.max_slide_m > 0) {
      const double limit = weight_[i] * s.max_slide_m;
      const Eigen::Vector3d d = y - X;
      if (d.norm() > limit) {
        y = X + d * (limit / d.norm());
        cap = true;
      }
    }
    const WallProjection p = surface_->project(y, h0_[i], s.projection_iterations, s.projection_tolerance_m);
    if (!p.converged && p.residual_m > 1e-5) {  // keep the old constraint rather than a bad point
      targets_.row(i) = ui.transpose();
      velocity_.row(i).setZero();
      ++failures;
      continue;
    }
    const Eigen::Vector3d moved = p.point_m - x;
    targets_.row(i) = (p.point_m - X).transpose();
    velocity_.row(i) = cap ? Eigen::RowVector3d::Zero() : Eigen::RowVector3d((moved / dt).transpose());
    ++moving;
    capped += cap ? 1 : 0;
    max_move = std::max(max_move, moved.norm());
    max_slide = std::max(max_slide, (p.point_m - X).norm());
    max_pen = std::max(max_pen, -surface_->signedDistance(p.point_m));
  }
  // Slides of nodes that did not move this step count for the maximum too.
  for (int i = 0; i < n; ++i) max_slide = std::max(max_slide, targets_.row(i).norm());
  SlidingStepStats st;
  st.moving = moving;
  st.stuck = stuck;
  st.capped = capped;
  st.stiffness_limited = limited;
  st.projection_failures = failures;
  st.max_move_m = max_move;
  st.max_slide_m = max_slide;
  st.max_penetration_m = std::max(0.0, max_pen);
  st.seconds = since(t0);
  return st;
}

Points ChestWallSliding::slidingVectors() const {
  Points out = Points::Zero(num_mesh_nodes_, 3);
  for (size_t i = 0; i < nodes_.size(); ++i) out.row(nodes_[i]) = targets_.row(i);
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
