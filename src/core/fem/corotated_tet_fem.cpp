#include "breast_sim/core/fem/corotated_tet_fem.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <Eigen/Dense>
#include <omp.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
// The AVX-512 kernels (element update, stiffness gather), chosen at run time (updateHasSimd,
// gatherHasSimd) beside the portable ones.
#define BREAST_SIM_FEM_AVX512 1
#endif

#include "breast_sim/core/fem/polar_decomposition.h"
#include "breast_sim/core/fem/polar_decomposition_detail.h"

namespace breast_sim::core {

CorotatedTetFem::CorotatedTetFem(const TetMesh& mesh, const ElasticMaterial& material, int pattern_rings)
    : tets_(mesh.tets()), rest_(mesh.nodes()), material_(material), pattern_(mesh.tets(), mesh.numNodes(), pattern_rings) {
  material_.validate();
  lambda_ = material_.lameLambda();
  mu_ = material_.lameMu();
  trace_lambda_ = lambda_;
  const int nt = mesh.numTets();
  const size_t num_batches = (static_cast<size_t>(nt) + kBatch - 1) / kBatch;
  grads_.resize(12 * static_cast<size_t>(nt));
  batch_grads_.assign(12 * kBatch * num_batches, 0.0);
  volumes_.resize(nt);
  rotations_.assign(9 * kBatch * num_batches, 0.0);
  records_raw_.assign(kRecordTrace * static_cast<size_t>(nt) + 8, 0.0);
  elem_forces_.assign(12 * static_cast<size_t>(nt), 0.0);
  modulus_factor_ = Eigen::VectorXd::Ones(nt);
  base_scale_ = Eigen::VectorXd::Ones(nt);
  von_mises_ = Eigen::VectorXd::Zero(nt);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    double* g = &grads_[12 * static_cast<size_t>(e)];
    volumes_[e] = restShapeGradients(rest_, tets_, e, g);
    const size_t b = static_cast<size_t>(e / kBatch), l = static_cast<size_t>(e % kBatch);
    for (int k = 0; k < 12; ++k) batch_grads_[12 * kBatch * b + k * kBatch + l] = g[k];
    for (int k = 0; k < 9; k += 4) rotations_[9 * kBatch * b + k * kBatch + l] = 1.0;
    double* rec = records() + kRecordTrace * static_cast<size_t>(e);
    const double root_w = std::sqrt(volumes_[e]);  // E_r = 1
    for (int k = 0; k < 12; ++k) rec[k] = root_w * g[k];
  }
  const int nn = pattern_.numNodes();
  // Fixed chunks of batches for the node forces (withChunkForces): as many as threads could ever
  // use here. Each chunk adds into an array over the nodes its elements touch (1.4–1.6 × N entries
  // for all chunks together on the phantom), so force_tets_ holds each element's nodes as slots of
  // its chunk's array; a node sums the slots it has in chunk order.
  const int chunks = static_cast<int>(std::max<size_t>(1, std::min<size_t>(kForceChunks, num_batches)));
  chunk_batch_.resize(static_cast<size_t>(chunks) + 1);
  for (int c = 0; c <= chunks; ++c) chunk_batch_[c] = static_cast<int>(num_batches * static_cast<size_t>(c) / chunks);
  force_tets_.resize(4 * static_cast<size_t>(nt));
  chunk_start_.assign(1, 0);
  std::vector<int> slot_of(static_cast<size_t>(nn), -1), touched, node_slots;  // node_slots: (node, slot) pairs
  for (int c = 0; c < chunks; ++c) {
    touched.clear();
    const int e_end = std::min(nt, chunk_batch_[c + 1] * kBatch);
    for (int e = chunk_batch_[c] * kBatch; e < e_end; ++e)
      for (int i = 0; i < 4; ++i) touched.push_back(tets_(e, i));
    std::sort(touched.begin(), touched.end());
    touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
    for (size_t q = 0; q < touched.size(); ++q) {
      slot_of[touched[q]] = static_cast<int>(q);
      node_slots.push_back(touched[q]);
      node_slots.push_back(chunk_start_.back() + static_cast<int>(q));
    }
    for (int e = chunk_batch_[c] * kBatch; e < e_end; ++e)
      for (int i = 0; i < 4; ++i) force_tets_[4 * static_cast<size_t>(e) + i] = slot_of[tets_(e, i)];
    chunk_start_.push_back(chunk_start_.back() + static_cast<int>(touched.size()));
  }
  chunk_forces_.assign(3 * static_cast<size_t>(chunk_start_.back()), 0.0);
  cover_start_.assign(static_cast<size_t>(nn) + 1, 0);
  for (size_t k = 0; k < node_slots.size(); k += 2) ++cover_start_[node_slots[k] + 1];
  for (int n = 0; n < nn; ++n) cover_start_[n + 1] += cover_start_[n];
  cover_slot_.resize(cover_start_[nn]);
  {
    std::vector<int> fill(cover_start_.begin(), cover_start_.end() - 1);
    for (size_t k = 0; k < node_slots.size(); k += 2) cover_slot_[fill[node_slots[k]]++] = node_slots[k + 1];  // chunk order
  }
  incident_slots_.resize(4 * static_cast<size_t>(pattern_.incidentStart(nn)));
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n)
    for (int k = pattern_.incidentStart(n); k < pattern_.incidentStart(n + 1); ++k) {
      const int* slot = pattern_.blockSlot(pattern_.incidentElement(k)) + 4 * pattern_.incidentLocal(k);
      for (int j = 0; j < 4; ++j) incident_slots_[4 * static_cast<size_t>(k) + j] = 3 * slot[j];
    }
}

