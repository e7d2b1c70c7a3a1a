#pragma once
/// @file wall_slip.h
/// Implicit sliding on the chest wall: the wall nodes are free DOFs held on the wall by springs that
/// the implicit step takes into its matrix (DynamicSimulator::setNodeSprings), instead of moving
/// displacement constraints updated after each step (chest_wall_sliding.h, seed 2.4 / [GLDW10]).
///
/// Why: with the explicit update the wall lags the tissue by a step; under the stiffening loop of
/// seed Figure 2 its moves flattened and inverted the rim elements (measured on the two-breast
/// phantom: 74–96 % of the steps reversed, the loop never settled). Here the wall's reaction, the
/// slide and the tissue are solved together, so nothing lags and no move has to be taken back.
///
/// Per wall node i (area A_i, rest signed distance h0_i, normal n_i = ∇h at the start of the step),
/// with h the chest wall's signed distance from the segmentation (ChestWallSurface, no analytic
/// model) and P = I − n nᵀ the tangent projector, the spring is
///   K_i = A_i [κ_n n nᵀ + (κ_f + κ_g,i) P],
///   f_i = −A_i κ_n (h(x_i) − h0_i) n − A_i P [κ_f (x_i − s_i) + κ_g,i (x_i − r_i)]
///  - normal: a stiff penalty keeps the node at its rest distance from the wall (bilateral: the
///    fascia holds the breast on the wall in any posture); its force is the wall's normal reaction
///    F_n,i = A_i κ_n |h − h0|, linearised about the current point, re-linearised every step (curved
///    walls: the projection follows the wall, the normal turns with it);
///  - friction, stick or slip per node: a sticking node is held by a tangential stick spring κ_f to its
///    stick point s_i (it moves elastically by at most limit / (A κ_f): 0.14 mm at the defaults under
///    700 Pa of pressure); when after an accepted step that spring's force exceeds the static limit
///    μ_s F_n + τ0 A_i the node slips: the stick spring is dropped and the kinetic friction
///    μ_k F_n + τ0 A_i acts against its slip direction as a constant force of the step (F_n from the
///    start of the step); when its tangential speed falls below stick_speed_mps or reverses, it sticks
///    again where it is (s_i = x_i, put on the wall);
///  - limiting factors (seed): the retromammary fascia lets the breast slide on the pectoral fascia
///    but holds it, more so toward the sternum and the axilla. Every wall node is tethered to its rest
///    point r_i by a tangential spring κ_g,i = κ_0 / w_i, with w_i ∈ (0, 1] the limiting weight of
///    ChestWallSliding (the seed's bimodal Gaussian z, the thickness factor; 0 for nodes held there).
///    For a tangential traction τ the settled slide is then τ w_i / κ_0: the seed's "d = d + z D_f"
///    scales each explicit move by z, this scales the settled slide by it (a move scaled by z alone
///    only slows a node, which still slides until its traction is gone: measured on the two-breast
///    phantom, medial rim nodes with z ≈ 0.15 slid as far as with z = 1). Without a tether (κ_0 = 0)
///    only friction holds the wall, and a breast whose tangential load exceeds μ_k times its normal
///    load slides off;
///  - held nodes: a node of the set where the field describes no wall (ChestWallSliding::heldFlags:
///    farther than max_wall_distance_m from it, deeper than σ inside the mask, or within σ of the
///    image border) gets K_i = A_i κ_n I anchored at its rest point: it has no level to slide on;
///  - contact: free skin nodes may not enter the wall: a node whose h is below contact_gap_m gets a
///    normal penalty to that level (unilateral, decided from x_t each step).
/// All stiffnesses are per unit wall area [Pa/m], so they do not depend on the mesh size.
#include <memory>
#include <vector>

#include <Eigen/Dense>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"

