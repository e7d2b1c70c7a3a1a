#include "breast_sim/core/fem/dynamic_simulator.h"

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/solver/rank_one_sum.h"
#include "breast_sim/core/thread_budget.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace breast_sim::core {

namespace {
double since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

void addToTotals(StepTotals& t, const StepStats& st) {
  ++t.steps;
  t.iterations += st.solve.iterations;
  t.reused_matrix += st.matrix_reused;
  t.assembly_seconds += st.assembly_seconds;
  t.setup_seconds += st.setup_seconds;
  t.solve_seconds += st.solve.seconds;
  t.total_seconds += st.total_seconds;
}
}  // namespace

void DynamicsParams::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "dynamics '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(time_step_s > 0) || !std::isfinite(time_step_s)) bad("time_step_s", time_step_s, "a positive time step in s, e.g. 0.033");
  if (!(mass_damping_per_s >= 0)) bad("mass_damping_per_s", mass_damping_per_s, "≥ 0 [1/s]");
  if (!(stiffness_damping_s >= 0)) bad("stiffness_damping_s", stiffness_damping_s, "≥ 0 [s]");
  if (!gravity_mps2.allFinite()) bad("gravity_mps2", gravity_mps2.norm(), "finite components [m/s²]");
}

DynamicSimulator::DynamicSimulator(const TetMesh& mesh, std::unique_ptr<ElementFormulation> elements,
                                   const ElasticMaterial& material, const DynamicsParams& params,
                                   std::unique_ptr<LinearSolver> solver)
    : rest_(mesh.nodes()), num_nodes_(mesh.numNodes()), elements_(std::move(elements)), params_(params),
      solver_(std::move(solver)) {
  params_.validate();
  material.validate();
  if (!elements_ || !solver_) throw std::invalid_argument("DynamicSimulator: element formulation and solver are required");
  const int n3 = 3 * num_nodes_;
  mass_ = Eigen::VectorXd::Zero(num_nodes_);
  const Eigen::VectorXd vol = mesh.tetVolumes();
  for (int e = 0; e < mesh.numTets(); ++e)
    for (int i = 0; i < 4; ++i) mass_[mesh.tets()(e, i)] += 0.25 * material.density_kg_per_m3 * vol[e];
  // A node attached to no element keeps a tiny mass so the system stays regular.
  const double floor = 1e-9 * mass_.maxCoeff();
  for (int n = 0; n < num_nodes_; ++n) mass_[n] = std::max(mass_[n], floor);
  external_force_ = Eigen::VectorXd::Zero(n3);
  constrained_.assign(n3, 0);
  is_target_.assign(n3, 0);
  constraint_velocity_ = Eigen::VectorXd::Zero(n3);
  target_displacement_ = Eigen::VectorXd::Zero(n3);
  state_.displacement_m = Eigen::VectorXd::Zero(n3);
  state_.velocity_mps = Eigen::VectorXd::Zero(n3);
  // A formulation whose stiffness has a rank-one part and a solver that applies it without a
  // matrix: assemble only the compact part (fem/element_formulation.h).
  split_ = elements_->compactPattern() != nullptr && solver_->acceptsRankOneSum();
  A_ = split_ ? elements_->compactPattern()->matrix() : elements_->pattern().matrix();
  f_el_ = Eigen::VectorXd::Zero(n3);
  rhs_ = Eigen::VectorXd::Zero(n3);
  v_next_ = Eigen::VectorXd::Zero(n3);
  constraint_force_ = Eigen::VectorXd::Zero(n3);
  spring_force_ = Eigen::VectorXd::Zero(n3);
  spring_anchor_.resize(0, 3);
  spring_constant_.resize(0, 3);
  saved_start_.assign(1, 0);
  x_ = rest_;
  // Diagonal positions: columns are sorted, found once by binary search (the pattern is fixed).
  diag_pos_.resize(n3);
  const int* outer = A_.outerIndexPtr();
  const int* inner = A_.innerIndexPtr();
  for (int r = 0; r < n3; ++r)
    diag_pos_[r] = static_cast<int>(std::lower_bound(inner + outer[r], inner + outer[r + 1], r) - inner);
  if (split_) {
    free_mask_.assign(n3, 1.0);
    RankOneSum R = elements_->rankOneStiffness();
    R.free = free_mask_.data();
    rank_one_work_.assign(static_cast<size_t>(std::max(R.terms, 1)), 0.0);
    rank_one_product_ = Eigen::VectorXd::Zero(n3);
    solver_->analyzeWithRankOne(A_, R);
  } else {
    solver_->analyzePattern(A_);
  }
}

