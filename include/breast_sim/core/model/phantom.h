#pragma once
/// @file phantom.h
/// The software breast phantom of the seed paper (sections 2.1 and 3.3): half-ellipsoidal breasts on
/// a planar or cylindrical chest wall, in a hanging "prone" shape and a flatter, wider, laterally
/// shifted "supine" target shape of the same volume; as a label image plus analytic surfaces.
///
/// Frame: LPS patient coordinates in metres (x towards the patient's left, y posterior, z superior).
/// The chest-wall surface passes through y = 0 at x = 0 and the breasts protrude anteriorly (−y):
///  - planar wall:      the plane y = 0;
///  - cylindrical wall: the cylinder about the axis {x = 0, y = R} of radius R, whose anterior
///                      surface is y = R − sqrt(R² − x²) (it curves posteriorly away from the sternum).
/// Tissue lies anterior to the wall (planar: y < 0; cylindrical: distance from the axis > R).
///
/// What is exact and what is approximated:
///  - inside tests (HalfEllipsoid::contains, Phantom::insideProne/insideSupine, analyticLabel) are
///    exact;
///  - volumes: 2/3·π·a·b·c exactly on the planar wall; on the cylindrical wall the half-ellipsoid
///    plus the sliver between its base plane and the curved wall, computed by a 1-D Gauss–Legendre
///    quadrature of closed-form slice integrals, converged to ~1e-12 relative (not a closed form);
///  - surfaces are triangulations whose vertices lie exactly on the analytic surfaces, so their
///    enclosed volume is smaller than the analytic one by O(edge² / curvature radius²) (~0.1% at the
///    default 2 mm edge);
///  - the skin layer is the shell between the ellipsoid and a concentric one with every semi-axis
///    reduced by the thickness: exact thickness along the semi-axes, approximate elsewhere;
///  - the label image samples the analytic labels at voxel centres (or sub-samples, see
///    PhantomParams::supersampling), so the voxel volume carries a staircase error.

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/model/point_embedding.h"  // Lesion

namespace breast_sim::core {

/// Shape of the chest wall the breasts are attached to.
enum class ChestWallShape { kPlanar, kCylindrical };

/// Which breast a single-breast phantom represents; sets its lateral direction (left: +x, right: −x).
enum class BreastSide { kLeft, kRight };

/// Parameters of the software phantom. SI units (m, rad, m/s²); the YAML case file uses mm and
/// degrees (see loadPhantomParams; docs/case_files.md lists every key with these defaults).
struct PhantomParams {
  int num_breasts = 1;                       ///< 1 (centred at x = 0) or 2 (centred at x = ±separation/2)
  BreastSide side = BreastSide::kLeft;       ///< single breast only: which side it is
  double breast_separation_m = 0.18;         ///< two breasts: distance between their centres along x [m]
  ChestWallShape chest_wall_shape = ChestWallShape::kPlanar;
  double chest_wall_radius_m = 0.2;          ///< cylindrical wall only: radius R [m]
  double chest_wall_thickness_m = 0.01;      ///< chest-wall slab (label 40) behind the breasts [m]

  double lateral_semi_axis_m = 0.06;         ///< prone semi-axis a along the wall, lateral [m]
  double si_semi_axis_m = 0.055;             ///< prone semi-axis b, superior-inferior [m]
  double depth_m = 0.07;                     ///< prone semi-axis c, anterior depth (wall → nipple) [m]
  /// Fibroglandular core (label 29): concentric ellipsoid with semi-axes scaled by this; 0 = none.
  double gland_scale = 0.5;
  double skin_thickness_m = 0.0;             ///< skin layer (label 2) [m]; 0 = none