void CorotatedTetFem::setModulusFactors(const Eigen::VectorXd& factors) {
  if (factors.size() != modulus_factor_.size())
    throw std::invalid_argument("setModulusFactors: " + std::to_string(factors.size()) + " factors for " +
                                std::to_string(modulus_factor_.size()) + " elements");
  for (Eigen::Index e = 0; e < factors.size(); ++e)
    if (!(factors[e] > 0) || !std::isfinite(factors[e]))
      throw std::invalid_argument("setModulusFactors: factor of element " + std::to_string(e) + " is " +
                                  std::to_string(factors[e]) + "; factors must be positive and finite");
  // The stiffness records hold √(V E_r)-scaled gradients: rescale them to the new factors (the
  // stiffening loop calls this every step: 1.2 M values at 48k elements, so on every thread). The
  // element forces and von Mises stresses of the last update are linear in E_r: rescaled too, so
  // that an update() at the same positions needs no new rotations.
  double* const recs = records();
  const bool forces = elem_forces_.size() == 12 * static_cast<size_t>(factors.size());
#pragma omp parallel for schedule(static)
  for (Eigen::Index e = 0; e < factors.size(); ++e) {
    const double ratio = factors[e] / modulus_factor_[e], rescale = std::sqrt(ratio);
    double* const rec = recs + record_ * static_cast<size_t>(e);
    for (int k = 0; k < record_; ++k) rec[k] *= rescale;
    if (forces) {
      double* const fe = &elem_forces_[12 * static_cast<size_t>(e)];
      for (int k = 0; k < 12; ++k) fe[k] *= ratio;
      von_mises_[e] *= ratio;
    }
  }
  modulus_factor_ = factors;
}

void CorotatedTetFem::setElementYoungsModuli(const Eigen::VectorXd& youngs_modulus_pa) {
  const Eigen::Index nt = base_scale_.size();
  Eigen::VectorXd scale = Eigen::VectorXd::Ones(nt);
  if (youngs_modulus_pa.size() != 0) {
    if (youngs_modulus_pa.size() != nt)
      throw std::invalid_argument("setElementYoungsModuli: " + std::to_string(youngs_modulus_pa.size()) +
                                  " moduli for " + std::to_string(nt) + " elements (give one per element, or none)");
    for (Eigen::Index e = 0; e < nt; ++e) {
      if (!(youngs_modulus_pa[e] > 0) || !std::isfinite(youngs_modulus_pa[e]))
        throw std::invalid_argument("setElementYoungsModuli: modulus of element " + std::to_string(e) + " is " +
                                    std::to_string(youngs_modulus_pa[e]) + " Pa; moduli must be positive and finite");
      scale[e] = youngs_modulus_pa[e] / material_.youngs_modulus_pa;
    }
  }
  // The stiffness records hold √(V E_r b_e)-scaled gradients: rescale them to the new b_e.
  double* const recs = records();
#pragma omp parallel for schedule(static)
  for (Eigen::Index e = 0; e < nt; ++e) {
    const double rescale = std::sqrt(scale[e] / base_scale_[e]);
    double* const rec = recs + record_ * static_cast<size_t>(e);
    for (int k = 0; k < record_; ++k) rec[k] *= rescale;
  }
  base_scale_ = scale;
  updated_at_valid_ = false;  // forces and stresses come from the next update
}

Eigen::Matrix3d CorotatedTetFem::rotation(int e) const {
  Eigen::Matrix3d R;
  const double* r = &rotations_[9 * kBatch * static_cast<size_t>(e / kBatch) + e % kBatch];
  for (int k = 0; k < 9; ++k) R.data()[k] = r[k * kBatch];
  return R;
}