void DynamicSimulator::fixNodes(const std::vector<int>& nodes) {
  for (int n : nodes) {
    if (n < 0 || n >= num_nodes_)
      throw std::invalid_argument("fixNodes: node " + std::to_string(n) + " is not in [0, " + std::to_string(num_nodes_) + ")");
    for (int c = 0; c < 3; ++c) {
      constrained_[3 * n + c] = 1;
      is_target_[3 * n + c] = 0;
    }
  }
}

void DynamicSimulator::clearConstraints() {
  std::fill(constrained_.begin(), constrained_.end(), 0);
  std::fill(is_target_.begin(), is_target_.end(), 0);
}

void DynamicSimulator::constrainedNodes(std::vector<char>& fixed) const {
  fixed.resize(static_cast<size_t>(num_nodes_));
  for (size_t n = 0; n < fixed.size(); ++n) fixed[n] = constrained_[3 * n] || constrained_[3 * n + 1] || constrained_[3 * n + 2];
}

void DynamicSimulator::setNodeTargets(const std::vector<int>& nodes, const Points& targets_m) {
  if (static_cast<Eigen::Index>(nodes.size()) != targets_m.rows())
    throw std::invalid_argument("setNodeTargets: " + std::to_string(nodes.size()) + " nodes but " +
                                std::to_string(targets_m.rows()) + " targets");
  for (size_t i = 0; i < nodes.size(); ++i) {
    const int n = nodes[i];
    if (n < 0 || n >= num_nodes_)
      throw std::invalid_argument("setNodeTargets: node " + std::to_string(n) + " is not in [0, " + std::to_string(num_nodes_) + ")");
    if (!targets_m.row(static_cast<Eigen::Index>(i)).allFinite())
      throw std::invalid_argument("setNodeTargets: target of node " + std::to_string(n) + " is not finite");
    for (int c = 0; c < 3; ++c) {
      constrained_[3 * n + c] = 1;
      is_target_[3 * n + c] = 1;
      target_displacement_[3 * n + c] = targets_m(static_cast<Eigen::Index>(i), c);
    }
  }
}

void DynamicSimulator::addNodalForces(const std::vector<int>& nodes, const Points& forces_n) {
  if (static_cast<Eigen::Index>(nodes.size()) != forces_n.rows())
    throw std::invalid_argument("addNodalForces: " + std::to_string(nodes.size()) + " nodes but " +
                                std::to_string(forces_n.rows()) + " forces");
  for (size_t i = 0; i < nodes.size(); ++i) {
    const int n = nodes[i];
    if (n < 0 || n >= num_nodes_)
      throw std::invalid_argument("addNodalForces: node " + std::to_string(n) + " is not in [0, " + std::to_string(num_nodes_) + ")");
    for (int c = 0; c < 3; ++c) external_force_[3 * n + c] += forces_n(static_cast<Eigen::Index>(i), c);
  }
}

const Eigen::VectorXd& DynamicSimulator::elasticForces() {
  for (int n = 0; n < num_nodes_; ++n)
    x_.row(n) = rest_.row(n) + state_.displacement_m.segment<3>(3 * n).transpose();
  elements_->update(x_, f_el_);
  return f_el_;
}

