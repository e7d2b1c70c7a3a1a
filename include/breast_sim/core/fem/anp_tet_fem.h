#pragma once
/// @file anp_tet_fem.h
/// Average-nodal-pressure (ANP) linear tetrahedra [Bonet & Burton 1998; Joldes, Wittek & Miller
/// 2009, the element NiftySim uses for breast work]: linear tetrahedra without volumetric locking.

#include <memory>
#include <mutex>
#include <vector>

#include "breast_sim/core/fem/block_pattern.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/elastic_material.h"
#include "breast_sim/core/fem/element_formulation.h"

namespace breast_sim::core {

/// Why: a linear tetrahedron has one volume ratio J_e, and with ν → 0.5 (λ/μ = 24 at ν = 0.48) the
/// mesh can only bend by keeping every element's volume, which a mesh of linear tetrahedra cannot
/// do for most smooth deformations: it locks. Against quadratic tetrahedra (CalculiX C3D10) our
/// phantom's C3D4 solution is 1.2 mm off at ν = 0.48 (docs/speed_accuracy/locking.txt).
/// ANP penalises the volume change of each node's star instead: with V_e the rest volume and
/// w_ne = V_e / Σ_{e'∋n} V_e' the share of element e in node n's star,
///   J̄_n = Σ_{e∋n} w_ne J_e                      (the star's current over its rest volume)
///   W   = Σ_e V_e Ψ_dev(F_e) + Σ_n κ_n/2 · V̂_n (J̄_n − 1)²,   V̂_n = Σ_{e∋n} V_e / 4,
/// so there are about 5× fewer volume constraints (one per node, not per element) and the locking
/// goes. Ψ_dev is the deviatoric co-rotated energy (CorotatedTetFem, VolumeTerm::kNone:
/// P = 2μ R dev(S − I)), κ = λ + 2μ/3 the bulk modulus, κ_n = κ Σ_e w_ne E_r,e b_e (the stiffening
/// factors and per-tissue moduli averaged over the star). The forces are −∂W/∂x: each element
/// feels the average of its four nodal pressures p_n = κ_n (J̄_n − 1),
///   f_e,i = −V_e p̄_e ∂J_e/∂x_i,   p̄_e = ¼ Σ_{n∈e} p_n,   ∂J_e/∂x_i = cof F_e ∇N_i,
/// exactly the ANP element. The volumetric stiffness is the Gauss–Newton part
///   K_vol = Σ_n κ_n V̂_n b_n b_nᵀ,   b_n = ∂J̄_n/∂x = Σ_{e∋n} w_ne ∂J_e/∂x,
/// symmetric positive semi-definite, exact at rest (as CorotatedTetFem's kDeterminant term, it
/// drops the indefinite Σ_e V_e p̄_e ∂²J_e/∂x²). b_n spans node n's star, so K couples nodes two
/// element layers apart: pattern() is the two-ring BlockPattern, about 4× the entries of the
/// linear tetrahedra's (the multigrid must estimate its fine-level eigenvalue bound: the bound 4
/// holds only for four-node element matrices). Solvers that take a rank-one sum get the split
/// K = K_c + K_vol instead: compactPattern() is the one-ring pattern of the deviatoric and element
/// terms, rankOneStiffness() the sum Σ_n κ_n V̂_n b_n b_nᵀ, one term per node star, so no
/// two-ring matrix is assembled or multiplied (solver/rank_one_sum.h).
///
/// Element volume fraction β (setElementVolumeFraction): ANP constrains volume per node star, not
/// per element, so a single element can flatten or invert at the price of its shear energy alone
/// (as the seed's trace term lets it: docs/corotated) while its star keeps its volume. With β > 0
/// a share of the bulk modulus stays on each element's own J_e:
///   W_vol = Σ_n (1 − β) κ_n/2 · V̂_n (J̄_n − 1)² + Σ_e β κ_e/2 · V_e (J_e − 1)²,
/// forces f_e,i = −V_e ((1 − β) p̄_e + β κ_e (J_e − 1)) ∂J_e/∂x_i and the Gauss–Newton stiffness
/// gains β κ_e V_e ∂J_e/∂x ∂J_e/∂xᵀ per element. β = 0 is pure ANP; β = 1 the deviatoric/volumetric
/// split of linear tetrahedra (locking again). κ_e = κ E_r,e b_e.
///
/// Inversion barrier J_b (setInversionBarrier): a one-sided element term c κ_e/2 · V_e (J_b − J_e)₊²
/// that is zero while an element keeps more than the fraction J_b of its volume and resists
/// further compression below it, c times as stiffly as the bulk modulus, as the neo-Hookean
/// energy's log J does. Under the supine load ANP alone leaves a few rim elements (one free node
/// over a clamped face) inverted while their stars keep their volume (bench_speed_accuracy --study
/// locking); the barrier stops them without touching the locking-free response of the rest
/// (measured at 6k elements, ν 0.48: J_b 0.3 with c = 100 leaves none of 5 inverted for +0.04 mm
/// mean error; c = 1 leaves 2). Its force is continuous (the energy is C¹), its Gauss–Newton
/// stiffness c κ_e V_e ∂J_e/∂x ∂J_e/∂xᵀ is added for the elements below J_b at the last update.
/// J_b = 0 = off (the default).
/// \note The deviatoric part (rotations, von Mises stress, modulus factors, per-tissue moduli) is a
/// CorotatedTetFem on the one-ring pattern; vonMisesStress() is its (pressure does not enter a von
/// Mises norm).
class AnpTetFem : public ElementFormulation {
 public:
  /// @throws std::invalid_argument for an invalid material.
  AnpTetFem(const TetMesh& mesh, const ElasticMaterial& material);
  AnpTetFem(const AnpTetFem&) = delete;
  AnpTetFem& operator=(const AnpTetFem&) = delete;

