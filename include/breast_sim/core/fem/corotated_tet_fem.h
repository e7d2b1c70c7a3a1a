#pragma once
/// @file corotated_tet_fem.h
/// Co-rotated linear elasticity on linear tetrahedra [RB86, GW08].

#include <cstdint>
#include <vector>

#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/fem/element_formulation.h"
#include "breast_sim/core/fem/polar_decomposition.h"

namespace breast_sim::core {

/// Co-rotated linear tetrahedra: each element's rest stiffness K_e0 (for E0, ν) is rotated by the
/// element's rotation R_e from the polar decomposition of its deformation gradient and scaled by
/// its modulus factor E_r: K_e = E_r · R_e K_e0 R_eᵀ; the elastic force is −E_r R_e K_e0 (R_eᵀ x − X).
/// An optional per-element base modulus (setElementYoungsModuli: tissues of different stiffness)
/// multiplies E_r in both.
///
/// K_e0 is never stored: its 3×3 blocks V(λ a bᵀ + μ b aᵀ + μ (a·b) I), with a, b the shape-function
/// gradients of the two nodes, are formed on the fly from the rotated gradients R_e ∇N_i, which
/// costs fewer flops than streaming 144 stored values per element from memory.
/// The per-element work of update() (deformation gradient, rotation, stress, forces) runs on
/// batches of kRotationBatch elements in structure-of-arrays form, in loops over the batch the
/// compiler vectorises; the rotations by rotationsOf() (polar_decomposition.h).
/// The stiffness assembly runs in parallel over nodes (each node gathers its rows from its
/// elements), so no two threads write the same entry; the node forces are summed per fixed chunk of
/// batches into an array of the chunk's own, and the arrays added in chunk order (the sums depend
/// neither on the thread count nor on timing).
class CorotatedTetFem : public ElementFormulation {
 public:
  /// @param pattern_rings  the reach of pattern() (BlockPattern): 1, or 2 for a formulation that
  ///        adds terms spanning node stars to this one's matrix (AnpTetFem)
  /// @throws std::invalid_argument for an invalid material.
  CorotatedTetFem(const TetMesh& mesh, const ElasticMaterial& material, int pattern_rings = 1);
  // records() points into records_raw_ at a 64-byte boundary: a copy of the buffer can sit at another
  // offset from one, so copies are not made (a move keeps the buffer). The mesh is const: no assignment.
  CorotatedTetFem(const CorotatedTetFem&) = delete;
  CorotatedTetFem& operator=(const CorotatedTetFem&) = delete;
  CorotatedTetFem(CorotatedTetFem&&) = default;
  CorotatedTetFem& operator=(CorotatedTetFem&&) = delete;

  void update(const Points& x, Eigen::VectorXd& f) override;
  void addStiffness(double scale, SparseMatrix& A) const override;
  /// Sets A = scale · K: as zeroing A and addStiffness(), in one pass (each node's rows are cleared
  /// when the gather reaches them, so they are written once, from cache, instead of streamed twice).
  /// @throws std::invalid_argument if A does not have pattern()'s size and entry count.
  void assignStiffness(double scale, SparseMatrix& A) const override;
  const BlockPattern& pattern() const override { return pattern_; }
  const Eigen::VectorXd& modulusFactors() const override { return modulus_factor_; }
  void setModulusFactors(const Eigen::VectorXd& factors) override;
  const Eigen::VectorXd& vonMisesStress() const override { return von_mises_; }

  /// Per-element base Young's moduli [Pa] (#T), e.g. a stiff inclusion in softer tissue: element e
  /// takes E_e = b_e E0 with b_e = youngs_modulus_pa[e] / material.youngs_modulus_pa, and the
  /// modulus factor E_r of the stiffening loop multiplies it (E = E_r b_e E0; ν is the same
  /// everywhere). Stiffness, forces and the von Mises stress (the real stress [Pa]) scale with
  /// E_r b_e; modulusFactors() stays E_r alone. Empty = E0 for every element (the default).
  /// @throws std::invalid_argument for a wrong size or a non-positive or non-finite modulus (names
  ///         the element).
  void setElementYoungsModuli(const Eigen::VectorXd& youngs_modulus_pa);
  /// b_e = E_e / E0 per element (ones unless setElementYoungsModuli() was called).
  const Eigen::VectorXd& baseModulusScales() const { return base_scale_; }

