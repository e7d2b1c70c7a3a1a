// The readers' limits: sizes a file merely claims are checked against the bytes present (or a stated
// maximum) before anything is allocated, counts are computed without overflow, non-finite or
// out-of-range values are refused, and every error names the file and the fault. One test per fault
// the fuzz targets (fuzz/) exercise; each fails without its check.

#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/state_file.h"
#include "temp_dir.h"

namespace {

using namespace breast_sim::core;
using breast_sim::test::TempDir;

/// The message of the std::runtime_error `f` throws ("" when it throws nothing, the type name when
/// it throws something else).
std::string errorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::runtime_error& e) {
    return e.what();
  } catch (const std::exception& e) {
    return std::string("unexpected ") + typeid(e).name() + ": " + e.what();
  }
  return "";
}

void expectError(const std::function<void()>& f, const std::vector<std::string>& says) {
  const std::string message = errorOf(f);
  ASSERT_FALSE(message.empty()) << "no error";
  for (const std::string& s : says) EXPECT_NE(message.find(s), std::string::npos) << "'" << s << "' not in: " << message;
}

std::string readBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

void writeBytes(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
}

// ---- state files ----------------------------------------------------------------------------------

StateFile smallState() {
  StateFile f;
  f.nodes = 4;
  f.tets = 1;
  f.mesh_fingerprint = 4503599627370497.0;
  PipelineState& s = f.state;
  s.simulation.displacement_m = Eigen::VectorXd::LinSpaced(12, -1e-3, 1e-3);
  s.simulation.velocity_mps = Eigen::VectorXd::Constant(12, 2e-4);
  s.simulation.time_s = 3.25;
  s.simulation.step = 17;
  s.modulus_factors = Eigen::VectorXd::Constant(1, 1.25);
  s.alpha.alpha_per_pa = 2e-4;
  s.alpha.phase = AlphaController::Phase::kSettling;
  s.alpha.rate = 0.5;
  s.alpha.oscillations = 2;
  s.alpha.runs[0] = -1;
  s.alpha.runs[1] = 1;
  s.stage = PipelineStage::kMorphing;
  s.sliding_targets_m = Points::Constant(2, 3, 0.01);
  s.sliding_slip_directions = Points::Zero(2, 3);
  s.morphing_forces_n = Points::Constant(1, 3, 0.25);
  s.gravity_load_mps2 = Eigen::Vector3d(0.0, 9.81, 9.81);
  f.has_gravity_load = f.has_rest_shape = true;
  f.rest_m = Points::Constant(4, 3, 0.02);
  s.element_alpha_per_pa = Eigen::VectorXd::Constant(1, 3e-5);
  return f;
}

/// Byte offset of section `index` (0 = header) in a file written by writeStateFile.
std::size_t sectionOffset(const std::string& bytes, int index) {
  std::size_t at = 8;
  for (int s = 0; s < index; ++s) {
    std::int64_t n = 0;
    std::memcpy(&n, bytes.data() + at, 8);
    at += 8 + 8 * static_cast<std::size_t>(n);
  }
  return at;
}

void setValue(std::string& bytes, int section, int value, double v) {
  std::memcpy(&bytes[sectionOffset(bytes, section) + 8 + 8 * static_cast<std::size_t>(value)], &v, 8);
}