namespace breast_sim::core {

struct WallSlipSettings {
  /// κ_n: normal penalty per wall area [Pa/m], > 0. 1e8: 700 Pa of wall pressure (a 7 cm column of
  /// tissue under 1 g) leaves the node 7 µm off its level, ~250× stiffer than the tissue (E/h).
  double normal_stiffness_pa_per_m = 1e8;
  /// κ_f: tangential stick stiffness per area [Pa/m], > 0 (elastic pre-slip = limit / κ_f).
  double friction_stiffness_pa_per_m = 1e6;
  double static_friction = 0.2;      ///< μ_s [-], ≥ 0
  double kinetic_friction = 0.15;    ///< μ_k [-], in [0, μ_s]
  double static_threshold_pa = 0.0;  ///< τ0: traction needed besides friction [Pa], ≥ 0
  /// A slipping node whose tangential speed falls below this sticks again [m/s], ≥ 0.
  double stick_speed_mps = 1e-4;
  /// κ_0: tangential tether per wall area of a node with weight 1 [Pa/m], ≥ 0 (a node of weight w
  /// gets κ_0 / w); 0 = no tether: free sliding governed by friction and shape alone (the seed's
  /// bypass of the limiting factors; the default, because the phantom's supine target moves its whole
  /// base 15 mm laterally: measured at 8.9k elements, morphing reaches 0.18 / 0.43 mm mean / p95 with
  /// κ_0 = 0, 0.35 / 1.30 mm at 2e4 and 0.69 / 4.13 mm at 5e4). 5e4: a tangential traction of 500 Pa
  /// slides a node of weight 1 by 10 mm.
  double tether_stiffness_pa_per_m = 0.0;
  /// stickReversed(): a slipping node driven back against its slip direction by more than this (and
  /// more than its pre-slip length) is set sticking and the step repeated [m], ≥ 0. Back moves below
  /// a millimetre are common in converging runs and do little work.
  double reversal_tolerance_m = 1e-3;
  /// Weights below this count as this [-], in (0, 1] (a held node, w = 0, gets κ_0 / min_weight).
  double min_weight = 1e-3;
  bool contact = true;               ///< unilateral skin–wall contact
  double contact_gap_m = 0.2e-3;     ///< a free skin node is held at least this far off the wall [m], ≥ 0
  /// Skin nodes farther from the wall than this at rest are never contact candidates [m], > gap.
  double contact_range_m = 10e-3;

  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// Linear node springs of another part (e.g. the morphing's implicit pull), given to
/// WallSlip::beforeStep to be set together with the wall's (the simulator holds one set of springs,
/// one block per node): f_i = −K_i (x_i − a_i).
struct NodeSprings {
  std::vector<int> nodes;
  std::vector<Eigen::Matrix3d> stiffness_n_per_m;  ///< symmetric 3×3 [N/m] per node
  Points anchors_m;                                ///< a position per node [m]
};

/// What the last afterStep() saw.
struct WallSlipStats {
  int slipping = 0;              ///< wall nodes slipping after the step
  int contacts = 0;              ///< skin nodes held off the wall in the last step
  double max_slide_m = 0.0;      ///< largest tangential displacement of a wall node from rest [m]
  double max_normal_error_m = 0.0;  ///< largest |h − h0| of a wall node [m]
};

class WallSlip {
 public:
  /// @param geometry the wall nodes, their areas, rest distances and limiting weights (the node set
  ///                 and limiting factors of `settings.sliding`, built by ChestWallSliding::fromCase)
  WallSlip(std::shared_ptr<const ChestWallSliding> geometry, const TetMesh& mesh, const WallSlipSettings& settings);
  /// Builds the geometry from a case (the chest-wall mask of its label image) and sliding settings.
  static WallSlip fromCase(const ModelCase& model_case, const TetMesh& mesh, const SlidingSettings& sliding,
                           const WallSlipSettings& settings);

