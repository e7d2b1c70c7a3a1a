// Label-image readers on malformed input: the message names the file and the fault.

#include "breast_sim/core/image/label_image.h"

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <gtest/gtest.h>

#include "breast_sim/core/image/image_io_detail.h"
#include "label_image_fixtures.h"

namespace {

using breast_sim::core::LabelImage;
using breast_sim::core::readLabelImage;
using breast_sim::core::writeLabelImage;

using namespace breast_sim::core::label_image_fixtures;

const ::testing::Environment* const kCleanup =
    ::testing::AddGlobalTestEnvironment(new TempFolderCleanup);

struct BadFile {
  std::string name;               ///< what is wrong
  std::string file;               ///< file name, extension chooses the reader
  std::string bytes;              ///< content ("" with no_file: not created)
  std::vector<std::string> says;  ///< substrings the message must contain
  std::string extra_file = "";    ///< optional data file name …
  std::string extra_bytes = "";   ///< … and content
  bool no_file = false;
};

std::string nrrdHeader(const std::string& fields) {
  return "NRRD0004\ndimension: 3\n" + fields + "\n";
}

TEST(LabelImageReader, RejectsMalformedFilesNamingFileAndFault) {
  const std::string lps = "space: left-posterior-superior\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n";
  const std::string mha_head = "ObjectType = Image\nNDims = 3\nElementSpacing = 1 1 1\n";
  NiftiFields four_d;
  four_d.dim[0] = 4;
  four_d.dim[4] = 2;
  NiftiFields wrong_size;
  wrong_size.sizeof_hdr = 350;
  NiftiFields huge_dims;
  for (int d = 1; d <= 3; ++d) huge_dims.dim[d] = 32767;
  NiftiFields far_offset;
  far_offset.vox_offset = 1e30f;  // casting this to size_t was undefined behaviour
  NiftiFields infinite_offset;
  infinite_offset.vox_offset = INFINITY;
  NiftiFields offset_past_end;
  offset_past_end.vox_offset = 1000;
  const std::vector<BadFile> cases = {
      {"sizes has two values", "two_sizes.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5\nencoding: raw\n") + std::string(35, '\0'),
       {"header field 'sizes' has 2 values, expected 3 (dimension: 3)"}},
      {"raw data truncated", "truncated.nrrd",
       nrrdHeader("type: uint16\nsizes: 7 5 3\nendian: little\nencoding: raw\n") +
           std::string(100, '\0'),
       {"truncated", "expected 210 bytes", "found 100"}},
      {"endian missing for int16", "no_endian.nrrd",
       nrrdHeader("type: int16\nsizes: 7 5 3\nencoding: raw\n") + std::string(210, '\0'),
       {"'endian' is missing"}},
      {"unknown type", "complex.nrrd",
       nrrdHeader("type: complex\nsizes: 7 5 3\nencoding: raw\n"), {"header field 'type'", "complex"}},
      {"not a NRRD file", "text.nrrd", "hello, world\n", {"not a NRRD file"}},
      {"dimension 2", "flat.nrrd", "NRRD0004\ndimension: 2\ntype: uint8\nsizes: 7 5\nencoding: raw\n\n",
       {"'dimension' is 2", "only 3-D"}},
      {"negative label", "negative.nrrd",
       nrrdHeader("type: int16\nsizes: 7 5 3\nendian: big\nencoding: raw\n") +
           markedData<std::int16_t>(-3, true),
       {"voxel (5, 1, 2) holds -3", "[0, 65535]"}},
      {"non-integral label", "fraction.nrrd",
       nrrdHeader("type: float\nsizes: 7 5 3\nendian: little\nencoding: raw\n") +
           markedData<float>(2.5f, false),
       {"holds 2.5"}},
      {"label above 65535", "huge.nrrd",
       nrrdHeader("type: uint32\nsizes: 7 5 3\nendian: little\nencoding: raw\n") +
           markedData<std::uint32_t>(70000, false),
       {"holds 70000"}},
      {"sheared space directions", "sheared.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5 3\nencoding: raw\nspace: LPS\n"
                  "space directions: (1,0,0) (0.5,1,0) (0,0,1)\nspace origin: (0,0,0)\n") +
           std::string(105, '\0'),
       {"not orthogonal", "axes 0 and 1"}},
      {"space directions with two vectors", "two_directions.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5 3\nencoding: raw\nspace: LPS\n"
                  "space directions: (1,0,0) (0,1,0)\n") + std::string(105, '\0'),
       {"'space directions' has 2 vectors, expected 3"}},
      {"bzip2 encoding", "bzip.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5 3\nencoding: bzip2\n") + "BZh9",
       {"'encoding' is 'bzip2', which is not supported", "raw, gzip, ascii"}},
      {"corrupt gzip", "corrupt.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5 3\nencoding: gzip\n" + lps) + "\x1f\x8b this is not deflate data",
       {"compressed data is corrupt"}},
      {"missing data file", "lost.nhdr",
       "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 7 5 3\nencoding: raw\ndata file: nowhere.raw\n",
       {"data file", "nowhere.raw", "cannot open"}},
      {"ascii data too short", "short.nrrd",
       nrrdHeader("type: uint8\nsizes: 7 5 3\nencoding: ascii\n") + "1 2 3" + std::string(300, ' '),
       {"expected 105 values, found 3"}},
      // 2^31 labels (4 GiB) were allocated before the text was parsed.
      {"ascii count beyond the data", "ascii_claim.nrrd",
       nrrdHeader("type: uint8\nsizes: 1024 1024 2048\nencoding: ascii\n") + "1 2 3\n",
       {"ASCII voxel data is truncated: expected 2147483648 values, but its 6 bytes hold at most 3"}},
      {"MetaImage ascii count beyond the data", "ascii_claim.mha",
       mha_head + "DimSize = 1024 1024 2048\nElementType = MET_UCHAR\nBinaryData = False\n"
                  "ElementDataFile = LOCAL\n1 2 3\n",
       {"ASCII voxel data is truncated: expected 2147483648 values, but its 6 bytes hold at most 3"}},
      // A folder opened like a file and its "size" (2^63 on some file systems) was allocated.
      {"data file that is a folder", "folder.nhdr",
       "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 7 5 3\nencoding: raw\ndata file: .\n",
       {"data file:", "is a folder, not a file"}},
      {"MetaImage data file that is a folder", "folder.mhd",
       mha_head + "DimSize = 7 5 3\nElementType = MET_UCHAR\nElementDataFile = .\n",
       {"data file:", "is a folder, not a file"}},
      // The name was cut at its NUL byte, which left the header's own folder.
      {"data file name with a NUL byte", "nul.nhdr",
       "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 7 5 3\nencoding: raw\ndata file: " + std::string("\0\0x\n", 4),
       {"the data file name '??x' is empty or holds control characters"}},
      {"MetaImage without DimSize", "no_size.mha",
       mha_head + "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + std::string(105, '\0'),
       {"'DimSize' is missing"}},
      {"MetaImage data truncated", "short.mha",
       mha_head + "DimSize = 7 5 3\nElementType = MET_SHORT\nElementDataFile = LOCAL\n" +
           std::string(200, '\0'),
       {"truncated", "expected 210 bytes", "found 200"}},
      {"MetaImage TransformMatrix with 4 values", "matrix.mha",
       mha_head + "TransformMatrix = 1 0 0 1\nDimSize = 7 5 3\nElementType = MET_UCHAR\n"
                  "ElementDataFile = LOCAL\n" + std::string(105, '\0'),
       {"'TransformMatrix' has 4 values, expected 9"}},
      {"MetaImage corrupt compressed data", "corrupt.mha",
       mha_head + "DimSize = 7 5 3\nElementType = MET_UCHAR\nCompressedData = True\n"
                  "ElementDataFile = LOCAL\nnot zlib at all",
       {"compressed data is corrupt"}},
      {"MetaImage vector type", "vector.mha",
       mha_head + "DimSize = 7 5 3\nElementType = MET_FLOAT_ARRAY\nElementDataFile = LOCAL\n",
       {"'ElementType' is 'MET_FLOAT_ARRAY'"}},
      {"MetaImage without ElementDataFile", "no_data.mha", mha_head + "DimSize = 7 5 3\n",
       {"'ElementDataFile'"}},
      {"NIfTI with a wrong sizeof_hdr", "wrong.nii",
       niftiHeader(wrong_size) + markedData<std::uint8_t>(5, false),
       {"not a NIfTI-1 file", "sizeof_hdr is 350"}},
      {"NIfTI data truncated", "short.nii", niftiHeader(NiftiFields()) + std::string(50, '\0'),
       {"truncated", "expected 105 bytes", "found 50"}},
      {"NIfTI with a time axis", "four_d.nii",
       niftiHeader(four_d) + std::string(210, '\0'), {"dim[4] is 2", "more than 3 dimensions"}},
      {"NIfTI shorter than a header", "stub.nii.gz", std::string(100, 'x'),
       {"fewer than a NIfTI-1 header's 348"}},
      // Each size is fine but the product wraps: 2^22·2^21·2^21 = 2^64 and 2^30·2^30·16 = 2^64
      // were 0 voxels, which read "successfully" and crashed in labelAt().
      {"NRRD sizes whose product wraps to 0", "wrap.nrrd",
       nrrdHeader("type: uint8\nsizes: 4194304 2097152 2097152\nencoding: raw\n") + std::string(16, '\0'),
       {"header field 'sizes' is '4194304 2097152 2097152'", "4194304×2097152×2097152 ≈ 1.84e+19 voxels",
        "more than the 2147483648 (2^31) a label image may hold"}},
      {"NRRD sizes 2^30 2^30 16", "wrap16.nrrd",
       nrrdHeader("type: uint8\nsizes: 1073741824 1073741824 16\nencoding: gzip\n") + std::string(16, '\0'),
       {"header field 'sizes' is '1073741824 1073741824 16'", "more than the 2147483648"}},
      {"NRRD sizes just over 2^31 voxels", "over.nrrd",
       nrrdHeader("type: uint8\nsizes: 2048 1024 1025\nencoding: raw\n") + std::string(16, '\0'),
       {"2048×1024×1025 = 2149580800 voxels, more than the 2147483648"}},
      {"NRRD size above INT_MAX", "int_max.nrrd",
       nrrdHeader("type: uint8\nsizes: 4294967297 1 1\nencoding: raw\n") + std::string(16, '\0'),
       {"'sizes' value '4294967297' is not an integer from 1 to 2147483647"}},
      {"MetaImage DimSize whose product wraps to 0", "wrap.mha",
       mha_head + "DimSize = 4194304 2097152 2097152\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
           std::string(16, '\0'),
       {"header field 'DimSize' is '4194304 2097152 2097152'", "more than the 2147483648"}},
      {"MetaImage DimSize 2^30 2^30 16", "wrap16.mha",
       mha_head + "DimSize = 1073741824 1073741824 16\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
           std::string(16, '\0'),
       {"header field 'DimSize' is '1073741824 1073741824 16'", "more than the 2147483648"}},
      {"NIfTI with more than 2^31 voxels", "huge.nii", niftiHeader(huge_dims) + std::string(16, '\0'),
       {"header field 'dim[1..3]' is '32767 32767 32767'", "32767×32767×32767 = 35181150961663 voxels",
        "more than the 2147483648"}},
      {"NIfTI vox_offset 1e30", "far_offset.nii",
       niftiHeader(far_offset) + markedData<std::uint8_t>(5, false),
       {"vox_offset is 1.0000000150474662e+30", "expected an integer from 348 to the file size (457 bytes)"}},
      {"NIfTI vox_offset infinite", "inf_offset.nii",
       niftiHeader(infinite_offset) + markedData<std::uint8_t>(5, false),
       {"vox_offset is inf;", "expected an integer from 348"}},
      {"NIfTI vox_offset past the end of the file", "past_end.nii",
       niftiHeader(offset_past_end) + markedData<std::uint8_t>(5, false),
       {"vox_offset is 1000;", "to the file size (457 bytes)"}},
      {"unknown extension", "labels.png", "PNG", {"unknown extension"}},
      {"file missing", "absent.nrrd", "", {"cannot open"}, "", "", true},
  };
  for (const BadFile& c : cases) {
    SCOPED_TRACE(c.name);
    const std::string path = tempPath(c.file);
    std::filesystem::remove(path);
    if (!c.no_file) writeBytes(path, c.bytes);
    if (!c.extra_file.empty()) writeBytes(tempPath(c.extra_file), c.extra_bytes);
    const std::string message = errorOf([&] { readLabelImage(path); });
    ASSERT_FALSE(message.empty()) << "no std::runtime_error thrown";
    EXPECT_EQ(message.rfind(path + ": ", 0), 0u) << "message does not start with the path: " << message;
    for (const std::string& s : c.says) {
      EXPECT_NE(message.find(s), std::string::npos) << "'" << s << "' not in: " << message;
    }
  }
}