namespace {

constexpr int W = kRotationBatch;

/// The arithmetic of one batch of W elements of CorotatedTetFem::update(), on component-major
/// arrays v[k·W + l] (see updateBatches): from the node positions xs (x_0..x_3, 12) and the shape
/// gradients g (12), F and its rotation R (9; rotationsOf for the first m lanes when corotated, the
/// identity otherwise), the element forces f = −V R σ ∇N_i (12), √(V E_r) R ∇N_i (12), with
/// kDeterminant √(V E_r) cof F ∇N_i (12), and the squared von Mises stress vm2; sf is E_r (times the
/// element's base modulus scale b_e, setElementYoungsModuli), vol V [m³] and root_w √(V E_r).
/// \note It is compiled twice (updateBatchPortable, updateBatchAvx512), inlined with rotationsOf's
/// lane arithmetic into each. An earlier try compiled only this kernel and rotationsOf for AVX-512
/// (GCC target_clones) and did not pay (1 thread, update 5.1–5.3 ms either way): the batch's
/// gathers and transposes around it stayed two-wide, and the square roots were scalar calls behind
/// an errno branch (CGAL's -frounding-math and -fmath-errno, both off for this file now, see
/// CMakeLists.txt). With the whole batch in one function and the roots vectorised, bench_fem_assembly
/// (48.8k, 1 thread, process CPU time, both kernels in the same repetitions, before the roots were
/// vectorised) gave update trace 5.3 ms portable against 4.1 ms AVX-512, determinant 6.1 against 4.5.
template <bool kDeterminant>
__attribute__((always_inline)) inline void batchKernel(const double* __restrict xs, const double* __restrict g,
                                                       const double* __restrict sf, const double* __restrict vol,
                                                       const double* __restrict root_w, int m, bool corotated,
                                                       double lambda, double two_mu, double* __restrict Rb,
                                                       double* __restrict f, double* __restrict rg,
                                                       double* __restrict cg, double* __restrict vm2) {
  alignas(64) double F[9 * W];
  // F = Σ_i x_i ∇N_iᵀ, column-major: F[(r + 3c)·W + l].
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      for (int l = 0; l < W; ++l)
        F[(r + 3 * c) * W + l] = xs[r * W + l] * g[c * W + l] + xs[(3 + r) * W + l] * g[(3 + c) * W + l] +
                                 xs[(6 + r) * W + l] * g[(6 + c) * W + l] + xs[(9 + r) * W + l] * g[(9 + c) * W + l];
  if (corotated) detail::rotationsOfLanes(F, Rb, m);
  for (int l = corotated ? m : 0; l < W; ++l)
    for (int k = 0; k < 9; ++k) Rb[k * W + l] = k % 4 == 0 ? 1.0 : 0.0;
  for (int l = 0; l < W; ++l) {
    double Fl[9], Rl[9];
    for (int k = 0; k < 9; ++k) Fl[k] = F[k * W + l], Rl[k] = Rb[k * W + l];
    // Fr = Rᵀ F; co-rotated strain ε = sym(Fr) − I.
    double Fr[9];
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) Fr[p + 3 * q] = Rl[3 * p] * Fl[3 * q] + Rl[3 * p + 1] * Fl[3 * q + 1] + Rl[3 * p + 2] * Fl[3 * q + 2];
    const double e00 = Fr[0] - 1.0, e11 = Fr[4] - 1.0, e22 = Fr[8] - 1.0;
    const double e01 = 0.5 * (Fr[3] + Fr[1]), e12 = 0.5 * (Fr[7] + Fr[5]), e02 = 0.5 * (Fr[6] + Fr[2]);
    // Co-rotated stress σ with P = R σ (corotated_tet_fem.h, VolumeTerm); symmetric.
    double s00, s11, s22, s01, s12, s02;
    if constexpr (!kDeterminant) {
      const double p = lambda * (e00 + e11 + e22);
      s00 = p + two_mu * e00, s11 = p + two_mu * e11, s22 = p + two_mu * e22;
      s01 = two_mu * e01, s12 = two_mu * e12, s02 = two_mu * e02;
    } else {
      // Rᵀ cof F = J S⁻¹ (symmetric for the polar R): λ (J − 1) sym(Rᵀ cof F); the columns of
      // cof F are cross products of F's columns.
      const double cof[9] = {Fl[4] * Fl[8] - Fl[5] * Fl[7], Fl[5] * Fl[6] - Fl[3] * Fl[8], Fl[3] * Fl[7] - Fl[4] * Fl[6],
                             Fl[7] * Fl[2] - Fl[8] * Fl[1], Fl[8] * Fl[0] - Fl[6] * Fl[2], Fl[6] * Fl[1] - Fl[7] * Fl[0],
                             Fl[1] * Fl[5] - Fl[2] * Fl[4], Fl[2] * Fl[3] - Fl[0] * Fl[5], Fl[0] * Fl[4] - Fl[1] * Fl[3]};
      const double J = Fl[0] * cof[0] + Fl[1] * cof[1] + Fl[2] * cof[2];
      double rc[9];
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q)
          rc[p + 3 * q] = Rl[3 * p] * cof[3 * q] + Rl[3 * p + 1] * cof[3 * q + 1] + Rl[3 * p + 2] * cof[3 * q + 2];
      const double h = lambda * (J - 1.0);
      s00 = h * rc[0] + two_mu * e00, s11 = h * rc[4] + two_mu * e11, s22 = h * rc[8] + two_mu * e22;
      s01 = h * (0.5 * (rc[3] + rc[1])) + two_mu * e01;
      s12 = h * (0.5 * (rc[7] + rc[5])) + two_mu * e12;
      s02 = h * (0.5 * (rc[6] + rc[2])) + two_mu * e02;
      // ∂J/∂x_i = cof F ∇N_i, kept for the volumetric (Gauss–Newton) part of the stiffness.
      for (int i = 0; i < 4; ++i)
        for (int r = 0; r < 3; ++r)
          cg[(3 * i + r) * W + l] = root_w[l] * (cof[r] * g[(3 * i) * W + l] + cof[r + 3] * g[(3 * i + 1) * W + l] +
                                                 cof[r + 6] * g[(3 * i + 2) * W + l]);
    }
    // The modulus factor E_r scales σ.
    const double s = sf[l];
    s00 *= s, s11 *= s, s22 *= s, s01 *= s, s12 *= s, s02 *= s;
    const double d01 = s00 - s11, d12 = s11 - s22, d20 = s22 - s00;
    vm2[l] = 0.5 * (d01 * d01 + d12 * d12 + d20 * d20) + 3.0 * (s01 * s01 + s12 * s12 + s02 * s02);
    // RS = −V R σ; element forces f_i = RS ∇N_i, and R ∇N_i for the stiffness.
    const double sig[9] = {s00, s01, s02, s01, s11, s12, s02, s12, s22};
    double RS[9];
    for (int r = 0; r < 3; ++r)
      for (int q = 0; q < 3; ++q)
        RS[r + 3 * q] = -vol[l] * (Rl[r] * sig[3 * q] + Rl[r + 3] * sig[3 * q + 1] + Rl[r + 6] * sig[3 * q + 2]);
    for (int i = 0; i < 4; ++i) {
      const double g0 = g[(3 * i) * W + l], g1 = g[(3 * i + 1) * W + l], g2 = g[(3 * i + 2) * W + l];
      for (int r = 0; r < 3; ++r) {
        f[(3 * i + r) * W + l] = RS[r] * g0 + RS[r + 3] * g1 + RS[r + 6] * g2;
        rg[(3 * i + r) * W + l] = root_w[l] * (Rl[r] * g0 + Rl[r + 3] * g1 + Rl[r + 6] * g2);
      }
    }
  }
}

