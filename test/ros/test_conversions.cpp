#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/surface_tracker.h"
#include "breast_sim/ros_interface/tracker_simulation.h"

using namespace breast_sim;

namespace {
core::TetMesh twoTets() {
  core::Points x(5, 3);
  x << 0, 0, 0, 0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01, 0.01, 0.01, 0.01;
  core::Tets t(2, 4);
  t << 0, 1, 2, 3, 1, 2, 3, 4;
  core::TetMesh m(x, t, {1, 2});
  m.setNodeSet(core::node_sets::kChestWall, {0, 1, 2});
  m.setNodeSet(core::node_sets::kSkin, {3, 4});
  return m;
}
}  // namespace

TEST(Conversions, MeshRoundTripsThroughTheMessage) {
  const core::TetMesh m = twoTets();
  core::Points u = core::Points::Random(5, 3) * 1e-3;
  const auto msg = ros_interface::toMessage(m, u, "breast_model", ros::Time(12.5));
  EXPECT_EQ(msg.header.frame_id, "breast_model");
  const core::TetMesh back = ros_interface::meshFromMessage(msg);
  EXPECT_EQ(back.nodes(), m.nodes());
  EXPECT_EQ(back.tets(), m.tets());
  EXPECT_EQ(back.regionLabels(), m.regionLabels());
  EXPECT_EQ(back.nodeSet(core::node_sets::kChestWall), m.nodeSet(core::node_sets::kChestWall));
  EXPECT_EQ(ros_interface::displacementFromMessage(msg), u);
}

TEST(Conversions, MalformedMessagesAreRejectedWithTheField) {
  auto msg = ros_interface::toMessage(twoTets(), core::Points(), "f", ros::Time(0));
  auto expectError = [](const TetrahedralMesh& m, const std::string& field) {
    try {
      ros_interface::meshFromMessage(m);
      ros_interface::displacementFromMessage(m);
      FAIL() << "expected an error about " << field;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(field), std::string::npos) << e.what();
    }
  };
  auto a = msg;
  a.rest_positions.pop_back();
  expectError(a, "rest_positions");
  auto b = msg;
  b.tetrahedra[3] = 99;
  expectError(b, "node 99");
  auto c = msg;
  c.region_labels.push_back(1);
  expectError(c, "region_labels");
  auto d = msg;
  d.displacements = {1.0, 2.0};
  expectError(d, "displacements");
}

// ---------------------------------------------------------------------------------------------------
// Clouds, poses, gravity, display surfaces, markers.

TEST(Conversions, CloudRoundTripsAndDropsNonFinitePoints) {
  core::Points p(4, 3);
  p << 0.1, 0.2, 0.3, 1, 2, 3, std::nan(""), 0, 0, -0.5, 0.25, 0.125;
  const auto msg = ros_interface::cloudToMessage(p, "tracker", ros::Time(3));
  EXPECT_EQ(msg.width, 4u);
  EXPECT_FALSE(msg.is_dense);
  const auto back = ros_interface::pointsFromCloud(msg);
  EXPECT_EQ(back.total, 4u);
  EXPECT_EQ(back.non_finite, 1u);
  ASSERT_EQ(back.points_m.rows(), 3);
  EXPECT_NEAR(back.points_m(0, 0), 0.1, 1e-7);  // float32 on the wire
  EXPECT_NEAR(back.points_m(2, 2), 0.125, 0);
}

TEST(Conversions, HugeCloudsAreReadWithAStride) {
  core::Points p = core::Points::Random(10000, 3);
  const auto back = ros_interface::pointsFromCloud(ros_interface::cloudToMessage(p, "f", ros::Time(0)), 3000);
  EXPECT_EQ(back.stride, 4u);
  EXPECT_EQ(back.points_m.rows(), 2500);
  EXPECT_NEAR(back.points_m(1, 0), p(4, 0), 1e-6);
}

