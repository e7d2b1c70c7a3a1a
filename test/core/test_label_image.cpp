// Label-image readers and writers: geometry of hand-written files, round trips, the VICTRE
// phantom, and the index ↔ physical mapping. Malformed input: test_label_image_malformed.cpp.

#include "breast_sim/core/image/label_image.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>
#include <unistd.h>

#include "label_image_fixtures.h"

namespace {

using breast_sim::core::LabelImage;
using breast_sim::core::readLabelImage;
using breast_sim::core::writeLabelImage;

using namespace breast_sim::core::label_image_fixtures;

const ::testing::Environment* const kCleanup =
    ::testing::AddGlobalTestEnvironment(new TempFolderCleanup);

/// Checks the hand-made image: size, spacing (0.5, 1, 2) mm, voxel (5,1,2) at `expected_m`
/// holding label 5, and nothing else labelled.
void expectMarkedImage(const LabelImage& image, const Eigen::Vector3d& expected_m,
                       double tolerance_m = 1e-12) {
  EXPECT_EQ(image.size, Eigen::Vector3i(7, 5, 3));
  EXPECT_TRUE(image.spacing_m.isApprox(mm(0.5, 1.0, 2.0), 1e-9)) << image.spacing_m.transpose();
  const Eigen::Vector3d p = image.indexToPhysical(Eigen::Vector3d(5, 1, 2));
  EXPECT_LT((p - expected_m).norm(), tolerance_m)
      << "voxel (5,1,2) at " << (p * 1e3).transpose() << " mm, expected "
      << (expected_m * 1e3).transpose() << " mm";
  EXPECT_EQ(image.labelAt(expected_m), 5);
  EXPECT_EQ(image.at(5, 1, 2), 5);
  EXPECT_EQ(std::count(image.labels.begin(), image.labels.end(), 0), kVoxels - 1);
  EXPECT_NO_THROW(image.validate());
}

// ---------------------------------------------------------------------------------------------------
// (1) Orientation of hand-written files. The expected positions are worked out by hand from
// p = origin + Σ index_a · axis_a, with the axis vectors (spacing included) as written.

// Rotation of 90° about z in LPS: axis i → +y, axis j → −x, axis k → +z.
//   p(5,1,2) = (10, −20, 30) + 5·(0, 0.5, 0) + 1·(−1, 0, 0) + 2·(0, 0, 2) = (9, −17.5, 34) mm
const Eigen::Vector3d kRotatedVoxel = mm(9.0, -17.5, 34.0);
// Permutation with a flip (left-handed): axis i → +z, axis j → +x, axis k → −y.
//   p(5,1,2) = (10, −20, 30) + 5·(0, 0, 0.5) + 1·(1, 0, 0) + 2·(0, −2, 0) = (11, −24, 32.5) mm
const Eigen::Vector3d kFlippedVoxel = mm(11.0, -24.0, 32.5);

TEST(LabelImageReader, HandWrittenNrrdPutsTheVoxelWhereTheHeaderSays) {
  const std::string common = "dimension: 3\nsizes: 7 5 3\nkinds: domain domain domain\n";
  {
    SCOPED_TRACE("LPS, rotated, int16 big-endian raw");
    const std::string path = tempPath("hand_lps.nrrd");
    writeBytes(path, "NRRD0004\n# rotation of 90 degrees about z\ntype: short\n" + common +
                         "space: left-posterior-superior\n"
                         "space directions: (0,0.5,0) (-1,0,0) (0,0,2)\n"
                         "endian: big\nencoding: raw\nspace origin: (10,-20,30)\n\n" +
                         markedData<std::int16_t>(5, true));
    const LabelImage image = readLabelImage(path);
    expectMarkedImage(image, kRotatedVoxel);
    const Eigen::Matrix3d expected_direction =
        (Eigen::Matrix3d() << 0, -1, 0, 1, 0, 0, 0, 0, 1).finished();
    EXPECT_TRUE(image.direction.isApprox(expected_direction)) << image.direction;
    EXPECT_TRUE(image.origin_m.isApprox(mm(10, -20, 30)));
  }
  {
    SCOPED_TRACE("RAS, the same grid written in RAS coordinates, uint8 raw");
    // RAS = LPS with x and y negated: axes (0,−0.5,0) (1,0,0) (0,0,2), origin (−10, 20, 30).
    const std::string path = tempPath("hand_ras.nrrd");
    writeBytes(path, "NRRD0005\ntype: uint8\n" + common +
                         "space: right-anterior-superior\n"
                         "space directions: (0,-0.5,0) (1,0,0) (0,0,2)\n"
                         "encoding: raw\nspace origin: (-10,20,30)\n\n" +
                         markedData<std::uint8_t>(5, false));
    expectMarkedImage(readLabelImage(path), kRotatedVoxel);
  }
  {
    SCOPED_TRACE("detached header, left-handed permutation, uint16 little-endian, byte skip");
    const std::string path = tempPath("hand_detached.nhdr");
    writeBytes(tempPath("hand_detached_data.bin"), "JUNK" + markedData<std::uint16_t>(5, false));
    writeBytes(path, "NRRD0004\ntype: unsigned short\n" + common +
                         "space: LPS\nspace directions: (0,0,0.5) (1,0,0) (0,-2,0)\n"
                         "endian: little\nencoding: raw\nspace origin: (10,-20,30)\n"
                         "data file: hand_detached_data.bin\nbyte skip: 4\n");
    const LabelImage image = readLabelImage(path);
    expectMarkedImage(image, kFlippedVoxel);
    EXPECT_NEAR(image.direction.determinant(), -1.0, 1e-12);
  }
  {
    SCOPED_TRACE("ascii encoding with spacings and no space: identity grid at 0");
    // p(5,1,2) = (5·0.5, 1·1, 2·2) = (2.5, 1, 4) mm
    std::string values;
    for (long v = 0; v < kVoxels; ++v) values += (v == kMarked ? "5\n" : "0\n");
    const std::string path = tempPath("hand_ascii.nrrd");
    writeBytes(path, "NRRD0004\ntype: int\n" + common +
                         "spacings: 0.5 1 2\nencoding: ascii\n\n" + values);
    const LabelImage image = readLabelImage(path);
    expectMarkedImage(image, mm(2.5, 1.0, 4.0));
    EXPECT_TRUE(image.direction.isIdentity());
  }
  {
    SCOPED_TRACE("3D-right-handed (taken as it is), float little-endian, units in mm");
    const std::string path = tempPath("hand_float.nrrd");
    writeBytes(path, "NRRD0004\ntype: float\n" + common +
                         "space: 3D-right-handed\n"
                         "space directions: (0,0.5,0) (-1,0,0) (0,0,2)\n"
                         "space units: \"mm\" \"mm\" \"mm\"\n"
                         "endian: little\nencoding: raw\nspace origin: (10,-20,30)\n\n" +
                         markedData<float>(5.0f, false));
    expectMarkedImage(readLabelImage(path), kRotatedVoxel);
  }
}

TEST(LabelImageReader, HandWrittenMetaImagePutsTheVoxelWhereTheHeaderSays) {
  {
    SCOPED_TRACE(".mha, rotated, MET_USHORT big-endian");
    // TransformMatrix lists axis i's direction (0,1,0), then axis j's (−1,0,0), then axis k's.
    const std::string path = tempPath("hand_rotated.mha");
    writeBytes(path,
               "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = True\n"
               "CompressedData = False\nTransformMatrix = 0 1 0 -1 0 0 0 0 1\n"
               "Offset = 10 -20 30\nCenterOfRotation = 0 0 0\nAnatomicalOrientation = LPI\n"
               "ElementSpacing = 0.5 1 2\nDimSize = 7 5 3\nElementType = MET_USHORT\n"
               "ElementDataFile = LOCAL\n" +
                   markedData<std::uint16_t>(5, true));
    expectMarkedImage(readLabelImage(path), kRotatedVoxel);
  }
  {
    SCOPED_TRACE(".mhd with a separate raw file, left-handed permutation, MET_UCHAR, HeaderSize");
    const std::string path = tempPath("hand_flipped.mhd");
    writeBytes(tempPath("hand_flipped.raw"), "abc" + markedData<std::uint8_t>(5, false));
    writeBytes(path,
               "ObjectType = Image\r\nNDims = 3\r\nTransformMatrix = 0 0 1 1 0 0 0 -1 0\r\n"
               "Offset = 10 -20 30\r\nElementSpacing = 0.5 1 2\r\nDimSize = 7 5 3\r\n"
               "ElementType = MET_UCHAR\r\nHeaderSize = 3\r\nElementDataFile = hand_flipped.raw\r\n");
    expectMarkedImage(readLabelImage(path), kFlippedVoxel);
  }
  {
    SCOPED_TRACE(".mha without TransformMatrix (identity), MET_DOUBLE");
    // p(5,1,2) = (10 + 2.5, −20 + 1, 30 + 4) = (12.5, −19, 34) mm
    const std::string path = tempPath("hand_identity.mha");
    writeBytes(path,
               "NDims = 3\nDimSize = 7 5 3\nElementSpacing = 0.5 1 2\nPosition = 10 -20 30\n"
               "ElementType = MET_DOUBLE\nElementDataFile = LOCAL\n" +
                   markedData<double>(5.0, false));
    expectMarkedImage(readLabelImage(path), mm(12.5, -19.0, 34.0));
  }
}

/// The hand-made test image in memory, with one of the two directions above.
LabelImage markedImage(const Eigen::Matrix3d& direction) {
  LabelImage image(Eigen::Vector3i(7, 5, 3), mm(0.5, 1.0, 2.0), mm(10, -20, 30));
  image.direction = direction;
  image.at(5, 1, 2) = 5;
  return image;
}
const Eigen::Matrix3d kRotation = (Eigen::Matrix3d() << 0, -1, 0, 1, 0, 0, 0, 0, 1).finished();
const Eigen::Matrix3d kFlip = (Eigen::Matrix3d() << 0, 1, 0, 0, 0, -1, 1, 0, 0).finished();

TEST(LabelImageNifti, OurWriterKeepsTheVoxelInPlace) {
  for (const std::string ext : {".nii", ".nii.gz"}) {
    for (const bool flipped : {false, true}) {
      SCOPED_TRACE(ext + (flipped ? std::string(" left-handed") : std::string(" rotated")));
      const std::string path = tempPath(std::string("ours_") + (flipped ? "flip" : "rot") + ext);
      writeLabelImage(path, markedImage(flipped ? kFlip : kRotation));
      // NIfTI stores geometry as float32.
      expectMarkedImage(readLabelImage(path), flipped ? kFlippedVoxel : kRotatedVoxel, 1e-9);
    }
  }
}

TEST(LabelImageNifti, HandWrittenHeadersUseSformThenQformThenPixdim) {
  {
    SCOPED_TRACE("qform only, 90 degrees about z, qfac = -1");
    // RAS axes = R·diag(0.5, 1, −2) with R the 90° rotation about z: (0,0.5,0) (−1,0,0) (0,0,−2).
    //   p_RAS(5,1,2) = (−10, 20, 30) + (0, 2.5, 0) + (−1, 0, 0) + (0, 0, −4) = (−11, 22.5, 26)
    //   p_LPS = (11, −22.5, 26) mm
    NiftiFields f;
    f.pixdim[0] = -1;
    f.qform_code = 1;
    f.quatern[2] = static_cast<float>(std::sqrt(0.5));  // d = sin 45°, a = cos 45°
    f.qoffset[0] = -10;
    f.qoffset[1] = 20;
    f.qoffset[2] = 30;
    const std::string path = tempPath("hand_qform.nii");
    writeBytes(path, niftiHeader(f) + markedData<std::uint8_t>(5, false));
    const LabelImage image = readLabelImage(path);
    expectMarkedImage(image, mm(11.0, -22.5, 26.0), 1e-9);
    EXPECT_NEAR(image.direction.determinant(), -1.0, 1e-9);
  }
  {
    SCOPED_TRACE("sform (code 2) wins over a different qform; int16 with scl_slope 2.5");
    // sform RAS: axes (−0.5,0,0) (0,−1,0) (0,0,2), origin (5, 6, 7):
    //   p_RAS(5,1,2) = (5 − 2.5, 6 − 1, 7 + 4) = (2.5, 5, 11); p_LPS = (−2.5, −5, 11) mm
    // The stored value 2 becomes 2 · 2.5 + 0 = 5.
    NiftiFields f;
    f.datatype = 4;  // DT_INT16
    f.bitpix = 16;
    f.scl_slope = 2.5f;
    f.qform_code = 1;  // identity rotation at (0,0,0): must be ignored
    f.sform_code = 2;
    const float srow[3][4] = {{-0.5f, 0, 0, 5}, {0, -1, 0, 6}, {0, 0, 2, 7}};
    std::memcpy(f.srow, srow, sizeof srow);
    const std::string path = tempPath("hand_sform.nii");
    writeBytes(path, niftiHeader(f) + markedData<std::int16_t>(2, false));
    const LabelImage image = readLabelImage(path);
    expectMarkedImage(image, mm(-2.5, -5.0, 11.0));
    EXPECT_TRUE(image.direction.isIdentity(1e-12)) << image.direction;
  }
  {
    SCOPED_TRACE("no qform, no sform: pixdim only, taken as it is; float32");
    // p(5,1,2) = (2.5, 1, 4) mm
    NiftiFields f;
    f.datatype = 16;  // DT_FLOAT32
    f.bitpix = 32;
    const std::string path = tempPath("hand_pixdim.nii");
    writeBytes(path, niftiHeader(f) + markedData<float>(5.0f, false));
    expectMarkedImage(readLabelImage(path), mm(2.5, 1.0, 4.0));
  }
  {
    SCOPED_TRACE("big-endian header and data, identity qform");
    // p_RAS = (−10, 20, 30) + (2.5, 1, 4) = (−7.5, 21, 34); p_LPS = (7.5, −21, 34) mm
    NiftiFields f;
    f.big_endian = true;
    f.datatype = 512;  // DT_UINT16
    f.bitpix = 16;
    f.qform_code = 1;
    f.qoffset[0] = -10;
    f.qoffset[1] = 20;
    f.qoffset[2] = 30;
    const std::string path = tempPath("hand_big_endian.nii");
    writeBytes(path, niftiHeader(f) + markedData<std::uint16_t>(5, true));
    expectMarkedImage(readLabelImage(path), mm(7.5, -21.0, 34.0));
  }
}

TEST(LabelImageNifti, OurQformAgreesWithOurSform) {
  // Zeroing sform_code makes the reader fall back to the qform, which must give the same grid
  // (the left-handed case needs qfac = −1).
  const Eigen::Matrix3d oblique =
      Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, -2, 3).normalized()).toRotationMatrix();
  const std::vector<std::pair<std::string, Eigen::Matrix3d>> cases = {
      {"rotated", kRotation}, {"left-handed", kFlip}, {"oblique", oblique},
      {"oblique left-handed", oblique * Eigen::Vector3d(1, 1, -1).asDiagonal()}};
  for (const auto& [name, direction] : cases) {
    SCOPED_TRACE(name);
    const LabelImage written = markedImage(direction);
    const std::string path = tempPath("qform_check.nii");
    writeLabelImage(path, written);
    std::string bytes = readBytes(path);
    ASSERT_GE(bytes.size(), 352u);
    bytes[254] = 0;  // sform_code (little-endian int16)
    bytes[255] = 0;
    writeBytes(path, bytes);
    const LabelImage read = readLabelImage(path);
    EXPECT_TRUE(read.direction.isApprox(written.direction, 1e-6)) << read.direction;
    EXPECT_TRUE(read.origin_m.isApprox(written.origin_m, 1e-7));
    EXPECT_TRUE(read.spacing_m.isApprox(written.spacing_m, 1e-7));
  }
}

