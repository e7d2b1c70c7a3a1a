#pragma once
/// @file surface_morphing.h
/// Surface morphing (seed section 2.5): at every step, each chosen surface vertex gets a force
/// proportional to the vector from its current position to the nearest target point; the forces
/// accumulate in the simulator and are never reset, so an overshoot corrects itself (an integral
/// controller on the surface distance).

#include <memory>
#include <vector>

#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/morphing/surface_field.h"

namespace breast_sim::core {

struct MorphingOptions {
  /// Force added per step and vertex = gain · A_i · v_i, with A_i the vertex's share of the skin
  /// area [m²] and v_i the vector to the target [m]: a pressure per metre of distance and step
  /// [Pa/m]. Scale-free in the mesh size. The default pulls the 2 kPa phantom onto its target in a
  /// few tens of steps of 0.033 s.
  double gain_pa_per_m = 2.0e4;
  /// Vertices farther than this from the target get no force [m] (outliers, parts the scanner does
  /// not see); 0 = no limit.
  double max_distance_m = 0.05;
  /// Anti-windup: a vertex's accumulated force is capped at this traction times its area [Pa]
  /// (0 = no cap). A target part the model cannot reach (behind a fixed wall, a scanner outlier)
  /// would otherwise pull ever harder and distort the rest; 5 kPa is several times what the 2 kPa
  /// phantom needs to take its supine shape.
  double max_traction_pa = 5.0e3;
  /// Which vertices: the skin node set without the nodes the simulator holds (fixed or moved by
  /// sliding), so the morphing never fights a constraint.
  bool skip_constrained = true;
  /// Implicit pull (augmented Lagrangian): besides the accumulated forces, each pulled vertex gets a
  /// spring k · A_i · n nᵀ towards its nearest target point (n: the unit vector to it), re-anchored
  /// every step and solved with the tissue by the implicit step [Pa/m]; 0 = none (the seed's explicit
  /// forces alone). The accumulated force is then the Lagrange multiplier of "vertex on the target"
  /// and the gain its update: with gain = k every error mode shrinks per converged step by s / (s + k)
  /// (s: the tissue's stiffness per area for that mode), instead of 1 − gain / s, which for the
  /// explicit forces alone must stay > −1 for the softest mode and so is close to 1 for the stiff,
  /// short-wavelength ones that make the last tenths of a millimetre.
  double spring_pa_per_m = 0.0;
  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

class SurfaceMorphing {
 public:
  /// @param skin_nodes  the surface vertices that may be pulled (e.g. the "skin" node set)
  /// @param constrained_nodes  nodes to leave out when options.skip_constrained (e.g. the chest wall)
  /// @throws std::invalid_argument for invalid options or node indices, or no vertex left.
  SurfaceMorphing(const TetMesh& mesh, std::shared_ptr<const SurfaceVectorField> field,
                  const std::vector<int>& skin_nodes, const std::vector<int>& constrained_nodes,
                  const MorphingOptions& options = {});

  /// Adds this step's forces at the simulator's current positions (call before its step()).
  /// @return the mean distance of the pulled vertices to the target [m] before the step
  double addForces(DynamicSimulator& sim);
  /// The distances of the pulled vertices to the target at the simulator's current positions,
  /// without adding forces (also stored in lastDistances()). count is the number of vertices.
  DistanceStats measure(const DynamicSimulator& sim);
  /// Distance of each pulled vertex to the target [m] at the last addForces() or measure() (addForces
  /// with alongNormal(): its component along the normal).
  const Eigen::VectorXd& lastDistances() const { return distance_; }
  /// Statistics of lastDistances() (mean, 95th percentile, max).
  DistanceStats lastStats() const;
  /// A new target field (e.g. a new tracker frame); the accumulated forces stay.
  /// @throws std::invalid_argument for a null field.
  void setField(std::shared_ptr<const SurfaceVectorField> field);
  /// Replaces the accumulated forces (a restored snapshot): the simulator's external forces become
  /// exactly these on the pulled vertices (any other external force is cleared).
  /// @throws std::invalid_argument when the size is not #vertices × 3.
  void restoreForces(DynamicSimulator& sim, const Points& accumulated_n);

  /// Along the normal: each step's force keeps only the component of the vector to the target along
  /// the vertex's current outward skin normal (area-weighted over its skin faces). A surface scan
  /// tells how far the skin is from the surface, not where along it a vertex lies: the nearest point
  /// of a noisy, decimated cloud lies off the normal by a random tangential offset, which the
  /// accumulated forces would sum into a slide of the skin along itself. Off by default (a target
  /// surface's nearest point is where a vertex belongs).
  void setAlongNormal(bool on) { along_normal_ = on; }
  bool alongNormal() const { return along_normal_; }

  const std::vector<int>& vertices() const { return vertices_; }
  /// Area share of each pulled vertex [m²] (rest configuration).
  const Eigen::VectorXd& vertexAreas() const { return area_; }
  /// Forces added so far, summed per pulled vertex [N] (#vertices × 3).
  const Points& accumulatedForces() const { return total_; }
  /// The implicit pull's springs (options().spring_pa_per_m) at the positions of the last
  /// addForces(): per pulled vertex whose direction to the target is known, the block
  /// k A_i n nᵀ [N/m] and its anchor, the nearest target point [m]. Empty lists when the spring is off.
  void springs(std::vector<int>& nodes, std::vector<Eigen::Matrix3d>& stiffness_n_per_m, Points& anchors_m) const;
  const MorphingOptions& options() const { return options_; }

 private:
  const Points rest_;
  std::shared_ptr<const SurfaceVectorField> field_;
  MorphingOptions options_;
  std::vector<int> vertices_;
  Eigen::VectorXd area_;
  Points total_;
  Points step_forces_;
  Eigen::VectorXd distance_;
  Points anchor_;  // nearest target point per vertex at the last addForces() [m]
  Points normal_;  // unit direction to it (the last known one while the vertex sits on the target)
  bool along_normal_ = false;
  Triangles skin_faces_;        // boundary faces with all three nodes on the skin (outward)
  std::vector<int> slot_;       // per mesh node: its row in vertices_, −1 for none
  Points vertex_normals_;       // per pulled vertex, summed face normals at the current positions (kept buffer)
};

}  // namespace breast_sim::core
