// Checkpoint names and case fingerprints (ros_interface/node_checkpoint.h): the fingerprint changes
// with any node coordinate, element index or setting, and is the same for the same case.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>

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