TEST(StateFile, RoundTripsEverySection) {
  TempDir dir("state_file");
  const StateFile f = smallState();
  writeStateFile(dir.path("s.bin"), f);
  const StateFile g = readStateFile(dir.path("s.bin"));
  EXPECT_EQ(g.nodes, 4);
  EXPECT_EQ(g.tets, 1);
  EXPECT_EQ(g.mesh_fingerprint, f.mesh_fingerprint);
  EXPECT_EQ(g.state.simulation.displacement_m, f.state.simulation.displacement_m);
  EXPECT_EQ(g.state.simulation.velocity_mps, f.state.simulation.velocity_mps);
  EXPECT_EQ(g.state.simulation.step, 17);
  EXPECT_EQ(g.state.simulation.time_s, 3.25);
  EXPECT_EQ(g.state.modulus_factors, f.state.modulus_factors);
  EXPECT_EQ(g.state.alpha.phase, AlphaController::Phase::kSettling);
  EXPECT_EQ(g.state.alpha.runs[0], -1);
  EXPECT_EQ(g.state.alpha.runs[1], 1);
  EXPECT_EQ(g.state.alpha.oscillations, 2);
  EXPECT_EQ(g.state.stage, PipelineStage::kMorphing);
  EXPECT_EQ(g.state.sliding_targets_m, f.state.sliding_targets_m);
  EXPECT_EQ(g.state.sliding_slip_directions, f.state.sliding_slip_directions);
  EXPECT_EQ(g.state.morphing_forces_n, f.state.morphing_forces_n);
  EXPECT_TRUE(g.has_gravity_load);
  EXPECT_EQ(g.state.gravity_load_mps2, f.state.gravity_load_mps2);
  EXPECT_TRUE(g.has_rest_shape);
  EXPECT_EQ(g.rest_m, f.rest_m);
  EXPECT_EQ(g.state.element_alpha_per_pa, f.state.element_alpha_per_pa);
  // A local alpha the reader would refuse is not written, and the file stays as it was. (The
  // writer checks it itself: it is built into the readers' library, without the stiffening driver.)
  StateFile bad = f;
  bad.state.element_alpha_per_pa[0] = -1.0;
  try {
    writeStateFile(dir.path("s.bin"), bad);
    ADD_FAILURE() << "written";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("a local alpha is negative or not finite"), std::string::npos) << e.what();
  }
  EXPECT_EQ(readStateFile(dir.path("s.bin")).state.element_alpha_per_pa, f.state.element_alpha_per_pa);
  // No temporary is left beside the file.
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir.path(""))) files += entry.is_regular_file();
  EXPECT_EQ(files, 1);
}

TEST(StateFile, ReadsFilesOfEarlierVersions) {
  TempDir dir("state_file");
  writeStateFile(dir.path("s.bin"), smallState());
  const std::string full = readBytes(dir.path("s.bin"));
  // Without the local alphas, then also without the rest shape, then also without the gravity load,
  // then also without slip directions.
  const std::size_t ends[] = {sectionOffset(full, 10), sectionOffset(full, 9), sectionOffset(full, 8),
                              sectionOffset(full, 7)};
  for (int k = 0; k < 4; ++k) {
    SCOPED_TRACE(k);
    writeBytes(dir.path("old.bin"), full.substr(0, ends[k]));
    const StateFile g = readStateFile(dir.path("old.bin"));
    EXPECT_EQ(g.state.element_alpha_per_pa.size(), 0);
    EXPECT_EQ(g.has_rest_shape, k == 0);
    EXPECT_EQ(g.has_gravity_load, k <= 1);
    EXPECT_EQ(g.state.sliding_slip_directions.rows(), k == 3 ? 0 : 2);
  }
}

TEST(StateFile, RefusesASectionLongerThanTheFileBeforeAllocating) {
  TempDir dir("state_file");
  writeStateFile(dir.path("s.bin"), smallState());
  std::string bytes = readBytes(dir.path("s.bin"));
  const std::int64_t huge = std::int64_t{1} << 34;  // 128 GiB of doubles
  std::memcpy(&bytes[sectionOffset(bytes, 2)], &huge, 8);
  writeBytes(dir.path("huge.bin"), bytes);
  expectError([&] { readStateFile(dir.path("huge.bin")); },
              {dir.path("huge.bin"), "displacement section", "says 17179869184 values"});
  const std::int64_t negative = -3;
  std::memcpy(&bytes[sectionOffset(bytes, 2)], &negative, 8);
  writeBytes(dir.path("negative.bin"), bytes);
  expectError([&] { readStateFile(dir.path("negative.bin")); }, {"displacement section", "says -3 values"});
}

TEST(StateFile, RefusesHeaderCountsThatAreNotWholeNumbersInRange) {
  TempDir dir("state_file");
  writeStateFile(dir.path("s.bin"), smallState());
  const std::string good = readBytes(dir.path("s.bin"));
  struct Case {
    int value;
    double v;
    std::string says;
  };
  const std::vector<Case> cases = {
      {0, std::nan(""), "value 0 of the header section is nan"},
      {0, 1e300, "the node count is 1.0000000000000001e+300"},  // once cast to int: undefined
      {1, 2.5, "the element count is 2.5"},
      {1, -1.0, "the element count is -1"},
      {3, 1e19, "the step is 1e+19"},
      {5, 2.0, "the alpha phase (0 search, 1 settling) is 2"},
      {7, 3e9, "the oscillation count is 3000000000"},
      {8, 7.0, "the stage is 7"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.says);
    std::string bytes = good;
    setValue(bytes, 0, c.value, c.v);
    writeBytes(dir.path("bad.bin"), bytes);
    expectError([&] { readStateFile(dir.path("bad.bin")); }, {dir.path("bad.bin"), c.says});
  }
  std::string bytes = good;
  setValue(bytes, 1, 2, 5.0);
  writeBytes(dir.path("runs.bin"), bytes);
  expectError([&] { readStateFile(dir.path("runs.bin")); }, {"a run direction is 5"});
}

