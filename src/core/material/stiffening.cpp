#include "breast_sim/core/material/stiffening.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include <Eigen/Geometry>

#include "breast_sim/core/mesh/tet_quality.h"
#include "../util/number_text.h"
#include "../util/ordered_sum.h"
#include "breast_sim/core/thread_budget.h"

namespace breast_sim::core {

namespace {

[[noreturn]] void bad(const char* who, const char* name, double v, const char* range) {
  std::ostringstream s;
  s << who << " '" << name << "' = " << v << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

}  // namespace

// ---------------------------------------------------------------------------------------------------
void AlphaControllerParams::validate() const {
  const char* w = "alpha controller";
  if (!(min_alpha_per_pa > 0) || !std::isfinite(min_alpha_per_pa))
    bad(w, "min_alpha_per_pa", min_alpha_per_pa, "a positive finite α floor [1/Pa], e.g. 1e-7");
  if (!(max_alpha_per_pa >= min_alpha_per_pa) || !std::isfinite(max_alpha_per_pa))
    bad(w, "max_alpha_per_pa", max_alpha_per_pa, "finite and ≥ min_alpha_per_pa [1/Pa], e.g. 1e4");
  if (!(initial_alpha_per_pa >= min_alpha_per_pa && initial_alpha_per_pa <= max_alpha_per_pa))
    bad(w, "initial_alpha_per_pa", initial_alpha_per_pa, "within [min_alpha_per_pa, max_alpha_per_pa] [1/Pa], e.g. 1e-2");
  if (!(decrease_factor > 0 && decrease_factor < 1))
    bad(w, "decrease_factor", decrease_factor, "in (0, 1), e.g. 0.8");
  if (!(increase_factor > 1) || !std::isfinite(increase_factor))
    bad(w, "increase_factor", increase_factor, "> 1 and finite, e.g. 2");
  if (!(rate_halving > 0 && rate_halving < 1)) bad(w, "rate_halving", rate_halving, "in (0, 1), e.g. 0.5");
  if (!(reversal_growth >= 1) || !std::isfinite(reversal_growth))
    bad(w, "reversal_growth", reversal_growth, ">= 1 and finite (1: no growth), e.g. 2");
  if (!(min_rate >= 0 && min_rate <= 1 - decrease_factor))
    bad(w, "min_rate", min_rate, "in [0, 1 − decrease_factor], e.g. 1e-3");
}

AlphaController::AlphaController(const AlphaControllerParams& params) : params_(params) {
  params_.validate();
  restart();
}

void AlphaController::restart() { restart(params_.initial_alpha_per_pa); }

void AlphaController::restart(double alpha_per_pa) {
  if (!std::isfinite(alpha_per_pa))
    bad("alpha controller", "restart alpha_per_pa", alpha_per_pa, "a finite α [1/Pa]");
  s_ = State{};
  s_.alpha_per_pa = std::clamp(alpha_per_pa, params_.min_alpha_per_pa, params_.max_alpha_per_pa);
}

void AlphaController::recordChange(int direction) {
  if (direction == s_.runs[0]) return;  // same run
  s_.runs[2] = s_.runs[1];
  s_.runs[1] = s_.runs[0];
  s_.runs[0] = direction;
  if (s_.runs[0] == -1 && s_.runs[1] == 1 && s_.runs[2] == -1) {  // decrease, increase, decrease
    ++s_.oscillations;
    if (s_.phase == Phase::kSearch) {
      s_.phase = Phase::kSettling;
      s_.rate = std::max((1.0 - params_.decrease_factor) * params_.rate_halving, params_.min_rate);
    } else {
      s_.rate = std::max(s_.rate * params_.rate_halving, params_.min_rate);
    }
  }
}

void AlphaController::onAccepted() {
  const double f = s_.phase == Phase::kSearch ? params_.decrease_factor : 1.0 - s_.rate;
  s_.alpha_per_pa = std::max(s_.alpha_per_pa * f, params_.min_alpha_per_pa);
  recordChange(-1);
}

void AlphaController::onReversed(int attempt) {
  double f = params_.increase_factor;
  if (attempt > 1 && params_.reversal_growth > 1) f *= std::pow(params_.reversal_growth, attempt - 1);
  if (s_.phase == Phase::kSettling && attempt <= 2) {
    // Up by k ρ; a second reversal of the step by 2 k ρ before the search phase's factor. (The
    // search phase's ×2 at once, which the settling descent, × (1 − ρ) per step, takes ~700 steps to
    // undo at ρ = 1e-3, moved the skin 9 mm in one tracking frame, and the tracked lesions ended
    // 5.4 mm from where the same clouds led with one cloud fewer; ×1.01 was enough. Doubling the
    // increment on every repeated reversal instead cost 96 reverted steps of the morphing stage
    // against 6; this costs 15. docs/tracking.md, "Dropped clouds".)
    const double k = (params_.increase_factor - 1.0) / (1.0 - params_.decrease_factor);
    f = 1.0 + k * s_.rate * attempt;
  }
  s_.alpha_per_pa = std::min(s_.alpha_per_pa * f, params_.max_alpha_per_pa);
  recordChange(+1);
}

// ---------------------------------------------------------------------------------------------------
void SettleCriterion::validate() const {
  const char* w = "settle criterion";
  if (!(max_speed_mps > 0) || !std::isfinite(max_speed_mps))
    bad(w, "max_speed_mps", max_speed_mps, "a positive speed [m/s], e.g. 1e-3");
  if (!(max_relative_residual > 0) || !std::isfinite(max_relative_residual))
    bad(w, "max_relative_residual", max_relative_residual, "a positive ratio, e.g. 1e-2");
  if (consecutive_steps < 1) bad(w, "consecutive_steps", consecutive_steps, "≥ 1");
  if (!(max_modulus_excess > 0) || !std::isfinite(max_modulus_excess))
    bad(w, "max_modulus_excess", max_modulus_excess, "a positive share E_r − 1, e.g. 1e-3");
}

SettleCheck evaluateSettle(const SettleCriterion& criterion, const Eigen::VectorXd& velocity_mps,
                           const Eigen::VectorXd& elastic_force_n, const Eigen::VectorXd& external_force_n,
                           const Eigen::VectorXd& mass_kg, const Eigen::Vector3d& gravity_mps2,
                           const std::vector<char>& fixed_node) {
  const Eigen::Index n = mass_kg.size();
  if (velocity_mps.size() != 3 * n || elastic_force_n.size() != 3 * n ||
      (external_force_n.size() != 0 && external_force_n.size() != 3 * n) || static_cast<Eigen::Index>(fixed_node.size()) != n)
    throw std::invalid_argument("evaluateSettle: sizes do not match " + std::to_string(n) + " nodes");
  double vmax2 = 0.0, r2 = 0.0, l2 = 0.0;
  bool finite = true;
  for (Eigen::Index i = 0; i < n; ++i) {
    if (fixed_node[i]) continue;
    const Eigen::Vector3d v = velocity_mps.segment<3>(3 * i);
    Eigen::Vector3d load = mass_kg[i] * gravity_mps2;
    if (external_force_n.size()) load += external_force_n.segment<3>(3 * i);
    const Eigen::Vector3d res = load + elastic_force_n.segment<3>(3 * i);
    if (!v.allFinite() || !res.allFinite()) finite = false;
    vmax2 = std::max(vmax2, v.squaredNorm());
    r2 += res.squaredNorm();
    l2 += load.squaredNorm();
  }
  SettleCheck c;
  c.max_speed_mps = finite ? std::sqrt(vmax2) : std::numeric_limits<double>::quiet_NaN();
  c.relative_residual = !finite ? std::numeric_limits<double>::quiet_NaN() : l2 > 0 ? std::sqrt(r2 / l2) : std::sqrt(r2);
  c.below = finite && c.max_speed_mps < criterion.max_speed_mps && c.relative_residual < criterion.max_relative_residual;
  return c;
}

// ---------------------------------------------------------------------------------------------------
void StiffeningParams::validate() const {
  alpha.validate();
  settle.validate();
  const char* w = "stiffening";
  if (max_reversals_per_step < 1) bad(w, "max_reversals_per_step", max_reversals_per_step, "≥ 1, e.g. 10");
  if (history_size < 1) bad(w, "history_size", history_size, "≥ 1 stored states, e.g. 8");
  if (!(gravity_direction_tolerance_deg >= 0 && gravity_direction_tolerance_deg <= 180))
    bad(w, "gravity_direction_tolerance_deg", gravity_direction_tolerance_deg, "in [0, 180] degrees, e.g. 5");
  if (!(max_modulus_factor > 1) || !std::isfinite(max_modulus_factor))
    bad(w, "max_modulus_factor", max_modulus_factor, "> 1 and finite, e.g. 1e6");
}

void deformationMeasures(const TetMesh& mesh, const Eigen::VectorXd& u, double& volume_change_percent,
                         double& max_displacement_m) {
  const int nn = mesh.numNodes();
  if (u.size() != 3 * nn) throw std::invalid_argument("deformationMeasures: displacement size does not match the mesh");
  double vmax2 = 0.0;
  bool finite = true;
  for (int i = 0; i < nn; ++i) {
    const double d2 = u.segment<3>(3 * i).squaredNorm();
    if (!std::isfinite(d2)) finite = false;
    vmax2 = std::max(vmax2, d2);
  }
  max_displacement_m = finite ? std::sqrt(vmax2) : std::numeric_limits<double>::quiet_NaN();
  const Tets& T = mesh.tets();
  const double v = util::orderedSum(mesh.numTets(), true, [&](long e) {
    Eigen::Vector3d p[4];
    for (int k = 0; k < 4; ++k) p[k] = mesh.nodes().row(T(e, k)).transpose() + u.segment<3>(3 * T(e, k));
    return signedTetVolume(p[0], p[1], p[2], p[3]);
  });
  const double v0 = mesh.volume();
  volume_change_percent = 100.0 * (v - v0) / v0;
}

double admissibleStepFraction(const TetMesh& mesh, const Eigen::VectorXd& u0, const Eigen::VectorXd& u1,
                              double j_collapsed, double keep) {
  const int nn = mesh.numNodes(), nt = mesh.numTets();
  if (u0.size() != 3 * nn || u1.size() != 3 * nn)
    throw std::invalid_argument("admissibleStepFraction: displacements of " + std::to_string(u0.size()) + " and " +
                                std::to_string(u1.size()) + " DOFs for a mesh of " + std::to_string(nn) + " nodes");
  if (!(j_collapsed >= 0) || !std::isfinite(j_collapsed))
    bad("admissibleStepFraction", "j_collapsed", j_collapsed, "a finite volume ratio >= 0");
  if (!(keep > 0 && keep < 1)) bad("admissibleStepFraction", "keep", keep, "a share in (0, 1), e.g. 0.25");
  const Tets& tets = mesh.tets();
  const Points& X = mesh.nodes();
  double fraction = 1.0;
#pragma omp parallel for schedule(static) reduction(min : fraction)
  for (int e = 0; e < nt; ++e) {
    // Edge matrices at the start (a), their change over the step (b) and at rest: J(t) = det(a + t b) / det(rest).
    Eigen::Vector3d a[3], b[3], r[3];
    const int n0 = tets(e, 0);
    for (int k = 0; k < 3; ++k) {
      const int n = tets(e, k + 1);
      r[k] = (X.row(n) - X.row(n0)).transpose();
      a[k] = r[k] + u0.segment<3>(3 * n) - u0.segment<3>(3 * n0);
      b[k] = u1.segment<3>(3 * n) - u1.segment<3>(3 * n0) - (u0.segment<3>(3 * n) - u0.segment<3>(3 * n0));
    }
    const double rest = r[0].dot(r[1].cross(r[2]));
    // det(a + t b) = c0 + c1 t + c2 t² + c3 t³ (c1 = tr(adj(a) b), c2 = tr(adj(b) a)).
    const double c0 = a[0].dot(a[1].cross(a[2])) / rest;
    const double c1 = (b[0].dot(a[1].cross(a[2])) + b[1].dot(a[2].cross(a[0])) + b[2].dot(a[0].cross(a[1]))) / rest;
    const double c2 = (a[0].dot(b[1].cross(b[2])) + a[1].dot(b[2].cross(b[0])) + a[2].dot(b[0].cross(b[1]))) / rest;
    const double c3 = b[0].dot(b[1].cross(b[2])) / rest;
    if (!(c0 > j_collapsed)) continue;  // at or below the bound already: does not limit the step
    const double bound = j_collapsed + keep * (c0 - j_collapsed);
    auto below = [&](double t) { return !(c0 + t * (c1 + t * (c2 + t * c3)) >= bound); };  // NaN counts as below
    // J(t) is monotone between the roots of J'(t) = c1 + 2 c2 t + 3 c3 t²: the first of those pieces
    // of [0, 1] whose end is below the bound holds the first crossing, found by bisection.
    double ends[4];
    int count = 0;
    const double qa = 3.0 * c3, qb = 2.0 * c2, qc = c1;
    if (std::abs(qa) > 1e-14 * (std::abs(qb) + std::abs(qc))) {
      const double disc = qb * qb - 4.0 * qa * qc;
      if (disc > 0.0) {
        const double sq = std::sqrt(disc);
        const double q = -0.5 * (qb + (qb >= 0.0 ? sq : -sq));  // the stable form of the two roots
        const double roots[2] = {q / qa, q != 0.0 ? qc / q : q / qa};
        for (double t : roots)
          if (t > 0.0 && t < 1.0) ends[count++] = t;
      }
    } else if (qb != 0.0) {
      const double t = -qc / qb;
      if (t > 0.0 && t < 1.0) ends[count++] = t;
    }
    std::sort(ends, ends + count);
    ends[count++] = 1.0;
    double lo = 0.0, hi = -1.0;
    for (int i = 0; i < count; ++i) {
      if (below(ends[i])) {
        hi = ends[i];
        break;
      }
      lo = ends[i];
    }
    if (hi < 0) continue;
    while (hi - lo > 1e-9) {
      const double m = 0.5 * (lo + hi);
      (below(m) ? hi : lo) = m;
    }
    fraction = std::min(fraction, lo);
  }
  return fraction;
}

// ---------------------------------------------------------------------------------------------------
StiffeningSimulation::StiffeningSimulation(DynamicSimulator& sim, const TetMesh& mesh, const StiffeningParams& params)
    : sim_(sim), mesh_(mesh), params_(params), controller_((params.validate(), params.alpha)) {
  if (sim_.numNodes() != mesh_.numNodes())
    throw std::invalid_argument("StiffeningSimulation: the simulator has " + std::to_string(sim_.numNodes()) +
                                " nodes, the mesh " + std::to_string(mesh_.numNodes()));
  if (sim_.elements().modulusFactors().size() != mesh_.numTets())
    throw std::invalid_argument("StiffeningSimulation: the element formulation has " +
                                std::to_string(sim_.elements().modulusFactors().size()) + " elements, the mesh " +
                                std::to_string(mesh_.numTets()));
  fixed_node_.assign(mesh_.numNodes(), 0);
  element_alpha_ = Eigen::VectorXd::Zero(mesh_.numTets());
  x_ = mesh_.nodes();
  rest_volume_ = mesh_.tetVolumes();
  refreshStress();
  last_inverted_ = countInverted();
  pushHistory();
}

void StiffeningSimulation::fixNodes(const std::vector<int>& nodes) {
  sim_.fixNodes(nodes);  // validates the indices
  loadChanged();
}

bool StiffeningSimulation::setGravity(const Eigen::Vector3d& g) {
  if (!g.allFinite()) bad("stiffening", "gravity_mps2 norm", g.norm(), "finite components [m/s²]");
  const Eigen::Vector3d old = sim_.params().gravity_mps2;
  sim_.setGravity(g);
  loadChanged();
  bool changed;
  if (old.norm() == 0.0 || g.norm() == 0.0) {
    changed = (old.norm() == 0.0) != (g.norm() == 0.0);
  } else {
    const double c = std::clamp(old.normalized().dot(g.normalized()), -1.0, 1.0);
    changed = std::acos(c) * 180.0 / 3.14159265358979323846 > params_.gravity_direction_tolerance_deg;
  }
  if (changed) restartAlphaSearch();
  return changed;
}

void StiffeningSimulation::restartAlphaSearch() {
  controller_.restart();
  loadChanged();
  element_alpha_.setZero();
}

void StiffeningSimulation::loadChanged() {
  settle_run_ = 0;
  releasing_ = false;
  release_failed_ = false;
}

void StiffeningSimulation::restartAlphaSearch(double alpha_per_pa) {
  controller_.restart(alpha_per_pa);
  loadChanged();  // the local α's stay: the load is the same
}

void StiffeningSimulation::addNodalForces(const std::vector<int>& nodes, const Points& forces_n) {
  sim_.addNodalForces(nodes, forces_n);  // validates
  loadChanged();
}

void StiffeningSimulation::clearExternalForces() {
  sim_.clearExternalForces();
  loadChanged();
}

void StiffeningSimulation::refreshStress() {
  f_el_ = sim_.elasticForces();
  stressFromElements();
}

void StiffeningSimulation::stressFromElements() {
  const ElementFormulation& el = sim_.elements();
  base_stress_ = el.vonMisesStress().cwiseQuotient(el.modulusFactors());
}

void StiffeningSimulation::setModuli(const Eigen::VectorXd& stress) {
  const double a = alpha();
  const Eigen::VectorXd& current = sim_.elements().modulusFactors();
  Eigen::VectorXd& er = modulus_buffer_;  // a kept buffer: setModuli runs every step
  er.resize(stress.size());
  for (Eigen::Index e = 0; e < stress.size(); ++e) {
    const double s = std::isfinite(stress[e]) ? stress[e] : 0.0;
    er[e] = std::min(1.0 + std::max(a, element_alpha_[e]) * s, params_.max_modulus_factor);
    // A locally stiffened element keeps its largest modulus: one that followed its own lagged stress
    // would swing between a stiff and a soft state, step after step, and the shape never settles.
    if (element_alpha_[e] > a) er[e] = std::max(er[e], current[e]);
  }
  sim_.elements().setModulusFactors(er);
}

std::vector<int> StiffeningSimulation::invertedElements() {
  const Eigen::VectorXd& u = sim_.state().displacement_m;
  for (int n = 0; n < mesh_.numNodes(); ++n) x_.row(n) = mesh_.nodes().row(n) + u.segment<3>(3 * n).transpose();
  return invertedTets(mesh_.tets(), x_);
}

std::vector<int> StiffeningSimulation::invalidElements(const Eigen::VectorXd& u_start, int& recovering) {
  const double j_min = sim_.elements().collapsedVolumeRatio();  // 0: inverted elements only
  const Eigen::VectorXd& u = sim_.state().displacement_m;
  for (int n = 0; n < mesh_.numNodes(); ++n) x_.row(n) = mesh_.nodes().row(n) + u.segment<3>(3 * n).transpose();
  const Tets& tets = mesh_.tets();
  const int nt = mesh_.numTets();
  std::vector<char>& bad = invalid_flags_;  // a kept buffer: this runs after every trial step
  bad.resize(static_cast<size_t>(nt));
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    const double v = signedTetVolume(x_.row(tets(e, 0)), x_.row(tets(e, 1)), x_.row(tets(e, 2)), x_.row(tets(e, 3)));
    bad[static_cast<size_t>(e)] = !(v > j_min * rest_volume_[e]);  // NaN counts too
  }
  // The few invalid ones: were they invalid at the start too, and did they gain volume since?
  auto startVolume = [&](int e) {
    Eigen::Vector3d p[4];
    for (int k = 0; k < 4; ++k) {
      const int n = tets(e, k);
      p[k] = mesh_.nodes().row(n).transpose() + u_start.segment<3>(3 * n);
    }
    return signedTetVolume(p[0], p[1], p[2], p[3]);
  };
  std::vector<int> out;
  recovering = 0;
  for (int e = 0; e < nt; ++e) {
    if (!bad[static_cast<size_t>(e)]) continue;
    const double v0 = startVolume(e);
    const double v = signedTetVolume(x_.row(tets(e, 0)), x_.row(tets(e, 1)), x_.row(tets(e, 2)), x_.row(tets(e, 3)));
    if (!(v0 > j_min * rest_volume_[e]) && v > v0) ++recovering;  // false for NaN
    else out.push_back(e);
  }
  return out;
}

int StiffeningSimulation::countInverted() { return static_cast<int>(invertedElements().size()); }

double StiffeningSimulation::modulusExcess() const {
  const double a = alpha();
  const Eigen::VectorXd& er = sim_.elements().modulusFactors();
  double m = 0.0;
  for (Eigen::Index e = 0; e < er.size(); ++e)
    if (element_alpha_[e] <= a) m = std::max(m, er[e] - 1.0);
  return m;
}

void StiffeningSimulation::pushHistory() {
  // A full history hands its oldest entry's storage to the new one (equal sizes: no allocation).
  HistoryEntry entry;
  if (!history_.empty() && static_cast<int>(history_.size()) >= params_.history_size) {
    entry = std::move(history_.back());
    history_.pop_back();
  }
  snapshot(entry);
  history_.push_front(std::move(entry));
  while (static_cast<int>(history_.size()) > params_.history_size) history_.pop_back();
}

const StiffeningSimulation::HistoryEntry& StiffeningSimulation::history(int k) const {
  if (k < 0 || k >= historySize())
    throw std::out_of_range("history: entry " + std::to_string(k) + " is not in [0, " + std::to_string(historySize()) + ")");
  return history_[static_cast<size_t>(k)];
}

void StiffeningSimulation::snapshot(HistoryEntry& e) const {
  e.state = sim_.state();
  e.modulus_factors = sim_.elements().modulusFactors();
  e.controller = controller_.state();
  e.element_alpha = element_alpha_;
}

void StiffeningSimulation::applySnapshot(const SimulationState& state, const Eigen::VectorXd& modulus_factors,
                                         const AlphaController::State& controller,
                                         const Eigen::VectorXd& local_alpha_per_pa) {
  checkElementAlpha(local_alpha_per_pa, mesh_.numTets());
  sim_.restore(state);
  sim_.elements().setModulusFactors(modulus_factors);
  controller_.setState(controller);
  if (local_alpha_per_pa.size() == 0) element_alpha_.setZero();
  else element_alpha_ = local_alpha_per_pa;
}

void StiffeningSimulation::restoreSnapshot(const SimulationState& state, const Eigen::VectorXd& modulus_factors,
                                           const AlphaController::State& controller,
                                           const Eigen::VectorXd& local_alpha_per_pa) {
  applySnapshot(state, modulus_factors, controller, local_alpha_per_pa);
  resync();
}

void StiffeningSimulation::revertTo(int k) {
  {
    const HistoryEntry& e = history(k);  // applied before the deque changes below
    applySnapshot(e.state, e.modulus_factors, e.controller, e.element_alpha);
  }
  history_.erase(history_.begin(), history_.begin() + k);
  refreshStress();
  last_inverted_ = countInverted();
  loadChanged();
}

void StiffeningSimulation::checkElementAlpha(const Eigen::VectorXd& alpha_per_pa, Eigen::Index elements) {
  if (alpha_per_pa.size() != 0 && alpha_per_pa.size() != elements)
    throw std::invalid_argument("local alphas for " + std::to_string(alpha_per_pa.size()) + " elements, the model has " +
                                std::to_string(elements) + " (one per element, or none)");
  for (Eigen::Index e = 0; e < alpha_per_pa.size(); ++e)
    if (!(alpha_per_pa[e] >= 0.0) || !std::isfinite(alpha_per_pa[e]))
      throw std::invalid_argument("the local alpha " + util::numberText(alpha_per_pa[e]) + " /Pa at element " +
                                  std::to_string(e) + "; a local alpha is finite and >= 0");
}

void StiffeningSimulation::setElementAlpha(const Eigen::VectorXd& alpha_per_pa) {
  checkElementAlpha(alpha_per_pa, mesh_.numTets());
  if (alpha_per_pa.size() == 0) element_alpha_.setZero();
  else element_alpha_ = alpha_per_pa;
}

void StiffeningSimulation::setTracking(bool on) {
  if (tracking_ && !on) refreshStress();
  tracking_ = on;
}

void StiffeningSimulation::resync() {
  refreshStress();
  last_inverted_ = countInverted();
  history_.clear();
  pushHistory();
  loadChanged();
}

StiffeningStepResult StiffeningSimulation::step() {
  // The latest choice; the simulator's step inside takes the sample and its count stays for the rest.
  const ThreadCountScope threads(ThreadCountScope::Sample::reuse);
  const auto t0 = std::chrono::steady_clock::now();
  StiffeningStepResult r;
  const bool reversal = params_.update_moduli && params_.reversal;
  if (!reversal) {
    if (params_.update_moduli) setModuli(base_stress_);  // α stays at the initial value
    sim_.step();  // a solver failure propagates: nothing to fall back to without reversal
    r.advanced = true;
  } else {
    SimulationState& saved = step_start_;  // a kept buffer: no allocation per step
    saved = sim_.state();
    Eigen::VectorXd& stress = trial_stress_;  // the stress the trials' moduli follow (a kept buffer)
    stress = base_stress_;
    // A release in progress (one that tracking began in) keeps its own limit: its end drops the
    // local α's.
    const int max_reversals = tracking_ && !releasing_ ? std::min(params_.max_reversals_per_step, kTrackingReversals)
                                                       : params_.max_reversals_per_step;
    for (int attempt = 1;; ++attempt) {
      setModuli(stress);
      bool solved = true;
      try {
        sim_.step();
      } catch (const std::runtime_error&) {
        solved = false;  // e.g. non-finite velocities: treated like an inversion
      }
      int recovering = 0;
      std::vector<int> inverted = solved ? invalidElements(saved.displacement_m, recovering) : std::vector<int>{};
      const double j_collapsed = sim_.elements().collapsedVolumeRatio();
      if (solved && !inverted.empty() && j_collapsed > 0.0) {
        // Shortened steps (see the class comment): the share s of the increment that keeps every
        // element off the collapsed ratio, when it is large enough to be worth taking.
        const double s = admissibleStepFraction(mesh_, saved.displacement_m, sim_.state().displacement_m, j_collapsed, kStepKeep);
        if (s >= kMinStepFraction) {
          shortened_ = sim_.state();
          shortened_.displacement_m = saved.displacement_m + s * (shortened_.displacement_m - saved.displacement_m);
          shortened_.velocity_mps *= s;
          sim_.restore(shortened_);
          inverted = invalidElements(saved.displacement_m, recovering);
          if (inverted.empty()) r.step_fraction = s;
        }
      }
      if (solved && inverted.empty()) {
        if (!hold_alpha_) {
          // Releasing: α halves (see the class comment); else the controller's decrease.
          if (releasing_) release_alpha_ *= 0.5;
          else controller_.onAccepted();
        }
        r.advanced = true;
        r.recovering_elements = recovering;
        break;
      }
      if (solved) {
        // Stress at the rejected end of the trial (see the file comment); NaN entries are ignored.
        sim_.elasticForces();
        const Eigen::VectorXd& vm = sim_.elements().vonMisesStress();
        const Eigen::VectorXd& er = sim_.elements().modulusFactors();
        for (Eigen::Index e = 0; e < stress.size(); ++e) {
          const double trial = vm[e] / er[e];
          if (std::isfinite(trial) && trial > stress[e]) stress[e] = trial;
        }
      }
      sim_.restore(saved);
      ++reversed_;
      ++r.reversals;
      if ((releasing_ || tracking_) && solved) {
        // Only the inverting elements stiffen; the global α stays. An element first gets the α the
        // release started from (it was valid there; local reversals: the initial α, or twice the
        // global one when that is higher), then doubles.
        const double a = alpha();
        const double first = releasing_ ? release_start_alpha_ : std::max(2.0 * a, controller_.params().initial_alpha_per_pa);
        // Capped at the controller's ceiling: an element no α fixes (held inverted by its neighbours,
        // or at max_modulus_factor) would otherwise double without end, step after step.
        const double cap = controller_.params().max_alpha_per_pa;
        for (int e : inverted) element_alpha_[e] = std::min(element_alpha_[e] > a ? 2.0 * element_alpha_[e] : first, cap);
      } else {
        releasing_ = false;  // a failed solve: the controller's search again
        controller_.onReversed(attempt);
      }
      if (attempt >= max_reversals) {
        r.reversal_limit_hit = true;
        ++limit_hits_;
        if (releasing_) {
          // Local α's cannot keep this step valid: the release ends for this load, the controller's
          // α (valid where the shape settled) takes over, and settled becomes the shape's criterion.
          releasing_ = false;
          release_failed_ = true;
          element_alpha_.setZero();
        }
        setModuli(stress);  // the stiffest moduli tried, with the increased α, for the next call
        break;
      }
    }
  }
  // Tracking: the next step's moduli from the stress at this step's start: the elements still hold
  // the update the step began with (a shortened step restores no update, a reverted trial is
  // updated again by the repeat).
  if (tracking_ && r.advanced) stressFromElements();
  else refreshStress();
  // An accepted step with reversal was just checked: no element is inverted at this state, unless
  // one is still recovering.
  last_inverted_ = reversal && r.advanced && r.recovering_elements == 0 ? 0 : countInverted();
  if (r.advanced) {
    ++accepted_;
    // The settle check; tracking frames have no elastic forces at the end of the step and do not
    // settle. Constrained nodes and external forces as the simulator has them, however they were
    // set (through this class or on the simulator directly, e.g. sliding's moving targets). Node
    // springs (implicit sliding, wall_slip.h) are loads on their nodes like external forces
    // (without springs the external forces themselves, with them a kept buffer).
    if (!tracking_) {
      sim_.constrainedNodes(fixed_node_);
      if (!sim_.springNodes().empty()) {
        loads_ = sim_.externalForces();
        sim_.addCurrentSpringForces(loads_);
      }
      const Eigen::VectorXd& loads = sim_.springNodes().empty() ? sim_.externalForces() : loads_;
      r.settle = evaluateSettle(params_.settle, sim_.state().velocity_mps, f_el_, loads, sim_.lumpedMass(),
                                sim_.params().gravity_mps2, fixed_node_);
    }
    if (r.step_fraction < 1.0) ++shortened_steps_;
    // A shortened step, or one with a recovering element, is no settled one.
    settle_run_ = r.settle.below && r.step_fraction == 1.0 && r.recovering_elements == 0 ? settle_run_ + 1 : 0;
    // The moduli this step ran with: how far its equilibrium is from the base material's.
    excess_ = params_.update_moduli ? modulusExcess() : 0.0;
    const bool shape_settled = settle_run_ >= params_.settle.consecutive_steps;
    settled_ = shape_settled && (!reversal || release_failed_ || excess_ <= params_.settle.max_modulus_excess);
    if (shape_settled && !settled_ && reversal && !releasing_) {
      releasing_ = true;
      release_alpha_ = release_start_alpha_ = controller_.alpha();
    }
    if (settled_ && steps_to_settle_ < 0) steps_to_settle_ = accepted_;
    pushHistory();
  }
  r.inverted_elements = last_inverted_;
  r.alpha_per_pa = alpha();
  wall_ += since(t0);
  return r;
}

RunStats StiffeningSimulation::stats() const {
  RunStats s;
  s.steps = accepted_;
  s.reversed_steps = reversed_;
  s.reversal_fraction = accepted_ + reversed_ > 0 ? static_cast<double>(reversed_) / static_cast<double>(accepted_ + reversed_) : 0.0;
  s.reversal_limit_hits = limit_hits_;
  s.shortened_steps = shortened_steps_;
  s.final_alpha_per_pa = params_.update_moduli ? alpha() : 0.0;
  s.inverted_elements = last_inverted_;
  s.nan = !sim_.state().displacement_m.allFinite();
  deformationMeasures(mesh_, sim_.state().displacement_m, s.volume_change_percent, s.max_displacement_m);
  s.max_modulus_factor = sim_.elements().modulusFactors().maxCoeff();
  s.settled = settled_;
  s.steps_to_settle = steps_to_settle_;
  s.max_modulus_excess = excess_;
  s.releasing = releasing_;
  const double a = alpha();
  s.locally_stiffened_elements = static_cast<int>((element_alpha_.array() > a).count());
  if (s.locally_stiffened_elements > 0) {
    const Eigen::VectorXd v = mesh_.tetVolumes().cwiseAbs();
    const double local = (element_alpha_.array() > a).select(v.array(), 0.0).sum();
    s.locally_stiffened_volume_percent = 100.0 * local / v.sum();
  }
  s.simulated_time_s = sim_.state().time_s;
  s.wall_seconds = wall_;
  return s;
}

}  // namespace breast_sim::core
