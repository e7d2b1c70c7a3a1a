// The core's DICOM reader (mri/dicom_scan.h): small hand-made files in each transfer syntax that walk
// to the end, each way of claiming more than a file holds refused with the element, its claim and the
// file's size, a folder holding a damaged slice refused by name while the same folder without it reads
// as before, and slices whose attributes GDCM would abort on refused with the attribute.
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>

#include "breast_sim/core/mri/dicom_scan.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "dicom_test_files.h"
#include "mri_test_images.h"
#include "temp_dir.h"

using namespace breast_sim::core;
using breast_sim::test::messageOf;
using breast_sim::test::TempDir;
using namespace breast_sim::test::dicom;

namespace {

// A small image's elements: its series UID and 16 bytes of pixel data.
std::string image(bool explicit_vr = false, bool big = false) {
  Bytes b(explicit_vr, big);
  b.element(0x0020, 0x000E, "UI", uid("1.2.3.4"));
  b.element(0x7FE0, 0x0010, "OW", std::string(16, '\x01'));
  return b.str();
}

std::string write(const TempDir& dir, const std::string& name, const std::string& bytes) {
  const std::string path = dir.path(name);
  std::ofstream(path, std::ios::binary) << bytes;
  return path;
}

std::string readAll(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

}  // namespace

TEST(DicomScan, FilesOfEverySyntaxWalkToTheirEnd) {
  TempDir dir("breast_sim_dicom_scan");
  // Implicit and explicit little endian, explicit big endian.
  for (const auto& [name, syntax, explicit_vr, big] :
       {std::tuple<const char*, const char*, bool, bool>{"implicit.dcm", kImplicit, false, false},
        {"explicit.dcm", kExplicit, true, false},
        {"big.dcm", kBig, true, true}}) {
    SCOPED_TRACE(name);
    const DicomFileScan scan = scanDicomFile(write(dir, name, part10(syntax, image(explicit_vr, big))));
    EXPECT_TRUE(scan.is_dicom);
    EXPECT_EQ(scan.transfer_syntax, syntax);
    EXPECT_EQ(scan.series_uid, "1.2.3.4");
    EXPECT_TRUE(scan.has_pixel_data);
  }
  // Sequences of defined and undefined length with items of both kinds, a UN sequence (implicit VR
  // inside), and encapsulated pixel data (an empty offset table, two fragments).
  Bytes nested(false);
  nested.element(0x0008, 0x0100, "SH", "CODE01");
  Bytes defined_item(true);
  defined_item.element(0x0008, 0x0100, "SH", "CODE01");
  Bytes b(true);
  b.head(0x0008, 0x1140, "SQ", kUndefined)
      .head(0xFFFE, 0xE000, "", kUndefined).element(0x0008, 0x1150, "UI", uid("1.2.840.10008.5.1.4.1.1.4")).head(0xFFFE, 0xE00D, "", 0)
      .head(0xFFFE, 0xE000, "", static_cast<std::uint32_t>(defined_item.str().size())).raw(defined_item.str())
      .head(0xFFFE, 0xE0DD, "", 0);
  b.head(0x0009, 0x1010, "UN", kUndefined)
      .head(0xFFFE, 0xE000, "", static_cast<std::uint32_t>(nested.str().size())).raw(nested.str())
      .head(0xFFFE, 0xE0DD, "", 0);
  b.element(0x0020, 0x000E, "UI", uid("1.2.3.4"));
  b.head(0x7FE0, 0x0010, "OB", kUndefined)
      .head(0xFFFE, 0xE000, "", 0)
      .head(0xFFFE, 0xE000, "", 6).raw(std::string("\xFF\xD8\xFF\xE0\x00\x10", 6))
      .head(0xFFFE, 0xE000, "", 4).raw(std::string("\xFF\xD9\x00\x00", 4))
      .head(0xFFFE, 0xE0DD, "", 0);
  const DicomFileScan jpeg = scanDicomFile(write(dir, "jpeg.dcm", part10(kJpeg, b.str())));
  EXPECT_TRUE(jpeg.has_pixel_data);
  EXPECT_EQ(jpeg.series_uid, "1.2.3.4");
  // An implicit-VR value of 13 bytes holds 10 (a GE writer's bug, read as GDCM reads it): the element
  // after its 10 bytes is found.
  Bytes ge(false);
  ge.head(0x0010, 0x0010, "", 13).raw("DOE^JOHN^^");  // 10 bytes of the value, then the next element
  const std::string ge_file = part10(kImplicit, ge.str() + image());
  EXPECT_TRUE(scanDicomFile(write(dir, "ge13.dcm", ge_file)).has_pixel_data);
  // Files that are not DICOM Part 10 are not DICOM here, and nothing else of them is read.
  EXPECT_FALSE(scanDicomFile(write(dir, "notes.txt", "patient notes")).is_dicom);
  EXPECT_FALSE(scanDicomFile(write(dir, "raw.dcm", std::string(200, '\0') + image())).is_dicom);
}

TEST(DicomScan, ClaimsBeyondTheFileAreRefusedNamingElementClaimAndSize) {
  TempDir dir("breast_sim_dicom_scan_bad");
  struct Case {
    const char* name;
    std::string bytes;
    std::vector<std::string> says;
  };
  Bytes huge(false);
  huge.element(0x0020, 0x000E, "UI", uid("1.2.3.4")).head(0x7FE0, 0x0010, "", 1398756436).raw(std::string(16, '\0'));
  const std::string huge_file = part10(kImplicit, huge.str());
  Bytes big_huge(true, true);
  big_huge.head(0x7FE0, 0x0010, "OW", 0x40000000).raw(std::string(16, '\0'));
  Bytes item_past_sequence(true);
  item_past_sequence.head(0x0008, 0x1140, "SQ", 16).head(0xFFFE, 0xE000, "", 100).raw(std::string(8, '\0'))
      .raw(image(true));
  Bytes element_past_item(true);
  element_past_item.head(0x0008, 0x1140, "SQ", kUndefined).head(0xFFFE, 0xE000, "", 12)
      .head(0x0008, 0x0100, "SH", 200).raw(std::string(4, 'A')).head(0xFFFE, 0xE0DD, "", 0);
  Bytes open_item(true);
  open_item.head(0x0008, 0x1140, "SQ", kUndefined).head(0xFFFE, 0xE000, "", kUndefined).element(0x0008, 0x0100, "SH", "AB");
  Bytes deep(true);
  for (int level = 0; level < 40; ++level) deep.head(0x0008, 0x1140, "SQ", kUndefined).head(0xFFFE, 0xE000, "", kUndefined);
  Bytes unknown_vr(true);
  unknown_vr.raw(std::string("\x10\x00\x10\x00", 4) + "ZZ" + std::string("\x04\x00", 2) + "ABCD");
  Bytes undefined_text(true);
  undefined_text.head(0x0008, 0x0100, "UT", kUndefined).raw("ABCD");
  Bytes fragment_past_end(true);
  fragment_past_end.head(0x7FE0, 0x0010, "OB", kUndefined).head(0xFFFE, 0xE000, "", 0).head(0xFFFE, 0xE000, "", 5000).raw("AB");
  const std::vector<Case> cases = {
      {"huge.dcm", huge_file,
       {"a damaged DICOM file (" + std::to_string(huge_file.size()) + " bytes)", "data element (7FE0,0010)",
        "claims 1398756436 bytes, but only 16 follow in the file", "remove the file from the folder"}},
      {"big_endian.dcm", part10(kBig, big_huge.str()), {"(7FE0,0010)", "claims 1073741824 bytes"}},
      {"item_past_sequence.dcm", part10(kExplicit, item_past_sequence.str()),
       {"data element (FFFE,E000)", "claims 100 bytes", "before the end of its enclosing item"}},
      {"element_past_item.dcm", part10(kExplicit, element_past_item.str()), {"(0008,0100)", "claims 200 bytes"}},
      {"open_item.dcm", part10(kExplicit, open_item.str()), {"has no item delimiter (FFFE,E00D)"}},
      {"deep.dcm", part10(kExplicit, deep.str()), {"sequences nest deeper than 32 levels"}},
      {"unknown_vr.dcm", part10(kExplicit, unknown_vr.str()), {"(0010,0010)", "unknown VR bytes 5A 5A"}},
      {"undefined_text.dcm", part10(kExplicit, undefined_text.str()), {"(0008,0100)", "VR UT has an undefined length"}},
      {"fragment_past_end.dcm", part10(kJpeg, fragment_past_end.str()), {"(FFFE,E000)", "claims 5000 bytes"}},
      {"truncated_header.dcm", part10(kExplicit, std::string("\x08\x00\x16\x00UI", 6)), {"has a header of 8 bytes, but only 6 follow"}},
      {"implicit_but_explicit.dcm", part10(kImplicit, image(true)),
       {"the meta information gives implicit VR", "written with explicit VRs ('UI')"}},
      {"deflated.dcm", part10("1.2.840.10008.1.2.1.99", image(true)), {"deflated transfer syntax", "not read"}},
      {"private_syntax.dcm", part10("1.2.3.4.5", image(true)), {"transfer syntax '1.2.3.4.5'", "not one of DICOM's"}},
      {"no_meta.dcm", std::string(128, '\0') + "DICM" + image(), {"no meta information (group 0002)"}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const std::string path = write(dir, c.name, c.bytes);
    const std::string m = messageOf([&] { scanDicomFile(path); });
    EXPECT_EQ(m.rfind(path + ": ", 0), 0u) << m;
    for (const std::string& part : c.says) EXPECT_NE(m.find(part), std::string::npos) << "missing '" << part << "' in: " << m;
  }
}

// The fuzz finding: one file of a series whose pixel data claim 1.4 GB (GDCM allocated the claim while
// ITK listed the folder): the folder is refused naming the file, and the folder without it reads as
// before. Files that are not images are skipped.
TEST(DicomScan, AFolderWithADamagedSliceIsRefusedNamingItAndReadsWithoutIt) {
  TempDir dir("breast_sim_dicom_folder");
  ScalarImage volume;
  volume.geometry.size = Eigen::Vector3i(6, 5, 4);
  volume.geometry.spacing_m = Eigen::Vector3d(0.9e-3, 1.1e-3, 2e-3);
  volume.values.resize(120);
  for (int v = 0; v < 120; ++v) volume.values[v] = static_cast<float>(3 * v - 40);
  writeDicomSeries(dir.path("series"), volume);
  const MriVolume clean = readMriVolume(dir.path("series"));
  // Beside the slices: notes, a file without the preamble and a DICOM file without an image are skipped.
  write(dir, "series/README.txt", "exported from the scanner");
  write(dir, "series/raw_dataset", image());
  Bytes no_image(false);
  no_image.element(0x0020, 0x000E, "UI", uid("1.2.3.4"));
  write(dir, "series/DICOMDIR", part10(kImplicit, no_image.str()));
  const MriVolume with_others = readMriVolume(dir.path("series"));
  EXPECT_EQ(with_others.image.values, clean.image.values);
  EXPECT_EQ(with_others.info.files, 4);
  EXPECT_EQ(with_others.info.series_uid, clean.info.series_uid);
  // A copy of slice 2 whose Pixel Data (7FE0,0010) claims 1.4 GB.
  std::string bytes = readAll(dir.path("series/IM00002.dcm"));
  const std::string pixel_tag("\xE0\x7F\x10\x00", 4);
  const std::size_t at = bytes.rfind(pixel_tag);
  ASSERT_NE(at, std::string::npos);
  const std::uint32_t claim = 1398756436;
  for (int i = 0; i < 4; ++i) bytes[at + 4 + i] = static_cast<char>((claim >> (8 * i)) & 0xFF);
  const std::string damaged = write(dir, "series/IM00002_copy.dcm", bytes);
  for (const std::string& path : {dir.path("series"), dir.path("series/IM00001.dcm")}) {
    SCOPED_TRACE(path);
    const std::string m = messageOf([&] { readMriVolume(path); });
    EXPECT_EQ(m.rfind(damaged + ": a damaged DICOM file (" + std::to_string(bytes.size()) + " bytes): data element (7FE0,0010)", 0), 0u) << m;
    EXPECT_NE(m.find("claims 1398756436 bytes"), std::string::npos) << m;
  }
  std::filesystem::remove(damaged);
  EXPECT_EQ(readMriVolume(dir.path("series")).image.values, clean.image.values);
}

// Slices written by hand in each byte order and bit layout read to their values; a slice whose
// attributes GDCM would abort on or misread (found by fuzz_mri_dicom: SamplesPerPixel 2 stopped the
// process in gdcm::PixelFormat) is refused naming the file and the attribute.
TEST(DicomScan, SlicesReadByTheirAttributesOrAreRefusedNamingOne) {
  TempDir dir("breast_sim_dicom_slices");
  // 12 bits stored at bits 4..15 (high bit 15), signed, with a rescale: the value is the stored bits,
  // sign-extended, times the slope plus the intercept; the bits below are not part of it.
  Slice twelve;
  twelve.big = true;
  twelve.explicit_vr = true;
  twelve.stored = 12;
  twelve.sign = 1;
  twelve.slope = "2";
  twelve.intercept = "-1";
  twelve.pixels = {0x0010 | 0x7, 0x0FF0, 0xFFF0, 0x8000 | 0xF, 0x0000, 0x7FF0};
  for (int k = 0; k < 3; ++k) {
    twelve.z_mm = 1.5 * k;
    write(dir, "twelve/s" + std::to_string(k) + ".dcm", (std::filesystem::create_directories(dir.path("twelve")), slice(twelve)));
  }
  const MriVolume v = readMriVolume(dir.path("twelve"));
  EXPECT_EQ(v.info.files, 3);
  EXPECT_EQ(v.info.pixel_type, "short");
  EXPECT_EQ(v.info.series_description, "hand-made");
  const std::vector<float> one = {2 * 1 - 1, 2 * 255 - 1, 2 * -1 - 1, 2 * -2048 - 1, -1, 2 * 2047 - 1};
  for (int k = 0; k < 3; ++k)
    for (int p = 0; p < 6; ++p) EXPECT_EQ(v.image.values[6 * k + p], one[p]) << k << " " << p;
  // Geometry: 3 columns along i at 0.25 mm, 2 rows along j at 0.5 mm, slices 1.5 mm apart.
  EXPECT_EQ(v.image.geometry.size, Eigen::Vector3i(3, 2, 3));
  EXPECT_LT((v.image.geometry.spacing_m - Eigen::Vector3d(0.25e-3, 0.5e-3, 1.5e-3)).norm(), 1e-12);
  EXPECT_LT((v.image.geometry.origin_m - Eigen::Vector3d(-10e-3, 20.5e-3, 0)).norm(), 1e-12);
  // 8-bit unsigned in implicit VR.
  Slice byte;
  byte.bits = byte.stored = 8;
  byte.high = 7;
  byte.pixels = {0, 1, 2, 253, 254, 255};
  std::filesystem::create_directories(dir.path("bytes"));
  for (int k = 0; k < 2; ++k) {
    byte.z_mm = k;
    write(dir, "bytes/s" + std::to_string(k) + ".dcm", slice(byte));
  }
  EXPECT_EQ(readMriVolume(dir.path("bytes")).image.values[5], 255.0f);

  struct Bad {
    const char* name;
    Slice slice;
    std::string says;
  };
  std::vector<Bad> bad(8, Bad{"", Slice{}, ""});
  bad[0] = {"samples", Slice{}, "voxels with 2 components"};
  bad[0].slice.samples = "2";
  bad[1] = {"colour", Slice{}, "PhotometricInterpretation (0028,0004) is 'RGB'"};
  bad[1].slice.photometric = "RGB";
  bad[2] = {"frames", Slice{}, "a multi-frame DICOM file (4 frames), which is not read"};
  bad[2].slice.frames = "4";
  bad[3] = {"bits", Slice{}, "BitsAllocated (0028,0100) is 12"};
  bad[3].slice.bits = 12;
  bad[4] = {"stored", Slice{}, "BitsStored (0028,0101) 17 and HighBit (0028,0102) 15 do not fit"};
  bad[4].slice.stored = 17;
  bad[5] = {"position", Slice{}, "no ImagePositionPatient (0020,0032)"};
  bad[5].slice.position = false;
  bad[6] = {"slope", Slice{}, "RescaleSlope (0028,1053) is 'x1': not 1 finite number"};
  bad[6].slice.slope = "x1";
  bad[7] = {"short", Slice{}, "the pixel data hold 10 bytes, where 2 rows x 3 columns x 2 bytes need 12"};
  bad[7].slice.pixels.pop_back();
  for (const Bad& b : bad) {
    SCOPED_TRACE(b.name);
    std::filesystem::create_directories(dir.path(b.name));
    write(dir, std::string(b.name) + "/good.dcm", slice(Slice{}));
    Slice second = b.slice;
    second.z_mm = 1;
    const std::string path = write(dir, std::string(b.name) + "/bad.dcm", slice(second));
    const std::string m = messageOf([&] { readMriVolume(dir.path(b.name)); });
    EXPECT_EQ(m.rfind(path + ": ", 0), 0u) << m;
    EXPECT_NE(m.find(b.says), std::string::npos) << m;
  }
  // Compressed pixel data: not read, with the way to convert them.
  Bytes jpeg(true);
  jpeg.element(0x0020, 0x000E, "UI", uid("1.2.3.4"))
      .head(0x7FE0, 0x0010, "OB", kUndefined).head(0xFFFE, 0xE000, "", 0).head(0xFFFE, 0xE0DD, "", 0);
  std::filesystem::create_directories(dir.path("jpeg"));
  const std::string path = write(dir, "jpeg/a.dcm", part10(kJpeg, jpeg.str()));
  const std::string m = messageOf([&] { readMriVolume(path); });
  EXPECT_NE(m.find(path + ": compressed DICOM (transfer syntax 1.2.840.10008.1.2.4.50), which is not read"), std::string::npos) << m;
  EXPECT_NE(m.find("gdcmconv --raw"), std::string::npos) << m;
}