// ---------------------------------------------------------------------------------------------------
// (2) Round trips through our writers

TEST(LabelImageWriter, EveryFormatRoundTrips) {
  LabelImage wide(Eigen::Vector3i(9, 7, 5), mm(0.7, 0.8, 1.3), mm(-12.5, 40.25, 3.0));
  wide.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  for (int k = 0; k < 5; ++k) {
    for (int j = 0; j < 7; ++j) {
      for (int i = 0; i < 9; ++i) wide.at(i, j, k) = static_cast<std::uint16_t>((i * 3001 + j * 7 + k) % 65536);
    }
  }
  LabelImage narrow = markedImage(kFlip);  // labels ≤ 255: written as uint8
  narrow.at(0, 0, 0) = 255;

  for (const std::string ext : {".nrrd", ".nhdr", ".mha", ".mhd", ".nii", ".nii.gz"}) {
    for (const auto* image : {&wide, &narrow}) {
      const bool is_wide = image == &wide;
      SCOPED_TRACE(ext + (is_wide ? std::string(" uint16 oblique") : std::string(" uint8 flipped")));
      const std::string path = tempPath(std::string("round_trip_") + (is_wide ? "wide" : "narrow") + ext);
      writeLabelImage(path, *image);
      const LabelImage back = readLabelImage(path);
      const bool nifti = ext.rfind(".nii", 0) == 0;
      const double position_tolerance = nifti ? 1e-8 : 1e-12;  // NIfTI geometry is float32
      EXPECT_EQ(back.size, image->size);
      EXPECT_TRUE(back.labels == image->labels);
      EXPECT_LT((back.spacing_m - image->spacing_m).cwiseAbs().maxCoeff(), position_tolerance);
      EXPECT_LT((back.origin_m - image->origin_m).cwiseAbs().maxCoeff(), position_tolerance);
      EXPECT_LT((back.direction - image->direction).cwiseAbs().maxCoeff(), nifti ? 1e-6 : 1e-12)
          << back.direction;
    }
  }
}

