#pragma once
/// @file chest_wall_sliding.h
/// Sliding of the breast on the chest wall (seed section 2.4, after [GLDW10]): the chest-wall nodes
/// carry displacement constraints (DynamicSimulator::setNodeTargets) that are moved after every
/// step along the wall, in proportion to the force the constraint has to supply, under friction.
///
/// Per step and sliding node i (positions x = X + u at the end of the step):
///  1. Constraint (reaction) force, quasi-static approximation:
///       r_i = −(f_el,i(x) + m_i g + f_ext,i)                                           [N]
///     the force the wall must supply for node i to be in equilibrium (inertia m_i a_i and Rayleigh
///     damping at the node are neglected: the constraint moves slowly, and the seed runs towards a
///     settled state). The node pushes on the wall with −r_i, i.e. the applied load f_i = −r_i.
///  2. Normal n (chest_wall_surface.h) at x_i; traction of the node's share A_i of the wall area
///     (a third of each chest-wall boundary triangle it belongs to):
///       τ_n = |f_i·n| / A_i (pressing or pulling: the constraint is bilateral, the tissue is attached
///       by fascia),  τ_t = (f_i − (f_i·n) n) / A_i                                     [Pa]
///  3. Friction: a node at rest stays while |τ_t| ≤ μ_s τ_n + τ_0 (static); otherwise (or while it
///     is moving) the driving traction is |τ_t| − μ_k τ_n − τ_0 (kinetic), ≥ 0, along τ_t.
///  4. Velocity v_i = w_i · mobility · (driving traction) · τ_t/|τ_t| [m/s] (w_i: limiting factors);
///     with inertia β: v_i ← β P_t v_i,prev + (1 − β) v_i (P_t: onto the current tangent plane).
///     The move dt · v_i is clamped to max_step_m and, once attach() has measured the node's
///     stiffness along the move, k_i = tᵀ K_ii t (K_ii its 3×3 diagonal block of K at attach time,
///     t the unit driving direction) [N/m], to
///     (driving traction) · A_i / (κ k_i): 1/κ of the move that would by itself cancel the driving
///     force. The update is explicit (a relaxation step), and without this cap it oscillates
///     node against node once dt · mobility · k_i / A_i > 2 (fine meshes, long steps); κ = 1.
///  5. New constraint point x_i + dt v_i, projected back onto the wall (the node keeps its rest
///     signed distance h_i0 = clamp(h(X_i), 0, max_wall_distance_m): it slides parallel to the
///     wall and never enters it); with a permissible shift (max_slide_m > 0) the total slide
///     |x_i − X_i| is capped at w_i · max_slide_m first.
///
/// Robustness (what keeps the constraint moves from inverting elements, which no stiffening α can
/// undo because the targets force them): the traction of step 2 is averaged over a ring of wall
/// neighbours (area-weighted), the moves are smoothed over the wall graph (held nodes count with
/// move 0), rim nodes (wall and skin) follow the mean move of their wall neighbours, and the skin
/// nodes within max_wall_distance_m of the wall next to the rim join the set (rim band: without
/// it the skin next to the rim folds onto the wall and pushes a free node through a rim sliver);
/// finally a volume guard halves the moves of the sliding corners of any wall element the moves
/// would take below min_volume_fraction of its rest volume. afterStep() adds the take-back of a
/// move after a stiffening call that could not advance.
///
/// Skin–wall contact (afterStep(), contact = true). As the breast spreads beyond its footprint
/// under supine gravity, the free skin next to the rim falls onto the chest wall; a free node that
/// reaches the wall (or the plane of a rim triangle that lies on it) flattens and inverts the
/// elements between it and the wall, which no α and no constraint move prevents (measured, see
/// docs/sliding.md, "The explicit update"). So after every accepted step each free skin node (node set
/// "skin", not yet constrained) whose signed wall distance, predicted two steps ahead along its
/// approach velocity, h_pred = h(x) + 2 dt min(0, ∇h·u̇) (two: a falling node still accelerates),
/// or h(x) itself, is at most contact_tolerance_m becomes a contact node: a
/// sliding constraint held at the level ℓ = max(contact_gap_m, h(x)) of the wall (it is caught where
/// it is; a node that crossed into the wall is put back at the gap: never inside). Under a pressing
/// load ℓ descends half way to the gap per step (the skin settles onto the wall). A contact node
/// then slides like a rim node: it follows the mean move of its constrained neighbours closer to
/// the wall (graph distance), else it moves by its own traction under the same friction law, with
/// the limiting weight of its touch-down point on the wall (the Gaussian there, times the mean
/// thickness factor of its constrained neighbours) and its permissible shift counted from its
/// touch-down point. The contact is unilateral (contact_release): a contact node whose load pulls
/// it off the wall with more than contact_release_pa of normal traction in three accepted calls in
/// a row is freed (one call's reaction carries inertia: a node caught falling, a bounce; a released node
/// is caught again only once it comes within contact_gap_m / 2). The chest-wall attachment of the rest
/// footprint (nodes()) stays bilateral: fascia. Contacts are part of the take-back like the wall:
/// the simulator's state does not hold constraints, and stiff.revertTo(0) restores the state of the
/// last accepted step, the state the contact was made at, so the kept constraint is consistent;
/// its pending move is halved, then held, as the wall's.
/// \note DynamicSimulator has no call that frees single nodes, so a release calls
/// clearConstraints() and re-imposes every other constraint: the sliding set and the remaining
/// contacts as targets, the nodes that were constrained by others at attach() as fixed nodes (where
/// they are). A target that another component set on a node outside the sliding set would thus
/// become a fixation; nothing in breast_sim does that (the pipeline constrains only the wall).
///
/// Limiting factors w_i ∈ [0, 1], each optional (all off: the seed's bypass, "free sliding governed
/// by friction and shape alone"):
///  - tissue thickness: the distance from the wall to the skin along the rest normal (ray marching
///    in the label image), divided by its maximum over the sliding nodes;
///  - the seed's bimodal Gaussian
///       z(u, v) = A exp(−((u−u0)²/(2σu²) + (v−v0)²/(2σv²))) + A exp(−((u−u1)²/(2σu²) + (v−v1)²/(2σv²)))
///    clamped to [0, 1], in chest-wall plane coordinates (u, v): the plane through the nipples'
///    midpoint perpendicular to the anterior direction a (prone gravity, chest wall → nipple);
///    each mode is centred at its nipple's foot point on the wall (closest wall point);
///    u along the nipple-to-nipple direction projected into that plane (lateral, towards the first
///    nipple), v = a × u (superior for LPS images with a = −y and u = +x). (u_k, v_k) are the foot
///    points' coordinates (not the nipples projected along a, which a curved wall shifts
///    laterally); σu, σv by default half of a breast's extent along u and v, measured from the
///    sliding nodes closest to each nipple. The seed uses one v0 for both modes; here each
///    nipple gives its own v_k (equal for a symmetric patient). With one nipple there is one mode.
///
/// \note Without a permissible shift the limiting factors scale only the rate (seed: d = d + z D_f):
/// a settled state is then the same with or without them. max_slide_m > 0 makes them limit the
/// final slide (the seed's "permissible shift") — the default.
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/tissue_labels.h"
#include "breast_sim/core/sliding/chest_wall_surface.h"