StepStats DynamicSimulator::step() {
  const ThreadCountScope threads(ThreadCountScope::Sample::take);  // from the machine's load
  StepStats st;
  const auto t0 = std::chrono::steady_clock::now();
  const double dt = params_.time_step_s;
  const int n3 = 3 * num_nodes_;
  elasticForces();  // rotations at x_t and f_el(x_t)

  // A = M(1 + dt α_M) + dt(dt + α_K) K.
  double* values = A_.valuePtr();
  const int* outer = A_.outerIndexPtr();
  const int* inner = A_.innerIndexPtr();
  const double stiffness_scale = dt * (dt + params_.stiffness_damping_s);
  // Matrix reuse: the matrix (and the solver's set-up) of an earlier step, if nothing that enters
  // it changed since (the element linearisation lags by design, setMatrixReuse). What a later
  // reusing step compares with is recorded only while reuse is on.
  const bool record = matrix_reuse_ > 1;
  const bool reuse = !split_ && record && matrix_age_ > 0 && matrix_age_ < matrix_reuse_ &&
                     elim_for_ == constrained_ && dt == assembled_params_.time_step_s &&
                     params_.mass_damping_per_s == assembled_params_.mass_damping_per_s &&
                     params_.stiffness_damping_s == assembled_params_.stiffness_damping_s && springsAsAssembled();
  st.matrix_reused = reuse;
  if (!reuse) {
    matrix_age_ = 0;  // no matrix to reuse until the solver's set-up below succeeded
    if (split_) elements_->assignCompactStiffness(stiffness_scale, A_);
    else elements_->assignStiffness(stiffness_scale, A_);
  }
  const double mass_scale = 1.0 + dt * params_.mass_damping_per_s;
  const double* mass = mass_.data();
  const double* vel = state_.velocity_mps.data();
  const double* fext = external_force_.data();
  const double* fel = f_el_.data();
  const int* diag = diag_pos_.data();
  double* rhs = rhs_.data();
  const double g[3] = {params_.gravity_mps2[0], params_.gravity_mps2[1], params_.gravity_mps2[2]};
#pragma omp parallel for schedule(static)
  for (int n = 0; n < num_nodes_; ++n)
    for (int c = 0; c < 3; ++c) {
      const int r = 3 * n + c;
      if (!reuse) values[diag[r]] += mass_scale * mass[n];
      rhs[r] = mass[n] * vel[r] + dt * (fext[r] + mass[n] * g[c] + fel[r]);
    }

  // Constrained DOFs: prescribed velocity, eliminated symmetrically. The lists of what to visit
  // depend only on the constraint set; they are rebuilt when it changed since the last step.
  // Measured (bench_fem_assembly "overhead" = step assembly − update − stiffness, chest wall fixed,
  // 2 threads, minima, quiet machine): 47.5k tets 2.6–2.8 → 0.4–0.5 ms, 308k tets 8.6 → 6.2 ms;
  // whole step assembly 47.5k tets 21.0–22.3 → 13.4 ms, 308k tets 167 → 75 ms.
  if (elim_for_ != constrained_) {
    elim_for_ = constrained_;
    for (int r = 0; r < n3 && split_; ++r) free_mask_[r] = constrained_[r] ? 0.0 : 1.0;
    constrained_rows_.clear();
    elim_row_.clear();
    elim_pos_.clear();
    elim_start_.assign(1, 0);
    saved_start_.assign(1, 0);
    for (int r = 0; r < n3; ++r) {
      if (constrained_[r]) {
        constrained_rows_.push_back(r);
        saved_start_.push_back(saved_start_.back() + (outer[r + 1] - outer[r]));
        continue;
      }
      const size_t before = elim_pos_.size();
      for (int k = outer[r]; k < outer[r + 1]; ++k)
        if (constrained_[inner[k]]) elim_pos_.push_back(k);
      if (elim_pos_.size() > before) {
        elim_row_.push_back(r);
        elim_start_.push_back(static_cast<int>(elim_pos_.size()));
      }
    }
  }
  const int num_constrained = static_cast<int>(constrained_rows_.size());
  for (int q = 0; q < num_constrained; ++q) {
    const int r = constrained_rows_[q];
    constraint_velocity_[r] = is_target_[r] ? (target_displacement_[r] - state_.displacement_m[r]) / dt : 0.0;
  }
  // Node springs, implicitly: f_s(x_{t+1}) ≈ f_s(x_t) − K dt v_{t+1} gives dt² K in the matrix and
  // dt f_s(x_t) on the right-hand side. The node's own 3×3 block is contiguous in each of its rows
  // (columns sorted, the diagonal at diag_pos_).
  spring_force_.setZero(n3);
  if (!reuse && record) assembled_spring_scale_.resize(spring_nodes_.size());
  for (size_t i = 0; i < spring_nodes_.size(); ++i) {
    const int n = spring_nodes_[i];
    const Eigen::Vector3d x = rest_.row(n).transpose() + state_.displacement_m.segment<3>(3 * n);
    const Eigen::Vector3d f = -spring_k_[i] * (x - spring_anchor_.row(static_cast<Eigen::Index>(i)).transpose()) +
                              spring_constant_.row(static_cast<Eigen::Index>(i)).transpose();
    spring_force_.segment<3>(3 * n) = f;
    for (int c = 0; c < 3; ++c) {
      const int r = 3 * n + c;
      double* block = values + diag[r] - c;  // columns 3n, 3n+1, 3n+2 of row r
      if (!reuse) {
        if (record) {  // what holds the node without its spring: its smallest diagonal entry
          double& held = assembled_spring_scale_[i];
          held = c == 0 ? block[c] : std::min(held, block[c]);
        }
        for (int d = 0; d < 3; ++d) block[d] += dt * dt * spring_k_[i](c, d);
      }
      rhs[r] += dt * f[c];
    }
  }

  const double* cv = constraint_velocity_.data();
  saved_values_.resize(static_cast<size_t>(saved_start_.back()));
  saved_rhs_.resize(static_cast<size_t>(num_constrained));
  elim_values_.resize(elim_pos_.size());
  double* elim_values = elim_values_.data();
#pragma omp parallel
  {
#pragma omp for schedule(static) nowait
    for (int q = 0; q < num_constrained; ++q) {
      const int r = constrained_rows_[q];
      // The full row and right-hand side, kept for the reaction force after the solve (a reused
      // matrix keeps the rows of its assembly).
      if (!reuse) {
        std::copy(values + outer[r], values + outer[r + 1], saved_values_.data() + saved_start_[q]);
        std::fill(values + outer[r], values + outer[r + 1], 0.0);
        values[diag[r]] = 1.0;
      }
      saved_rhs_[q] = rhs[r];
      rhs[r] = cv[r];
    }
    // Move the known constrained velocities to the right-hand side and drop their columns (in
    // ascending column order, as a pass over the whole row would); the dropped values are kept for
    // the steps that reuse the matrix.
#pragma omp for schedule(static)
    for (int q = 0; q < static_cast<int>(elim_row_.size()); ++q) {
      const int r = elim_row_[q];
      double b = rhs[r];
      for (int p = elim_start_[q]; p < elim_start_[q + 1]; ++p) {
        const int k = elim_pos_[p];
        if (!reuse) {
          elim_values[p] = values[k];
          values[k] = 0.0;
        }
        b -= elim_values[p] * cv[inner[k]];
      }
      rhs[r] = b;
    }
  }
  // The rank-one part R of the stiffness (split_): the solver applies it masked to the free DOFs;
  // the known constrained velocities move its columns to the right-hand side, as above for A_.
  RankOneSum R;
  if (split_) {
    R = elements_->rankOneStiffness();
    R.scale = stiffness_scale;
    bool moving = false;
    for (int q = 0; q < num_constrained && !moving; ++q) moving = cv[constrained_rows_[q]] != 0.0;
    if (moving) {
      Eigen::VectorXd& vc = v_next_;  // scratch until the solve: the constrained velocities alone
      vc.setZero(n3);
      for (int q = 0; q < num_constrained; ++q) vc[constrained_rows_[q]] = cv[constrained_rows_[q]];
      rank_one_product_.setZero();
      addRankOneProduct(R, vc.data(), 1.0, rank_one_product_.data(), rank_one_work_.data());
      for (int r = 0; r < n3; ++r)
        if (!constrained_[r]) rhs[r] -= rank_one_product_[r];
    }
    R.free = free_mask_.data();
  }
  st.assembly_seconds = since(t0);

  const auto t1 = std::chrono::steady_clock::now();
  if (reuse) {
    ++matrix_age_;
  } else {
    if (split_) solver_->factorizeWithRankOne(A_, R);
    else solver_->factorize(A_);
    matrix_age_ = 1;
    if (record) {
      assembled_params_ = params_;
      assembled_spring_nodes_ = spring_nodes_;
      assembled_spring_k_ = spring_k_;
    }
  }
  st.setup_seconds = since(t1);
  v_next_ = state_.velocity_mps;  // warm start
  st.solve = solver_->solve(rhs_, v_next_);
  if (!v_next_.allFinite()) throw std::runtime_error("DynamicSimulator: the " + solver_->name() + " solve returned non-finite velocities");
  // A lagged linearisation can let a mode grow (an element turning fast, a spring turning): a
  // reusing step whose largest node move more than doubles the last step's is solved again with an
  // assembled matrix. Moves under a micrometre never count as growth.
  const double largest_move = record ? dt * maxNodalNorm(v_next_) : 0.0;
  if (reuse && largest_move > 2.0 * last_largest_move_ && largest_move > 1e-6) {
    matrix_age_ = 0;
    // The discarded attempt counts in the totals as a step() call of its own that did not reuse.
    st.matrix_reused = false;
    st.total_seconds = since(t0);
    addToTotals(totals_, st);
    ++totals_.resolved_assembled;
    return step();
  }
  last_largest_move_ = largest_move;
  // Reaction at each constrained DOF: the full row's residual, (A_r v − b_r) / dt [N].
  constraint_force_.setZero(n3);
  if (split_ && num_constrained > 0) {  // the rank-one part of the constrained rows, unmasked
    R.free = nullptr;
    rank_one_product_.setZero();
    addRankOneProduct(R, v_next_.data(), 1.0, rank_one_product_.data(), rank_one_work_.data());
  }
  for (int q = 0; q < num_constrained; ++q) {
    const int r = constrained_rows_[q];
    double a = -saved_rhs_[q] + (split_ ? rank_one_product_[r] : 0.0);
    const double* row = saved_values_.data() + saved_start_[q];
    for (int k = outer[r]; k < outer[r + 1]; ++k) a += row[k - outer[r]] * v_next_[inner[k]];
    constraint_force_[r] = a / dt;
  }
  state_.velocity_mps = v_next_;
  state_.displacement_m += dt * v_next_;
  state_.time_s += dt;
  ++state_.step;
  st.total_seconds = since(t0);
  addToTotals(totals_, st);
  return st;
}

