#include "breast_sim/core/fem/anp_tet_fem.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <memory>
#include <mutex>
#include <string>

#include <Eigen/Dense>

namespace breast_sim::core {

namespace {

/// Adds the 3×3 block u bᵀ at column `col` of a node's three rows.
inline void addOuter(double* row0, double* row1, double* row2, int col, double u0, double u1, double u2, const double* b) {
  const double b0 = b[0], b1 = b[1], b2 = b[2];
  row0[col] += u0 * b0, row0[col + 1] += u0 * b1, row0[col + 2] += u0 * b2;
  row1[col] += u1 * b0, row1[col + 1] += u1 * b1, row1[col + 2] += u1 * b2;
  row2[col] += u2 * b0, row2[col + 1] += u2 * b1, row2[col + 2] += u2 * b2;
}

}  // namespace

AnpTetFem::AnpTetFem(const TetMesh& mesh, const ElasticMaterial& material)
    : deviatoric_(mesh, material, /*pattern_rings=*/1), tets_(mesh.tets()) {
  deviatoric_.setVolumeTerm(CorotatedTetFem::VolumeTerm::kNone);
  kappa_ = material.lameLambda() + 2.0 * material.lameMu() / 3.0;
  const int nt = mesh.numTets(), nn = mesh.numNodes();
  const Points& rest = mesh.nodes();
  grads_.resize(12 * static_cast<size_t>(nt));
  volumes_.resize(nt);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    volumes_[e] = restShapeGradients(rest, tets_, e, &grads_[12 * static_cast<size_t>(e)]);
  }
  // Star weights w_ne and nodal rest volumes V̂_n.
  nodal_rest_volume_ = Eigen::VectorXd::Zero(nn);
  star_weight_.resize(star_.incidentStart(nn));
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n) {
    double sum = 0.0;
    for (int k = star_.incidentStart(n); k < star_.incidentStart(n + 1); ++k) sum += volumes_[star_.incidentElement(k)];
    for (int k = star_.incidentStart(n); k < star_.incidentStart(n + 1); ++k)
      star_weight_[k] = volumes_[star_.incidentElement(k)] / sum;
    nodal_rest_volume_[n] = sum / 4.0;
  }
  nodal_volume_ratio_ = Eigen::VectorXd::Ones(nn);
  nodal_pressure_ = Eigen::VectorXd::Zero(nn);
  nodal_stiffness_ = Eigen::VectorXd::Zero(nn);
  volume_ratio_.assign(nt, 1.0);
  dJ_.assign(12 * static_cast<size_t>(nt), 0.0);
  elem_forces_.assign(12 * static_cast<size_t>(nt), 0.0);
  element_stiffness_.assign(nt, 0.0);
  const int num_star = star_.neighbourStart(nn);
  b_.assign(3 * static_cast<size_t>(num_star), 0.0);
  // For row node a and each n in a's star (entry k): a's slot in n's star.
  own_slot_.resize(num_star);
  own_entry_.resize(num_star);
#pragma omp parallel for schedule(dynamic, 256)
  for (int a = 0; a < nn; ++a)
    for (int k = star_.neighbourStart(a); k < star_.neighbourStart(a + 1); ++k) {
      const int n = star_.neighbour(k);
      const int* const s_begin = star_.neighbourData() + star_.neighbourStart(n);
      const int* const s_end = star_.neighbourData() + star_.neighbourStart(n + 1);
      own_slot_[k] = static_cast<int>(std::lower_bound(s_begin, s_end, a) - s_begin);
      own_entry_[k] = star_.neighbourStart(n) + own_slot_[k];
    }
  updateStiffnessWeights();
}

const AnpTetFem::Wide& AnpTetFem::wide() const {
  std::call_once(wide_once_, [this] {
    auto w = std::make_unique<Wide>();
    w->pattern = BlockPattern(tets_, star_.numNodes(), 2);
    const BlockPattern& wide = w->pattern;
    const int nn = star_.numNodes(), num_star = star_.neighbourStart(nn);
    // For row node a and each n in a's star (entry k): n's two-ring slot in a's rows, and the
    // two-ring slots (in a's rows) of n's star nodes.
    w->narrow_to_wide.resize(num_star);
    w->wide_offset.assign(num_star + 1, 0);
    for (int a = 0; a < nn; ++a)
      for (int k = star_.neighbourStart(a); k < star_.neighbourStart(a + 1); ++k) {
        const int n = star_.neighbour(k);
        w->wide_offset[k + 1] = w->wide_offset[k] + (star_.neighbourStart(n + 1) - star_.neighbourStart(n));
      }
    w->wide_slot.resize(w->wide_offset[num_star]);
#pragma omp parallel for schedule(dynamic, 256)
    for (int a = 0; a < nn; ++a) {
      const int* const row_begin = wide.neighbourData() + wide.neighbourStart(a);
      const int* const row_end = wide.neighbourData() + wide.neighbourStart(a + 1);
      for (int k = star_.neighbourStart(a); k < star_.neighbourStart(a + 1); ++k) {
        const int n = star_.neighbour(k);
        const int* const s_begin = star_.neighbourData() + star_.neighbourStart(n);
        const int* const s_end = star_.neighbourData() + star_.neighbourStart(n + 1);
        w->narrow_to_wide[k] = static_cast<int>(std::lower_bound(row_begin, row_end, n) - row_begin);
        int* out = &w->wide_slot[w->wide_offset[k]];
        for (const int* m = s_begin; m != s_end; ++m) *out++ = static_cast<int>(std::lower_bound(row_begin, row_end, *m) - row_begin);
      }
    }
    w->narrow = star_.matrix();
    wide_ = std::move(w);
  });
  return *wide_;
}

