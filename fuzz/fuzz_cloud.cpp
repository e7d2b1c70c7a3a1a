// Fuzz target: the PointCloud2 -> points conversion (ros_interface/cloud_points.h), the one place the
// node reads bytes a tracker sends. The input chooses the message's layout (sizes, steps and fields,
// each from a small range or the whole 32-bit range, so both valid and contradicting layouts are
// reached) and its data bytes. Not findings: the points, or std::invalid_argument naming the
// PointCloud2. A finding aborts: another exception, or points that break the contract (non-finite,
// more than the message holds or than max_points).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <typeinfo>

#include <fuzzer/FuzzedDataProvider.h>

#include "breast_sim/ros_interface/cloud_points.h"

namespace {

// A 32-bit message field: mostly a small value a layout can satisfy, sometimes any value.
std::uint32_t layoutValue(FuzzedDataProvider& in, std::uint32_t small_max) {
  return in.ConsumeBool() ? in.ConsumeIntegral<std::uint32_t>() : in.ConsumeIntegralInRange<std::uint32_t>(0, small_max);
}

[[noreturn]] void finding(const char* what) {
  std::fprintf(stderr, "%s\n", what);
  std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const char* const kNames[] = {"x", "y", "z", "rgb", "intensity", "X"};
  FuzzedDataProvider in(data, size);
  sensor_msgs::PointCloud2 msg;
  msg.height = layoutValue(in, 4);
  msg.width = layoutValue(in, 64);
  msg.point_step = layoutValue(in, 48);
  msg.row_step = layoutValue(in, 1024);
  msg.is_bigendian = in.ConsumeBool() && in.ConsumeBool();
  const int fields = in.ConsumeIntegralInRange<int>(0, 6);
  for (int k = 0; k < fields; ++k) {
    sensor_msgs::PointField f;
    f.name = kNames[in.ConsumeIntegralInRange<int>(0, 5)];
    f.offset = layoutValue(in, 40);
    f.datatype = in.ConsumeIntegralInRange<std::uint8_t>(0, 9);
    f.count = 1;
    msg.fields.push_back(f);
  }
  const std::size_t max_points = in.ConsumeIntegralInRange<std::size_t>(0, 64);
  msg.data = in.ConsumeRemainingBytes<std::uint8_t>();
  try {
    const breast_sim::ros_interface::CloudPoints c = breast_sim::ros_interface::pointsFromCloud(msg, max_points);
    const std::size_t rows = static_cast<std::size_t>(c.points_m.rows());
    if (!c.points_m.allFinite()) finding("a non-finite point was returned");
    if (c.total != static_cast<std::size_t>(msg.width) * msg.height) finding("total is not width x height");
    if (rows + c.non_finite > c.total) finding("more points than the message holds");
    if (max_points > 0 && rows + c.non_finite > max_points) finding("more points than max_points");
  } catch (const std::invalid_argument& e) {
    if (std::string(e.what()).rfind("PointCloud2", 0) != 0) {
      std::fprintf(stderr, "error message does not name the PointCloud2: %s\n", e.what());
      std::abort();
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "unexpected exception %s: %s\n", typeid(e).name(), e.what());
    std::abort();
  }
  return 0;
}
