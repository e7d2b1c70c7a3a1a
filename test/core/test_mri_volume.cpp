// MRI volumes through ITK (mri/mri_volume.h): geometry and voxels kept by every format, DICOM and NIfTI
// of one volume segmented alike in mm, and each bad input's message.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "breast_sim/core/mri/mri_segmentation.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "mri_test_images.h"
#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::messageOf;
using breast_sim::test::TempDir;

namespace {

// A small volume on an oblique, anisotropic grid whose voxel values are integers (so DICOM's int16 keeps them).
ScalarImage obliqueVolume() {
  ScalarImage image;
  ImageGeometry& g = image.geometry;
  g.size = Eigen::Vector3i(9, 7, 6);
  g.spacing_m = Eigen::Vector3d(0.8e-3, 1.1e-3, 1.5e-3);
  g.origin_m = Eigen::Vector3d(-12.5e-3, 30.25e-3, 7.75e-3);
  const double a = 30.0 * M_PI / 180.0;
  g.direction << std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1;
  image.values.resize(static_cast<std::size_t>(g.numVoxels()));
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) image.values[g.index(i, j, k)] = static_cast<float>(100 * k + 10 * j + i);
  return image;
}

void expectSameGeometry(const ImageGeometry& a, const ImageGeometry& b, double tolerance_m, const std::string& what) {
  SCOPED_TRACE(what);
  EXPECT_EQ(a.size, b.size);
  EXPECT_LT((a.spacing_m - b.spacing_m).cwiseAbs().maxCoeff(), tolerance_m);
  EXPECT_LT((a.origin_m - b.origin_m).cwiseAbs().maxCoeff(), tolerance_m);
  EXPECT_LT((a.direction - b.direction).cwiseAbs().maxCoeff(), 1e-5);
}

// The same physical image on another grid: axes (i', j', k') = (k, nx − 1 − i, j), i.e. i' superior,
// j' towards the patient's right, k' posterior: a left-handed grid, so a DICOM reader must reverse the
// slice order to sort along the normal.
ScalarImage permuted(const ScalarImage& in) {
  const ImageGeometry& g = in.geometry;
  ScalarImage out;
  ImageGeometry& h = out.geometry;
  h.size = Eigen::Vector3i(g.size.z(), g.size.x(), g.size.y());
  h.spacing_m = Eigen::Vector3d(g.spacing_m.z(), g.spacing_m.x(), g.spacing_m.y());
  h.direction.col(0) = g.direction.col(2);
  h.direction.col(1) = -g.direction.col(0);
  h.direction.col(2) = g.direction.col(1);
  h.origin_m = g.indexToPhysical(Eigen::Vector3d(g.size.x() - 1, 0, 0));
  out.values.resize(in.values.size());
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) out.values[h.index(k, g.size.x() - 1 - i, j)] = in.values[g.index(i, j, k)];
  return out;
}

void writeText(const std::string& path, const std::string& text) { std::ofstream(path, std::ios::binary) << text; }

}  // namespace

TEST(MriVolume, EveryFileFormatKeepsGeometryAndVoxels) {
  const ScalarImage image = obliqueVolume();
  TempDir dir("breast_sim_mri_volume");
  for (const char* name : {"v.nii", "v.nii.gz", "v.nrrd", "v.mha"}) {
    SCOPED_TRACE(name);
    writeMriVolume(dir.path(name), image);
    const MriVolume back = readMriVolume(dir.path(name));
    // NIfTI keeps its geometry as float: about 1e-7 relative.
    expectSameGeometry(back.image.geometry, image.geometry, 1e-8, name);
    EXPECT_EQ(back.image.values, image.values);
  }
  EXPECT_EQ(readMriVolume(dir.path("v.nii.gz")).info.format, "NIfTI");
  EXPECT_EQ(readMriVolume(dir.path("v.nrrd")).info.format, "NRRD");
  EXPECT_EQ(readMriVolume(dir.path("v.mha")).info.format, "MetaImage");
}