void AnpTetFem::updateStiffnessWeights() {
  const Eigen::VectorXd& er = deviatoric_.modulusFactors();
  const Eigen::VectorXd& be = deviatoric_.baseModulusScales();
  const int nn = star_.numNodes();
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n) {
    double s = 0.0;
    for (int k = star_.incidentStart(n); k < star_.incidentStart(n + 1); ++k) {
      const int e = star_.incidentElement(k);
      s += star_weight_[k] * er[e] * be[e];
    }
    nodal_stiffness_[n] = nodalWeight(n, s);
  }
  const int nt = static_cast<int>(tets_.rows());
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e)
    element_stiffness_[e] = elementWeight(e, er[e] * be[e], volume_ratio_[e]);
}

void AnpTetFem::setElementVolumeFraction(double beta) {
  if (!(beta >= 0.0 && beta <= 1.0))
    throw std::invalid_argument("AnpTetFem: element volume fraction " + std::to_string(beta) +
                                " is outside [0, 1] (0 = pure average nodal pressure)");
  beta_ = beta;
  updateStiffnessWeights();
}

void AnpTetFem::setInversionBarrier(double volume_ratio, double stiffness_factor) {
  if (!(volume_ratio >= 0.0 && volume_ratio < 1.0))
    throw std::invalid_argument("AnpTetFem: inversion barrier at volume ratio " + std::to_string(volume_ratio) +
                                " is outside [0, 1) (0 = off; e.g. 0.3: an element resists compression below 30 % of its volume)");
  if (!(stiffness_factor > 0.0) || !std::isfinite(stiffness_factor))
    throw std::invalid_argument("AnpTetFem: inversion barrier stiffness factor " + std::to_string(stiffness_factor) +
                                " must be positive and finite (a multiple of the bulk modulus, e.g. 100)");
  barrier_j_ = volume_ratio;
  barrier_c_ = stiffness_factor;
  updateStiffnessWeights();
}

void AnpTetFem::setModulusFactors(const Eigen::VectorXd& factors) {
  deviatoric_.setModulusFactors(factors);
  updateStiffnessWeights();
}

void AnpTetFem::setElementYoungsModuli(const Eigen::VectorXd& youngs_modulus_pa) {
  deviatoric_.setElementYoungsModuli(youngs_modulus_pa);
  updateStiffnessWeights();
}