  void update(const Points& x, Eigen::VectorXd& f) override;
  void addStiffness(double scale, SparseMatrix& A) const override;
  void assignStiffness(double scale, SparseMatrix& A) const override;
  /// The two-ring pattern, built on first use (a split run never needs it).
  const BlockPattern& pattern() const override { return wide().pattern; }
  const BlockPattern* compactPattern() const override { return &star_; }
  void assignCompactStiffness(double scale, SparseMatrix& A) const override;
  RankOneSum rankOneStiffness() const override;
  const Eigen::VectorXd& modulusFactors() const override { return deviatoric_.modulusFactors(); }
  void setModulusFactors(const Eigen::VectorXd& factors) override;
  const Eigen::VectorXd& vonMisesStress() const override { return deviatoric_.vonMisesStress(); }

  /// Per-element base Young's moduli [Pa]; as CorotatedTetFem::setElementYoungsModuli.
  void setElementYoungsModuli(const Eigen::VectorXd& youngs_modulus_pa);
  /// Share β ∈ [0, 1] of the bulk modulus kept on each element's own volume ratio (see above; 0 by
  /// default). @throws std::invalid_argument outside [0, 1] (names the value).
  void setElementVolumeFraction(double beta);
  double elementVolumeFraction() const { return beta_; }
  /// Volume ratio J_b ∈ [0, 1) below which an element resists compression on its own, with the
  /// stiffness factor c (a multiple of the bulk modulus; see above; J_b = 0 = off).
  /// @throws std::invalid_argument for J_b outside [0, 1) or c not positive and finite.
  void setInversionBarrier(double volume_ratio, double stiffness_factor = 100.0);
  double inversionBarrier() const { return barrier_j_; }
  /// Elements below the barrier at the last update.
  int barrierActiveElements() const { return barrier_active_; }
  /// A third of the barrier's volume ratio (0.1 at J_b 0.3; 0 without a barrier): an element that
  /// its star let fall below it counts as collapsed. The barrier's force grows with J_b − J but its
  /// linearisation does not see how fast J falls along a step through a nearly flat element, so on
  /// the phantom's morphing (20.8k elements) the skin and rim elements reached J 0.002 in accepted
  /// steps, and from there every step inverted one at any α.
  double collapsedVolumeRatio() const override { return barrier_j_ / 3.0; }
  /// When false, the deviatoric part is not co-rotated (plain linear; comparisons only).
  void setCorotated(bool corotated) { deviatoric_.setCorotated(corotated); }