namespace breast_sim::core {

struct ModelCase;

/// Parameters of sliding. SI units; defaults work on the phantoms (config/phantom_*.yaml).
struct SlidingSettings {
  ChestWallFieldOptions field;  ///< normal field: σ = 2 mm

  /// Slide velocity per unit of net tangential traction [m/(Pa·s)] (a traction, not a nodal force,
  /// so it does not depend on the mesh size). 5e-5: 370 Pa (the tangential traction of a 0.35 kg
  /// breast on a 25° slope of its base under 2 g) slides ~2 cm/s.
  double mobility_m_per_pa_s = 5e-5;
  double static_friction = 0.2;      ///< μ_s [-], ≥ 0
  double kinetic_friction = 0.15;    ///< μ_k [-], in [0, μ_s]
  double static_threshold_pa = 0.0;  ///< τ_0: traction needed besides friction [Pa], ≥ 0
  double inertia = 0.0;              ///< β in [0, 1): share of the last velocity kept (0 = none)
  double max_step_m = 1e-3;          ///< largest move of a constraint per step [m], > 0
  /// κ of the stability cap (see the file comment) [-], in [1, 100]: larger is slower but safer.
  double stiffness_safety = 1.0;
  /// Nodes of the set farther than this from the wall surface at rest are held (not slid) [m]
  /// (rim nodes a skin element off the wall); in (0, 3σ]. So are nodes deeper than σ inside the
  /// wall mask and nodes within σ of the image border (see heldFlags()).
  double max_wall_distance_m = 3e-3;
  int projection_iterations = 8;        ///< Newton steps onto the wall, [1, 50]
  double projection_tolerance_m = 1e-7; ///< [m], > 0