TEST(LabelImageWriter, NrrdIsGzipInLps) {
  const std::string path = tempPath("header_check.nrrd");
  writeLabelImage(path, markedImage(kRotation));
  const std::string bytes = readBytes(path);
  EXPECT_NE(bytes.find("space: left-posterior-superior\n"), std::string::npos);
  EXPECT_NE(bytes.find("encoding: gzip\n"), std::string::npos);
  EXPECT_NE(bytes.find("space directions: (0,0.5,0) (-1,0,0) (0,0,2)\n"), std::string::npos) << bytes.substr(0, 400);
  EXPECT_NE(bytes.find("space origin: (10,-20,30)\n"), std::string::npos);
}

TEST(LabelImageWriter, NiftiRefusesSizesAbove32767InsteadOfTruncatingThem) {
  // dim[] is int16: 40000 used to be written as 40000 − 65536 = −25536.
  const LabelImage wide(Eigen::Vector3i(40000, 2, 1), mm(1, 1, 1), mm(0, 0, 0), 3);
  for (const std::string ext : {".nii", ".nii.gz"}) {
    SCOPED_TRACE(ext);
    const std::string path = tempPath("too_wide" + ext);
    std::filesystem::remove(path);
    const std::string message = errorOf([&] { writeLabelImage(path, wide); });
    EXPECT_EQ(message.rfind(path + ": ", 0), 0u) << message;
    EXPECT_NE(message.find("size 40000×2×1: axis i has 40000 voxels"), std::string::npos) << message;
    EXPECT_NE(message.find("at most 32767"), std::string::npos) << message;
    EXPECT_NE(message.find("write .nrrd or .mha instead"), std::string::npos) << message;
    EXPECT_FALSE(std::filesystem::exists(path)) << "nothing is written";
  }
  // NRRD, as the message suggests, holds it.
  const std::string nrrd = tempPath("too_wide.nrrd");
  writeLabelImage(nrrd, wide);
  const LabelImage back = readLabelImage(nrrd);
  EXPECT_EQ(back.size, wide.size);
  EXPECT_TRUE(back.labels == wide.labels);
}