  /// Frees the wall nodes in `sim` (their Dirichlet conditions) and sets the springs from its state.
  void attach(DynamicSimulator& sim);
  /// Before each step (and before each retry of a reversed step): the springs linearised at the
  /// simulator's current state. Contacts are decided here. `extra` springs are set with them (on a
  /// node that has a wall or contact spring too, the two are summed: K = K1 + K2, anchor a1 and the
  /// constant force K2 (a2 − a1), the same force at every position).
  void beforeStep(DynamicSimulator& sim, const NodeSprings* extra = nullptr);
  /// After an accepted step: the friction return mapping (stick points follow slipping nodes).
  WallSlipStats afterStep(const DynamicSimulator& sim);
  /// Kinetic friction acts in a step as a constant force against the slip direction of its start.
  /// A node whose driving load falls below that force comes to rest within the step, and in a long
  /// step the constant force then drives it back: friction does positive work (measured on the
  /// phantom, 7.1k elements, sliding stage at 0.33 s, morphing at 0.1 s: up to 350 of 392 wall nodes
  /// pushed back by up to 189 mm in one step, the breast oscillating with growing amplitude until it
  /// left the target). Coulomb friction instead holds a node that stops: call this after a step from
  /// `u_start_m` (3N [m], the displacement the step started from) and before afterStep(). Slipping
  /// nodes that moved against their slip direction by more than their elastic pre-slip length
  /// (limit / (A κ_f), the move a stick spring allows at the kinetic limit) and reversal_tolerance_m are set sticking at their
  /// start point (put on their wall level); the caller then repeats the step from u_start_m.
  /// @return the number of nodes set sticking (0: the step stands).
  /// @throws std::invalid_argument when u_start_m does not have 3N entries.
  int stickReversed(const DynamicSimulator& sim, const Eigen::VectorXd& u_start_m);

  /// Held: no wall node starts to slip, and the slipping ones stick where they are now (put on their
  /// wall level); each stays within its elastic pre-slip of its stick point (force / (A κ_f)). For
  /// tracking a surface scan, which sees the anterior skin and cannot observe a slide along the wall.
  void setHeld(bool held, const DynamicSimulator& sim);
  bool held() const { return held_; }

  const std::vector<int>& nodes() const { return nodes_; }
  const WallSlipSettings& settings() const { return settings_; }
  const ChestWallSliding& geometry() const { return *geometry_; }
  /// Stick points s_i [m], one row per node of nodes() (positions, not displacements).
  const Points& stickPoints() const { return stick_; }
  /// Per node of nodes(): 1 while slipping (kinetic friction), 0 while sticking.
  const std::vector<char>& slipping() const { return slipping_; }
  /// Per node of nodes(): the unit slip direction while slipping, a zero row while sticking.
  Points slipDirections() const;
  /// Restores stick points and, if given, slip directions as slipDirections() returned them (none:
  /// every node sticks), e.g. from a saved pipeline state. @throws on a wrong row count.
  void setStickPoints(const Points& stick_m, const Points& slip_directions = Points());
  /// Tether stiffness per node, κ_g,i [Pa/m].
  const Eigen::VectorXd& tetherStiffness() const { return tether_; }
  /// Sliding vector per mesh node [m]: a wall node's displacement projected on the wall's tangent
  /// plane at its rest point; 0 elsewhere (#N×3, for VTK point data and rviz arrows).
  Points slidingVectors(const DynamicSimulator& sim) const;

 private:
  std::shared_ptr<const ChestWallSliding> geometry_;
  const TetMesh& mesh_;
  WallSlipSettings settings_;
  std::vector<int> nodes_;
  Eigen::VectorXd area_, h0_, tether_;
  Points stick_;
  std::vector<char> slipping_;
  Points slip_dir_;                   // unit tangent of the slip velocity per node
  std::vector<char> on_wall_;         // per mesh node
  std::vector<int> contact_candidates_;
  double contact_area_m2_ = 0.0;      // nominal area of a skin node (the mean wall-node area)
  int last_contacts_ = 0;
  bool held_ = false;
  std::vector<int> spring_slot_;      // per mesh node: its row in beforeStep's springs, −1 = none (kept at −1 between steps)
};

}  // namespace breast_sim::core