TEST(MriVolume, DicomSeriesKeepsGeometryAndVoxels) {
  const ScalarImage image = obliqueVolume();
  TempDir dir("breast_sim_mri_dicom");
  DicomSeriesOptions o;
  o.uid_seed = 7;
  writeDicomSeries(dir.path("series"), image, o);
  ASSERT_EQ(std::distance(std::filesystem::directory_iterator(dir.path("series")), std::filesystem::directory_iterator()),
            image.geometry.size.z());
  const MriVolume back = readMriVolume(dir.path("series"));
  EXPECT_EQ(back.info.format, "DICOM");
  EXPECT_EQ(back.info.files, image.geometry.size.z());
  EXPECT_EQ(back.info.series_description, o.series_description);
  // Positions are written with 6 significant digits.
  expectSameGeometry(back.image.geometry, image.geometry, 1e-7, "folder");
  EXPECT_EQ(back.image.values, image.values);
  // One file of the series names the series.
  const MriVolume from_file = readMriVolume(dir.path("series/IM00003.dcm"));
  EXPECT_EQ(from_file.image.values, image.values);
  EXPECT_EQ(from_file.info.series_uid, back.info.series_uid);
}

TEST(MriVolume, DicomAndNiftiOfTheSameVolumeGiveTheSameLabelsInMm) {
  // A synthetic T1 image, rounded (DICOM stores int16), as NIfTI and as a DICOM series on its own grid,
  // and as a DICOM series on a permuted, left-handed grid of the same voxels.
  breast_sim::core::SyntheticMri mri = renderSyntheticT1(breast_sim::test::victreLps(), TissueLabels{},
                                                         breast_sim::test::smallImageParams(3));
  for (float& v : mri.image.values) v = std::round(v);
  TempDir dir("breast_sim_mri_orientation");
  writeMriVolume(dir.path("t1.nii.gz"), mri.image);
  writeDicomSeries(dir.path("dicom"), mri.image);
  writeDicomSeries(dir.path("dicom_permuted"), permuted(mri.image));
  const MriVolume nifti = readMriVolume(dir.path("t1.nii.gz"));
  const MriVolume dicom = readMriVolume(dir.path("dicom"));
  const MriVolume turned = readMriVolume(dir.path("dicom_permuted"));
  const MriSegmentation a = segmentProneMri(nifti.image);
  const MriSegmentation b = segmentProneMri(dicom.image);
  const MriSegmentation c = segmentProneMri(turned.image);
  // NIfTI (RAS on disk) and DICOM (LPS) of one grid: the same grid, voxels and labels.
  expectSameGeometry(dicom.image.geometry, nifti.image.geometry, 1e-7, "DICOM against NIfTI");
  EXPECT_EQ(dicom.image.values, nifti.image.values);
  EXPECT_EQ(b.labels.labels, a.labels.labels);
  // The permuted series: every voxel centre of one grid is one of the other's, with the same value.
  const ImageGeometry& g = nifti.image.geometry;
  long same = 0, voxels = 0, outline_differs = 0;
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) {
        const Eigen::Vector3d p = g.indexToPhysical(Eigen::Vector3d(i, j, k));
        const Eigen::Vector3d q = turned.image.geometry.physicalToIndex(p);
        ASSERT_LT((q - q.array().round().matrix()).cwiseAbs().maxCoeff(), 1e-3) << "voxel " << i << " " << j << " " << k;
        const Eigen::Vector3i qi = q.array().round().cast<int>();
        ASSERT_EQ(turned.image.values[turned.image.geometry.index(qi.x(), qi.y(), qi.z())], nifti.image.values[g.index(i, j, k)]);
        const std::uint16_t la = a.labels.labels[g.index(i, j, k)], lc = c.labels.at(qi.x(), qi.y(), qi.z());
        ++voxels;
        same += la == lc;
        outline_differs += (la == 0) != (lc == 0);
      }
  // Its segmentation sees the same voxels, but N4 shrinks the permuted grid into other blocks, so the
  // bias estimate, and with it a few voxels at class borders, differ.
  EXPECT_GT(static_cast<double>(same) / voxels, 0.997);
  EXPECT_LT(static_cast<double>(outline_differs) / voxels, 5e-4);
}

