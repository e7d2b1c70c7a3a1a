// The unloaded reference shape by a fixed-point iteration with Anderson mixing (unloaded_state.h,
// docs/unloaded_state.md).
#include "breast_sim/core/fem/unloaded_state.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <limits>
#include <memory>
#include <sstream>
#include <stdexcept>

#include <Eigen/QR>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/mesh/tet_quality.h"

namespace breast_sim::core {

namespace {

// Anderson mixing over this many previous steps (docs/unloaded_state.md, "Acceleration").
constexpr int kAndersonDepth = 5;
// A stiffened forward settle gives up after this many calls in a row that could not advance (each
// already reverted max_reversals_per_step times), as the pipeline's gravity stage does.
constexpr int kMaxStuckCalls = 5;
// The forward settles stop at an increment of at most this share of the iteration's tolerance
// (docs/unloaded_state.md, "Forward settles").
constexpr double kSettleToleranceShare = 0.25;
// A plain step that folds elements is halved down to this share of the residual before giving up.
constexpr double kMinStepFraction = 1.0 / 64.0;

[[noreturn]] void bad(const std::string& field, double value, const std::string& range) {
  std::ostringstream s;
  s << "recoverUnloadedShape: " << field << " = " << value << " is invalid: expected " << range;
  throw std::invalid_argument(s.str());
}

std::string mm(double m) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g mm", m * 1e3);
  return buf;
}

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Largest and mean nodal norm of a 3N vector.
void nodalNorms(const Eigen::VectorXd& v, double& max_m, double& mean_m) {
  max_m = 0.0;
  double sum = 0.0;
  const Eigen::Index n = v.size() / 3;
  for (Eigen::Index i = 0; i < n; ++i) {
    const double a = v.segment<3>(3 * i).norm();
    max_m = std::max(max_m, a);
    sum += a;
  }
  mean_m = n > 0 ? sum / static_cast<double>(n) : 0.0;
}

Eigen::VectorXd flat(const Points& p) { return Eigen::Map<const Eigen::VectorXd>(p.data(), p.size()); }
Points unflat(const Eigen::VectorXd& v) { return Eigen::Map<const Points>(v.data(), v.size() / 3, 3); }

// Anderson mixing (type II, Walker & Ni 2011) of the fixed-point map G(X) = X + f(X),
// f(X) = x_loaded − x(X), with mixing share β ≤ 1: X_{k+1} = X_k + β f_k − (ΔX + β ΔF) γ,
// γ = argmin ‖f_k − ΔF γ‖.
class Anderson {
 public:
  explicit Anderson(int depth) : depth_(depth) {}
  void reset() {
    dx_.clear();
    df_.clear();
    has_last_ = false;
  }
  // The next iterate from (x, f); records the step from the last call.
  Eigen::VectorXd next(const Eigen::VectorXd& x, const Eigen::VectorXd& f, bool& accelerated, double beta = 1.0) {
    if (has_last_) {
      dx_.push_back(x - last_x_);
      df_.push_back(f - last_f_);
      if (static_cast<int>(dx_.size()) > depth_) {
        dx_.pop_front();
        df_.pop_front();
      }
    }
    last_x_ = x;
    last_f_ = f;
    has_last_ = true;
    accelerated = false;
    if (dx_.empty() || depth_ == 0) return x + beta * f;
    const int m = static_cast<int>(dx_.size());
    Eigen::MatrixXd F(x.size(), m), X(x.size(), m);
    for (int j = 0; j < m; ++j) {
      F.col(j) = df_[static_cast<size_t>(j)];
      X.col(j) = dx_[static_cast<size_t>(j)];
    }
    const Eigen::VectorXd gamma = F.colPivHouseholderQr().solve(f);
    if (!gamma.allFinite()) return x + beta * f;
    accelerated = true;
    return x + beta * f - (X + beta * F) * gamma;
  }

 private:
  int depth_;
  std::deque<Eigen::VectorXd> dx_, df_;
  Eigen::VectorXd last_x_, last_f_;
  bool has_last_ = false;
};

}  // namespace

void UnloadedStateOptions::validate() const {
  if (max_iterations < 1) bad("max_iterations", max_iterations, "at least 1");
  if (!(tolerance_m > 0.0) || !std::isfinite(tolerance_m)) bad("tolerance_m", tolerance_m, "a finite length > 0 [m]");
  if (max_growing_iterations < 1) bad("max_growing_iterations", max_growing_iterations, "at least 1");
  try {
    stiffening.validate();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("recoverUnloadedShape: stiffening: ") + e.what());
  }
}