TEST(LabelImageWriter, RejectsInvalidImagesAndUnknownExtensions) {
  LabelImage bad(Eigen::Vector3i(2, 2, 2), mm(1, 1, 1), mm(0, 0, 0));
  bad.labels.pop_back();
  EXPECT_THROW(writeLabelImage(tempPath("bad.nrrd"), bad), std::invalid_argument);
  const std::string message =
      errorOf([] { writeLabelImage(tempPath("image.png"), markedImage(kRotation)); });
  EXPECT_NE(message.find("unknown extension"), std::string::npos) << message;
}

// ---------------------------------------------------------------------------------------------------
// (3) The VICTRE phantom (test/data/README.md)

TEST(LabelImageReader, ReadsTheVictrePhantom) {
  const LabelImage image = readLabelImage(BREAST_SIM_TEST_DATA_DIR "/victre_labels_1mm.nrrd");
  EXPECT_EQ(image.size, Eigen::Vector3i(96, 111, 108));
  EXPECT_TRUE(image.spacing_m.isApprox(mm(1, 1, 1), 1e-12));
  EXPECT_LT((image.origin_m - mm(-9, -66.1689, -54.3962)).norm(), 1e-12);
  EXPECT_TRUE(image.direction.isIdentity());
  std::map<std::uint16_t, long> counts;
  for (std::uint16_t l : image.labels) ++counts[l];
  for (std::uint16_t l : {0, 1, 2, 29, 40}) {
    SCOPED_TRACE("label " + std::to_string(l));
    EXPECT_GT(counts[l], 0);
  }
  for (const auto& [label, count] : counts) {
    EXPECT_TRUE((std::set<int>{0, 1, 2, 29, 33, 40, 88, 95, 125, 150, 225}.count(label)))
        << "unexpected label " << label << " (" << count << " voxels)";
  }
  // The nipple centroid from the README lies in tissue, and the nipple label is near it.
  const Eigen::Vector3d nipple = mm(82.2, 0.1, -25.3);
  EXPECT_NE(image.labelAt(nipple), 0);
  EXPECT_EQ(image.labelAt(mm(86.0, 40.0, 50.0)), 0) << "a far grid corner is air";
  EXPECT_EQ(image.labelAt(mm(200, 0, 0), 7), 7) << "outside the grid";
}