TEST(Conversions, Float64CloudsAndPaddedRowsAreRead) {
  // A 2×2 organised cloud of FLOAT64 x, y, z with 8 bytes of padding per point and per row.
  sensor_msgs::PointCloud2 msg;
  msg.height = 2;
  msg.width = 2;
  for (int k = 0; k < 3; ++k) {
    sensor_msgs::PointField f;
    f.name = std::string(1, "xyz"[k]);
    f.offset = 8 + 8 * k;
    f.datatype = sensor_msgs::PointField::FLOAT64;
    f.count = 1;
    msg.fields.push_back(f);
  }
  msg.point_step = 32;
  msg.row_step = 72;
  msg.data.assign(144, 0);
  for (int i = 0; i < 4; ++i)
    for (int k = 0; k < 3; ++k) {
      const double v = 10 * i + k;
      std::memcpy(msg.data.data() + (i / 2) * 72 + (i % 2) * 32 + 8 + 8 * k, &v, 8);
    }
  const auto c = ros_interface::pointsFromCloud(msg);
  ASSERT_EQ(c.points_m.rows(), 4);
  EXPECT_EQ(c.points_m(3, 0), 30.0);
  EXPECT_EQ(c.points_m(2, 2), 22.0);
}

TEST(Conversions, MalformedCloudsAreRejectedWithTheField) {
  const auto good = ros_interface::cloudToMessage(core::Points::Random(5, 3), "f", ros::Time(0));
  auto expectError = [](const sensor_msgs::PointCloud2& m, const std::string& what) {
    try {
      ros_interface::pointsFromCloud(m);
      FAIL() << "expected an error about " << what;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  auto a = good;
  a.fields.pop_back();
  expectError(a, "'z'");
  auto b = good;
  b.data.resize(10);
  expectError(b, "truncated");
  auto c = good;
  c.fields[1].datatype = sensor_msgs::PointField::UINT8;
  expectError(c, "'y'");
  auto d = good;
  d.row_step = 4;
  expectError(d, "row_step");
  auto e = good;
  e.fields[2].offset = 100;
  expectError(e, "point_step");
  auto empty = good;
  empty.width = 0;
  empty.data.clear();
  EXPECT_EQ(ros_interface::pointsFromCloud(empty).points_m.rows(), 0);
}

TEST(Conversions, PosesAndTransformsRoundTrip) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  t.translation() << 0.1, -0.2, 0.3;
  EXPECT_TRUE(ros_interface::isometryFromPose(ros_interface::poseFromIsometry(t)).isApprox(t, 1e-12));
  EXPECT_TRUE(ros_interface::isometryFromTransform(ros_interface::transformFromIsometry(t)).isApprox(t, 1e-12));
  geometry_msgs::Pose zero;  // all-zero quaternion
  EXPECT_THROW(ros_interface::isometryFromPose(zero), std::invalid_argument);
}

TEST(Conversions, AQuaternionFarFromUnitLengthIsRefusedNotNormalised) {
  geometry_msgs::Pose pose;
  pose.orientation.w = 1e-5;  // would normalise to the identity; (1e-5, 0, 0, 0) as x, y, z to a 180° turn
  EXPECT_THROW(ros_interface::isometryFromPose(pose), std::invalid_argument);
  pose.orientation.w = 0;
  pose.orientation.x = 1e-5;
  try {
    ros_interface::isometryFromPose(pose);
    ADD_FAILURE() << "a quaternion of norm 1e-5 was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("norm 1e-05"), std::string::npos) << e.what();
  }
  pose.orientation.x = 0;
  pose.orientation.w = 1.0011;  // beyond 1 ± 1e-3
  EXPECT_THROW(ros_interface::isometryFromPose(pose), std::invalid_argument);
  pose.orientation.w = 1.0009;  // within: normalised
  EXPECT_TRUE(ros_interface::isometryFromPose(pose).linear().isApprox(Eigen::Matrix3d::Identity(), 1e-12));
  geometry_msgs::Transform t;
  t.rotation.w = 0.5;
  EXPECT_THROW(ros_interface::isometryFromTransform(t), std::invalid_argument);
}

TEST(Conversions, PointsTransformRigidly) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  t.translation() << 0.1, -0.2, 0.3;
  core::Points p(2, 3);
  p << 1, 0, 0, 0, 1, 0;
  const core::Points q = ros_interface::transformPoints(t, p);
  for (int i = 0; i < 2; ++i)
    EXPECT_TRUE(q.row(i).transpose().isApprox(t * Eigen::Vector3d(p.row(i).transpose()), 1e-12));
}

