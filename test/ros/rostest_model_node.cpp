// Integration test of the model node: it starts, publishes the phantom model and its lesions, and a
// bad case is refused with a reason while the last good model stays published.
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <ros/topic.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/LoadCase.h>
#include <breast_sim/TetrahedralMesh.h>

#include "breast_sim/ros_interface/conversions.h"

namespace {

template <typename Msg>
typename Msg::ConstPtr waitFor(const std::string& topic, double timeout_s) {
  ros::NodeHandle nh;
  return ros::topic::waitForMessage<Msg>(topic, nh, ros::Duration(timeout_s));
}

}  // namespace

TEST(ModelNode, PublishesTheModelAndLesions) {
  auto mesh = waitFor<breast_sim::TetrahedralMesh>("/breast_sim/deformed_mesh", 240.0);
  ASSERT_TRUE(mesh) << "no mesh on /breast_sim/deformed_mesh within 240 s";
  EXPECT_EQ(mesh->header.frame_id, "breast_model");
  const auto tet_mesh = breast_sim::ros_interface::meshFromMessage(*mesh);
  EXPECT_GT(tet_mesh.numTets(), 1500);
  EXPECT_LT(tet_mesh.numTets(), 6000);
  EXPECT_FALSE(mesh->chest_wall_nodes.empty());
  EXPECT_FALSE(mesh->skin_nodes.empty());
  auto lesions = waitFor<breast_sim::LesionArray>("/breast_sim/lesions", 10.0);
  ASSERT_TRUE(lesions);
  EXPECT_GE(lesions->lesions.size(), 1u);
  for (const auto& l : lesions->lesions) {
    EXPECT_FALSE(l.id.empty());
    EXPECT_DOUBLE_EQ(l.position.x, l.prone_position.x);  // no deformation yet
  }
}

TEST(ModelNode, BadCaseIsRefusedAndTheModelIsKept) {
  ros::NodeHandle nh, pnh("~");
  auto before = waitFor<breast_sim::TetrahedralMesh>("/breast_sim/deformed_mesh", 240.0);
  ASSERT_TRUE(before);
  ASSERT_TRUE(ros::service::waitForService("/breast_sim/load_case", ros::Duration(30.0)));
  breast_sim::LoadCase srv;
  pnh.getParam("bad_case_file", srv.request.case_file);
  ASSERT_TRUE(ros::service::call("/breast_sim/load_case", srv));
  EXPECT_FALSE(srv.response.success);
  EXPECT_NE(srv.response.message.find("does_not_exist.yaml"), std::string::npos) << srv.response.message;
  auto after = waitFor<breast_sim::TetrahedralMesh>("/breast_sim/deformed_mesh", 10.0);
  ASSERT_TRUE(after);
  EXPECT_EQ(after->tetrahedra.size(), before->tetrahedra.size());
  EXPECT_EQ(after->header.stamp, before->header.stamp);
}

TEST(ModelNode, GoodCaseReplacesTheModel) {
  ros::NodeHandle pnh("~");
  auto before = waitFor<breast_sim::TetrahedralMesh>("/breast_sim/deformed_mesh", 240.0);
  ASSERT_TRUE(before);
  ASSERT_TRUE(ros::service::waitForService("/breast_sim/load_case", ros::Duration(30.0)));
  breast_sim::LoadCase srv;
  pnh.getParam("good_case_file", srv.request.case_file);
  srv.request.target_elements = 2000;
  ASSERT_TRUE(ros::service::call("/breast_sim/load_case", srv));
  ASSERT_TRUE(srv.response.success) << srv.response.message;
  EXPECT_NE(srv.response.message.find("tetrahedra"), std::string::npos) << srv.response.message;
  auto after = waitFor<breast_sim::TetrahedralMesh>("/breast_sim/deformed_mesh", 10.0);
  ASSERT_TRUE(after);
  EXPECT_GT(after->header.stamp, before->header.stamp);
  EXPECT_LT(after->tetrahedra.size(), before->tetrahedra.size());  // 2000 rather than 3000 elements
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "model_node_test");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  return RUN_ALL_TESTS();
}