TEST(LabelImageReader, ReadsTheHalfMillimetrePhantomQuicklyWithTheDocumentedHistogram) {
  // shared/ lies beside the repository (in CI's clone too) and at /work/shared on a workstation.
  std::string path;
  for (const std::string& candidate :
       {std::string(BREAST_SIM_TEST_DATA_DIR "/../../../shared/data/victre-phantom/"),
        std::string("/work/shared/data/victre-phantom/")}) {
    if (std::filesystem::exists(candidate + "breast_labels_0p5mm.nrrd")) {
      path = candidate + "breast_labels_0p5mm.nrrd";
      break;
    }
  }
  if (path.empty()) GTEST_SKIP() << "breast_labels_0p5mm.nrrd (shared/data/victre-phantom) is absent";
  const auto start = std::chrono::steady_clock::now();
  const LabelImage image = readLabelImage(path);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("read %s (%ld voxels) in %.3f s\n", path.c_str(), image.numVoxels(), seconds);
#ifdef NDEBUG
  EXPECT_LT(seconds, 1.0);
#endif
  EXPECT_EQ(image.size, Eigen::Vector3i(192, 223, 217));
  EXPECT_TRUE(image.spacing_m.isApprox(mm(0.5, 0.5, 0.5), 1e-12));
  std::map<std::uint16_t, long> counts;
  for (std::uint16_t l : image.labels) ++counts[l];
  // labels_histogram.txt beside the file
  const std::map<std::uint16_t, long> expected = {
      {0, 5254197}, {1, 2838912}, {2, 117446}, {29, 509620}, {33, 1257}, {40, 487041},
      {88, 65070},  {95, 1052},   {125, 3508}, {150, 5569},  {225, 7400}};
  EXPECT_EQ(counts, expected);
}