TEST(Conversions, GravityLoadFollowsTheTableTilt) {
  // The simulated tracker's table at its mean tilt gives the phantom's own supine gravity.
  const core::ModelCase c = core::loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  ros_interface::TrackerSimulation sim(c);
  const Eigen::Vector3d g_prone = 9.81 * c.prone_gravity_direction.normalized();
  const Eigen::Matrix3d model_from_world = sim.worldFromModel(0.0).linear().transpose();
  const Eigen::Vector3d load = ros_interface::gravityLoad(model_from_world, 9.81, g_prone);
  EXPECT_TRUE((load + g_prone).isApprox(c.phantom->gravity_supine_mps2, 1e-9)) << (load + g_prone).transpose();
  // A quarter of the tilt period later the table has rolled by the amplitude (2°).
  const Eigen::Matrix3d r2 = sim.worldFromModel(2.0).linear().transpose();
  EXPECT_NEAR(ros_interface::angleDeg(ros_interface::gravityLoad(r2, 9.81, g_prone) + g_prone, load + g_prone), 2.0, 1e-9);
  // The node's update rule: a turn beyond the threshold, or a change beyond 1 % of g (0.0981 m/s²).
  const Eigen::Vector3d current(0, 9.81, 0);
  const Eigen::Vector3d turned = Eigen::AngleAxisd(0.4 * M_PI / 180, Eigen::Vector3d::UnitX()) * current;  // 0.068 m/s² apart
  EXPECT_FALSE(ros_interface::gravityLoadChanged(turned, current, 0.5, 9.81));
  EXPECT_TRUE(ros_interface::gravityLoadChanged(turned, current, 0.3, 9.81));
  EXPECT_FALSE(ros_interface::gravityLoadChanged(1.005 * current, current, 0.5, 9.81));
  EXPECT_TRUE(ros_interface::gravityLoadChanged(1.02 * current, current, 0.5, 9.81));
  EXPECT_NEAR(ros_interface::angleDeg(Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY()), 90.0, 1e-12);
  EXPECT_EQ(ros_interface::angleDeg(Eigen::Vector3d::Zero(), Eigen::Vector3d::UnitY()), 0.0);
}

TEST(Conversions, SimulatedTrackerCloudsAreTheSameInBothFrames) {
  const core::ModelCase c = core::loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  ros_interface::TrackerSimulationOptions o;
  o.points = 500;
  ros_interface::TrackerSimulation a(c, o), b(c, o);
  const double t = 1.3;
  const core::Points in_model = a.cloudInModel(t);
  const core::Points in_tracker = b.cloudInTracker(t);
  const Eigen::Isometry3d model_from_tracker = (a.worldFromTracker().inverse() * a.worldFromModel(t)).inverse();
  EXPECT_LT((ros_interface::transformPoints(model_from_tracker, in_tracker) - in_model).cwiseAbs().maxCoeff(), 1e-12);
  // As recorded: the same points after a round trip through single precision in the tracker frame
  // (~10 nm off at these coordinates, not exactly the same), and the bag's message, converted as
  // the node converts it, gives what the offline references use.
  ros_interface::TrackerSimulation r(c, o), m(c, o);
  const core::Points recorded = r.cloudAsRecordedInModel(t);
  const double off = (recorded - in_model).cwiseAbs().maxCoeff();
  EXPECT_GT(off, 0.0);
  EXPECT_LT(off, 1e-7);
  const sensor_msgs::PointCloud2 msg = ros_interface::cloudToMessage(m.cloudInTracker(t), "tracker", ros::Time(100.0));
  const core::Points from_msg = ros_interface::transformPoints(m.worldFromModel(t).inverse() * m.worldFromTracker(),
                                                               ros_interface::pointsFromCloud(msg).points_m);
  EXPECT_LT((from_msg - recorded).cwiseAbs().maxCoeff(), 1e-15);
  // Noise-free and without outliers the points lie on the visible supine skin (breathing ≤ 1 mm).
  o.noise_m = 0;
  o.outlier_fraction = 0;
  o.breathing_amplitude_m = 0;
  ros_interface::TrackerSimulation clean(c, o);
  const core::SurfaceDistance d(clean.visibleSkin());
  EXPECT_LT(d.stats(clean.cloudInModel(0.7)).max_m, 1e-9);
}