TetMesh withNodes(const TetMesh& mesh, const Points& nodes_m) {
  if (nodes_m.rows() != mesh.numNodes())
    throw std::invalid_argument("withNodes: " + std::to_string(nodes_m.rows()) + " node rows for a mesh of " +
                                std::to_string(mesh.numNodes()) + " nodes");
  // TetMesh would silently turn an inverted element over: refuse it here.
  const std::vector<int> inv = invertedTets(mesh.tets(), nodes_m);
  if (!inv.empty())
    throw std::invalid_argument("withNodes: " + std::to_string(inv.size()) + " elements are inverted or degenerate at the " +
                                "given nodes (the first: element " + std::to_string(inv.front()) + ")");
  TetMesh out(nodes_m, mesh.tets(), mesh.regionLabels());
  for (const auto& [name, nodes] : mesh.nodeSets()) out.setNodeSet(name, nodes);
  return out;
}

GravityLoading loadWithGravity(const TetMesh& rest, const SimulationSettings& settings,
                               const Eigen::Vector3d& gravity_mps2, const StiffeningParams& stiffening,
                               const Points& initial_displacement_m, std::vector<TetMesh> coarse_meshes,
                               const Points& meshed_nodes_m) {
  const auto t0 = Clock::now();
  if (initial_displacement_m.size() > 0 && initial_displacement_m.rows() != rest.numNodes())
    throw std::invalid_argument("loadWithGravity: initial_displacement_m has " +
                                std::to_string(initial_displacement_m.rows()) + " rows for a mesh of " +
                                std::to_string(rest.numNodes()) + " nodes");
  GravityLoading out;
  SimulationSettings s = settings;
  s.dynamics.gravity_mps2 = gravity_mps2;
  const SettleOptions& so = s.settle;
  SimulatorBuild b = buildSimulator(rest, s, std::move(coarse_meshes), meshed_nodes_m);
  DynamicSimulator& sim = *b.simulator;
  const bool displaced = initial_displacement_m.size() > 0 && initial_displacement_m.cwiseAbs().maxCoeff() > 0.0;
  if (displaced) {
    SimulationState st = sim.state();
    st.displacement_m = flat(initial_displacement_m);
    st.velocity_mps.setZero();
    sim.restore(st);
  }
  auto finish = [&](std::string why) {
    out.failure = std::move(why);
    out.seconds = since(t0);
    return out;
  };
  try {
    if (!s.stiffening) {
      const SettleResult r = settle(sim, so);
      out.steps = r.steps;
      out.displacement_m = sim.displacement();
      if (!r.settled)
        return finish("the loading did not settle in " + std::to_string(r.steps) + " steps (last increment " +
                      mm(r.last_increment_m) + ")");
    } else {
      DynamicsParams p = sim.params();
      p.time_step_s = so.time_step_s > 0 ? so.time_step_s : s.dynamics.time_step_s;
      sim.setParams(p);
      StiffeningSimulation stiff(sim, rest, stiffening);
      stiff.setGravity(gravity_mps2);
      // The α search starts at its floor and rises only where a step would invert: the initial α
      // would first lift the tissue by stiffening it (from rest: 21 steps instead of 6 on the 2.2k
      // phantom; near the equilibrium, where later loadings start, it would undo the start).
      stiff.restartAlphaSearch(stiffening.alpha.min_alpha_per_pa);
      Eigen::VectorXd previous = sim.state().displacement_m;
      long calls = 0;
      int quiet = 0, stuck = 0;
      bool settled = false;
      double last = 0.0;
      while (out.steps < so.max_steps && calls < 2L * so.max_steps) {
        ++calls;
        const StiffeningStepResult r = stiff.step();
        if (!r.advanced) {
          if (++stuck >= kMaxStuckCalls) {
            out.displacement_m = sim.displacement();
            out.inverted_elements = r.inverted_elements;
            return finish("the stiffened loading could not advance (" + std::to_string(stuck) +
                          " calls in a row reverted " + std::to_string(stiffening.max_reversals_per_step) +
                          " times) after " + std::to_string(out.steps) + " steps");
          }
          continue;
        }
        stuck = 0;
        ++out.steps;
        const Eigen::VectorXd& u = sim.state().displacement_m;
        last = maxNodalNorm(u - previous);
        previous = u;
        quiet = last <= so.increment_tolerance_m ? quiet + 1 : 0;
        if (stiff.settled() && quiet >= so.consecutive_steps) {
          settled = true;
          break;
        }
      }
      out.displacement_m = sim.displacement();
      if (!settled) {
        std::ostringstream m;
        m << "the stiffened loading did not settle in " << out.steps << " steps (last increment " << mm(last)
          << ", modulus excess " << stiff.stats().max_modulus_excess << ")";
        return finish(m.str());
      }
      const RunStats st = stiff.stats();
      if (st.max_modulus_excess > stiff.params().settle.max_modulus_excess) {
        // Settled only with the material stiffened (elements would invert at the base material's
        // equilibrium): not the loading of this material.
        std::ostringstream m;
        m << "the stiffened loading settled only with the material stiffened by up to E_r - 1 = "
          << st.max_modulus_excess << " (elements invert at the base material's equilibrium)";
        return finish(m.str());
      }
    }
  } catch (const std::runtime_error& e) {
    out.displacement_m = Points();
    return finish(std::string("the loading failed: ") + e.what());
  }
  if (!out.displacement_m.allFinite()) return finish("the loading gave a non-finite displacement");
  out.inverted_elements = static_cast<int>(invertedTets(rest.tets(), rest.nodes() + out.displacement_m).size());
  if (out.inverted_elements > 0)
    return finish("the loading inverts " + std::to_string(out.inverted_elements) + " elements");
  out.settled = true;
  out.seconds = since(t0);
  return out;
}