/// Adds element e's forces fe (12 [N]) to its four nodes in node_forces (3 per slot; slots: the
/// chunk's, force_tets): the one order in which both update() paths, a fresh update and one at the
/// same positions, sum them.
inline void addElementForces(const int* tets, size_t e, const double* fe, double* node_forces) {
  for (int i = 0; i < 4; ++i) {
    double* const fn = node_forces + 3 * static_cast<size_t>(tets[4 * e + i]);
    fn[0] += fe[3 * i], fn[1] += fe[3 * i + 1], fn[2] += fe[3 * i + 2];
  }
}

/// What one batch of CorotatedTetFem::update() reads and writes (updateBatch).
struct UpdateArgs {
  const double* batch_grads;  // per batch, component-major
  double* rotations;          // per batch, component-major
  const double* volumes;
  const double* modulus_factor;
  const double* base_scale;
  const int* tets;            // row-major #T × 4 (Tets)
  const int* force_tets;      // 4 per element: its nodes' slots in its chunk's node forces
  int num_tets;
  const double* x;            // row-major #N × 3 (Points) [m]
  double* von_mises;
  double* elem_forces;
  double* records;
  int stride;                 // record length
  bool corotated;
  double lambda, two_mu;
};

/// Batch b of CorotatedTetFem::update(): component-major arrays v[k·W + l] (lane l = element
/// e0 + l); every arithmetic loop runs over l without a branch, so it vectorises (see rotationsOf
/// for why: no conditional expressions, square roots in loops of their own). Lanes past the last
/// element compute on zeros and the identity and are not written back. The element forces are
/// kept per element (for an update at the same positions, see update()) and added to the chunk's
/// node forces (node_forces, 3 per node) by addElementForces, as update()'s reuse path adds the kept
/// ones. Inline, so that each instantiation below compiles it for its own instruction set.
template <bool kDeterminant>
__attribute__((always_inline)) inline void updateBatch(const UpdateArgs& a, int b, double* node_forces) {
  const int e0 = b * W, m = std::min(W, a.num_tets - e0);
  const double* const g = a.batch_grads + 12 * W * static_cast<size_t>(b);
  double* const Rb = a.rotations + 9 * W * static_cast<size_t>(b);
  alignas(64) double xs[12 * W], f[12 * W], rg[12 * W], cg[12 * W], sf[W], vol[W], root_w[W], vm2[W];
  for (int l = 0; l < W; ++l) {
    const bool in = l < m;
    vol[l] = in ? a.volumes[e0 + l] : 0.0;
    sf[l] = in ? a.modulus_factor[e0 + l] * a.base_scale[e0 + l] : 0.0;  // E_r b_e
    for (int i = 0; i < 4; ++i) {
      const size_t node = in ? static_cast<size_t>(a.tets[4 * static_cast<size_t>(e0 + l) + i]) : 0;
      for (int c = 0; c < 3; ++c) xs[(3 * i + c) * W + l] = in ? a.x[3 * node + c] : 0.0;
    }
  }
#pragma omp simd
  for (int l = 0; l < W; ++l) root_w[l] = std::sqrt(sf[l] * vol[l]);
  batchKernel<kDeterminant>(xs, g, sf, vol, root_w, m, a.corotated, a.lambda, a.two_mu, Rb, f, rg, cg, vm2);
  // Back to per-element storage.
#pragma omp simd
  for (int l = 0; l < W; ++l) vm2[l] = std::sqrt(vm2[l]);
  for (int l = 0; l < m; ++l) {
    const size_t e = static_cast<size_t>(e0 + l);
    a.von_mises[e] = vm2[l];
    double* const fe = a.elem_forces + 12 * e;
    double* const rec = a.records + a.stride * e;
    for (int k = 0; k < 12; ++k) fe[k] = f[k * W + l];
    addElementForces(a.force_tets, e, fe, node_forces);
    for (int k = 0; k < 12; ++k) rec[k] = rg[k * W + l];
    if constexpr (kDeterminant)
      for (int k = 0; k < 12; ++k) rec[12 + k] = cg[k * W + l];
  }
}

template <bool kDeterminant>
void updateBatchPortable(const UpdateArgs& a, int b, double* node_forces) {
  updateBatch<kDeterminant>(a, b, node_forces);
}

#ifdef BREAST_SIM_FEM_AVX512
/// The same batch compiled for AVX-512 (one batch of 8 doubles is one vector; the compiler may
/// contract products and sums into fused multiply-adds, so it equals the portable one to rounding).
template <bool kDeterminant>
__attribute__((target("avx512f,avx512vl,avx512dq,avx2,fma"))) void updateBatchAvx512(const UpdateArgs& a, int b, double* node_forces) {
  updateBatch<kDeterminant>(a, b, node_forces);
}
#endif

}  // namespace

bool CorotatedTetFem::updateHasSimd() {
#ifdef BREAST_SIM_FEM_AVX512
  static const bool has = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
                          __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx2") &&
                          __builtin_cpu_supports("fma");
  return has;
#else
  return false;
#endif
}