TEST(Conversions, DecimatedSurfaceFitsTheBudgetAndKeepsValidIndices) {
  // A finely triangulated square plate 0.1 m × 0.1 m.
  const int n = 40;
  core::Points x((n + 1) * (n + 1), 3);
  for (int i = 0; i <= n; ++i)
    for (int j = 0; j <= n; ++j) x.row(i * (n + 1) + j) << 0.1 * i / n, 0.1 * j / n, 0.0;
  core::Triangles t(2 * n * n, 3);
  for (int i = 0, k = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      const int a = i * (n + 1) + j, b = a + 1, c = a + n + 1, d = c + 1;
      t.row(k++) << a, b, d;
      t.row(k++) << a, d, c;
    }
  const auto all = ros_interface::decimateSurface(x, t, 0);
  EXPECT_EQ(all.triangles.rows(), t.rows());
  const auto small = ros_interface::decimateSurface(x, t, 500);
  EXPECT_LE(small.triangles.rows(), 500);
  EXPECT_GT(small.triangles.rows(), 100);  // not collapsed to nothing
  EXPECT_GT(small.cell_m, 0.0);
  for (Eigen::Index i = 0; i < small.triangles.size(); ++i) {
    ASSERT_GE(small.triangles.data()[i], 0);
    ASSERT_LT(small.triangles.data()[i], static_cast<int>(small.vertices.size()));
  }
  // The decimated plate still covers most of the plate's area (slow reference: the exact 0.01 m²).
  double area = 0;
  for (Eigen::Index i = 0; i < small.triangles.rows(); ++i) {
    const Eigen::Vector3d a = x.row(small.vertices[small.triangles(i, 0)]), b = x.row(small.vertices[small.triangles(i, 1)]),
                          c = x.row(small.vertices[small.triangles(i, 2)]);
    area += 0.5 * (b - a).cross(c - a).norm();
  }
  EXPECT_GT(area, 0.8 * 0.01);
  EXPECT_LT(area, 1.01 * 0.01);
  const auto marker = ros_interface::surfaceMarker(small, x, "m", ros::Time(1));
  EXPECT_EQ(marker.points.size(), static_cast<size_t>(3 * small.triangles.rows()));
  EXPECT_EQ(marker.type, visualization_msgs::Marker::TRIANGLE_LIST);
  core::Triangles bad = t;
  bad(0, 0) = 99999;
  EXPECT_THROW(ros_interface::decimateSurface(x, bad, 10), std::invalid_argument);
}

namespace {
// A UV sphere of radius r about the origin, triangles wound outward (right-hand rule).
void uvSphere(double r, int n_lat, int n_lon, core::Points& x, core::Triangles& t) {
  x.resize(2 + (n_lat - 1) * n_lon, 3);
  x.row(0) << 0, 0, r;
  for (int i = 1; i < n_lat; ++i)
    for (int j = 0; j < n_lon; ++j) {
      const double th = M_PI * i / n_lat, ph = 2 * M_PI * j / n_lon;
      x.row(1 + (i - 1) * n_lon + j) << r * std::sin(th) * std::cos(ph), r * std::sin(th) * std::sin(ph), r * std::cos(th);
    }
  const int south = static_cast<int>(x.rows()) - 1;
  x.row(south) << 0, 0, -r;
  auto ring = [&](int i, int j) { return 1 + (i - 1) * n_lon + (j % n_lon); };
  std::vector<Eigen::Vector3i> f;
  for (int j = 0; j < n_lon; ++j) f.emplace_back(0, ring(1, j), ring(1, j + 1));
  for (int i = 1; i < n_lat - 1; ++i)
    for (int j = 0; j < n_lon; ++j) {
      f.emplace_back(ring(i, j), ring(i + 1, j), ring(i + 1, j + 1));
      f.emplace_back(ring(i, j), ring(i + 1, j + 1), ring(i, j + 1));
    }
  for (int j = 0; j < n_lon; ++j) f.emplace_back(south, ring(n_lat - 1, j + 1), ring(n_lat - 1, j));
  t.resize(static_cast<Eigen::Index>(f.size()), 3);
  for (size_t i = 0; i < f.size(); ++i) t.row(static_cast<Eigen::Index>(i)) = f[i].transpose();
}

Eigen::Vector3d markerPoint(const visualization_msgs::Marker& m, size_t i) {
  return Eigen::Vector3d(m.points[i].x, m.points[i].y, m.points[i].z);
}
}  // namespace