  /// Supine depth c' = supine_depth_scale · c (flatter); the other semi-axes grow so that
  /// a'·b'·c' = a·b·c: a' = a·s^(−share), b' = b·s^(−(1−share)), s = supine_depth_scale.
  /// On the cylindrical wall c' is then corrected so that the two volumes are equal.
  double supine_depth_scale = 0.5;
  double supine_lateral_share = 0.5;         ///< share in [0, 1] of the widening that goes lateral
  /// Each supine shape is moved this far along the wall (arc length) away from the sternum [m].
  double supine_lateral_shift_m = 0.015;
  /// Supine gravity is tilted about the z axis by this angle [rad]; positive tilts it towards the
  /// patient's left (+x), negative towards the right.
  double supine_gravity_tilt_rad = 10.0 * 3.14159265358979323846 / 180.0;
  double gravity_mps2 = 9.81;                ///< magnitude of gravity [m/s²]

  double voxel_size_m = 1e-3;                ///< isotropic voxel size of the label image [m]
  double margin_m = 5e-3;                    ///< air around the phantom [m]; at least 3 voxels are kept
  /// Sub-samples per axis and voxel (1 = voxel centre; n > 1: majority of n³, ties → centre label).
  /// \note Majority voting does not reduce the staircase bias: sub-samples come in pairs mirrored
  /// about the centre, so wherever the boundary is locally planar the majority equals the centre
  /// sample. Measured tissue volume vs analytic, n = 1 / 2 / 3: default case at 1 mm +0.028% for
  /// all three (identical images); two-breast curved case at 1 mm −0.034% / −0.039% / −0.037%, at
  /// 2 mm −0.067% / −0.098% / −0.103%. Centre sampling is as close or closer and 2.5–12× faster, hence
  /// the default 1; n > 1 only smooths labels of thin or small structures (skin, small lesions).
  int supersampling = 1;
  double surface_edge_m = 2e-3;              ///< target edge length of the analytic surfaces [m]

  /// Lesions in the prone phantom, LPS [m]; each must lie inside the prone tissue. Those with
  /// radius > 0 are painted as label 200 (sphere ∩ tissue).
  std::vector<Lesion> lesions = defaultLesions();

  /// The two lesions of the default case, inside the default breast.
  static std::vector<Lesion> defaultLesions();

  /// Checks ranges and geometric consistency (breasts clear of each other and within the
  /// cylindrical wall's front half, lesions inside the prone tissue).
  /// @throws std::invalid_argument naming the YAML key, its value (mm, degrees) and what is expected.
  void validate() const;
};

/// One half-ellipsoidal breast shape attached to the chest wall: the ellipsoid centred at a point
/// of the wall surface, its depth axis along the wall's outward (anterior) normal there, cut by the
/// wall. Local coordinates of a point p: u = (p − c)·t (lateral), v = p.z − c.z (SI),
/// w = (p − c)·n (depth).
struct HalfEllipsoid {
  Eigen::Vector3d base_centre_m = Eigen::Vector3d::Zero();  ///< c: on the wall surface [m]
  Eigen::Vector3d lateral_axis{1.0, 0.0, 0.0};  ///< t: unit, tangent to the wall in the axial plane
  Eigen::Vector3d depth_axis{0.0, -1.0, 0.0};   ///< n: unit outward wall normal (t × z = n)
  double lateral_m = 0.0;                       ///< semi-axis a along t [m]
  double si_m = 0.0;                            ///< semi-axis b along z [m]
  double depth_m = 0.0;                         ///< semi-axis c along n [m]
  double wall_radius_m = 0.0;                   ///< 0: planar wall; else the cylinder radius R [m]

  /// (u, v, w) of a point [m].
  Eigen::Vector3d localCoordinates(const Eigen::Vector3d& p_m) const;
  /// Whether p is strictly inside the ellipsoid and strictly anterior to the wall.
  bool contains(const Eigen::Vector3d& p_m) const;
  /// The tip of the depth axis, c + depth·n (the nipple of a prone shape) [m].
  Eigen::Vector3d apex() const { return base_centre_m + depth_m * depth_axis; }
  /// Enclosed volume [m³]: exact on the planar wall, converged quadrature on the cylindrical one.
  double volume() const;
  /// Closed, outward-oriented triangulation: the skin (ellipsoid part) and the base on the wall.
  /// Rings of constant parameter around the apex; roughly `edge_m` long edges [m].
  void appendSurface(double edge_m, Points& vertices_m, Triangles& triangles,
                     std::vector<bool>& is_skin) const;
};

/// The chest wall: its anterior surface and the slab of given thickness behind it.
struct ChestWall {
  ChestWallShape shape = ChestWallShape::kPlanar;
  double radius_m = 0.0;     ///< cylindrical wall: R [m]
  double thickness_m = 0.0;  ///< slab thickness along the wall normal [m]