template <bool kDeterminant>
void CorotatedTetFem::updateBatches(const Points& x, Eigen::VectorXd& f) {
  const int nt = static_cast<int>(tets_.rows());
  static_assert(kVolumeGrads == 12, "updateBatch writes the volume gradients after the 12 rotated ones");
  UpdateArgs a;
  a.batch_grads = batch_grads_.data();
  a.rotations = rotations_.data();
  a.volumes = volumes_.data();
  a.modulus_factor = modulus_factor_.data();
  a.base_scale = base_scale_.data();
  a.tets = tets_.data();
  a.force_tets = force_tets_.data();
  a.num_tets = nt;
  a.x = x.data();
  a.von_mises = von_mises_.data();
  a.elem_forces = elem_forces_.data();
  a.records = records();
  a.stride = record_;
  a.corotated = corotated_;
  a.lambda = volumeLambda();
  a.two_mu = 2.0 * mu_;
  void (*batch)(const UpdateArgs&, int, double*) = updateBatchPortable<kDeterminant>;
#ifdef BREAST_SIM_FEM_AVX512
  if (simd_kernels_ && updateHasSimd()) batch = updateBatchAvx512<kDeterminant>;
#endif
  // Measured (bench_fem_assembly, 48.8k tets, 1 thread, medians of 40, old and new binaries
  // interleaved on a loaded machine): update (rotations + forces) trace 10.5–10.9 → 5.0 ms,
  // determinant 11.9 → 6.0 ms; of which rotations 7.9–8.5 → 2.8 ms.
  withChunkForces(f, [&](double* node_forces, int b) { batch(a, b, node_forces); });
}

template <class BatchFn>
void CorotatedTetFem::withChunkForces(Eigen::VectorXd& f, BatchFn&& batch) {
  // Each chunk of batches adds its elements' forces to a node-force array of its own (the nodes it
  // touches: cache-resident), whichever thread runs it, and every node sums its slots in chunk
  // order: no two threads write the same entry, and neither the timing nor the number of threads
  // changes a sum. (A gather per node from the per-element array would visit the elements in an
  // order the prefetcher cannot follow.)
  const int chunks = static_cast<int>(chunk_batch_.size()) - 1;
  const int nn = pattern_.numNodes();
  f.resize(3 * static_cast<Eigen::Index>(nn));  // every entry is written below
  double* const out = f.data();
  double* const buffers = chunk_forces_.data();
#pragma omp parallel
  {
#pragma omp for schedule(static)
    for (int c = 0; c < chunks; ++c) {
      double* const mine = buffers + 3 * static_cast<size_t>(chunk_start_[c]);
      std::fill(mine, buffers + 3 * static_cast<size_t>(chunk_start_[c + 1]), 0.0);
      for (int b = chunk_batch_[c]; b < chunk_batch_[c + 1]; ++b) batch(mine, b);
    }
#pragma omp for schedule(static)
    for (int n = 0; n < nn; ++n) {
      double s0 = 0.0, s1 = 0.0, s2 = 0.0;
      for (int k = cover_start_[n]; k < cover_start_[n + 1]; ++k) {
        const double* v = buffers + 3 * static_cast<size_t>(cover_slot_[k]);
        s0 += v[0], s1 += v[1], s2 += v[2];
      }
      out[3 * n] = s0, out[3 * n + 1] = s1, out[3 * n + 2] = s2;
    }
  }
}

void CorotatedTetFem::update(const Points& x, Eigen::VectorXd& f) {
  const int nt = static_cast<int>(tets_.rows());
  const bool determinant = volume_term_ == VolumeTerm::kDeterminant && corotated_;
  stiffness_is_determinant_ = determinant;
  trace_lambda_ = volume_term_ == VolumeTerm::kNone ? -2.0 * mu_ / 3.0 : lambda_;
  const int stride = determinant ? kRecordDeterminant : kRecordTrace;
  if (stride != record_) {
    record_ = stride;
    records_raw_.assign(static_cast<size_t>(stride) * nt + 8, 0.0);
  }
  // At the positions of the last update, with the same formulation, the rotations, forces, von Mises
  // stresses and stiffness records are still valid (setModulusFactors rescales them): the stiffening
  // loop evaluates the stress after a step and the next step's forces at the same positions.
  const bool same = updated_at_valid_ && updated_corotated_ == corotated_ && updated_volume_term_ == volume_term_ &&
                    updated_at_.rows() == x.rows() && updated_at_.cols() == x.cols() &&
                    std::equal(x.data(), x.data() + x.size(), updated_at_.data());
  if (!same) {
    if (determinant) updateBatches<true>(x, f);
    else updateBatches<false>(x, f);
    updated_at_ = x;
    updated_at_valid_ = true;
    updated_corotated_ = corotated_;
    updated_volume_term_ = volume_term_;
    return;
  }
  // The node forces from the kept element forces, in the batches' order (the same sums as the
  // update that computed them, when the modulus factors did not change since).
  const double* const fe_all = elem_forces_.data();
  const int* const tets = force_tets_.data();
  withChunkForces(f, [&](double* node_forces, int b) {
    const int e0 = b * kBatch, e1 = std::min(nt, e0 + kBatch);
    for (int e = e0; e < e1; ++e)
      addElementForces(tets, static_cast<size_t>(e), fe_all + 12 * static_cast<size_t>(e), node_forces);
  });
}

void CorotatedTetFem::addStiffness(double scale, SparseMatrix& A) const {
  if (stiffness_is_determinant_) gatherStiffness<true, false>(scale, A);
  else gatherStiffness<false, false>(scale, A);
}

void CorotatedTetFem::assignStiffness(double scale, SparseMatrix& A) const {
  if (A.rows() != 3 * pattern_.numNodes() || A.nonZeros() != pattern_.matrix().nonZeros())
    throw std::invalid_argument("assignStiffness: A is " + std::to_string(A.rows()) + " x " + std::to_string(A.cols()) +
                                " with " + std::to_string(A.nonZeros()) + " entries; it must have pattern()'s " +
                                std::to_string(pattern_.matrix().nonZeros()) + " entries");
  if (stiffness_is_determinant_) gatherStiffness<true, true>(scale, A);
  else gatherStiffness<false, true>(scale, A);
}