TEST(Conversions, SkinMarkerIsWoundOutwardSeeThroughAndShadedTheSameOnBothSides) {
  core::Points x;
  core::Triangles t;
  uvSphere(0.05, 40, 80, x, t);
  // The input is outward: every face normal points away from the centre.
  for (Eigen::Index f = 0; f < t.rows(); ++f) {
    const Eigen::Vector3d a = x.row(t(f, 0)), b = x.row(t(f, 1)), c = x.row(t(f, 2));
    ASSERT_GT((b - a).cross(c - a).dot(a + b + c), 0.0) << "test sphere face " << f;
  }
  // Down to 1/8 of the sphere's 6240 faces (the node keeps 4000 of a skin's); far coarser clusters of a
  // UV sphere leave a few fins along meridians that face neither way.
  for (int budget : {0, 3000, 800}) {
    const auto surface = ros_interface::decimateSurface(x, t, budget);
    const auto m = ros_interface::surfaceMarker(surface, x, "m", ros::Time(1));
    const size_t nt = m.points.size() / 3;
    ASSERT_GT(nt, 50u);
    int inward = 0;
    for (size_t f = 0; f < nt; ++f) {
      const Eigen::Vector3d a = markerPoint(m, 3 * f), b = markerPoint(m, 3 * f + 1), c = markerPoint(m, 3 * f + 2);
      inward += (b - a).cross(c - a).dot((a + b + c) / 3.0) <= 0.0;  // centroid of the sphere: the origin
    }
    EXPECT_EQ(inward, 0) << "budget " << budget << ": " << inward << " of " << nt << " marker triangles face inward";
    // See-through, one opaque colour per face (rviz then draws the faces unlit: no black back faces).
    EXPECT_GT(m.color.a, 0.2f);
    EXPECT_LT(m.color.a, 0.9f);
    ASSERT_EQ(m.colors.size(), nt);
    for (const auto& col : m.colors) {
      EXPECT_EQ(col.a, 1.0f);
      EXPECT_GT(col.r + col.g + col.b, 0.5f);  // no face is drawn near black
    }
  }
  // The same surface wound inward is drawn inward, in the same shades.
  core::Triangles rev = t;
  rev.col(1).swap(rev.col(2));
  const auto out = ros_interface::surfaceMarker(ros_interface::decimateSurface(x, t, 0), x, "m", ros::Time(1));
  const auto in = ros_interface::surfaceMarker(ros_interface::decimateSurface(x, rev, 0), x, "m", ros::Time(1));
  ASSERT_EQ(in.colors.size(), out.colors.size());
  for (size_t f = 0; f < in.colors.size(); ++f) {
    const Eigen::Vector3d a = markerPoint(in, 3 * f), b = markerPoint(in, 3 * f + 1), c = markerPoint(in, 3 * f + 2);
    ASSERT_LT((b - a).cross(c - a).dot(a + b + c), 0.0);
    ASSERT_FLOAT_EQ(in.colors[f].r, out.colors[f].r);
  }
}