// ---------------------------------------------------------------------------------------------------
// (4) The index ↔ physical mapping

TEST(LabelImage, PhysicalToIndexInvertsIndexToPhysical) {
  const std::vector<std::pair<std::string, Eigen::Matrix3d>> directions = {
      {"identity", Eigen::Matrix3d::Identity()},
      {"rotated", kRotation},
      {"left-handed", kFlip},
      {"oblique", Eigen::AngleAxisd(1.1, Eigen::Vector3d(3, -1, 2).normalized()).toRotationMatrix()}};
  for (const auto& [name, direction] : directions) {
    SCOPED_TRACE(name);
    LabelImage image(Eigen::Vector3i(7, 5, 3), mm(0.5, 1.0, 2.0), mm(10, -20, 30));
    image.direction = direction;
    for (const Eigen::Vector3d& ijk :
         {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(5, 1, 2), Eigen::Vector3d(-1.25, 3.5, 7.75),
          Eigen::Vector3d(6.49, 4.2, 0.01)}) {
      EXPECT_LT((image.physicalToIndex(image.indexToPhysical(ijk)) - ijk).norm(), 1e-9);
    }
    const Eigen::Vector3d p = mm(3.0, -7.0, 11.0);
    EXPECT_LT((image.indexToPhysical(image.physicalToIndex(p)) - p).norm(), 1e-15);
  }
}