std::string gzipped(const std::string& bytes) {
  return breast_sim::core::image_io::deflateBytes(bytes, breast_sim::core::image_io::Wrapper::kGzip);
}

// A .nii.gz stream that goes on past the bytes its header describes was inflated to the end, however
// large: it is refused once it passes them.
TEST(LabelImageReader, GzipStreamLargerThanItsNiftiHeaderSaysIsRefused) {
  const std::string image = niftiHeader(NiftiFields()) + markedData<std::uint8_t>(5, false);
  const std::string path = tempPath("bomb.nii.gz");
  writeBytes(path, gzipped(image + std::string(8 << 20, '\0')));
  const std::string message = errorOf([&] { readLabelImage(path); });
  EXPECT_NE(message.find(path + ": the gzip stream decompresses to more than the 457 bytes its header describes "
                                "(vox_offset 352 + 7×5×3 uint8 values)"),
            std::string::npos)
      << message;
  // The same image without the tail reads.
  writeBytes(path, gzipped(image));
  EXPECT_EQ(readLabelImage(path).at(5, 1, 2), 5);
  // And so does an uncompressed one with a tail, as before (nothing is inflated).
  writeBytes(tempPath("tail.nii"), image + std::string(1000, '\0'));
  EXPECT_EQ(readLabelImage(tempPath("tail.nii")).at(5, 1, 2), 5);
}