TEST(Conversions, DecimatedPhantomSkinKeepsItsOutwardWinding) {
  // The phantom's skin (outward faces) decimated to the node's default budget: each display triangle
  // faces the way the skin faces at its three vertices (the area-weighted vertex normals).
  const core::ModelCase c = core::loadModelCase(std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/phantom_default.yaml");
  ASSERT_TRUE(c.phantom);
  const core::TargetSurface skin = core::skinTarget(c.phantom->prone_surface);
  const core::Points& x = skin.vertices_m;
  core::Points vn = core::Points::Zero(x.rows(), 3);
  for (Eigen::Index f = 0; f < skin.triangles.rows(); ++f) {
    const Eigen::RowVector3d a = x.row(skin.triangles(f, 0)), b = x.row(skin.triangles(f, 1)), c3 = x.row(skin.triangles(f, 2));
    const Eigen::RowVector3d n = (b - a).cross(c3 - a);
    for (int k = 0; k < 3; ++k) vn.row(skin.triangles(f, k)) += n;
  }
  for (int budget : {4000, 1000}) {
    const auto surface = ros_interface::decimateSurface(x, skin.triangles, budget);
    ASSERT_GT(surface.triangles.rows(), budget / 4);
    int against = 0;
    for (Eigen::Index f = 0; f < surface.triangles.rows(); ++f) {
      const int i = surface.vertices[static_cast<size_t>(surface.triangles(f, 0))],
                j = surface.vertices[static_cast<size_t>(surface.triangles(f, 1))],
                k = surface.vertices[static_cast<size_t>(surface.triangles(f, 2))];
      const Eigen::RowVector3d n = (x.row(j) - x.row(i)).cross(x.row(k) - x.row(i));
      against += n.dot(vn.row(i) + vn.row(j) + vn.row(k)) <= 0.0;
    }
    EXPECT_EQ(against, 0) << "budget " << budget << ": " << against << " of " << surface.triangles.rows()
                          << " display triangles face inward";
  }
}

TEST(Conversions, LesionMessagesMarkersAndFrames) {
  std::vector<core::Lesion> lesions = {{"L1", Eigen::Vector3d(0.01, 0.02, 0.03), 0.005}, {"L2", Eigen::Vector3d::Zero(), 0.0}};
  core::Points x(2, 3);
  x << 0.011, 0.022, 0.033, 0.001, 0.002, 0.003;
  const auto msg = ros_interface::lesionsMessage(lesions, x, "breast_model", ros::Time(2), true, "ok");
  ASSERT_EQ(msg.lesions.size(), 2u);
  EXPECT_TRUE(msg.valid);
  EXPECT_TRUE(msg.lesions[1].valid);
  const auto invalid = ros_interface::lesionsMessage(lesions, x, "breast_model", ros::Time(2), false, "drift");
  EXPECT_FALSE(invalid.valid);
  EXPECT_FALSE(invalid.lesions[0].valid);
  EXPECT_EQ(invalid.status, "drift");
  EXPECT_EQ(msg.lesions[1].id, "L2");
  EXPECT_DOUBLE_EQ(msg.lesions[0].position.y, 0.022);
  EXPECT_DOUBLE_EQ(msg.lesions[0].prone_position.y, 0.02);
  EXPECT_EQ(msg.lesions[0].position_covariance_type, breast_sim::Lesion::COVARIANCE_UNKNOWN);
  EXPECT_EQ(msg.lesions[0].region_confidence, 0.0);
  for (double c : msg.lesions[0].position_covariance) EXPECT_EQ(c, 0.0);
  const auto markers = ros_interface::lesionMarkers(lesions, x, "breast_model", ros::Time(2));
  ASSERT_EQ(markers.markers.size(), 6u);  // sphere + label + region each
  EXPECT_DOUBLE_EQ(markers.markers[0].scale.x, 0.01);
  EXPECT_DOUBLE_EQ(markers.markers[3].scale.x, 0.004);  // a point lesion is drawn 4 mm wide
  // Without regions the region markers are deleted (none of an earlier precomputation lingers).
  EXPECT_EQ(markers.markers[2].ns, "lesion_regions");
  EXPECT_EQ(markers.markers[2].action, visualization_msgs::Marker::DELETE);
  const auto tfs = ros_interface::lesionTransforms(lesions, x, "breast_model", "lesion_", ros::Time(2));
  ASSERT_EQ(tfs.size(), 2u);
  EXPECT_EQ(tfs[0].child_frame_id, "lesion_L1");
  EXPECT_DOUBLE_EQ(tfs[1].transform.translation.z, 0.003);
  EXPECT_THROW(ros_interface::lesionsMessage(lesions, core::Points(1, 3), "f", ros::Time(0), true, ""), std::invalid_argument);
}

// The region of a lesion reaches the message (covariance, row-major) and the marker (an ellipsoid
// whose axes and diameters are the region's): a point on the marker's surface is on the region's.
TEST(Conversions, LesionRegionsInMessageAndMarker) {
  std::vector<core::Lesion> lesions = {{"L1", Eigen::Vector3d(0.01, 0.02, 0.03), 0.005}};
  core::Points x(1, 3);
  x << 0.011, 0.022, 0.033;
  // Samples spread 3 : 2 : 1 along axes rotated about z by 30 degrees, off-centre.
  const Eigen::Matrix3d r = Eigen::AngleAxisd(M_PI / 6, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  std::vector<Eigen::Vector3d> samples;
  const Eigen::Vector3d centre = x.row(0).transpose();
  for (int k = 0; k < 3; ++k)
    for (double sgn : {-1.0, 1.0}) samples.push_back(centre + sgn * (3.0 - k) * 1e-3 * r.col(k));
  samples.push_back(centre + Eigen::Vector3d(0.2e-3, -0.1e-3, 0.3e-3));
  const std::vector<core::LesionRegion> regions = {core::lesionRegion(centre, samples, 0.95)};
  const auto msg = ros_interface::lesionsMessage(lesions, x, "breast_model", ros::Time(2), true, "ok", &regions);
  const auto& l = msg.lesions[0];
  EXPECT_EQ(l.position_covariance_type, breast_sim::Lesion::COVARIANCE_ENSEMBLE);
  EXPECT_DOUBLE_EQ(l.region_confidence, 0.95);
  EXPECT_DOUBLE_EQ(l.region_scale, core::regionScale(0.95, 7));
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) EXPECT_DOUBLE_EQ(l.position_covariance[3 * a + b], regions[0].covariance_m2(a, b));
  const auto markers = ros_interface::lesionMarkers(lesions, x, "breast_model", ros::Time(2), &regions);
  ASSERT_EQ(markers.markers.size(), 3u);
  const auto& e = markers.markers[2];
  EXPECT_EQ(e.ns, "lesion_regions");
  EXPECT_EQ(e.action, visualization_msgs::Marker::ADD);
  EXPECT_EQ(e.type, visualization_msgs::Marker::SPHERE);
  const Eigen::Quaterniond q(e.pose.orientation.w, e.pose.orientation.x, e.pose.orientation.y, e.pose.orientation.z);
  EXPECT_NEAR(q.norm(), 1.0, 1e-12);
  const Eigen::Vector3d half(e.scale.x / 2, e.scale.y / 2, e.scale.z / 2);
  EXPECT_GE(half.x(), half.y());
  EXPECT_GE(half.y(), half.z());
  const Eigen::Vector3d c(e.pose.position.x, e.pose.position.y, e.pose.position.z);
  const Eigen::Matrix3d cinv = regions[0].covariance_m2.inverse();
  for (int k = 0; k < 3; ++k) {
    // The marker's surface point along its local axis k is on the region's boundary.
    const Eigen::Vector3d p = c + q.toRotationMatrix().col(k) * half(k);
    EXPECT_NEAR((p - centre).dot(cinv * (p - centre)), l.region_scale * l.region_scale, 1e-6) << "axis " << k;
  }
  const std::vector<core::LesionRegion> none;
  EXPECT_THROW(ros_interface::lesionMarkers(lesions, x, "f", ros::Time(0), &none), std::invalid_argument);
  EXPECT_THROW(ros_interface::lesionsMessage(lesions, x, "f", ros::Time(0), true, "", &none), std::invalid_argument);
}

TEST(Conversions, SlidingArrowsSkipShortVectorsAndRespectTheBudget) {
  core::Points x = core::Points::Zero(10, 3), v = core::Points::Zero(10, 3);
  for (int i = 0; i < 10; ++i) v(i, 0) = 1e-3 * i;  // node 0 does not move
  const auto m = ros_interface::slidingMarkers(x, v, {0, 1, 2, 3, 4, 5, 6, 7, 8, 9}, 2.0, 0.5e-3, 0, "f", ros::Time(0));
  ASSERT_EQ(m.markers.size(), 10u);  // DELETEALL + 9 arrows
  EXPECT_EQ(m.markers[0].action, visualization_msgs::Marker::DELETEALL);
  EXPECT_DOUBLE_EQ(m.markers[1].points[1].x, 2.0 * 1e-3);
  const auto few = ros_interface::slidingMarkers(x, v, {0, 1, 2, 3, 4, 5, 6, 7, 8, 9}, 1.0, 0.0, 3, "f", ros::Time(0));
  EXPECT_LE(few.markers.size(), 4u);
  EXPECT_THROW(ros_interface::slidingMarkers(x, v, {10}, 1.0, 0.0, 0, "f", ros::Time(0)), std::invalid_argument);
}

// ---------------------------------------------------------------------------------------------------
// Cloud filtering and ICP (PCL).

namespace {
core::Points spherePatch(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  core::Points p(n, 3);
  for (int i = 0; i < n; ++i) {
    // A bumpy cap (not rotationally symmetric, so ICP has a unique answer).
    const double a = 0.04 * u(rng), b = 0.04 * u(rng);
    p.row(i) << a, b, 0.02 * std::exp(-(a * a + 2 * b * b) / 0.0008) + 0.004 * std::sin(60 * a);
  }
  return p;
}
}  // namespace

TEST(CloudProcessing, VoxelGridDecimatesAndOutliersGo) {
  core::Points p = spherePatch(20000, 3);
  ros_interface::CloudFilterOptions o;
  o.remove_outliers = false;
  const core::Points d = ros_interface::filterCloud(p, o);
  EXPECT_LT(d.rows(), 2000);  // 80 mm × 80 mm at 3 mm: about 700 cells
  EXPECT_GT(d.rows(), 300);
  // Ten far strays are removed by the statistical filter, the surface stays.
  core::Points q(d.rows() + 10, 3);
  q.topRows(d.rows()) = d;
  for (int i = 0; i < 10; ++i) q.row(d.rows() + i) << 0.2 + 0.05 * i, 0.3, -0.2;
  o.remove_outliers = true;
  o.voxel_leaf_m = 0;
  const core::Points f = ros_interface::filterCloud(q, o);
  EXPECT_LE(f.rows(), d.rows());
  EXPECT_GT(f.rows(), 0.9 * d.rows());
  EXPECT_LT(f.col(0).maxCoeff(), 0.1);
}

TEST(CloudProcessing, IcpRecoversASmallMisregistrationAndRefusesALargeOne) {
  const core::Points reference = spherePatch(4000, 5);
  Eigen::Isometry3d mis = Eigen::Isometry3d::Identity();
  mis.linear() = Eigen::AngleAxisd(1.5 * M_PI / 180.0, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
  mis.translation() << 0.002, -0.001, 0.0015;
  // The scanner saw part of the same surface points (exact correspondences exist).
  const core::Points cloud = ros_interface::transformPoints(mis, reference.topRows(3000));
  ros_interface::IcpOptions o;
  o.max_iterations = 50;
  const auto r = ros_interface::rigidAlign(cloud, reference, Eigen::Isometry3d::Identity(), o);
  ASSERT_TRUE(r.applied) << r.note;
  // The correction undoes the misregistration: residual pose error well below the 2.7 mm offset.
  const Eigen::Isometry3d err = r.transform * mis;
  EXPECT_LT(err.translation().norm(), 0.3e-3);
  EXPECT_LT(Eigen::AngleAxisd(err.linear()).angle() * 180 / M_PI, 0.2);
  EXPECT_LT(r.rms_m, 0.5e-3);
  o.max_translation_m = 0.0005;  // the same correction is now beyond the limit
  const auto refused = ros_interface::rigidAlign(cloud, reference, Eigen::Isometry3d::Identity(), o);
  EXPECT_FALSE(refused.applied);
  EXPECT_TRUE(refused.transform.isApprox(Eigen::Isometry3d::Identity()));
  EXPECT_NE(refused.note.find("beyond"), std::string::npos) << refused.note;
}