  bool thickness_limit = false;  ///< scale by local tissue thickness / its maximum
  bool gaussian_limit = true;    ///< the seed's bimodal Gaussian z(u, v)
  double gaussian_amplitude = 1.0;  ///< A [-], > 0 (z is clamped to 1)
  /// σu = σv = this [m]; 0 = per axis gaussian_sigma_fraction × a breast's extent along it.
  double gaussian_sigma_m = 0.0;
  double gaussian_sigma_fraction = 0.5;  ///< seed: half a breast's diameter; in (0, 2]
  /// Permissible total slide at weight 1 [m]; a node's slide is capped at w_i times this; 0 = no cap.
  double max_slide_m = 0.03;

  // Robustness of the constraint moves (both update() and afterStep()); see the file comment.
  /// Rings of area-weighted traction averaging over the wall graph (a node and its wall neighbours):
  /// τ_i = Σ_j f_j / Σ_j A_j over the ring. Nodal reactions of an unstructured mesh vary from node to
  /// node far more than the traction they sample; in [0, 20], 0 = none.
  int traction_smoothing_rings = 1;
  /// Jacobi sweeps of neighbour averaging of the move field, m_i ← (m_i + mean_j m_j) / 2 (held
  /// nodes take part with move 0, so moving regions blend into held ones); in [0, 50], 0 = none.
  int move_smoothing_iterations = 2;
  /// Rim nodes (in both the sliding set and `skin`: where the skin meets the wall) take the mean
  /// move of their non-rim wall neighbours instead of their own: their reaction carries the skin's
  /// pull, not the wall's traction.
  bool rim_follows_neighbours = true;
  /// Rim band: the skin nodes within max_wall_distance_m of the wall that are joined to the rim
  /// through skin nodes join the sliding set (held at their rest distance from the wall, following
  /// the rim like it follows the wall). Without it, the skin next to the rim folds onto the wall as
  /// the breast spreads: a free skin node is pushed through the rim triangle of a sliver whose three
  /// other corners are constrained, an inversion no α prevents (measured: rim elements flattened to
  /// 2 % of their rest volume over accepted steps, then inverting at E_r = 1e6).
  bool rim_band = true;
  /// Volume guard [-], in [0, 1): a move may not take a wall element (one with a sliding node) below
  /// this fraction of its rest volume unless the element grows; the moves of its sliding nodes are
  /// halved until it holds (at most 6 times, then they are not moved). 0 = only non-inversion.
  double min_volume_fraction = 0.3;
  /// afterStep(): the moves are scaled by a factor s in [min_move_scale, 1] that is halved after a
  /// stiffening call whose step reversed (the move may have caused it) and grows by 1.25 after clean
  /// steps; a call that could not advance takes the last move back by half (and s by a quarter)
  /// until s < min_move_scale, then holds the wall. In (0, 1].
  double min_move_scale = 1.0 / 64.0;

