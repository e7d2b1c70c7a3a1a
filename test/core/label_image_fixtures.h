#pragma once
// Shared by the label-image tests (test_label_image, test_label_image_malformed): a temporary folder,
// raw bytes in a chosen byte order, the hand-made 7×5×3 test image as voxel data, hand-made NIfTI-1
// headers, and the message of a thrown std::runtime_error.

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <system_error>

#include <Eigen/Core>
#include <gtest/gtest.h>
#include <unistd.h>

namespace breast_sim::core::label_image_fixtures {

inline std::string tempPath(const std::string& name) {
  static const std::filesystem::path dir = [] {
    const auto d = std::filesystem::temp_directory_path() /
                   ("breast_sim_test_label_image_" + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    return d;
  }();
  return (dir / name).string();
}

/// Removes the temporary folder after the last test; each test file registers one.
class TempFolderCleanup : public ::testing::Environment {
 public:
  void TearDown() override {
    std::error_code ignored;
    std::filesystem::remove_all(std::filesystem::path(tempPath("x")).parent_path(), ignored);
  }
};

inline void writeBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  ASSERT_TRUE(out.good()) << path;
}

inline std::string readBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

inline Eigen::Vector3d mm(double x, double y, double z) { return Eigen::Vector3d(x, y, z) * 1e-3; }

inline bool hostIsBigEndian() {
  const std::uint16_t one = 1;
  unsigned char first = 0;
  std::memcpy(&first, &one, 1);
  return first == 0;
}

/// One value in the byte order asked for.
template <typename T>
std::string encode(T value, bool big_endian) {
  std::string b(sizeof(T), '\0');
  std::memcpy(b.data(), &value, sizeof(T));
  if (big_endian != hostIsBigEndian()) std::reverse(b.begin(), b.end());
  return b;
}

// The hand-made test image: 7×5×3 voxels, all 0 except label 5 at (i, j, k) = (5, 1, 2), which
// is voxel 5 + 7·(1 + 5·2) = 82.
constexpr long kVoxels = 7 * 5 * 3;
constexpr long kMarked = 82;

/// The voxel data of the test image as values of type T.
template <typename T>
std::string markedData(T value, bool big_endian, long at = kMarked) {
  std::string out;
  for (long v = 0; v < kVoxels; ++v) out += encode<T>(v == at ? value : T(0), big_endian);
  return out;
}

/// what() of the std::runtime_error `f` throws, or "" if it throws none.
inline std::string errorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}

// Fields of a hand-made NIfTI-1 header, written at the offsets of nifti1.h.
struct NiftiFields {
  bool big_endian = false;
  int sizeof_hdr = 348;
  short dim[8] = {3, 7, 5, 3, 1, 1, 1, 1};
  short datatype = 2;  // DT_UINT8
  short bitpix = 8;
  float pixdim[8] = {1, 0.5f, 1, 2, 0, 0, 0, 0};
  float scl_slope = 0;
  float scl_inter = 0;
  short qform_code = 0;
  short sform_code = 0;
  float quatern[3] = {0, 0, 0};
  float qoffset[3] = {0, 0, 0};
  float srow[3][4] = {{0, 0, 0, 0}, {0, 0, 0, 0}, {0, 0, 0, 0}};
  float vox_offset = 352;
};

/// 348-byte header + 4-byte extension flag; vox_offset as given (352 by default), units mm.
inline std::string niftiHeader(const NiftiFields& f) {
  std::string h(352, '\0');
  const auto put = [&](std::size_t offset, const std::string& bytes) {
    std::memcpy(&h[offset], bytes.data(), bytes.size());
  };
  const bool be = f.big_endian;
  put(0, encode<std::int32_t>(f.sizeof_hdr, be));
  for (int d = 0; d < 8; ++d) put(40 + 2 * d, encode<std::int16_t>(f.dim[d], be));
  put(70, encode<std::int16_t>(f.datatype, be));
  put(72, encode<std::int16_t>(f.bitpix, be));
  for (int d = 0; d < 8; ++d) put(76 + 4 * d, encode<float>(f.pixdim[d], be));
  put(108, encode<float>(f.vox_offset, be));
  put(112, encode<float>(f.scl_slope, be));
  put(116, encode<float>(f.scl_inter, be));
  h[123] = 2;  // NIFTI_UNITS_MM
  put(252, encode<std::int16_t>(f.qform_code, be));
  put(254, encode<std::int16_t>(f.sform_code, be));
  for (int i = 0; i < 3; ++i) put(256 + 4 * i, encode<float>(f.quatern[i], be));
  for (int i = 0; i < 3; ++i) put(268 + 4 * i, encode<float>(f.qoffset[i], be));
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) put(280 + 16 * r + 4 * c, encode<float>(f.srow[r][c], be));
  }
  put(344, std::string("n+1\0", 4));
  return h;
}

}  // namespace breast_sim::core::label_image_fixtures