void DynamicSimulator::setNodeSprings(const std::vector<int>& nodes, const std::vector<Eigen::Matrix3d>& stiffness_n_per_m,
                                      const Points& anchors_m, const Points& forces_n) {
  if (nodes.size() != stiffness_n_per_m.size() || static_cast<Eigen::Index>(nodes.size()) != anchors_m.rows() ||
      (anchors_m.rows() > 0 && anchors_m.cols() != 3) ||
      (forces_n.size() > 0 && (forces_n.rows() != anchors_m.rows() || forces_n.cols() != 3)))
    throw std::invalid_argument("setNodeSprings: " + std::to_string(nodes.size()) + " nodes, " +
                                std::to_string(stiffness_n_per_m.size()) + " stiffness blocks and " +
                                std::to_string(anchors_m.rows()) + " anchors (and " + std::to_string(forces_n.rows()) +
                                " constant forces, or none); give one of each per node");
  std::vector<char> seen(static_cast<size_t>(num_nodes_), 0);
  for (size_t i = 0; i < nodes.size(); ++i) {
    const int n = nodes[i];
    if (n < 0 || n >= num_nodes_)
      throw std::invalid_argument("setNodeSprings: node " + std::to_string(n) + " is not in [0, " + std::to_string(num_nodes_) + ")");
    if (seen[static_cast<size_t>(n)]++)
      throw std::invalid_argument("setNodeSprings: node " + std::to_string(n) + " is given twice; sum its springs into one block");
    const Eigen::Matrix3d& k = stiffness_n_per_m[i];
    if (!k.allFinite() || !anchors_m.row(static_cast<Eigen::Index>(i)).allFinite() ||
        (forces_n.size() > 0 && !forces_n.row(static_cast<Eigen::Index>(i)).allFinite()) ||
        (k - k.transpose()).cwiseAbs().maxCoeff() > 1e-9 * std::max(1.0, k.cwiseAbs().maxCoeff()))
      throw std::invalid_argument("setNodeSprings: the spring of node " + std::to_string(n) +
                                  " is not finite or not symmetric; K must be a symmetric 3x3 block [N/m]");
  }
  spring_nodes_ = nodes;
  spring_k_ = stiffness_n_per_m;
  spring_anchor_ = anchors_m;
  spring_constant_ = forces_n.size() > 0 ? forces_n : Points(Points::Zero(anchors_m.rows(), 3));
}