void AnpTetFem::update(const Points& x, Eigen::VectorXd& f) {
  deviatoric_.update(x, f);
  const int nt = static_cast<int>(tets_.rows()), nn = star_.numNodes();
  // J_e and ∂J_e/∂x_i = cof F ∇N_i per element.
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    const double* g = &grads_[12 * static_cast<size_t>(e)];
    double F[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};  // column-major: F(r, c) = F[r + 3c] = Σ_i x_i,r ∇N_i,c
    for (int i = 0; i < 4; ++i) {
      const int node = tets_(e, i);
      for (int c = 0; c < 3; ++c)
        for (int r = 0; r < 3; ++r) F[r + 3 * c] += x(node, r) * g[3 * i + c];
    }
    // cof F: columns are cross products of F's columns (cof(:,0) = F1 × F2, …).
    const double cof[9] = {F[4] * F[8] - F[5] * F[7], F[5] * F[6] - F[3] * F[8], F[3] * F[7] - F[4] * F[6],
                           F[7] * F[2] - F[8] * F[1], F[8] * F[0] - F[6] * F[2], F[6] * F[1] - F[7] * F[0],
                           F[1] * F[5] - F[2] * F[4], F[2] * F[3] - F[0] * F[5], F[0] * F[4] - F[1] * F[3]};
    volume_ratio_[e] = F[0] * cof[0] + F[1] * cof[1] + F[2] * cof[2];
    double* d = &dJ_[12 * static_cast<size_t>(e)];
    for (int i = 0; i < 4; ++i)
      for (int r = 0; r < 3; ++r)
        d[3 * i + r] = cof[r] * g[3 * i] + cof[r + 3] * g[3 * i + 1] + cof[r + 6] * g[3 * i + 2];
  }
  // Nodal volume ratios, pressures and the stiffness weights.
  const Eigen::VectorXd& er = deviatoric_.modulusFactors();
  const Eigen::VectorXd& be = deviatoric_.baseModulusScales();
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n) {
    double j = 0.0, s = 0.0;
    const int k0 = star_.incidentStart(n), k1 = star_.incidentStart(n + 1);
    for (int k = k0; k < k1; ++k) {
      const int e = star_.incidentElement(k);
      j += star_weight_[k] * volume_ratio_[e];
      s += star_weight_[k] * er[e] * be[e];
    }
    if (k0 == k1) j = 1.0;
    nodal_volume_ratio_[n] = j;
    nodal_pressure_[n] = (1.0 - beta_) * kappa_ * s * (j - 1.0);
    nodal_stiffness_[n] = nodalWeight(n, s);
  }
  // Element forces −V_e (p̄_e + β κ_e (J_e − 1) − c κ_e (J_b − J_e)₊) ∂J_e/∂x_i, and the weight
  // of each element's own Gauss–Newton term, κ_e V_e (β + c [J_e < J_b]).
  const double jb = barrier_j_, cb = barrier_c_;  // the barrier force below; its stiffness is elementWeight()
  int barrier_active = 0;
#pragma omp parallel for schedule(static) reduction(+ : barrier_active)
  for (int e = 0; e < nt; ++e) {
    const double pbar = 0.25 * (nodal_pressure_[tets_(e, 0)] + nodal_pressure_[tets_(e, 1)] + nodal_pressure_[tets_(e, 2)] +
                                nodal_pressure_[tets_(e, 3)]);
    const double ke = kappa_ * er[e] * be[e], j = volume_ratio_[e];
    const bool active = barrierActive(j);  // J_b = 0 is off, also for inverted elements (J < 0)
    barrier_active += active;
    element_stiffness_[e] = elementWeight(e, er[e] * be[e], j);
    const double w = -volumes_[e] * (pbar + beta_ * ke * (j - 1.0) - (active ? cb * ke * (jb - j) : 0.0));
    const double* d = &dJ_[12 * static_cast<size_t>(e)];
    double* fe = &elem_forces_[12 * static_cast<size_t>(e)];
    for (int k = 0; k < 12; ++k) fe[k] = w * d[k];
  }
  barrier_active_ = barrier_active;
  // Per node: add the volumetric forces to the deviatoric ones, and form b_n over its star.
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n) {
    double fx = 0, fy = 0, fz = 0;
    double* const bn = &b_[3 * static_cast<size_t>(star_.neighbourStart(n))];
    std::fill(bn, bn + 3 * (star_.neighbourStart(n + 1) - star_.neighbourStart(n)), 0.0);
    for (int k = star_.incidentStart(n); k < star_.incidentStart(n + 1); ++k) {
      const int e = star_.incidentElement(k), i = star_.incidentLocal(k);
      const double* fe = &elem_forces_[12 * static_cast<size_t>(e) + 3 * i];
      fx += fe[0];
      fy += fe[1];
      fz += fe[2];
      const double w = star_weight_[k];
      const double* d = &dJ_[12 * static_cast<size_t>(e)];
      const int* slot = star_.blockSlot(e) + 4 * i;  // slots of e's nodes in n's star
      for (int j = 0; j < 4; ++j)
        for (int c = 0; c < 3; ++c) bn[3 * slot[j] + c] += w * d[3 * j + c];
    }
    f[3 * n] += fx;
    f[3 * n + 1] += fy;
    f[3 * n + 2] += fz;
  }
}

void AnpTetFem::addVolumetricStiffness(double scale, SparseMatrix& A) const {
  // Row node a gathers κ_n V̂_n b_n[a] b_n[m]ᵀ over the nodes n of its star and the nodes m of n's
  // star: each row is written by one thread.
  const Wide& w2 = wide();
  const int nn = star_.numNodes();
  double* const values = A.valuePtr();
  const int* const outer = A.outerIndexPtr();
#pragma omp parallel for schedule(dynamic, 64)
  for (int a = 0; a < nn; ++a) {
    double* const row0 = values + outer[3 * a];
    const int len = outer[3 * a + 1] - outer[3 * a];
    double* const row1 = row0 + len;
    double* const row2 = row1 + len;
    for (int k = star_.neighbourStart(a); k < star_.neighbourStart(a + 1); ++k) {
      const int n = star_.neighbour(k);
      const int s0 = star_.neighbourStart(n), deg = star_.neighbourStart(n + 1) - s0;
      const double* const bn = &b_[3 * static_cast<size_t>(s0)];
      const double w = scale * nodal_stiffness_[n];
      const double* const ba = bn + 3 * own_slot_[k];
      const double u0 = w * ba[0], u1 = w * ba[1], u2 = w * ba[2];
      const int* const slots = &w2.wide_slot[w2.wide_offset[k]];
      for (int q = 0; q < deg; ++q) addOuter(row0, row1, row2, 3 * slots[q], u0, u1, u2, bn + 3 * q);
    }
  }
}