TEST(StateFile, RefusesNonFiniteValues) {
  TempDir dir("state_file");
  writeStateFile(dir.path("s.bin"), smallState());
  const std::string good = readBytes(dir.path("s.bin"));
  const double inf = std::numeric_limits<double>::infinity();
  struct Case {
    int section, value;
    double v;
    std::string says;
  };
  const std::vector<Case> cases = {
      {2, 4, inf, "value 4 of the displacement section is inf"},
      {3, 0, std::nan(""), "value 0 of the velocity section is nan"},
      {4, 0, -inf, "value 0 of the modulus factor section is -inf"},
      {4, 0, 0.0, "the modulus factor of element 0 is 0"},
      {8, 1, inf, "value 1 of the gravity load section is inf"},
      {9, 11, std::nan(""), "value 11 of the rest shape section is nan"},
      {10, 0, inf, "value 0 of the local alpha section is inf"},
      {10, 0, -1e-6, "the local alpha of element 0 is -9.9999999999999995e-07 1/Pa"},
      {0, 2, inf, "value 2 of the header section is inf"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.says);
    std::string bytes = good;
    setValue(bytes, c.section, c.value, c.v);
    writeBytes(dir.path("bad.bin"), bytes);
    expectError([&] { readStateFile(dir.path("bad.bin")); }, {dir.path("bad.bin"), c.says});
  }
}

TEST(StateFile, RefusesSectionsThatDoNotMatchTheHeader) {
  TempDir dir("state_file");
  StateFile f = smallState();
  writeStateFile(dir.path("s.bin"), f);
  std::string bytes = readBytes(dir.path("s.bin"));
  setValue(bytes, 0, 0, 5.0);  // 5 nodes, but 12 displacement values
  writeBytes(dir.path("nodes.bin"), bytes);
  expectError([&] { readStateFile(dir.path("nodes.bin")); },
              {"the displacement section has 12 values, expected 15 (5 nodes in the header)"});
  bytes = readBytes(dir.path("s.bin"));
  std::string alphas = bytes.substr(0, sectionOffset(bytes, 10));  // two local alphas for one element
  const std::int64_t two = 2;
  const double a[2] = {1e-5, 1e-5};
  alphas.append(reinterpret_cast<const char*>(&two), 8).append(reinterpret_cast<const char*>(a), 16);
  writeBytes(dir.path("alphas.bin"), alphas);
  expectError([&] { readStateFile(dir.path("alphas.bin")); },
              {"the local alpha section has 2 values, expected 1 (1 elements in the header, or none)"});
  writeBytes(dir.path("trailing.bin"), bytes + "xyz");
  expectError([&] { readStateFile(dir.path("trailing.bin")); }, {"3 bytes follow the last section"});
  writeBytes(dir.path("truncated.bin"), bytes.substr(0, sectionOffset(bytes, 3) + 4));
  expectError([&] { readStateFile(dir.path("truncated.bin")); }, {"the velocity section is missing"});
  writeBytes(dir.path("magic.bin"), "BSSTATE2" + bytes.substr(8));
  expectError([&] { readStateFile(dir.path("magic.bin")); }, {"not a breast_sim state file"});
}

TEST(StateFile, NamesAFolderGivenAsTheFile) {
  TempDir dir("state_file");
  std::filesystem::create_directory(dir.path("folder.bin"));
  expectError([&] { readStateFile(dir.path("folder.bin")); }, {dir.path("folder.bin"), "is a folder, not a state file"});
}

// ---- case files -----------------------------------------------------------------------------------

/// An image case on a small label image beside it, with `extra` appended to its image: map.
std::string imageCase(const TempDir& dir, const std::string& extra) {
  LabelImage image(Eigen::Vector3i(7, 5, 3), Eigen::Vector3d::Constant(4e-3), Eigen::Vector3d::Zero(), 1);
  writeLabelImage(dir.path("image.nrrd"), image);
  return dir.write("case.yaml", "image:\n  path: image.nrrd\n  labels: {fat: [1]}\n" + extra);
}