void DynamicSimulator::clearNodeSprings() {
  spring_nodes_.clear();
  spring_k_.clear();
  spring_anchor_.resize(0, 3);
  spring_constant_.resize(0, 3);
}

Eigen::VectorXd DynamicSimulator::currentSpringForces() const {
  Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * num_nodes_);
  addCurrentSpringForces(f);
  return f;
}

void DynamicSimulator::addCurrentSpringForces(Eigen::VectorXd& f) const {
  if (f.size() != 3 * num_nodes_)
    throw std::invalid_argument("addCurrentSpringForces: the vector has " + std::to_string(f.size()) +
                                " entries, the model 3 x " + std::to_string(num_nodes_));
  for (size_t i = 0; i < spring_nodes_.size(); ++i) {
    const int n = spring_nodes_[i];
    const Eigen::Vector3d x = rest_.row(n).transpose() + state_.displacement_m.segment<3>(3 * n);
    f.segment<3>(3 * n) += -spring_k_[i] * (x - spring_anchor_.row(static_cast<Eigen::Index>(i)).transpose()) +
                           spring_constant_.row(static_cast<Eigen::Index>(i)).transpose();
  }
}

void DynamicSimulator::restore(const SimulationState& s) {
  if (s.displacement_m.size() != 3 * num_nodes_ || s.velocity_mps.size() != 3 * num_nodes_)
    throw std::invalid_argument("restore: the state has " + std::to_string(s.displacement_m.size()) +
                                " DOFs, the model " + std::to_string(3 * num_nodes_));
  state_ = s;
  matrix_age_ = 0;
  solver_->forgetSolutions();  // the steps after a restore depend on the state alone
}