namespace {

/// What the stiffness gather of a range of nodes reads and writes (CorotatedTetFem::gatherStiffness).
struct GatherArgs {
  double* values;          // A's values
  const int* outer;        // A's row starts
  const double* recs;      // the element records
  const int* islots;       // per incidence and j: 3·block slot
  const int* inc_start;    // the pattern's incidentStart
  const int* incident;     // the pattern's incidences: element·4 + local index
  int num_incidences;
  double sl, sm;           // scale·λ, scale·μ
};

// The element records are prefetched this many incidences ahead (see gatherStiffness).
constexpr int kGatherAhead = 8;

template <int kStride>
inline void prefetchRecord(const GatherArgs& a, int k) {
  const double* r = a.recs + kStride * static_cast<size_t>(a.incident[k] >> 2);
  for (int line = 0; line < kStride; line += 8) __builtin_prefetch(r + line);
  __builtin_prefetch(r + kStride - 1);  // records are not line-aligned
}

/// Node n's three rows of A (row 1 and 2 follow row 0 at len and 2·len entries), cleared when
/// kAssign, and its incidences [k_begin, k_end), the first few of whose records are prefetched.
struct NodeRows {
  double *row0, *row1, *row2;
  int len, k_begin, k_end;
};

template <int kStride, bool kAssign>
inline NodeRows beginNode(const GatherArgs& a, int n) {
  const int len = a.outer[3 * n + 1] - a.outer[3 * n];
  double* const row0 = a.values + a.outer[3 * n];
  NodeRows r{row0, row0 + len, row0 + 2 * len, len, a.inc_start[n], a.inc_start[n + 1]};
  if constexpr (kAssign) std::fill(r.row0, r.row0 + 3 * r.len, 0.0);
  for (int k = r.k_begin; k < std::min(r.k_begin + kGatherAhead, a.num_incidences); ++k) prefetchRecord<kStride>(a, k);
  return r;
}

/// The portable gather of nodes [n0, n1): 36 scalar read-modify-writes per incidence.
template <int kStride, int kH, bool kAssign>
void gatherNodesScalar(const GatherArgs& a, int n0, int n1) {
  for (int n = n0; n < n1; ++n) {
    const NodeRows r = beginNode<kStride, kAssign>(a, n);
    for (int k = r.k_begin; k < r.k_end; ++k) {
      if (k + kGatherAhead < a.num_incidences) prefetchRecord<kStride>(a, k + kGatherAhead);
      const int i = a.incident[k] & 3;
      const double* const rec = a.recs + kStride * static_cast<size_t>(a.incident[k] >> 2);
      double g[12], h[12];
      for (int q = 0; q < 12; ++q) g[q] = rec[q];
      for (int q = 0; q < 12; ++q) h[q] = rec[kH + q];
      const double u0 = a.sl * h[3 * i], u1 = a.sl * h[3 * i + 1], u2 = a.sl * h[3 * i + 2];
      const double v0 = a.sm * g[3 * i], v1 = a.sm * g[3 * i + 1], v2 = a.sm * g[3 * i + 2];
      int slot[4];
      for (int j = 0; j < 4; ++j) slot[j] = a.islots[4 * static_cast<size_t>(k) + j];
      for (int j = 0; j < 4; ++j) {
        const double gj0 = g[3 * j], gj1 = g[3 * j + 1], gj2 = g[3 * j + 2];
        const double hj0 = h[3 * j], hj1 = h[3 * j + 1], hj2 = h[3 * j + 2];
        const double d = v0 * gj0 + v1 * gj1 + v2 * gj2;
        double* const p0 = r.row0 + slot[j];
        double* const p1 = r.row1 + slot[j];
        double* const p2 = r.row2 + slot[j];
        p0[0] += u0 * hj0 + gj0 * v0 + d;
        p0[1] += u0 * hj1 + gj0 * v1;
        p0[2] += u0 * hj2 + gj0 * v2;
        p1[0] += u1 * hj0 + gj1 * v0;
        p1[1] += u1 * hj1 + gj1 * v1 + d;
        p1[2] += u1 * hj2 + gj1 * v2;
        p2[0] += u2 * hj0 + gj2 * v0;
        p2[1] += u2 * hj1 + gj2 * v1;
        p2[2] += u2 * hj2 + gj2 * v2 + d;
      }
    }
  }
}

#if defined(__x86_64__) && defined(__GNUC__)
/// Rows r = 0..2 of element block (i, j): u_r h_j + a_j[r] μ a_i + (μ a_i·a_j) e_r, with v = μ a_i
/// and u_r = λ h_i[r] on every lane (lane 3 of the results is zero).
template <int kH>
__attribute__((target("avx512f,avx512vl,fma"), always_inline)) inline void gatherBlock(
    const double* rec, const double* hrec, int j, __m256d v, __m256d u0, __m256d u1, __m256d u2, __m256d& r0,
    __m256d& r1, __m256d& r2) {
  constexpr __mmask8 k3 = 0x7;
  const __m256d gj = _mm256_maskz_loadu_pd(k3, rec + 3 * j);
  const __m256d hj = kH == 0 ? gj : _mm256_maskz_loadu_pd(k3, hrec + 3 * j);
  __m256d d = _mm256_mul_pd(v, gj);
  d = _mm256_add_pd(d, _mm256_permute4x64_pd(d, 0x4E));  // (0+2, 1+3, 2+0, 3+1)
  d = _mm256_add_pd(d, _mm256_permute_pd(d, 0x5));       // every lane: 0+1+2+3
  r0 = _mm256_fmadd_pd(u0, hj, _mm256_mul_pd(_mm256_set1_pd(rec[3 * j]), v));
  r1 = _mm256_fmadd_pd(u1, hj, _mm256_mul_pd(_mm256_set1_pd(rec[3 * j + 1]), v));
  r2 = _mm256_fmadd_pd(u2, hj, _mm256_mul_pd(_mm256_set1_pd(rec[3 * j + 2]), v));
  r0 = _mm256_mask_add_pd(r0, 0x1, r0, d);
  r1 = _mm256_mask_add_pd(r1, 0x2, r1, d);
  r2 = _mm256_mask_add_pd(r2, 0x4, r2, d);
}

// The local indices other than i, for i = 0..3.
constexpr int kOthers[4][3] = {{1, 2, 3}, {0, 2, 3}, {0, 1, 3}, {0, 1, 2}};

/// The same gather with AVX-512VL: a block row's three values are one masked four-wide vector (the
/// fourth lane, which belongs to the next block or to another node's row, is never read or
/// written), so an incidence is 9 read-modify-writes instead of 36; the diagonal block (n, n), which
/// every incidence adds to, is summed in registers and written once.
template <int kStride, int kH, bool kAssign>
__attribute__((target("avx512f,avx512vl,fma"))) void gatherNodesAvx512(const GatherArgs& a, int n0, int n1) {
  constexpr __mmask8 k3 = 0x7;
  const __m256d sm = _mm256_set1_pd(a.sm);
  for (int n = n0; n < n1; ++n) {
    const NodeRows r = beginNode<kStride, kAssign>(a, n);
    __m256d diag0 = _mm256_setzero_pd(), diag1 = diag0, diag2 = diag0;
    for (int k = r.k_begin; k < r.k_end; ++k) {
      if (k + kGatherAhead < a.num_incidences) prefetchRecord<kStride>(a, k + kGatherAhead);
      const int i = a.incident[k] & 3;
      const double* const rec = a.recs + kStride * static_cast<size_t>(a.incident[k] >> 2);
      const double* const hrec = rec + kH;
      const __m256d v = _mm256_mul_pd(sm, _mm256_maskz_loadu_pd(k3, rec + 3 * i));  // μ a_i, lane 3 zero
      const __m256d u0 = _mm256_set1_pd(a.sl * hrec[3 * i]), u1 = _mm256_set1_pd(a.sl * hrec[3 * i + 1]),
                    u2 = _mm256_set1_pd(a.sl * hrec[3 * i + 2]);
      const int* const slot = a.islots + 4 * static_cast<size_t>(k);
      __m256d r0, r1, r2;
      gatherBlock<kH>(rec, hrec, i, v, u0, u1, u2, r0, r1, r2);
      diag0 = _mm256_add_pd(diag0, r0), diag1 = _mm256_add_pd(diag1, r1), diag2 = _mm256_add_pd(diag2, r2);
      for (int q = 0; q < 3; ++q) {
        const int j = kOthers[i][q];
        gatherBlock<kH>(rec, hrec, j, v, u0, u1, u2, r0, r1, r2);
        double* const p0 = r.row0 + slot[j];
        double* const p1 = r.row1 + slot[j];
        double* const p2 = r.row2 + slot[j];
        _mm256_mask_storeu_pd(p0, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p0), r0));
        _mm256_mask_storeu_pd(p1, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p1), r1));
        _mm256_mask_storeu_pd(p2, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p2), r2));
      }
    }
    if (r.k_begin < r.k_end) {
      double* const p0 = r.row0 + a.islots[4 * static_cast<size_t>(r.k_begin) + (a.incident[r.k_begin] & 3)];
      double* const p1 = p0 + r.len;
      double* const p2 = p1 + r.len;
      _mm256_mask_storeu_pd(p0, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p0), diag0));
      _mm256_mask_storeu_pd(p1, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p1), diag1));
      _mm256_mask_storeu_pd(p2, k3, _mm256_add_pd(_mm256_maskz_loadu_pd(k3, p2), diag2));
    }
  }
}
#endif

}  // namespace