  /// Bulk modulus κ = λ + 2μ/3 of the material [Pa].
  double bulkModulus() const { return kappa_; }
  /// Nodal volume ratios J̄_n at the last update (#N; 1 for a node in no element).
  const Eigen::VectorXd& nodalVolumeRatios() const { return nodal_volume_ratio_; }
  /// Nodal pressures p_n = (1 − β) κ_n (J̄_n − 1) at the last update [Pa] (#N; positive in expansion).
  const Eigen::VectorXd& nodalPressures() const { return nodal_pressure_; }
  /// Rest volume of node n's share of its star, V̂_n = Σ_{e∋n} V_e / 4 [m³] (#N).
  const Eigen::VectorXd& nodalRestVolumes() const { return nodal_rest_volume_; }

 private:
  CorotatedTetFem deviatoric_;  // Ψ_dev on the one-ring pattern
  // The one-ring pattern (deviatoric_'s): node n's star is its neighbour list here.
  const BlockPattern& star_ = deviatoric_.pattern();
  Tets tets_;
  double kappa_;
  double beta_ = 0.0;                // element volume fraction
  double barrier_j_ = 0.0;           // J_b of the inversion barrier (0 = off)
  double barrier_c_ = 100.0;         // its stiffness factor c (× κ_e)
  int barrier_active_ = 0;           // elements with J_e < J_b at the last update
  std::vector<double> element_stiffness_;  // κ_e V_e (β + [J_e < J_b]) at the last update [Pa m³]
  std::vector<double> grads_;        // 12 per element: ∇N_0..∇N_3 [1/m]
  std::vector<double> volumes_;      // V_e [m³]
  std::vector<double> star_weight_;  // per incidence k of star_ (node n, element e): w_ne
  Eigen::VectorXd nodal_rest_volume_, nodal_volume_ratio_, nodal_pressure_;
  Eigen::VectorXd nodal_stiffness_;  // (1 − β) κ_n V̂_n [Pa m³]: K_vol = Σ_n nodal_stiffness_n b_n b_nᵀ + …
  std::vector<double> volume_ratio_;  // J_e at the last update
  std::vector<double> dJ_;            // 12 per element: ∂J_e/∂x_i = cof F ∇N_i [m²]
  std::vector<double> elem_forces_;   // 12 per element: −V_e p̄_e ∂J_e/∂x_i [N]
  std::vector<double> b_;             // 3 per star_ entry (n, slot q): the block q of b_n [1/m]
  std::vector<int> own_slot_;         // per star_ entry (a, k): a's slot in the star of neighbour(k)
  std::vector<int> own_entry_;        // … and that slot's star_ entry: neighbourStart(neighbour(k)) + own_slot_[k]
  // What the assembled two-ring stiffness needs (pattern(), assignStiffness, addStiffness), built
  // on first use: the pattern; per star_ entry (a, k) the two-ring slot of neighbour(k) in a's
  // rows, and from wide_offset[k] the two-ring slots in a's rows of neighbour(k)'s star nodes; K_c
  // on the one-ring pattern, moved into the two-ring rows.
  struct Wide {
    BlockPattern pattern;
    std::vector<int> narrow_to_wide, wide_offset, wide_slot;
    mutable SparseMatrix narrow;
  };
  const Wide& wide() const;
  mutable std::unique_ptr<Wide> wide_;
  mutable std::once_flag wide_once_;
  bool barrierActive(double volume_ratio) const { return barrier_j_ > 0.0 && volume_ratio < barrier_j_; }
  // The stiffness weights, one formula each for update() and updateStiffnessWeights(): node n with
  // star-averaged modulus scale s, element e with its modulus scale and volume ratio J_e.
  double nodalWeight(int n, double s) const { return (1.0 - beta_) * kappa_ * s * nodal_rest_volume_[n]; }
  double elementWeight(int e, double scale, double j) const {
    return kappa_ * scale * volumes_[e] * (beta_ + (barrierActive(j) ? barrier_c_ : 0.0));
  }
  void updateStiffnessWeights();  // nodal_stiffness_ and element_stiffness_ for the current factors
  void addVolumetricStiffness(double scale, SparseMatrix& A) const;      // two-ring A
  void addElementVolumeStiffness(double scale, SparseMatrix& A) const;   // one-ring A
  void addWideStiffness(double scale, SparseMatrix& A, bool assign) const;
};

}  // namespace breast_sim::core