bool DynamicSimulator::springsAsAssembled() const {
  // A spring block may differ from the one in the reused matrix (a wall spring turning with the
  // wall as its node moves) while dt² ‖ΔK‖ (Frobenius) stays within this share of the smallest
  // diagonal entry its node has without the spring (mass and tissue): the difference acts as an
  // explicit spring. Measured in tracking frames: a wall spring lagged by 1.26 times that entry
  // doubled the largest move every frame (6.6 mm after six frames); the frames' own drift is about
  // 1e-9 of it. A spring added or removed always assembles.
  constexpr double kDrift = 0.05;
  if (spring_nodes_ != assembled_spring_nodes_) return false;
  const double dt2 = params_.time_step_s * params_.time_step_s;
  for (size_t i = 0; i < spring_k_.size(); ++i)
    if (!(dt2 * (spring_k_[i] - assembled_spring_k_[i]).norm() <= kDrift * assembled_spring_scale_[i])) return false;
  return true;
}

void DynamicSimulator::setMatrixReuse(int steps) {
  if (steps < 1)
    throw std::invalid_argument("setMatrixReuse: " + std::to_string(steps) +
                                " steps per assembly; give at least 1 (1 = assemble every step)");
  if (steps != matrix_reuse_) matrix_age_ = 0;  // the next step assembles and records what reuse compares
  matrix_reuse_ = steps;
}

Points DynamicSimulator::displacement() const {
  return Eigen::Map<const Points>(state_.displacement_m.data(), num_nodes_, 3);
}

}  // namespace breast_sim::core