bool CorotatedTetFem::gatherHasSimd() {
#ifdef BREAST_SIM_FEM_AVX512
  static const bool has = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
                          __builtin_cpu_supports("fma");
  return has;
#else
  return false;
#endif
}

template <bool kDeterminant, bool kAssign>
void CorotatedTetFem::gatherStiffness(double scale, SparseMatrix& A) const {
  // Block (i, j) of an element, with a = R ∇N (rotated shape gradients) and V including E_r:
  //   kTrace, R K_e0 Rᵀ:  V(λ a_i a_jᵀ + μ a_j a_iᵀ + μ (a_i·a_j) I)
  //   kDeterminant:       V(λ c_i c_jᵀ + μ a_j a_iᵀ + μ (a_i·a_j) I), c = cof F ∇N = ∂J/∂x: the μ part
  //                       of R K_e0 Rᵀ and the Gauss–Newton part of λ (J − 1) cof F, whose dropped
  //                       remainder λ (J − 1) ∂cof F/∂x is indefinite. SPD, and R K_e0 Rᵀ at rest.
  // Both are u h_jᵀ + a_j vᵀ + (v·a_j) I with u = λ h_i, v = μ a_i, h = a or c, the records holding
  // √(V E_r) a and √(V E_r) c.
  // Each node gathers its own three rows, so no two threads write the same entry. Everything is read
  // into locals before the writes to A (`values` could alias the gradients for the compiler, which
  // would otherwise reload them after every store). Node n's three rows are contiguous (3·deg
  // entries each), so its writes stay in one ~1 kB stretch of A (L1-resident). The element records
  // are prefetched a few incidences ahead.
  // Measured (bench_fem_assembly, 2 threads, minima over 40 or 20 runs, old and new binaries
  // interleaved, quiet machine): assemble (serial zeroing of A + this) 47.5k tets 8.4–9.9 → 3.9–4.0
  // ms, 308k tets 114.6 → 31.0 ms. Prefetching the element forces in update()'s node gather the
  // same way did not pay (measured, dropped). The determinant term's c in the same record, read and
  // prefetched with it, instead of a separate array: 48.8k tets, 1 thread, medians, 10.9–11.1 →
  // 6.1–6.4 ms (trace 5.6–5.8, unchanged). Prefetching 8 incidences ahead instead of 4: 1 thread,
  // process CPU time, medians, 3 interleaved runs: zero + add 5.1–5.8 → 5.1–5.4 ms (trace), 5.8–6.4
  // → 5.6–5.9 ms (det); 16 ahead was not distinguishable from 8. Records scaled by √(V E_r) without
  // the weight and padding (96 instead of 128 bytes, det 192 instead of 256), same measurement:
  // trace 5.7–5.9 → 4.8–5.2 ms, det 6.0–6.1 → 5.7–6.1 ms.
  const int nn = pattern_.numNodes();
  GatherArgs args;
  args.values = A.valuePtr();
  args.outer = A.outerIndexPtr();
  args.recs = records();
  args.islots = incident_slots_.data();
  args.inc_start = pattern_.incidentStarts();
  args.incident = pattern_.incidences();
  args.num_incidences = pattern_.incidentStart(nn);
  args.sl = scale * (kDeterminant ? lambda_ : volumeLambda());
  args.sm = scale * mu_;
  constexpr int kStride = kDeterminant ? kRecordDeterminant : kRecordTrace;
  constexpr int kH = kDeterminant ? kVolumeGrads : 0;  // where h starts in the record
  const bool simd = simd_kernels_ && gatherHasSimd();
  constexpr int kChunk = 64;  // nodes per scheduling chunk (node degrees vary)
  const int num_chunks = (nn + kChunk - 1) / kChunk;
#pragma omp parallel for schedule(dynamic, 1)
  for (int c = 0; c < num_chunks; ++c) {
    const int n0 = c * kChunk, n1 = std::min(nn, n0 + kChunk);
#ifdef BREAST_SIM_FEM_AVX512
    if (simd) {
      gatherNodesAvx512<kStride, kH, kAssign>(args, n0, n1);
      continue;
    }
#endif
    gatherNodesScalar<kStride, kH, kAssign>(args, n0, n1);
  }
}