  /// Skin–wall contact in afterStep() (see the file comment).
  bool contact = true;
  /// A free skin node becomes a contact node when its wall distance predicted one step ahead is at
  /// most this [m]; in (contact_gap_m, 3σ].
  double contact_tolerance_m = 0.5e-3;
  /// Smallest distance a contact node is held off the wall surface [m], in [0, contact_tolerance_m).
  double contact_gap_m = 0.2e-3;
  /// Unilateral contact: a contact node whose load pulls it off the wall is freed.
  bool contact_release = true;
  /// Normal traction [Pa] pulling a contact node off the wall beyond which it is freed, ≥ 0.
  double contact_release_pa = 50.0;

  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

/// What one sliding update did.
struct SlidingStepStats {
  int moving = 0;          ///< nodes whose constraint moved
  int stuck = 0;           ///< nodes held by static friction
  int capped = 0;          ///< nodes at their permissible shift
  int stiffness_limited = 0;    ///< moves shortened by the stability cap
  int projection_failures = 0;  ///< moves dropped because the projection did not converge
  double max_move_m = 0.0;      ///< largest constraint move of this step [m]
  double max_slide_m = 0.0;     ///< largest total slide [m]
  double max_penetration_m = 0.0;  ///< largest max(0, −h) over the targets [m] (0 = none inside)
  int guard_limited = 0;        ///< moves shortened by the volume guard
  int guard_held = 0;           ///< of which not moved at all (six halvings were not enough)
  int rim_nodes = 0;            ///< rim nodes that followed their neighbours
  double move_scale = 1.0;      ///< afterStep(): scale s of this step's moves
  bool taken_back = false;      ///< afterStep(): the stiffening call did not advance; the last move was shrunk
  bool held_wall = false;       ///< afterStep(): … and the wall is now held at its current position
  int contacts = 0;             ///< afterStep(): contact nodes after this call
  int contacts_added = 0;       ///< afterStep(): free skin nodes that touched the wall in this call
  int contacts_released = 0;    ///< afterStep(): contact nodes freed in this call (pulled off the wall)
  /// afterStep(): smallest signed wall distance of the free skin nodes after the call [m]
  /// (+inf without contact or skin).
  double min_free_skin_distance_m = 0.0;
  double seconds = 0.0;         ///< the update without the elastic forces [s]
  double force_seconds = 0.0;   ///< DynamicSimulator::elasticForces() in update(sim) [s] (0 in afterStep)
};

/// The sliding constraints of one node set on one chest wall.
class ChestWallSliding {
 public:
  /// @param mesh     the rest mesh
  /// @param nodes    the sliding nodes (usually the node set "chest_wall")
  /// @param surface  the chest wall (shared: one per image)
  /// @param labels   the segmentation the mesh was built from (thickness limit; may be null when
  ///                 thickness_limit is off) and its tissue labels
  /// @param nipples_m  nipple points [m] (Gaussian limit; 1 or 2 needed when it is on)
  /// @param anterior  unit direction chest wall → nipple (ModelCase::prone_gravity_direction)
  /// @throws std::invalid_argument for invalid settings, an empty or out-of-range node set, a
  ///         Gaussian limit without nipples (or more than two), a thickness limit without image.
  ChestWallSliding(const TetMesh& mesh, std::vector<int> nodes, std::shared_ptr<const ChestWallSurface> surface,
                   const SlidingSettings& settings, const LabelImage* labels, const TissueLabels& tissue,
                   const std::vector<Eigen::Vector3d>& nipples_m, const Eigen::Vector3d& anterior);

  /// Everything from a case: its image, chest-wall labels, nipples (the phantom's if the case has
  /// none), anterior direction and the model's "chest_wall" node set.
  static ChestWallSliding fromCase(const ModelCase& model_case, const TetMesh& mesh, const SlidingSettings& settings);

  /// Replaces the Dirichlet fixation of the sliding nodes by targets at their current displacement
  /// (and drops the contact nodes of an earlier run: they are made again as the skin touches),
  /// and measures each sliding node's stiffness k_i for the stability cap (one stiffness assembly at
  /// the current state).
  void attach(DynamicSimulator& sim);
  /// The 3×3 diagonal stiffness blocks K_ii of the sliding nodes [N/m], 9 per node (row-major),
  /// for the stability cap (empty before attach(): no cap).
  const Eigen::VectorXd& nodeStiffness() const { return stiffness_; }
  /// After sim.step(): computes the elastic forces at the current state (sim.elasticForces()),
  /// moves the constraints and hands them to sim.setNodeTargets.
  /// @param external_forces  the 3N external forces [N] added to sim (addNodalForces), if any
  SlidingStepStats update(DynamicSimulator& sim, const Eigen::VectorXd* external_forces = nullptr);
  /// The update itself from the state: u (3N [m]), f_el (3N [N]), lumped masses (N [kg]),
  /// gravity [m/s²], dt [s], f_ext (3N [N] or null). Returns the stats; targets() has the result.
  SlidingStepStats update(const Eigen::VectorXd& displacement_m, const Eigen::VectorXd& elastic_forces_n,
                          const Eigen::VectorXd& mass_kg, const Eigen::Vector3d& gravity_mps2, double dt_s,
                          const Eigen::VectorXd* external_forces_n = nullptr);
  /// The update from the loads the nodes put on the wall: u (3N [m]), loads (3N [N], e.g.
  /// −DynamicSimulator::constraintForces()), dt [s], move scale in (0, 1].
  SlidingStepStats updateFromLoads(const Eigen::VectorXd& displacement_m, const Eigen::VectorXd& wall_loads_n,
                                   double dt_s, double move_scale = 1.0);