void AnpTetFem::addElementVolumeStiffness(double scale, SparseMatrix& A) const {
  // κ_e V_e (β + c [J_e < J_b]) ∂J_e/∂x_i ∂J_e/∂x_jᵀ, gathered per row node from its elements
  // (into the one-ring pattern).
  const BlockPattern& one = star_;
  const int nn = star_.numNodes();
  double* const values = A.valuePtr();
  const int* const outer = A.outerIndexPtr();

#pragma omp parallel for schedule(dynamic, 64)
  for (int a = 0; a < nn; ++a) {
    double* const row0 = values + outer[3 * a];
    const int len = outer[3 * a + 1] - outer[3 * a];
    double* const row1 = row0 + len;
    double* const row2 = row1 + len;
    for (int k = one.incidentStart(a); k < one.incidentStart(a + 1); ++k) {
      const int e = one.incidentElement(k), i = one.incidentLocal(k);
      const double w = scale * element_stiffness_[e];
      if (w == 0.0) continue;  // β = 0 and the barrier inactive: most elements
      const double* d = &dJ_[12 * static_cast<size_t>(e)];
      const double u0 = w * d[3 * i], u1 = w * d[3 * i + 1], u2 = w * d[3 * i + 2];
      const int* slot = one.blockSlot(e) + 4 * i;
      for (int j = 0; j < 4; ++j) addOuter(row0, row1, row2, 3 * slot[j], u0, u1, u2, d + 3 * j);
    }
  }
}

void AnpTetFem::assignCompactStiffness(double scale, SparseMatrix& A) const {
  deviatoric_.assignStiffness(scale, A);  // checks A's size and entry count
  if (beta_ > 0.0 || barrier_j_ > 0.0) addElementVolumeStiffness(scale, A);
}

void AnpTetFem::addWideStiffness(double scale, SparseMatrix& A, bool assign) const {
  const Wide& w = wide();
  if (A.rows() != 3 * w.pattern.numNodes() || A.nonZeros() != w.pattern.matrix().nonZeros())
    throw std::invalid_argument("AnpTetFem: the matrix has " + std::to_string(A.rows()) + " rows and " +
                                std::to_string(A.nonZeros()) + " entries, the two-ring pattern " +
                                std::to_string(3 * w.pattern.numNodes()) + " and " +
                                std::to_string(w.pattern.matrix().nonZeros()));
  // K_c on the one-ring pattern, moved block by block into the two-ring rows, then K_vol.
  assignCompactStiffness(scale, w.narrow);
  const int nn = star_.numNodes();
  const double* nval = w.narrow.valuePtr();
  const int* nout = w.narrow.outerIndexPtr();
  double* const values = A.valuePtr();
  const int* const outer = A.outerIndexPtr();
#pragma omp parallel for schedule(static)
  for (int a = 0; a < nn; ++a)
    for (int r = 0; r < 3; ++r) {
      double* row = values + outer[3 * a + r];
      if (assign) std::fill(row, values + outer[3 * a + r + 1], 0.0);
      const double* from = nval + nout[3 * a + r];
      for (int k = star_.neighbourStart(a); k < star_.neighbourStart(a + 1); ++k) {
        double* to = row + 3 * w.narrow_to_wide[k];
        const double* f = from + 3 * (k - star_.neighbourStart(a));
        to[0] += f[0], to[1] += f[1], to[2] += f[2];
      }
    }
  addVolumetricStiffness(scale, A);
}

void AnpTetFem::addStiffness(double scale, SparseMatrix& A) const { addWideStiffness(scale, A, false); }

void AnpTetFem::assignStiffness(double scale, SparseMatrix& A) const { addWideStiffness(scale, A, true); }

RankOneSum AnpTetFem::rankOneStiffness() const {
  RankOneSum R;
  R.terms = R.nodes = star_.numNodes();
  R.term_start = R.node_start = star_.neighbourStarts();
  R.entry_node = R.node_term = star_.neighbourData();
  R.entry_vector = b_.data();
  R.weight = nodal_stiffness_.data();
  R.node_entry = own_entry_.data();
  return R;
}

}  // namespace breast_sim::core