Eigen::MatrixXd CorotatedTetFem::denseStiffness() const {
  const int nn = pattern_.numNodes();
  Eigen::MatrixXd K = Eigen::MatrixXd::Zero(3 * nn, 3 * nn);
  for (int e = 0; e < static_cast<int>(tets_.rows()); ++e) {
    // B (6×12, Voigt order xx yy zz xy yz xz with engineering shear) and C (6×6): K_e0 = V Bᵀ C B.
    const double* g = &grads_[12 * static_cast<size_t>(e)];
    Eigen::Matrix<double, 6, 12> B = Eigen::Matrix<double, 6, 12>::Zero();
    for (int i = 0; i < 4; ++i) {
      const double gx = g[3 * i], gy = g[3 * i + 1], gz = g[3 * i + 2];
      B(0, 3 * i) = gx;
      B(1, 3 * i + 1) = gy;
      B(2, 3 * i + 2) = gz;
      B(3, 3 * i) = gy, B(3, 3 * i + 1) = gx;
      B(4, 3 * i + 1) = gz, B(4, 3 * i + 2) = gy;
      B(5, 3 * i) = gz, B(5, 3 * i + 2) = gx;
    }
    Eigen::Matrix<double, 6, 6> C = Eigen::Matrix<double, 6, 6>::Zero();
    C.topLeftCorner<3, 3>().setConstant(stiffness_is_determinant_ ? 0.0 : volumeLambda());
    C.topLeftCorner<3, 3>().diagonal().array() += 2.0 * mu_;
    C.bottomRightCorner<3, 3>().diagonal().setConstant(mu_);
    const Eigen::Matrix<double, 12, 12> K0 = volumes_[e] * B.transpose() * C * B;
    const Eigen::Matrix3d R = rotation(e);
    Eigen::Matrix<double, 12, 12> Rb = Eigen::Matrix<double, 12, 12>::Zero();
    for (int i = 0; i < 4; ++i) Rb.block<3, 3>(3 * i, 3 * i) = R;
    Eigen::Matrix<double, 12, 12> Ke = modulus_factor_[e] * base_scale_[e] * Rb * K0 * Rb.transpose();
    if (stiffness_is_determinant_) {
      const Eigen::Map<const Eigen::Matrix<double, 12, 1>> c(records() + record_ * static_cast<size_t>(e) + kVolumeGrads);
      Ke += lambda_ * c * c.transpose();  // c = √(V E_r b_e) ∂J/∂x
    }
    for (int i = 0; i < 4; ++i)
      for (int j = 0; j < 4; ++j) K.block<3, 3>(3 * tets_(e, i), 3 * tets_(e, j)) += Ke.block<3, 3>(3 * i, 3 * j);
  }
  return K;
}

}  // namespace breast_sim::core