  /// The sliding step of the combined loop (seed Figure 2), called after EVERY
  /// StiffeningSimulation::step() (constraints attach()ed to stiff.simulator() first):
  ///  - the call advanced: the constraints move by the load the nodes put on the wall, read from the
  ///    step's constraint reactions (load = −sim.constraintForces(): the reaction of the constraint
  ///    rows, inertia and damping of the wall nodes included; no extra elastic-force evaluation),
  ///    scaled by the move scale s (halved if the call reversed a step, else ×1.25 up to 1), with the
  ///    volume guard on the wall elements;
  ///  - the call could not advance (reversal limit): if the wall moved last time, that move is taken
  ///    to be the cause (no α saves an inversion that the targets force): stiff.revertTo(0) undoes the
  ///    α escalation of the failed call, the pending move is halved and s quartered; once s falls
  ///    below min_move_scale the wall is held where it is. If the wall did not move, the failure is
  ///    not sliding's: nothing changes (α keeps rising as the seed's loop wants).
  /// The simulator never keeps targets that the guard did not pass. Usage:
  /// @code
  ///   StiffeningSimulation stiff(sim, mesh);
  ///   ChestWallSliding sliding = ChestWallSliding::fromCase(model_case, mesh, SlidingSettings{});
  ///   sliding.attach(sim);
  ///   for (int k = 0; k < max_calls; ++k) {
  ///     // (morphing forces, if any, go to sim.addNodalForces() before the step)
  ///     const StiffeningStepResult r = stiff.step();
  ///     const SlidingStepStats s = sliding.afterStep(stiff, r);
  ///     if (r.advanced && stiff.settled() && s.max_move_m < 1e-5) break;
  ///   }
  ///   Points arrows = sliding.slidingVectors();  // per node [m]
  /// @endcode
  /// @throws std::invalid_argument if stiff's simulator does not match the mesh.
  SlidingStepStats afterStep(StiffeningSimulation& stiff, const StiffeningStepResult& r);
  double moveScale() const { return move_scale_; }  ///< s of afterStep()
  /// Prescribes the constraint targets [m] (one row per node of nodes(), displacement from rest) and
  /// hands them to the simulator, unchecked (no guard, no projection): a wall moved from outside,
  /// e.g. a repositioned patient. afterStep() treats it like its own move: taken back if the next
  /// stiffening call cannot advance. @throws std::invalid_argument for a wrong row count.
  void setTargets(DynamicSimulator& sim, const Points& targets_m);

