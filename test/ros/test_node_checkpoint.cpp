// Checkpoint names and case fingerprints (ros_interface/node_checkpoint.h): the fingerprint changes
// with any node coordinate, element index or setting, and is the same for the same case. The
// multigrid levels kept beside the checkpoints read back to the bit, and an incomplete or damaged
// set is an error naming the file.
#include <gtest/gtest.h>

#include <stdlib.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "breast_sim/ros_interface/node_checkpoint.h"

using breast_sim::core::Points;
using breast_sim::core::TetMesh;
using breast_sim::core::Tets;
using namespace breast_sim::ros_interface;

namespace {

/// Two tetrahedra sharing a face.
TetMesh twoTets(double apex_z = 1.0) {
  Points nodes(5, 3);
  nodes << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, apex_z, 0.4, 0.4, -1;
  Tets tets(2, 4);
  tets << 0, 1, 2, 3, 0, 2, 1, 4;
  return TetMesh(nodes, tets);
}

}  // namespace

TEST(NodeCheckpoint, TheSameCaseGivesTheSameFingerprint) {
  EXPECT_EQ(caseFingerprint(twoTets(), "simulation: {youngs_modulus_pa: 2000}"),
            caseFingerprint(twoTets(), "simulation: {youngs_modulus_pa: 2000}"));
  EXPECT_NE(caseFingerprint(twoTets(), ""), 0u);
}

TEST(NodeCheckpoint, AnyChangeOfMeshOrSettingsChangesTheFingerprint) {
  const std::uint64_t base = caseFingerprint(twoTets(), "simulation: {youngs_modulus_pa: 2000}");
  // One node moved by one unit in the last place.
  EXPECT_NE(caseFingerprint(twoTets(std::nextafter(1.0, 2.0)), "simulation: {youngs_modulus_pa: 2000}"), base);
  // Another material.
  EXPECT_NE(caseFingerprint(twoTets(), "simulation: {youngs_modulus_pa: 2001}"), base);
  // The same nodes, elements numbered otherwise (the state's vectors would not fit).
  const TetMesh m = twoTets();
  Tets other = m.tets();
  other.row(0) << 0, 2, 3, 1;  // the same tetrahedron, positively oriented, its nodes in another order
  EXPECT_NE(caseFingerprint(TetMesh(m.nodes(), other), "simulation: {youngs_modulus_pa: 2000}"), base);
}

TEST(NodeCheckpoint, NamesHoldTheFingerprintInHex) {
  EXPECT_EQ(checkpointName(0x1234abcdULL), "checkpoint-000000001234abcd.state");
  EXPECT_EQ(checkpointPrefix(std::numeric_limits<std::uint64_t>::max()), "checkpoint-ffffffffffffffff");
  EXPECT_EQ(checkpointName(42), checkpointPrefix(42) + kCheckpointSuffix);
}

namespace {

/// A fresh temporary folder as the node's ~state_folder.
class LevelFolder : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string pattern = (std::filesystem::temp_directory_path() / "multigrid_levels_XXXXXX").string();
    ASSERT_NE(::mkdtemp(pattern.data()), nullptr);
    base_ = pattern;
    folder_ = std::make_unique<ConfinedFolder>(base_.string(), "~state_folder", false);
  }
  void TearDown() override {
    std::error_code ec;
    std::filesystem::remove_all(base_, ec);
  }
  std::filesystem::path base_;
  std::unique_ptr<ConfinedFolder> folder_;
};

/// Two levels whose coordinates need every bit of a double.
std::vector<TetMesh> twoLevels() {
  TetMesh a = twoTets(1.0 / 3.0);
  Points n = a.nodes();
  n(4, 0) = std::nextafter(0.1, 1.0);
  return {TetMesh(n, a.tets()), twoTets(std::sqrt(2.0))};
}

}  // namespace

TEST_F(LevelFolder, MultigridLevelsReadBackToTheBit) {
  EXPECT_EQ(multigridLevelName(0xabcULL, 1, 2), "multigrid-0000000000000abc-1of2.msh");
  EXPECT_FALSE(readMultigridLevels(*folder_, 7).has_value());
  const std::vector<TetMesh> levels = twoLevels();
  writeMultigridLevels(*folder_, 7, levels);
  writeMultigridLevels(*folder_, 8, {levels[1]});  // another case's level beside them
  const auto read = readMultigridLevels(*folder_, 7);
  ASSERT_TRUE(read.has_value());
  ASSERT_EQ(read->size(), 2u);
  for (size_t l = 0; l < 2; ++l) {
    EXPECT_EQ((*read)[l].nodes(), levels[l].nodes()) << "level " << l + 1;
    EXPECT_EQ((*read)[l].tets(), levels[l].tets()) << "level " << l + 1;
  }
  EXPECT_EQ(readMultigridLevels(*folder_, 8)->size(), 1u);
  // Written again (the same case loaded again): replaced, not refused.
  EXPECT_NO_THROW(writeMultigridLevels(*folder_, 7, levels));
}

TEST_F(LevelFolder, TheUnloadedShapeReadsBackToTheBit) {
  EXPECT_EQ(unloadedShapeName(0xabcULL), "unloaded-0000000000000abc.msh");
  EXPECT_FALSE(readUnloadedShape(*folder_, 7).has_value());
  const TetMesh x0 = twoLevels()[0];
  writeUnloadedShape(*folder_, 7, x0);
  writeUnloadedShape(*folder_, 8, twoLevels()[1]);  // another case's beside it
  const std::optional<Points> read = readUnloadedShape(*folder_, 7);
  ASSERT_TRUE(read.has_value());
  EXPECT_EQ(*read, x0.nodes());
  EXPECT_NO_THROW(writeUnloadedShape(*folder_, 7, x0));  // the same case again: replaced
  std::ofstream(base_ / unloadedShapeName(7)) << "$MeshFormat\n2.2 1 8\n";  // cut short
  try {
    readUnloadedShape(*folder_, 7);
    FAIL() << "a damaged shape was read";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("does not read"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(unloadedShapeName(7)), std::string::npos) << e.what();
  }
}

TEST_F(LevelFolder, AnIncompleteOrDamagedSetIsAnErrorNamingTheFile) {
  writeMultigridLevels(*folder_, 7, twoLevels());
  std::filesystem::remove(base_ / multigridLevelName(7, 2, 2));
  try {
    readMultigridLevels(*folder_, 7);
    FAIL() << "a set without its level 2 was read";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("incomplete"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(multigridLevelName(7, 2, 2)), std::string::npos) << e.what();
  }
  std::ofstream(base_ / multigridLevelName(7, 2, 2)) << "$MeshFormat\n2.2 1 8\n";  // cut short
  try {
    readMultigridLevels(*folder_, 7);
    FAIL() << "a damaged level was read";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("does not read"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(multigridLevelName(7, 2, 2)), std::string::npos) << e.what();
  }
  std::filesystem::remove(base_ / multigridLevelName(7, 1, 2));
  std::filesystem::remove(base_ / multigridLevelName(7, 2, 2));
  std::ofstream(base_ / "multigrid-0000000000000007-3of99.msh") << "x";
  EXPECT_THROW(readMultigridLevels(*folder_, 7), std::runtime_error);
}
