#include "breast_sim/ros_interface/cloud_points.h"

#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>

namespace breast_sim::ros_interface {

namespace {

const sensor_msgs::PointField* findField(const sensor_msgs::PointCloud2& msg, const char* name) {
  for (const auto& f : msg.fields)
    if (f.name == name) return &f;
  return nullptr;
}

double readFloat(const uint8_t* p, uint8_t datatype) {
  if (datatype == sensor_msgs::PointField::FLOAT32) {
    float v;
    std::memcpy(&v, p, sizeof v);
    return v;
  }
  double v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

}  // namespace

CloudPoints pointsFromCloud(const sensor_msgs::PointCloud2& msg, size_t max_points) {
  CloudPoints out;
  const size_t n = static_cast<size_t>(msg.width) * msg.height;
  out.total = n;
  if (n == 0) {
    out.points_m.resize(0, 3);
    return out;
  }
  const char* names[3] = {"x", "y", "z"};
  const sensor_msgs::PointField* f[3];
  for (int k = 0; k < 3; ++k) {
    f[k] = findField(msg, names[k]);
    if (!f[k])
      throw std::invalid_argument(std::string("PointCloud2: no field '") + names[k] +
                                  "'; a surface cloud needs FLOAT32 or FLOAT64 fields x, y, z");
    if (f[k]->datatype != sensor_msgs::PointField::FLOAT32 && f[k]->datatype != sensor_msgs::PointField::FLOAT64)
      throw std::invalid_argument(std::string("PointCloud2: field '") + names[k] + "' has datatype " +
                                  std::to_string(f[k]->datatype) + "; expected FLOAT32 (7) or FLOAT64 (8)");
    const size_t size = f[k]->datatype == sensor_msgs::PointField::FLOAT32 ? 4 : 8;
    if (f[k]->offset + size > msg.point_step)
      throw std::invalid_argument(std::string("PointCloud2: field '") + names[k] + "' at offset " +
                                  std::to_string(f[k]->offset) + " does not fit in point_step " +
                                  std::to_string(msg.point_step));
  }
  const bool host_big = [] {
    const uint16_t one = 1;
    uint8_t b;
    std::memcpy(&b, &one, 1);
    return b == 0;
  }();
  if (static_cast<bool>(msg.is_bigendian) != host_big)
    throw std::invalid_argument(std::string("PointCloud2: is_bigendian = ") + (msg.is_bigendian ? "true" : "false") +
                                " differs from this machine; publish the cloud in host byte order");
  if (static_cast<size_t>(msg.point_step) * msg.width > msg.row_step)
    throw std::invalid_argument("PointCloud2: row_step " + std::to_string(msg.row_step) + " < point_step " +
                                std::to_string(msg.point_step) + " x width " + std::to_string(msg.width));
  if (static_cast<size_t>(msg.row_step) * msg.height > msg.data.size())
    throw std::invalid_argument("PointCloud2: data has " + std::to_string(msg.data.size()) + " bytes, row_step x height = " +
                                std::to_string(static_cast<size_t>(msg.row_step) * msg.height) + " (truncated message)");
  out.stride = (max_points > 0 && n > max_points) ? (n + max_points - 1) / max_points : 1;
  out.points_m.resize(static_cast<Eigen::Index>((n + out.stride - 1) / out.stride), 3);
  Eigen::Index m = 0;
  for (size_t i = 0; i < n; i += out.stride) {
    const size_t row = i / msg.width, col = i % msg.width;
    const uint8_t* p = msg.data.data() + row * msg.row_step + col * msg.point_step;
    const double x = readFloat(p + f[0]->offset, f[0]->datatype);
    const double y = readFloat(p + f[1]->offset, f[1]->datatype);
    const double z = readFloat(p + f[2]->offset, f[2]->datatype);
    if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) {
      ++out.non_finite;
      continue;
    }
    out.points_m.row(m++) << x, y, z;
  }
  out.points_m.conservativeResize(m, 3);
  return out;
}

}  // namespace breast_sim::ros_interface