  /// The sliding nodes: the given set, then the rim band (rim_band) appended. Fixed after
  /// construction (contact nodes are separate: contactNodes()).
  const std::vector<int>& nodes() const { return base_nodes_; }
  const SlidingSettings& settings() const { return settings_; }
  const ChestWallSurface& surface() const { return *surface_; }
  /// Target displacements of the sliding nodes [m], one row per node of nodes().
  const Points& targets() const { return base_targets_; }
  /// The current contact nodes (skin nodes that touched the wall), in activation order.
  std::vector<int> contactNodes() const { return std::vector<int>(nodes_.begin() + num_base_, nodes_.end()); }
  /// Target displacements of the contact nodes [m], one row per node of contactNodes().
  Points contactTargets() const { return targets_.bottomRows(targets_.rows() - num_base_); }
  int contactsMade() const { return contacts_made_; }          ///< activations since attach()
  int contactsReleased() const { return contacts_released_; }  ///< releases since attach()
  /// Sliding vector per mesh node [m]: the total constraint displacement along the wall (target −
  /// rest) for sliding nodes, the slide since touch-down (target − touch-down point) for contact
  /// nodes, 0 elsewhere; #N×3 (for VTK point data and rviz arrows).
  Points slidingVectors() const;
  /// The per-node arrays below (weights() … rimFlags()) have one entry per node of nodes(), then
  /// one per contact node (contactNodes()).
  /// Limiting weight w_i ∈ [0, 1] per sliding node (1 with all limits off; 0 for held nodes).
  const Eigen::VectorXd& weights() const { return weight_; }
  const Eigen::VectorXd& thicknessFactors() const { return thickness_factor_; }  ///< 1 when off
  const Eigen::VectorXd& gaussianFactors() const { return gaussian_factor_; }    ///< 1 when off
  const Eigen::VectorXd& tissueThickness() const { return thickness_m_; }  ///< [m]; 0 when off
  const Eigen::VectorXd& nodeAreas() const { return area_; }  ///< wall area per node [m²]
  int heldNodes() const { return held_; }  ///< nodes the wall field cannot guide (heldFlags())
  /// Per node of nodes(): 1 if held where it is, else 0: where the wall field describes no wall to
  /// slide on. Measured on the VICTRE label image (config/victre_case.yaml, 21.8k elements, 715 wall
  /// nodes), with each kind left free: 35 farther than max_wall_distance_m (faces where the image
  /// border cuts the body, at the field's saturation: the breast does not stop sliding); 15 deeper
  /// than σ in the muscle (among them 5 of a one-voxel tissue filament, which slide 61–217 mm along
  /// its tube); 102 within σ of the image border (with the ANP element a few of them switch between
  /// stick and slip, moving 1–3 mm per step, and the stage does not settle).
  const std::vector<char>& heldFlags() const { return held_flag_; }
  /// Chest-wall plane frame of the Gaussian limit: origin [m], unit axes u and v.
  Eigen::Vector3d planeOrigin() const { return plane_origin_; }
  Eigen::Vector3d planeU() const { return plane_u_; }
  Eigen::Vector3d planeV() const { return plane_v_; }
  Eigen::Vector2d gaussianSigma() const { return gaussian_sigma_; }  ///< (σu, σv) [m]
  /// The bimodal Gaussian weight z(u, v) at a point (clamped to [0, 1]).
  double gaussianWeight(const Eigen::Vector3d& p_m) const;
  /// Centres of the Gaussian modes [m]: each nipple's foot point on the wall (the closest point of
  /// the chest-wall boundary triangles at rest, i.e. along the wall normal), not the nipple
  /// projected along the anterior direction (which a curved wall shifts laterally).
  const std::vector<Eigen::Vector3d>& gaussianCentres() const { return centre_points_; }
  /// Rim and rim-band nodes (sliding nodes that are also skin nodes), 0/1 per node of nodes().
  const std::vector<char>& rimFlags() const { return rim_flag_; }

 private:
  // Limiting factors at construction (sliding_limits.cpp), from rest_: thickness_m_ and
  // thickness_factor_ (ray marching in `labels`; 0 and 1 with the limit off); the chest-wall plane
  // frame, the Gaussian centres, σ and gaussian_factor_ (1 with the limit off). slot: the slot of
  // each mesh node, −1 outside the sliding set.
  void measureThickness(const LabelImage* labels, const TissueLabels& tissue);
  void placeGaussian(const TetMesh& mesh, const std::vector<int>& slot, const std::vector<Eigen::Vector3d>& nipples_m,
                     const Eigen::Vector3d& anterior);
  // Contact: frees pulled-off contact nodes and adds the free skin nodes that touch the wall as
  // slots (slot arrays compacted, graph rebuilt, constraints re-imposed on a release). Fills the
  // contact counts of st; returns whether a node was freed.
  bool updateContacts(DynamicSimulator& sim, const Eigen::VectorXd& load, SlidingStepStats& st);
  // Wall graph, rim levels of the contact slots and wall elements from the current slots.
  void buildGraph();
  // Drops the slots whose keep flag is 0 (every per-slot array).
  void compactSlots(const std::vector<char>& keep);

