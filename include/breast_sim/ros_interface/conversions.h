#pragma once
/// @file conversions.h
/// Pure conversions between core types and ROS messages, and the small pure functions the node wires
/// with (gravity from a pose, surface decimation for rviz, markers). Messages are validated before
/// anything is built from them; a malformed message raises std::invalid_argument naming the field and
/// the fix. Units: SI (REP 103), positions in metres in the frame the caller names.

#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <ros/time.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/TetrahedralMesh.h>
#include <geometry_msgs/Pose.h>
#include <geometry_msgs/TransformStamped.h>
#include <sensor_msgs/PointCloud2.h>
#include <visualization_msgs/Marker.h>
#include <visualization_msgs/MarkerArray.h>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/ros_interface/cloud_points.h"
#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/pipeline/lesion_uncertainty.h"

namespace breast_sim::ros_interface {

/// A TetrahedralMesh message of `mesh` with an optional displacement (#N×3 [m], or empty).
breast_sim::TetrahedralMesh toMessage(const core::TetMesh& mesh, const core::Points& displacement_m,
                                      const std::string& frame_id, const ros::Time& stamp);

/// The mesh (rest positions, tetrahedra, labels, chest-wall and skin node sets) of a message.
/// @throws std::invalid_argument when array lengths disagree, an index is out of range or a
///         tetrahedron is degenerate (the message says which).
core::TetMesh meshFromMessage(const breast_sim::TetrahedralMesh& msg);

/// Displacements of a message as #N×3 [m] (zeros when the message carries none).
/// @throws std::invalid_argument when the length is not 3 × #nodes.
core::Points displacementFromMessage(const breast_sim::TetrahedralMesh& msg);

/// Lesions at given current positions (#lesions×3 [m], e.g. ProneToSupinePipeline::lesionPositions()),
/// each and the array marked `valid` or not, with the `status` that says why. With `regions` (one per
/// lesion, lesion_uncertainty.h) each lesion carries its covariance [m²] and confidence region;
/// without, COVARIANCE_UNKNOWN and zeros.
/// @throws std::invalid_argument when the row count or the region count differs from the number of lesions.
breast_sim::LesionArray lesionsMessage(const std::vector<core::Lesion>& lesions, const core::Points& positions_m,
                                       const std::string& frame_id, const ros::Time& stamp, bool valid,
                                       const std::string& status,
                                       const std::vector<core::LesionRegion>* regions = nullptr);

/// A dense (height 1) PointCloud2 with FLOAT32 x, y, z fields of the given points [m].
sensor_msgs::PointCloud2 cloudToMessage(const core::Points& points_m, const std::string& frame_id,
                                        const ros::Time& stamp);

/// Rigid transform of a pose (position [m] + quaternion). A quaternion whose norm is within 1 ± 1e-3
/// is normalised; any other is refused, not normalised (a nearly zero one would become an arbitrary
/// rotation).
/// @throws std::invalid_argument for a non-finite value or a quaternion that is not of unit length.
Eigen::Isometry3d isometryFromPose(const geometry_msgs::Pose& pose);
geometry_msgs::Pose poseFromIsometry(const Eigen::Isometry3d& t);
/// As isometryFromPose, for a geometry_msgs/Transform.
Eigen::Isometry3d isometryFromTransform(const geometry_msgs::Transform& t);
geometry_msgs::Transform transformFromIsometry(const Eigen::Isometry3d& t);

/// Applies a rigid transform to every row of `points_m`.
core::Points transformPoints(const Eigen::Isometry3d& t, const core::Points& points_m);

/// The gravity load on the prone model [m/s²] when gravity points along −z of a frame G (REP 103:
/// z up) and `model_from_gravity` rotates G's vectors into the model frame:
/// load = R·(0, 0, −g) − g_prone, with g_prone the gravity the prone rest shape hangs under.
Eigen::Vector3d gravityLoad(const Eigen::Matrix3d& model_from_gravity, double g_mps2,
                            const Eigen::Vector3d& prone_gravity_mps2);

/// Angle between two vectors [deg] (0 when either is zero).
double angleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b);

/// The node's rule for following the table: the gravity load is set anew when the pose's `load`
/// turned by more than `threshold_deg` from the `current` one or differs from it by more than 1 % of
/// g [m/s²] (~gravity/update_threshold_deg); smaller changes keep the step's system as it is.
bool gravityLoadChanged(const Eigen::Vector3d& load, const Eigen::Vector3d& current, double threshold_deg, double g_mps2);

/// A surface decimated for display by vertex clustering on a grid: vertices falling into one cell
/// collapse onto one representative vertex; triangles that degenerate or repeat are dropped. A
/// clustered triangle is wound to agree with the input's area-weighted normal over its three cells
/// (undecimated, the input winding is kept), so an outward input (TetMesh::boundary()) stays outward.
struct DisplaySurface {
  std::vector<int> vertices;  ///< mesh node of each display vertex
  core::Triangles triangles;  ///< indices into `vertices`
  double cell_m = 0.0;        ///< the cell size that was used [m] (0: not decimated)
};

/// Decimates `triangles` (node indices into `positions_m`) to at most `max_triangles` (0 = keep all)
/// by doubling a clustering cell from the mean edge length until the count fits.
/// @throws std::invalid_argument for an index out of range.
DisplaySurface decimateSurface(const core::Points& positions_m, const core::Triangles& triangles, int max_triangles);

/// A TRIANGLE_LIST marker of a display surface at nodal positions `positions_m` (#nodes×3 [m]), the
/// triangles in the surface's winding. Drawn see-through (color.a < 1) so lesions inside show, and
/// with one colour per face (`colors`, a two-sided shade of the skin tone by the face's angle to a
/// fixed light): rviz then draws the faces unlit, so a face seen from inside (the skin's open base,
/// the far side through the near one) is not drawn black as an unlit back face.
visualization_msgs::Marker surfaceMarker(const DisplaySurface& surface, const core::Points& positions_m,
                                         const std::string& frame_id, const ros::Time& stamp);

/// A sphere (diameter = 2·max(radius, 2 mm)) and a text label per lesion, ids stable per index, and in
/// namespace "lesion_regions" the confidence ellipsoid of each lesion's `regions` entry (centred on
/// the current position, diameters 2 × the semi-axes, oriented by the axes), or a DELETE for that id
/// without regions, so a region of an earlier precomputation does not linger in rviz.
/// @throws std::invalid_argument when the row count or the region count differs from the number of lesions.
visualization_msgs::MarkerArray lesionMarkers(const std::vector<core::Lesion>& lesions, const core::Points& positions_m,
                                              const std::string& frame_id, const ros::Time& stamp,
                                              const std::vector<core::LesionRegion>* regions = nullptr);

/// One transform per lesion: parent `frame_id`, child `prefix + name`, translation = position.
std::vector<geometry_msgs::TransformStamped> lesionTransforms(const std::vector<core::Lesion>& lesions,
                                                              const core::Points& positions_m,
                                                              const std::string& frame_id, const std::string& prefix,
                                                              const ros::Time& stamp);

/// Arrows from the positions of `nodes` along their sliding vectors (×`scale`), for vectors longer
/// than `min_length_m`, at most `max_arrows` (evenly sub-sampled). The first marker is a DELETEALL so
/// arrows of an earlier frame disappear.
visualization_msgs::MarkerArray slidingMarkers(const core::Points& positions_m, const core::Points& vectors_m,
                                               const std::vector<int>& nodes, double scale, double min_length_m,
                                               int max_arrows, const std::string& frame_id, const ros::Time& stamp);

}  // namespace breast_sim::ros_interface