TEST(LabelImage, LabelAtTakesTheNearestVoxelCentreAndOutsideBeyond) {
  LabelImage image = markedImage(kRotation);
  const Eigen::Vector3d centre = image.indexToPhysical(Eigen::Vector3d(5, 1, 2));
  EXPECT_EQ(image.labelAt(image.indexToPhysical(Eigen::Vector3d(5.45, 0.6, 2.4))), 5);
  EXPECT_EQ(image.labelAt(image.indexToPhysical(Eigen::Vector3d(5.55, 1, 2))), 0);
  EXPECT_EQ(image.labelAt(image.indexToPhysical(Eigen::Vector3d(-0.4, 0, 0)), 9), 0);
  EXPECT_EQ(image.labelAt(image.indexToPhysical(Eigen::Vector3d(-0.6, 0, 0)), 9), 9);
  EXPECT_EQ(image.labelAt(image.indexToPhysical(Eigen::Vector3d(6.6, 0, 0)), 9), 9);
  EXPECT_EQ(image.labelAt(centre + Eigen::Vector3d(1e9, 0, 0), 9), 9);
  EXPECT_EQ(image.labelAt(Eigen::Vector3d(NAN, 0, 0), 9), 9);
}

TEST(LabelImage, ValidateRejectsInconsistentImages) {
  const LabelImage good = markedImage(kRotation);
  EXPECT_NO_THROW(good.validate());
  struct Case {
    std::string name;
    std::function<void(LabelImage&)> spoil;
  };
  const std::vector<Case> cases = {
      {"too few labels", [](LabelImage& im) { im.labels.pop_back(); }},
      {"zero size", [](LabelImage& im) { im.size.x() = 0; }},
      {"zero spacing", [](LabelImage& im) { im.spacing_m.y() = 0; }},
      {"NaN origin", [](LabelImage& im) { im.origin_m.z() = NAN; }},
      {"sheared direction", [](LabelImage& im) { im.direction(0, 1) = 0.1; }},
      {"scaled direction", [](LabelImage& im) { im.direction *= 2; }},
      // numVoxels() wraps to 0 here, which matched the empty label vector.
      {"sizes whose product wraps to 0",
       [](LabelImage& im) {
         im.size = Eigen::Vector3i(4194304, 2097152, 2097152);
         im.labels.clear();
       }},
      {"2^30 2^30 16",
       [](LabelImage& im) {
         im.size = Eigen::Vector3i(1 << 30, 1 << 30, 16);
         im.labels.clear();
       }},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    LabelImage image = good;
    c.spoil(image);
    EXPECT_THROW(image.validate(), std::invalid_argument);
  }
  EXPECT_THROW(LabelImage(Eigen::Vector3i(-1, 2, 2), mm(1, 1, 1), mm(0, 0, 0)), std::invalid_argument);
  EXPECT_THROW(LabelImage(Eigen::Vector3i(4194304, 2097152, 2097152), mm(1, 1, 1), mm(0, 0, 0)),
               std::invalid_argument);
}

TEST(LabelImage, ValidateCountsVoxelsWithoutOverflowUpTo2Pow31) {
  const auto messageOf = [](const LabelImage& image) -> std::string {
    try {
      image.validate();
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  LabelImage image = markedImage(kRotation);
  image.labels.clear();
  image.size = Eigen::Vector3i(2048, 1024, 1024);  // exactly 2^31: allowed, so the labels are short
  EXPECT_EQ(messageOf(image), "LabelImage: 0 labels for 2048×1024×1024 = 2147483648 voxels; "
                              "expected one label per voxel");
  image.size = Eigen::Vector3i(2048, 1024, 1025);
  EXPECT_EQ(messageOf(image), "LabelImage: size 2048×1024×1025 = 2149580800 voxels, more than the "
                              "2147483648 (2^31) a label image may hold");
  image.size = Eigen::Vector3i(4194304, 2097152, 2097152);
  EXPECT_EQ(messageOf(image), "LabelImage: size 4194304×2097152×2097152 ≈ 1.84e+19 voxels, more "
                              "than the 2147483648 (2^31) a label image may hold");
}

}  // namespace