  SlidingSettings settings_;
  std::shared_ptr<const ChestWallSurface> surface_;
  // Slots: the sliding nodes (nodes(), the first num_base_) then the contact nodes. Every per-slot
  // array below follows this order.
  std::vector<int> nodes_;
  std::vector<int> base_nodes_;
  int num_base_ = 0;
  Points base_targets_;  // the first num_base_ rows of targets_ (targets())
  int num_mesh_nodes_;
  Tets mesh_tets_;
  std::vector<int> slot_of_;          // per mesh node: slot or −1
  std::vector<int> skin_candidates_;  // skin nodes outside nodes()
  std::vector<char> released_;        // per mesh node: freed once (caught again only within the gap)
  std::vector<int> tension_calls_;    // per mesh node: accepted calls in a row pulling off the wall
  std::vector<int> foreign_fixed_;    // nodes constrained by others at attach()
  int contacts_made_ = 0, contacts_released_ = 0;
  Points origin_;        // per slot: where its slide is counted from (rest; touch-down for contacts)
  Points rest_;          // rest positions of the sliding nodes
  Points mesh_rest_;     // rest positions of all mesh nodes (volume guard)
  Points targets_;       // target displacements
  Points velocity_;      // constraint velocities [m/s]
  Eigen::VectorXd stiffness_;
  Eigen::VectorXd h0_, area_, weight_, thickness_factor_, gaussian_factor_, thickness_m_;
  std::vector<char> held_flag_;
  int held_ = 0;
  Eigen::Vector3d plane_origin_ = Eigen::Vector3d::Zero(), plane_u_ = Eigen::Vector3d::UnitX(),
                  plane_v_ = Eigen::Vector3d::UnitZ();
  std::vector<Eigen::Vector2d> centres_;
  std::vector<Eigen::Vector3d> centre_points_;
  Eigen::Vector2d gaussian_sigma_ = Eigen::Vector2d::Ones();
  // Wall graph (CSR over slots: sliding nodes joined by a tet edge), rim flags, and the wall
  // elements for the volume guard: tet nodes, slot per corner (−1 = not sliding), rest volume.
  std::vector<int> nbr_start_, nbr_;
  std::vector<char> rim_flag_;
  std::vector<int> rim_level_;  // 0 wall, 1 rim (wall and skin), 2… rim band rings
  std::vector<Eigen::Vector4i> wall_tets_, wall_slots_;
  std::vector<double> wall_rest_volume_;
  // afterStep(): move scale and whether the last call moved the wall.
  double move_scale_ = 1.0;
  bool last_moved_ = false;
};

/// Runs steps with a sliding update after each until both the largest nodal displacement change
/// and the largest constraint move of a step stay ≤ options.increment_tolerance_m for
/// options.consecutive_steps steps, or options.max_steps; the dynamics time step is used
/// (options.time_step_s is ignored: the explicit constraint update is tuned for it).
/// @param progress  called after every step with (step, increment [m], sliding stats); may be empty
struct SlidingSettleResult {
  bool settled = false;
  int steps = 0;
  double seconds = 0.0;          ///< wall time of everything [s]
  double sliding_seconds = 0.0;  ///< of which sliding updates without elastic forces [s]
  double force_seconds = 0.0;    ///< of which elastic forces for the sliding updates [s]
  double last_increment_m = 0.0;
  double max_slide_m = 0.0;
};
/// The combined loop with stiffening: stiff.step() then sliding.afterStep() until the stiffening
/// settle criterion holds on an advanced call and no constraint moved more than
/// increment_tolerance_m [m] for consecutive_steps calls in a row, or max_calls calls.
struct StiffSlidingSettleResult {
  bool settled = false;
  int calls = 0;                 ///< stiffening calls
  int take_backs = 0;            ///< calls that could not advance and took the move back
  double seconds = 0.0;          ///< wall time [s]
  double sliding_seconds = 0.0;  ///< of which in afterStep() [s]
  double max_slide_m = 0.0;      ///< at the end [m]
};
StiffSlidingSettleResult settleWithSlidingAndStiffening(
    StiffeningSimulation& stiff, ChestWallSliding& sliding, int max_calls, double increment_tolerance_m,
    int consecutive_steps = 3,
    const std::function<void(int, const StiffeningStepResult&, const SlidingStepStats&)>& progress = {});

SlidingSettleResult settleWithSliding(DynamicSimulator& sim, ChestWallSliding& sliding, int max_steps,
                                      double increment_tolerance_m, int consecutive_steps = 2,
                                      const std::function<void(int, double, const SlidingStepStats&)>& progress = {});

}  // namespace breast_sim::core