TEST(CaseFile, NonScalarKeysNameTheFile) {
  TempDir dir("case_file");
  // yaml-cpp's "bad conversion" without a file reached the caller.
  const std::string image = imageCase(dir, "  ? [a, b]\n  : 1\n");
  expectError([&] { loadModelCase(image); }, {image + ": 'image': a key is [a, b]; keys must be plain words"});
  const std::string phantom = dir.write("phantom.yaml", "phantom:\n  ? {x: 1}\n  : 2\n");
  expectError([&] { loadPhantomParams(phantom); }, {phantom, "a key of 'phantom:' is {x: 1}; keys must be plain words"});
  const std::string lesion = dir.write("lesion.yaml", "phantom:\n  lesions:\n    - {? [1]: 2, position_mm: [0, 0, 0]}\n");
  expectError([&] { loadPhantomParams(lesion); }, {lesion, "phantom.lesions[0]", "keys are name, position_mm, radius_mm"});
  // Merged over a base: the key is named with the file that holds it.
  dir.write("base.yaml", "phantom: {depth_mm: 40}\n");
  const std::string over = dir.write("over.yaml", "base: base.yaml\nphantom:\n  ? [z]\n  : 1\n");
  expectError([&] { loadPhantomParams(over); }, {over + ": 'phantom': a key is [z]; keys must be plain words"});
}

TEST(CaseFile, AFolderAsCaseOrBaseIsNamed) {
  TempDir dir("case_file");
  std::filesystem::create_directory(dir.path("folder.yaml"));
  expectError([&] { loadModelCase(dir.path("folder.yaml")); }, {dir.path("folder.yaml") + ": is a folder, not a case file"});
  const std::string c = dir.write("case.yaml", "base: folder.yaml\nphantom: {}\n");
  expectError([&] { loadPhantomParams(c); }, {dir.path("folder.yaml") + ": is a folder, not a case file (the base of"});
}

// The phantom's image grid is counted in int voxels: a voxel of 1e-300 mm or a margin of 1e300 mm
// overflowed the float-to-int conversion (undefined behaviour) before the image-size check.
TEST(CaseFile, PhantomSizesThatWouldOverflowTheGridAreRefused) {
  TempDir dir("case_file");
  struct Case {
    std::string yaml;
    std::string says;
  };
  const std::vector<Case> cases = {
      {"voxel_size_mm: 1.0e-300", "key 'phantom.voxel_size_mm' = 1e-300 mm: expected a positive step of at least 0.01 mm"},
      {"margin_mm: 1.0e+300", "key 'phantom.margin_mm' = 1e+300 mm: expected a length of at most 10000 mm"},
      {"lateral_semi_axis_mm: 1.0e+12", "key 'phantom.lateral_semi_axis_mm' = 1e+12 mm: expected a length of at most"},
      {"surface_edge_mm: 1.0e-9", "key 'phantom.surface_edge_mm' = 1e-09 mm: expected a positive step of at least 0.01 mm"},
      {"lesions: [{position_mm: [1.0e+300, 0, 0]}]", "key 'phantom.lesions[0]': a position or radius beyond 10000 mm"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.yaml);
    const std::string path = dir.write("phantom.yaml", "phantom:\n  " + c.yaml + "\n");
    expectError([&] { loadPhantomParams(path); }, {path, c.says});
  }
}

// Only the direction counts: (1e200, 1e200, 0) has an infinite norm but a direction; it was refused
// as "not finite" (or, normalised, became zero).
TEST(CaseFile, GravityDirectionOfAnyScaleIsNormalisedWithoutOverflow) {
  TempDir dir("case_file");
  const ModelCase big = loadModelCase(imageCase(dir, "  prone_gravity_direction: [1.0e+200, 1.0e+200, 0]\n"));
  EXPECT_NEAR(big.prone_gravity_direction.x(), std::sqrt(0.5), 1e-15);
  EXPECT_NEAR(big.prone_gravity_direction.y(), std::sqrt(0.5), 1e-15);
  EXPECT_EQ(big.prone_gravity_direction.z(), 0.0);
  const ModelCase tiny = loadModelCase(imageCase(dir, "  prone_gravity_direction: [0, -1.0e-310, 0]\n"));
  EXPECT_EQ(tiny.prone_gravity_direction, Eigen::Vector3d(0, -1, 0));
  const std::string zero = imageCase(dir, "  prone_gravity_direction: [0, 0, 0]\n");
  expectError([&] { loadModelCase(zero); }, {zero, "'image.prone_gravity_direction': must be a non-zero vector"});
}

}  // namespace