UnloadedStateResult recoverUnloadedShape(const TetMesh& loaded, const SimulationSettings& settings,
                                         const Eigen::Vector3d& gravity_mps2, const UnloadedStateOptions& options) {
  const auto t0 = Clock::now();
  if (!gravity_mps2.allFinite())
    bad("gravity_mps2 norm", gravity_mps2.norm(), "finite components [m/s²]");
  options.validate();
  SimulationSettings s = settings;
  s.dynamics.gravity_mps2 = gravity_mps2;
  s.validate();
  const bool multigrid = s.solver.kind == SolverSettings::Kind::kMultigrid;
  if (multigrid && options.coarse_meshes.empty())
    throw std::invalid_argument(
        "recoverUnloadedShape: solver 'multigrid' needs the coarse levels of the loaded shape "
        "(UnloadedStateOptions::coarse_meshes): give them, or choose 'aggregation' or 'cholmod'");
  if (!multigrid && !options.coarse_meshes.empty())
    throw std::invalid_argument("recoverUnloadedShape: " + std::to_string(options.coarse_meshes.size()) +
                                " coarse meshes given for a solver other than 'multigrid'");
  if (!s.fixed_node_set.empty() && !loaded.hasNodeSet(s.fixed_node_set)) {
    throw std::invalid_argument("recoverUnloadedShape: fixed_node_set '" + s.fixed_node_set +
                                "' is not a node set of the mesh" + loaded.nodeSetHint(s.fixed_node_set));
  }
  const int n = loaded.numNodes();
  const Eigen::VectorXd target = flat(loaded.nodes());
  std::vector<char> fixed(static_cast<size_t>(n), 0);
  if (!s.fixed_node_set.empty())
    for (int i : loaded.nodeSet(s.fixed_node_set)) fixed[static_cast<size_t>(i)] = 1;
  auto holdFixed = [&](Eigen::VectorXd& x) {
    for (int i = 0; i < n; ++i)
      if (fixed[static_cast<size_t>(i)]) x.segment<3>(3 * i) = target.segment<3>(3 * i);
  };

  Eigen::VectorXd x0 = target;
  if (options.initial_unloaded_nodes_m.size() > 0) {
    if (options.initial_unloaded_nodes_m.rows() != n)
      bad("initial_unloaded_nodes_m rows", static_cast<double>(options.initial_unloaded_nodes_m.rows()),
          std::to_string(n) + " (the mesh's nodes) or 0");
    x0 = flat(options.initial_unloaded_nodes_m);
    if (!x0.allFinite()) bad("initial_unloaded_nodes_m", std::numeric_limits<double>::quiet_NaN(), "finite positions [m]");
    holdFixed(x0);
    const size_t inv = invertedTets(loaded.tets(), unflat(x0)).size();
    if (inv > 0) bad("initial_unloaded_nodes_m inverted elements", static_cast<double>(inv), "0");
  }

  // The forward settles: at least as tight as the iteration's tolerance.
  SimulationSettings forward = s;
  forward.settle.increment_tolerance_m =
      std::min(s.settle.increment_tolerance_m, kSettleToleranceShare * options.tolerance_m);

  UnloadedStateResult res;
  res.unloaded_nodes_m = unflat(x0);
  double best = std::numeric_limits<double>::infinity();
  Eigen::VectorXd best_x0 = x0, best_f;  // the best X0 so far and its −residual
  int growing = 0;                        // loadings in a row that found no better X0
  double mixing = 1.0;                    // the share β of f in the next step (Anderson::next)
  Anderson anderson(kAndersonDepth);
  bool accelerated = false;
  double step = 1.0;  // the share of the plain step that gave x0
  auto fail = [&](int k, const std::string& why) {
    res.failure = "iteration " + std::to_string(k) + ": " + why;
    res.seconds = since(t0);
    return res;
  };

  for (int k = 1; k <= options.max_iterations; ++k) {
    res.iterations = k;
    const TetMesh rest = withNodes(loaded, unflat(x0));  // x0 was checked for inverted elements
    // The multigrid's levels mesh the loaded shape's domain: its prolongations are the loaded shape's.
    const GravityLoading l = loadWithGravity(rest, forward, gravity_mps2, options.stiffening, unflat(target - x0),
                                             options.coarse_meshes, multigrid ? loaded.nodes() : Points());
    if (!l.settled) {
      res.inverted_elements = l.inverted_elements;
      return fail(k, "the forward " + l.failure.substr(4));  // "the loading …" → "the forward loading …"
    }
    const Eigen::VectorXd u = flat(l.displacement_m);
    Eigen::VectorXd f = target - (x0 + u);  // −residual
    UnloadedIteration it;
    nodalNorms(f, it.max_residual_m, it.mean_residual_m);
    it.settle_steps = l.steps;
    it.seconds = l.seconds;
    it.accelerated = accelerated;
    it.step_fraction = step;
    res.history.push_back(it);
    const bool better = it.max_residual_m < best;
    if (better) {
      best = it.max_residual_m;
      best_x0 = x0;
      best_f = f;
      res.unloaded_nodes_m = unflat(x0);
      res.reloaded_nodes_m = unflat(x0 + u);
      res.max_residual_m = it.max_residual_m;
      res.mean_residual_m = it.mean_residual_m;
    }
    if (it.max_residual_m <= options.tolerance_m) {
      res.converged = true;
      res.seconds = since(t0);
      return res;
    }
    growing = better ? 0 : growing + 1;
    if (growing >= options.max_growing_iterations)
      return fail(k, "no better shape in " + std::to_string(growing) + " loadings in a row (the last re-loads to " +
                         mm(it.max_residual_m) + ", the best to " + mm(best) + ")");
    if (!better && !it.accelerated && it.step_fraction <= kMinStepFraction)
      return fail(k, "no better shape with the step from the best one shortened to " + std::to_string(it.step_fraction) +
                         " of its residual (the last re-loads to " + mm(it.max_residual_m) + ", the best to " +
                         mm(best) + ")");
    if (k == options.max_iterations) break;
    Eigen::VectorXd next;
    double plain = 1.0;  // the share of the plain step the fallback below starts from
    if (better) {
      next = anderson.next(x0, f, accelerated, mixing);
      plain = mixing;
    } else {
      // A step that made things worse: back to the best X0, whose plain step is shortened by half
      // per loading in a row that found none better (where a few nodes' fixed-point map does not
      // contract, the full step overshoots them), and the mixing starts again from there with the
      // shortened share of f for its mixing steps (on four soft samples of the VICTRE image's
      // lesion ensemble 14–22 loadings; 18–24 with full mixing steps after the step back).
      anderson.reset();
      anderson.next(best_x0, best_f, accelerated);  // records the best as the start of the new history
      accelerated = false;
      // Every step starts at the best X0: after a plain one (shortened where it would invert
      // elements), a shorter one, or it would load the same X0 again.
      plain = std::ldexp(1.0, -growing);
      if (!it.accelerated) plain = std::min(plain, 0.5 * it.step_fraction);
      plain = std::max(plain, kMinStepFraction);
      mixing = std::min(mixing, plain);
      x0 = best_x0;
      f = best_f;
      next = x0 + plain * f;
    }
    holdFixed(next);
    // A candidate must leave every element valid.
    auto invertedAt = [&](const Eigen::VectorXd& x) { return invertedTets(loaded.tets(), unflat(x)).size(); };
    size_t inv = invertedAt(next);
    step = plain;
    if (inv > 0) {
      // The step folds elements: take the plain step, shortened until none folds, and start the
      // mixing again from here (the shortened step is a valid secant pair for it).
      anderson.reset();
      anderson.next(x0, f, accelerated);  // records (x0, f) as the start of the new history
      accelerated = false;
      while (true) {
        next = x0 + step * f;
        holdFixed(next);
        inv = invertedAt(next);
        if (inv == 0 || step <= kMinStepFraction) break;
        step *= 0.5;
      }
    }
    if (inv > 0) {
      res.inverted_elements = static_cast<int>(inv);
      std::ostringstream m;
      m << "the next unloaded shape would have " << inv << " inverted elements, even with the step shortened to "
        << step << " of the residual";
      return fail(k, m.str());
    }
    x0 = next;
  }
  return fail(res.iterations, "not converged in " + std::to_string(res.iterations) + " iterations: largest residual " +
                                  mm(res.history.empty() ? 0.0 : res.history.back().max_residual_m) +
                                  " (smallest " + mm(best) + ") > tolerance " + mm(options.tolerance_m));
}

}  // namespace breast_sim::core