  /// Rotation of element e at the last update.
  Eigen::Matrix3d rotation(int e) const;
  /// When false, rotations stay identity: plain (not co-rotated) linear FEM, for comparisons.
  void setCorotated(bool corotated) { corotated_ = corotated; }

  /// What the volumetric (λ) part of the co-rotated stress penalises. With S = Rᵀ F the stretch and
  /// J = det F, the first Piola stress is P = E_r (2μ R (S − I) + λ v) with
  ///   kTrace:       v = (tr S − 3) R        classic co-rotated linear elasticity [RB86, GW08]
  ///   kDeterminant: v = (J − 1) cof F       "fixed co-rotated" (Stomakhin et al. 2012), cof F = J F⁻ᵀ
  ///   kNone:        no λ term, and the μ term made deviatoric: P = E_r 2μ R dev(S − I), i.e. λ
  ///                 replaced by −2μ/3 (bulk modulus 0). The volume change is then left to another
  ///                 part of the formulation (the nodal pressure of AnpTetFem).
  /// Both have the same linearisation at rest (J − 1 ≈ tr S − 3, cof F ≈ R), so small-strain results,
  /// the patch test and the stiffness R K_e0 Rᵀ are unchanged. They differ under large compression:
  /// tr S − 3 is only a linearised volume change, so with λ ≫ μ (ν = 0.48: λ/μ = 24) kTrace holds
  /// the SUM of the principal stretches, not their product: an element can flatten (stretches
  /// 1.5, 1.5, 0 keep tr S = 3 at J = 0) and pass through inversion (1.6, 1.6, −0.2) resisted by μ
  /// alone. Near the clamped rim under the supine load this makes spurious collapsed and inverted
  /// equilibria (docs/speed_accuracy.md, "Why co-rotated tetrahedra invert under the supine load"). kDeterminant penalises J − 1 itself, so flattening and
  /// inversion cost λ, as in the neo-Hookean reference.
  /// \note Stiffness: kTrace uses R K_e0 Rᵀ (it omits ∂R/∂x). kDeterminant replaces its λ part by
  /// the Gauss–Newton term λ V E_r (∂J/∂x)(∂J/∂x)ᵀ (∂J/∂x_i = cof F ∇N_i), dropping the indefinite
  /// λ (J − 1) ∂(cof F)/∂x: SPD, equal to R K_e0 Rᵀ at rest, and stiff enough under compression
  /// (cof F ∇N grows there) that the long settling steps do not overshoot. Both are exact at rest;
  /// elsewhere the implicit step is a quasi-Newton step converging to the same equilibrium.
  enum class VolumeTerm { kTrace, kDeterminant, kNone };
  /// The volumetric term of a new element set and of SimulationSettings: J − 1 (it measured closer
  /// to the neo-Hookean reference; docs/speed_accuracy.md).
  static constexpr VolumeTerm kDefaultVolumeTerm = VolumeTerm::kDeterminant;
  /// Selects the volumetric term (kDefaultVolumeTerm until called).
  void setVolumeTerm(VolumeTerm term) { volume_term_ = term; }
  VolumeTerm volumeTerm() const { return volume_term_; }
  /// Whether the stiffness gather and the element update may use their AVX-512 versions (when the
  /// processor has them, see gatherHasSimd() and updateHasSimd()); false selects the portable ones,
  /// the reference (on by default). Both give the same results up to rounding: fused multiply-adds,
  /// and the gather's diagonal block summed in registers before it is added to A.
  void setSimdKernels(bool simd) { simd_kernels_ = simd; }
  /// Whether this processor runs the AVX-512VL stiffness gather (checked once).
  static bool gatherHasSimd();
  /// Whether this processor runs update()'s element kernel compiled for AVX-512 (checked once): the
  /// same source as the portable one (SSE2, two lanes per vector), one batch of 8 elements per
  /// vector instead of four.
  static bool updateHasSimd();
  /// \note update() must run before addStiffness() and denseStiffness(): both use its rotations.

  /// Dense 3N×3N stiffness at the last update, element by element (the slow reference for tests).
  Eigen::MatrixXd denseStiffness() const;