TEST(LabelImageReader, TruncatedCompressedDataSaysHowManyBytesWereExpectedAndFound) {
  LabelImage image(Eigen::Vector3i(40, 30, 20), mm(1, 1, 1), mm(0, 0, 0));
  for (std::size_t v = 0; v < image.labels.size(); ++v) {
    image.labels[v] = static_cast<std::uint16_t>((v * 2654435761u) >> 16);  // incompressible
  }
  // Where each format's compressed stream starts: after the NRRD blank line, the MetaImage
  // ElementDataFile line, or at byte 0 of a .nii.gz.
  const std::vector<std::pair<std::string, std::string>> cases = {
      {".nrrd", "\n\n"}, {".mha", "ElementDataFile = LOCAL\n"}, {".nii.gz", ""}};
  for (const auto& [ext, marker] : cases) {
    SCOPED_TRACE(ext);
    const std::string path = tempPath("cut" + ext);
    writeLabelImage(path, image);
    const std::string bytes = readBytes(path);
    const std::size_t start = marker.empty() ? 0 : bytes.find(marker) + marker.size();
    ASSERT_LT(start, bytes.size());
    writeBytes(path, bytes.substr(0, start + (bytes.size() - start) / 2));
    const std::string message = errorOf([&] { readLabelImage(path); });
    EXPECT_NE(message.find("truncated"), std::string::npos) << message;
    EXPECT_NE(message.find("expected"), std::string::npos) << message;
    EXPECT_NE(message.find("found"), std::string::npos) << message;
  }
}

}  // namespace