  /// y of the wall surface at lateral position x [m] (cylindrical: R − sqrt(R² − x²), |x| < R).
  double surfaceY(double x_m) const;
  /// Whether p lies in the slab (planar: 0 ≤ y ≤ thickness; cylindrical: R − thickness ≤ r ≤ R).
  bool slabContains(const Eigen::Vector3d& p_m) const;
};

/// A closed triangulated surface of one or more components (one per breast).
struct PhantomSurface {
  Points vertices_m;          ///< #V×3 [m]
  Triangles triangles;        ///< #F×3, outward by the right-hand rule
  std::vector<bool> is_skin;  ///< #F: true for the skin (facing air), false for the base on the wall
};

/// The generated phantom.
/// \note Breasts, nipples and surface components are ordered left (+x) then right (−x).
struct Phantom {
  PhantomParams params;
  ChestWall chest_wall;
  /// Prone segmentation: 0 air, 1 fat, 2 skin, 29 gland, 40 chest wall, 200 lesion. Identity
  /// direction; voxel faces on multiples of the voxel size (so the planar wall y = 0 is a face plane).
  /// Covers the prone breasts, the chest slab behind them (across the whole image) and the margin;
  /// the supine shapes may reach beyond it.
  LabelImage labels;
  std::vector<HalfEllipsoid> prone_breasts;
  std::vector<HalfEllipsoid> supine_breasts;  ///< the supine target shapes
  PhantomSurface prone_surface;
  PhantomSurface supine_surface;
  double prone_volume_m3 = 0.0;   ///< analytic tissue volume, all breasts [m³]
  double supine_volume_m3 = 0.0;  ///< analytic target volume, all breasts [m³]
  std::vector<Eigen::Vector3d> nipples_m;  ///< apex of each prone breast (on the skin) [m]
  std::vector<Lesion> lesions;             ///< as in params
  Eigen::Vector3d gravity_prone_mps2 = Eigen::Vector3d::Zero();   ///< (0, −g, 0): anterior [m/s²]
  Eigen::Vector3d gravity_supine_mps2 = Eigen::Vector3d::Zero();  ///< g·(sin θ, cos θ, 0) [m/s²]

  bool insideProne(const Eigen::Vector3d& p_m) const;
  bool insideSupine(const Eigen::Vector3d& p_m) const;
  /// The exact prone label at a point (what the image samples).
  std::uint16_t analyticLabel(const Eigen::Vector3d& p_m) const;
};

/// Reads the `phantom:` map of a YAML case file (lengths in mm, angles in degrees). Missing keys
/// take the PhantomParams defaults; other top-level maps (meshing:, …) are ignored.
/// @throws std::runtime_error naming the file, the key, the value and what is expected: for an
///         unreadable file, a missing `phantom:` map, an unknown key inside it, a value of the
///         wrong type, or a value PhantomParams::validate rejects.
PhantomParams loadPhantomParams(const std::string& yaml_path);

/// Builds the phantom: shapes, gravity, volumes, surfaces and the label image (parallel over
/// slices; the result is identical for any thread count).
/// @throws std::invalid_argument as PhantomParams::validate.
Phantom generatePhantom(const PhantomParams& params);

/// Writes a surface in metres as Wavefront OBJ (`.obj`, skin and base faces in groups "skin" and
/// "chest_wall") or ASCII STL (`.stl`), chosen by extension.
/// @throws std::runtime_error naming the path for an unknown extension or a failed write.
void writePhantomSurface(const std::string& path, const PhantomSurface& surface);

}  // namespace breast_sim::core
