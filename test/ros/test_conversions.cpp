#include <gtest/gtest.h>

#include "breast_sim/ros_interface/conversions.h"

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

TEST(Conversions, LesionsMoveWithTheDisplacement) {
  const core::TetMesh m = twoTets();
  core::Points p(1, 3);
  p << 0.002, 0.002, 0.002;
  const core::PointEmbedding e(m, p, {"L1"});
  core::Points u = core::Points::Zero(5, 3);
  u.col(0).setConstant(0.005);  // rigid shift of 5 mm in x
  const auto msg = ros_interface::toMessage({{"L1", p.row(0).transpose(), 0.0}}, e, u, "f", ros::Time(1));
  ASSERT_EQ(msg.lesions.size(), 1u);
  EXPECT_NEAR(msg.lesions[0].position.x, 0.007, 1e-12);
  EXPECT_NEAR(msg.lesions[0].prone_position.x, 0.002, 1e-12);
}