 private:
  static constexpr int kBatch = kRotationBatch;  // elements per batch of update()
  static constexpr int kForceChunks = 32;         // chunks of batches the node forces are summed over
  const Tets tets_;
  const Points rest_;
  ElasticMaterial material_;
  double lambda_, mu_;
  BlockPattern pattern_;
  std::vector<double> grads_;       // 12 per element: ∇N_0..∇N_3 [1/m]
  std::vector<double> batch_grads_; // the same per batch of kBatch elements, component-major: [12·kBatch·b + k·kBatch + l]
  std::vector<double> volumes_;     // [m³]
  std::vector<double> rotations_;   // per batch, component-major as batch_grads_: [9·kBatch·b + k·kBatch + l], column-major
  // What addStiffness reads per element, packed into one record (the array starts on a 64-byte
  // boundary), scaled by √(V E_r) so that the blocks need no weight: √(V E_r) R ∇N_0..3 at the last
  // update [m^½] (12), and with the determinant volume term √(V E_r) cof F ∇N_0..3 (∂J/∂x_i) (12):
  // 12 or 24 doubles, 96 or 192 bytes (2 or 3 lines). The stiffness gather visits each element from
  // its 4 nodes in an order the hardware prefetcher cannot follow, so it is latency- and
  // bandwidth-bound: fewer lines per visit pay directly.
  static constexpr int kRecordTrace = 12, kRecordDeterminant = 24, kVolumeGrads = 12;
  int record_ = kRecordTrace;        // the record length in use (that of the last update)
  std::vector<double> records_raw_;  // record_ per element + 8 for the alignment
  double* records() { return alignedRecords(records_raw_.data()); }
  const double* records() const { return alignedRecords(records_raw_.data()); }
  static double* alignedRecords(const double* raw) {
    const auto a = reinterpret_cast<std::uintptr_t>(raw);
    return reinterpret_cast<double*>((a + 63) & ~static_cast<std::uintptr_t>(63));
  }
  std::vector<int> incident_slots_;  // per incidence k of the pattern (node order), j = 0..3: 3·blockSlot(e)[4i + j]
  std::vector<double> elem_forces_;  // 12 per element [N]
  Eigen::VectorXd modulus_factor_;   // E_r (stiffening)
  Eigen::VectorXd base_scale_;       // b_e = E_e / E0 (per-tissue moduli); the kernels use E_r b_e
  Eigen::VectorXd von_mises_;
  bool corotated_ = true;
  bool simd_kernels_ = true;
  VolumeTerm volume_term_ = kDefaultVolumeTerm;
  bool stiffness_is_determinant_ = false;  // the volume term at the last update()
  // The positions and formulation of the last element update: update() at the same ones reuses it.
  Points updated_at_;
  bool updated_at_valid_ = false;
  bool updated_corotated_ = true;
  VolumeTerm updated_volume_term_ = VolumeTerm::kTrace;
  double trace_lambda_ = 0.0;              // λ of the trace kernels at the last update(): λ, or −2μ/3 for kNone
  double volumeLambda() const { return trace_lambda_; }
  // The node forces summed over fixed chunks of batches (withChunkForces): chunk c holds batches
  // [chunk_batch_[c], chunk_batch_[c + 1]) and adds their forces to its own array over the nodes
  // its elements touch, slots [chunk_start_[c], chunk_start_[c + 1]) of chunk_forces_ (3 per slot);
  // force_tets_ gives each element's nodes as slots of its chunk; node n sums the slots
  // [cover_start_[n], cover_start_[n + 1]) of cover_slot_, in chunk order.
  std::vector<int> chunk_batch_, chunk_start_, force_tets_, cover_start_, cover_slot_;
  std::vector<double> chunk_forces_;  // [N]
  template <bool kDeterminant>
  void updateBatches(const Points& x, Eigen::VectorXd& f);
  /// f = the node forces batch(node_forces, b) adds for every batch b, summed per chunk of batches
  /// and then over chunks in chunk order: the same bits on any number of threads.
  template <class BatchFn>
  void withChunkForces(Eigen::VectorXd& f, BatchFn&& batch);
  template <bool kDeterminant, bool kAssign>
  void gatherStiffness(double scale, SparseMatrix& A) const;
};

}  // namespace breast_sim::core