TEST(MriVolume, BadInputsAreClearErrors) {
  TempDir dir("breast_sim_mri_bad");
  // A path that does not exist.
  EXPECT_NE(messageOf([&] { readMriVolume(dir.path("missing.nii")); }).find("no such file or folder"), std::string::npos);
  // A text file named like an image.
  writeText(dir.path("notes.nii"), "patient notes, not an image\n");
  std::string m = messageOf([&] { readMriVolume(dir.path("notes.nii")); });
  EXPECT_NE(m.find(dir.path("notes.nii")), std::string::npos) << m;
  EXPECT_NE(m.find("not an image of a supported format"), std::string::npos) << m;
  // A 2-D image, and a volume of one slice.
  writeText(dir.path("slice.mha"), "ObjectType = Image\nNDims = 2\nDimSize = 8 8\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
                                       std::string(64, '\1'));
  m = messageOf([&] { readMriVolume(dir.path("slice.mha")); });
  EXPECT_NE(m.find("a 2-D image (8 x 8 voxels)"), std::string::npos) << m;
  writeText(dir.path("one.mha"), "ObjectType = Image\nNDims = 3\nDimSize = 8 8 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
                                     std::string(64, '\1'));
  m = messageOf([&] { readMriVolume(dir.path("one.mha")); });
  EXPECT_NE(m.find("a 2-D image (8 x 8 x 1 voxels)"), std::string::npos) << m;
  // RGB voxels.
  writeText(dir.path("rgb.mha"), "ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementNumberOfChannels = 3\n"
                                 "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + std::string(192, '\1'));
  m = messageOf([&] { readMriVolume(dir.path("rgb.mha")); });
  EXPECT_NE(m.find("3 components"), std::string::npos) << m;
  EXPECT_NE(m.find("scalar (magnitude) image"), std::string::npos) << m;
  // A header that claims 10^15 voxels: refused before anything is allocated.
  writeText(dir.path("huge.mha"), "ObjectType = Image\nNDims = 3\nDimSize = 100000 100000 100000\nElementType = MET_FLOAT\n"
                                  "ElementDataFile = LOCAL\n" + std::string(16, '\0'));
  m = messageOf([&] { readMriVolume(dir.path("huge.mha")); });
  EXPECT_NE(m.find("100000 x 100000 x 100000 voxels, more than the"), std::string::npos) << m;
  // A voxel that is not a number.
  ScalarImage nan_image = obliqueVolume();
  nan_image.values[nan_image.geometry.index(2, 3, 4)] = std::numeric_limits<float>::quiet_NaN();
  writeMriVolume(dir.path("nan.nrrd"), nan_image);
  m = messageOf([&] { readMriVolume(dir.path("nan.nrrd")); });
  EXPECT_NE(m.find("voxel (2, 3, 4) is not a finite number"), std::string::npos) << m;
  // An unknown extension to write.
  m = messageOf([&] { writeMriVolume(dir.path("v.png"), obliqueVolume()); });
  EXPECT_NE(m.find("unknown extension"), std::string::npos) << m;
}

// NRRD and MetaImage are read by the core's parsers (image/scalar_image_io.h): every value type as
// float, the byte order, ASCII data, detached data and a RAS space as readLabelImage takes them.
TEST(MriVolume, NrrdAndMetaImageOfEveryValueTypeReadAsFloat) {
  TempDir dir("breast_sim_mri_types");
  const auto big16 = [](std::int16_t v) { return std::string{static_cast<char>((v >> 8) & 0xFF), static_cast<char>(v & 0xFF)}; };
  std::string shorts;
  for (int v = 0; v < 8; ++v) shorts += big16(static_cast<std::int16_t>(-300 + 100 * v));
  writeText(dir.path("short.nrrd"), "NRRD0004\ntype: short\ndimension: 3\nsizes: 2 2 2\nendian: big\nencoding: raw\n"
                                    "space: right-anterior-superior\nspace directions: (-1,0,0) (0,-2,0) (0,0,3)\n"
                                    "space origin: (10,20,30)\n\n" + shorts);
  MriVolume v = readMriVolume(dir.path("short.nrrd"));
  EXPECT_EQ(v.info.format, "NRRD");
  EXPECT_EQ(v.info.pixel_type, "short");
  EXPECT_EQ(v.image.values, (std::vector<float>{-300, -200, -100, 0, 100, 200, 300, 400}));
  EXPECT_LT((v.image.geometry.spacing_m - Eigen::Vector3d(1e-3, 2e-3, 3e-3)).norm(), 1e-12);
  EXPECT_LT((v.image.geometry.origin_m - Eigen::Vector3d(-10e-3, -20e-3, 30e-3)).norm(), 1e-12);  // RAS to LPS
  EXPECT_LT((v.image.geometry.direction - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  writeText(dir.path("text.nrrd"), "NRRD0004\ntype: double\ndimension: 3\nsizes: 2 1 2\nencoding: ascii\n\n0.5 -1e10\n2.25, 7\n");
  v = readMriVolume(dir.path("text.nrrd"));
  EXPECT_EQ(v.info.pixel_type, "double");
  EXPECT_EQ(v.image.values, (std::vector<float>{0.5f, -1e10f, 2.25f, 7.0f}));
  std::string longs;
  for (int k = 0; k < 4; ++k) longs += std::string(7, '\0') + static_cast<char>(k + 1);  // uint64, most significant byte first
  writeText(dir.path("u64.mha"), "ObjectType = Image\nNDims = 3\nDimSize = 1 2 2\nElementType = MET_ULONG_LONG\n"
                                 "BinaryDataByteOrderMSB = True\nElementSpacing = 0.5 0.5 0.5\nElementDataFile = LOCAL\n" + longs);
  v = readMriVolume(dir.path("u64.mha"));
  EXPECT_EQ(v.info.format, "MetaImage");
  EXPECT_EQ(v.info.pixel_type, "unsigned_long_long");
  EXPECT_EQ(v.image.values, (std::vector<float>{1, 2, 3, 4}));
  const float floats[4] = {-1.5f, 0.0f, 3.75f, 1e30f};
  writeText(dir.path("f.raw"), std::string(reinterpret_cast<const char*>(floats), sizeof floats));
  writeText(dir.path("f.mhd"), "ObjectType = Image\nNDims = 3\nDimSize = 2 2 1\nElementType = MET_FLOAT\nElementDataFile = f.raw\n");
  // A volume of one slice is not an MRI; the same data as 1 x 2 x 2 is.
  EXPECT_NE(messageOf([&] { readMriVolume(dir.path("f.mhd")); }).find("a 2-D image (2 x 2 x 1 voxels)"), std::string::npos);
  writeText(dir.path("f.mhd"), "ObjectType = Image\nNDims = 3\nDimSize = 1 2 2\nElementType = MET_FLOAT\nElementDataFile = f.raw\n");
  EXPECT_EQ(readMriVolume(dir.path("f.mhd")).image.values, std::vector<float>(floats, floats + 4));
}

// The inputs on which ITK's NRRD and MetaImage readers leaked (fuzz_mri_nrrd, fuzz_mri_metaimage): gzip
// or zlib data that fail while they are read, and malformed headers. Each is a clear error naming the
// file; the core's readers free what they allocated (the fuzz targets check it under ASan).
TEST(MriVolume, NrrdAndMetaImageWhoseDataFailAreClearErrors) {
  TempDir dir("breast_sim_mri_bad_data");
  ScalarImage image = obliqueVolume();
  writeMriVolume(dir.path("good.nrrd"), image);
  writeMriVolume(dir.path("good.mha"), image);
  std::string nrrd, mha;
  {
    std::ifstream a(dir.path("good.nrrd"), std::ios::binary), b(dir.path("good.mha"), std::ios::binary);
    nrrd.assign(std::istreambuf_iterator<char>(a), std::istreambuf_iterator<char>());
    mha.assign(std::istreambuf_iterator<char>(b), std::istreambuf_iterator<char>());
  }
  const std::size_t nrrd_data = nrrd.find("\n\n") + 2, mha_data = mha.find("ElementDataFile = LOCAL\n") + 24;
  ASSERT_LT(nrrd_data, nrrd.size());
  ASSERT_LT(mha_data, mha.size());
  struct Case {
    const char* name;
    std::string bytes;
    std::vector<std::string> says;
  };
  std::string corrupt_nrrd = nrrd, corrupt_mha = mha;
  for (std::size_t i = nrrd_data + 20; i < nrrd.size(); i += 7) corrupt_nrrd[i] = static_cast<char>(corrupt_nrrd[i] ^ 0x5A);
  for (std::size_t i = mha_data + 10; i < mha.size(); i += 7) corrupt_mha[i] = static_cast<char>(corrupt_mha[i] ^ 0x5A);
  const std::string values = std::to_string(9 * 7 * 6 * 4);
  const std::vector<Case> cases = {
      {"truncated.nrrd", nrrd.substr(0, nrrd_data + (nrrd.size() - nrrd_data) / 2),
       {"voxel data is truncated: expected " + values + " bytes after decompression"}},
      {"corrupt.nrrd", corrupt_nrrd, {"compressed data is corrupt (zlib:"}},
      {"truncated.mha", mha.substr(0, mha_data + (mha.size() - mha_data) / 2), {"compressed voxel data is truncated"}},
      {"corrupt.mha", corrupt_mha, {"compressed data is corrupt (zlib:"}},
      {"comma.mha", mha.substr(0, mha_data - 7) + ",LOCAL\n" + mha.substr(mha_data), {"data file:", ",LOCAL"}},
      {"rgb.nrrd", "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 3 4 4\nkinds: RGB-color domain domain\nencoding: raw\n\n" +
                       std::string(48, '\1'), {"voxels of 3 components", "scalar (magnitude) image"}},
      {"time.nrrd", "NRRD0004\ntype: uint8\ndimension: 4\nsizes: 2 2 2 3\nencoding: raw\n\n" + std::string(24, '\1'),
       {"a 4-D image (2 x 2 x 2 x 3 voxels: several volumes"}},
      {"flat.nrrd", "NRRD0004\ntype: uint8\ndimension: 2\nsizes: 8 8\nencoding: raw\n\n" + std::string(64, '\1'),
       {"a 2-D image (8 x 8 voxels)"}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    writeText(dir.path(c.name), c.bytes);
    const std::string m = messageOf([&] { readMriVolume(dir.path(c.name)); });
    EXPECT_EQ(m.rfind(dir.path(c.name) + ": ", 0), 0u) << m;
    for (const std::string& part : c.says) EXPECT_NE(m.find(part), std::string::npos) << "missing '" << part << "' in: " << m;
  }
}

// ITK's NIfTI reader aborts the process (vnl's SVD) on an orientation that is not finite
// (fuzz_mri_nifti): the header's numbers are checked first, and such a file is an error naming the field.
TEST(MriVolume, ANiftiHeaderWithoutFiniteOrientationIsAnErrorNotAnAbort) {
  TempDir dir("breast_sim_mri_bad");
  writeMriVolume(dir.path("good.nii"), obliqueVolume());
  std::string header;
  {
    std::ifstream in(dir.path("good.nii"), std::ios::binary);
    header.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  ASSERT_GT(header.size(), 348u);
  const auto patched = [&](const std::string& name, int offset, float value, int code_offset) {
    std::string bytes = header;
    std::memcpy(&bytes[offset], &value, 4);
    const std::int16_t code = 1;
    std::memcpy(&bytes[code_offset], &code, 2);
    std::ofstream(dir.path(name), std::ios::binary) << bytes;
    return dir.path(name);
  };
  const std::string nan_srow = patched("nan_srow.nii", 296, std::numeric_limits<float>::quiet_NaN(), 254);
  std::string m = messageOf([&] { readMriVolume(nan_srow); });
  EXPECT_EQ(m.rfind(nan_srow + ": the NIfTI header's srow_y (entry 0) is nan: not a finite number", 0), 0u) << m;
  const std::string huge_offset = patched("huge_qoffset.nii", 272, 7e22f, 252);
  m = messageOf([&] { readMriVolume(huge_offset); });
  EXPECT_NE(m.find(huge_offset + ": the NIfTI header's qoffset_x, y, z (entry 1) is 7e+22"), std::string::npos) << m;
  EXPECT_NE(m.find("the header is damaged, export the image again"), std::string::npos) << m;
  // A damaged sizeof_hdr does not hide the header: ITK reads it by its magic (found by fuzz_mri_nifti).
  std::string bad_size = header;
  const std::uint32_t damaged = 0xffff015cu;  // 348 in the low half only
  std::memcpy(&bad_size[0], &damaged, 4);
  const float nan_value = std::numeric_limits<float>::quiet_NaN();
  std::memcpy(&bad_size[324], &nan_value, 4);  // srow_z, entry 3
  const std::int16_t one = 1;
  std::memcpy(&bad_size[254], &one, 2);
  std::ofstream(dir.path("bad_size.nii"), std::ios::binary) << bad_size;
  m = messageOf([&] { readMriVolume(dir.path("bad_size.nii")); });
  EXPECT_NE(m.find("the NIfTI header's srow_z (entry 3) is nan"), std::string::npos) << m;
  // Neither 348 nor 540 and no NIfTI-1 magic: ITK still took such a file for NIfTI and aborted on its
  // sform (found by fuzz_mri_nifti: sizeof_hdr 655708, magic "n+2"); it is refused before ITK reads it.
  std::string odd_size = bad_size;
  const std::uint32_t odd = 0x000a015cu;
  std::memcpy(&odd_size[0], &odd, 4);
  std::memcpy(&odd_size[344], "n+2", 4);
  std::ofstream(dir.path("odd_size.nii"), std::ios::binary) << odd_size;
  m = messageOf([&] { readMriVolume(dir.path("odd_size.nii")); });
  EXPECT_NE(m.find(dir.path("odd_size.nii") + ": the NIfTI header's sizeof_hdr is 655708, neither 348"), std::string::npos) << m;
  // The same numbers in an unused transform (its code 0) do not matter.
  std::string unused = header;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::memcpy(&unused[296], &nan, 4);
  const std::int16_t zero = 0;
  std::memcpy(&unused[254], &zero, 2);
  std::ofstream(dir.path("unused.nii"), std::ios::binary) << unused;
  EXPECT_NO_THROW(readMriVolume(dir.path("unused.nii")));
}

TEST(MriVolume, BadDicomSeriesAreClearErrors) {
  TempDir dir("breast_sim_mri_bad_dicom");
  const ScalarImage image = obliqueVolume();
  // A slice missing from the middle of the series.
  writeDicomSeries(dir.path("gap"), image);
  std::filesystem::remove(dir.path("gap/IM00003.dcm"));
  std::string m = messageOf([&] { readMriVolume(dir.path("gap")); });
  EXPECT_NE(m.find("slices are not evenly spaced"), std::string::npos) << m;
  EXPECT_NE(m.find("3.00 mm where the slices are 1.50 mm apart: a slice is missing"), std::string::npos) << m;
  // A folder with one slice.
  ScalarImage one = image;
  one.geometry.size.z() = 1;
  one.values.resize(static_cast<std::size_t>(one.geometry.numVoxels()));
  writeDicomSeries(dir.path("single"), one);
  m = messageOf([&] { readMriVolume(dir.path("single")); });
  EXPECT_NE(m.find("a 2-D image (one slice of 9 x 7 voxels)"), std::string::npos) << m;
  // A folder holding two series: an error listing both, unless one is named.
  DicomSeriesOptions a, b;
  a.uid_seed = 1;
  b.uid_seed = 2;
  writeDicomSeries(dir.path("two"), image, a);
  writeDicomSeries(dir.path("other"), image, b);
  for (const auto& f : std::filesystem::directory_iterator(dir.path("other")))
    std::filesystem::copy_file(f.path(), dir.path("two/B_" + f.path().filename().string()));
  const std::string uid_b = readMriVolume(dir.path("other")).info.series_uid;
  m = messageOf([&] { readMriVolume(dir.path("two")); });
  EXPECT_NE(m.find("holds 2 DICOM series"), std::string::npos) << m;
  EXPECT_NE(m.find(uid_b + " (6 files)"), std::string::npos) << m;
  MriReadOptions named;
  named.series_uid = uid_b;
  EXPECT_EQ(readMriVolume(dir.path("two"), named).info.series_uid, uid_b);
  named.series_uid = "1.2.3";
  m = messageOf([&] { readMriVolume(dir.path("two"), named); });
  EXPECT_NE(m.find("holds no DICOM series with UID 1.2.3"), std::string::npos) << m;
  // A folder without DICOM files.
  std::filesystem::create_directories(dir.path("empty"));
  m = messageOf([&] { readMriVolume(dir.path("empty")); });
  EXPECT_NE(m.find("no DICOM image in this folder"), std::string::npos) << m;
  // Writing into a folder that already holds a series.
  m = messageOf([&] { writeDicomSeries(dir.path("gap"), image); });
  EXPECT_NE(m.find("the folder is not empty"), std::string::npos) << m;
}
