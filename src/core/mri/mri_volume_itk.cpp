// Reading NIfTI files and writing volumes and DICOM series through ITK, behind plain types
// (itk_bridge.h). One of the two sources that compile ITK's headers (mri_filters_itk.cpp is the other);
// it includes no Eigen (see itk_bridge.h). The NIfTI ImageIO is created by name rather than through
// ITK's factory, so nothing else (a PNG, a JPEG) is taken for an MRI; its header is checked before any
// voxel is allocated. NRRD, MetaImage and DICOM are read by the core (mri_volume.cpp says why).
#include "itk_image.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <stdexcept>
#include <string>
#include <system_error>
#include <vector>

#include <unistd.h>
#include <zlib.h>

#include <itkGDCMImageIO.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageSeriesWriter.h>
#include <itkMetaDataObject.h>
#include <itkMetaImageIO.h>
#include <itkNiftiImageIO.h>
#include <itkNrrdImageIO.h>

namespace breast_sim::core::itk_bridge {

namespace {

namespace fs = std::filesystem;
using FloatImage = itk::Image<float, 3>;

[[noreturn]] void fail(const std::string& path, const std::string& what) { throw std::runtime_error(path + ": " + what); }

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

bool endsWith(const std::string& s, const std::string& end) {
  return s.size() >= end.size() && s.compare(s.size() - end.size(), end.size(), end) == 0;
}

// ITK prints warnings (e.g. about a NIfTI sform) to its output window; the readers report problems
// as exceptions instead.
void quietItk() {
  static const bool done = [] {
    itk::Object::GlobalWarningDisplayOff();
    return true;
  }();
  (void)done;
}

// Checks what a header says before anything is allocated: scalar, 3-D, not too large.
void checkHeader(const std::string& path, itk::ImageIOBase& io, long max_voxels) {
  const unsigned components = io.GetNumberOfComponents();
  const auto pixel = io.GetPixelType();
  if (components != 1 || (pixel != itk::IOPixelEnum::SCALAR && pixel != itk::IOPixelEnum::UNKNOWNPIXELTYPE))
    fail(path, "voxels of type " + itk::ImageIOBase::GetPixelTypeAsString(pixel) + " with " + std::to_string(components) +
                   " components; the MRI must be a scalar (magnitude) image: export the magnitude, not RGB, vector "
                   "or complex data");
  std::vector<long> size;
  for (unsigned d = 0; d < io.GetNumberOfDimensions(); ++d) size.push_back(static_cast<long>(io.GetDimensions(d)));
  checkVolumeSize(path, size, max_voxels);
}

Volume fromItk(const FloatImage& image) {
  Volume out;
  for (int d = 0; d < 3; ++d) {
    out.grid.size[d] = static_cast<long>(image.GetLargestPossibleRegion().GetSize()[d]);
    out.grid.spacing_mm[d] = image.GetSpacing()[d];
    out.grid.origin_mm[d] = image.GetOrigin()[d];
    for (int r = 0; r < 3; ++r) out.grid.direction[3 * r + d] = image.GetDirection()[r][d];
  }
  const float* src = image.GetBufferPointer();
  out.values.assign(src, src + out.grid.count());
  return out;
}

// The spacing and the transforms in use of a NIfTI-1 header `h` in the byte order `swap` says.
void checkNiftiNumbersInOrder(const std::string& path, const unsigned char* h, bool swap) {
  const auto word = [&](int offset) {
    std::uint32_t u = 0;
    std::memcpy(&u, h + offset, 4);
    return swap ? __builtin_bswap32(u) : u;
  };
  const auto code = [&](int offset) {
    std::uint16_t u = 0;
    std::memcpy(&u, h + offset, 2);
    return swap ? static_cast<std::uint16_t>(__builtin_bswap16(u)) : u;
  };
  struct Field {
    const char* name;
    int offset, count;
    bool used;
  };
  const bool qform = code(252) != 0, sform = code(254) != 0;
  for (const Field& field : {Field{"pixdim", 76, 4, true}, Field{"quatern_b, c, d", 256, 3, qform},
                             Field{"qoffset_x, y, z", 268, 3, qform}, Field{"srow_x", 280, 4, sform},
                             Field{"srow_y", 296, 4, sform}, Field{"srow_z", 312, 4, sform}}) {
    if (!field.used) continue;
    for (int i = 0; i < field.count; ++i) {
      const std::uint32_t u = word(field.offset + 4 * i);
      float v = 0;
      std::memcpy(&v, &u, 4);
      if (!(std::abs(v) <= 1e7f)) {
        char value[48];
        std::snprintf(value, sizeof value, "%g", static_cast<double>(v));
        fail(path, std::string("the NIfTI header's ") + field.name + " (entry " + std::to_string(i) + ") is " + value +
                       ": not a finite number of at most 1e7; the header is damaged, export the image again");
      }
    }
  }
}

// ITK's NiftiImageIO turns the header's qform or sform into a direction matrix with vnl's SVD, which
// aborts the process on a value that is not finite (found by fuzz_mri_nifti). So the NIfTI-1 header's
// spacing and the orientation it uses are checked first: finite and at most 1e7 in magnitude (mm, or
// quaternion parts). gzread reads plain and gzip-compressed files alike, the 348 bytes only. A
// NIfTI-1 header is one with sizeof_hdr 348 or the magic "n+1" / "ni1" (ITK reads a header whose
// sizeof_hdr is damaged by its magic); its byte order is that of dim[0] in 1…7, as the NIfTI library
// decides it, else that of sizeof_hdr; with neither, both orders are checked. A NIfTI-2 header
// (sizeof_hdr 540) is left to ITK; any other file that ITK took for NIfTI is refused (one with a
// damaged sizeof_hdr and the magic "n+2" reached vnl's abort through a layout of ITK's own choosing).
void checkNiftiHeaderNumbers(const std::string& path) {
  unsigned char h[348];
  gzFile f = gzopen(path.c_str(), "rb");
  if (!f) return;  // ITK names what is wrong with the file
  const int got = gzread(f, h, sizeof h);
  gzclose(f);
  if (got != static_cast<int>(sizeof h)) return;
  std::uint32_t size = 0;
  std::memcpy(&size, h, 4);
  const bool magic = std::memcmp(h + 344, "n+1", 4) == 0 || std::memcmp(h + 344, "ni1", 4) == 0;
  if (size == 540 || __builtin_bswap32(size) == 540) return;  // NIfTI-2: ITK reads and checks it
  if (!magic && size != 348 && __builtin_bswap32(size) != 348)
    fail(path, "the NIfTI header's sizeof_hdr is " + std::to_string(size) +
                   ", neither 348 (NIfTI-1) nor 540 (NIfTI-2), and it has no NIfTI-1 magic: the header is damaged, "
                   "export the image again");
  std::uint16_t dim0 = 0;
  std::memcpy(&dim0, h + 40, 2);
  const std::uint16_t dim0_swapped = __builtin_bswap16(dim0);
  if (dim0 >= 1 && dim0 <= 7) {
    checkNiftiNumbersInOrder(path, h, false);
  } else if (dim0_swapped >= 1 && dim0_swapped <= 7) {
    checkNiftiNumbersInOrder(path, h, true);
  } else if (size == 348 || __builtin_bswap32(size) == 348) {
    checkNiftiNumbersInOrder(path, h, size != 348);
  } else {
    checkNiftiNumbersInOrder(path, h, false);
    checkNiftiNumbersInOrder(path, h, true);
  }
}

}  // namespace

bool isNifti(const std::string& path) {
  quietItk();
  return itk::NiftiImageIO::New()->CanReadFile(path.c_str());
}

Volume readNifti(const std::string& path, long max_voxels) {
  quietItk();
  checkNiftiHeaderNumbers(path);
  auto io = itk::NiftiImageIO::New();
  try {
    io->SetFileName(path);
    io->ReadImageInformation();
  } catch (const itk::ExceptionObject& e) {
    fail(path, std::string("cannot read the NIfTI header: ") + e.GetDescription());
  }
  checkHeader(path, *io, max_voxels);
  auto reader = itk::ImageFileReader<FloatImage>::New();
  reader->SetImageIO(io);
  reader->SetFileName(path);
  try {
    reader->Update();
  } catch (const itk::ExceptionObject& e) {
    fail(path, std::string("cannot read the NIfTI voxels (truncated or damaged file?): ") + e.GetDescription());
  }
  Volume out = fromItk(*reader->GetOutput());
  out.format = "NIfTI";
  out.pixel_type = itk::ImageIOBase::GetComponentTypeAsString(io->GetComponentType());
  return out;
}

namespace {

using Vec3 = std::array<double, 3>;
double dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}

// A name beside `path` for writing before the rename, with the same extension (ITK picks the
// encoding by extension, e.g. .nii.gz).
std::string temporaryBeside(const std::string& path, const std::string& extension) {
  const fs::path p(path);
  return (p.parent_path() / ("." + p.filename().string() + ".tmp" + std::to_string(::getpid()) + extension)).string();
}

std::string dicomNumber(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.6g", v);  // DICOM DS: at most 16 characters
  return buf;
}

}  // namespace

void writeVolume(const std::string& path, const Grid& grid, const std::vector<float>& values) {
  quietItk();
  const std::string l = lower(path);
  itk::ImageIOBase::Pointer io;
  std::string extension;
  if (endsWith(l, ".nii.gz")) io = itk::NiftiImageIO::New(), extension = ".nii.gz";
  else if (endsWith(l, ".nii")) io = itk::NiftiImageIO::New(), extension = ".nii";
  else if (endsWith(l, ".nrrd")) io = itk::NrrdImageIO::New(), extension = ".nrrd";
  else if (endsWith(l, ".mha")) io = itk::MetaImageIO::New(), extension = ".mha";
  else
    fail(path, "unknown extension for an MRI volume; use .nii, .nii.gz, .nrrd or .mha");
  auto image = makeImage<FloatImage>(grid);
  std::copy(values.begin(), values.end(), image->GetBufferPointer());
  const std::string tmp = temporaryBeside(path, extension);
  auto writer = itk::ImageFileWriter<FloatImage>::New();
  writer->SetImageIO(io);
  writer->SetFileName(tmp);
  writer->SetUseCompression(extension != ".nii");
  writer->SetInput(image);
  std::error_code ec;
  try {
    writer->Update();
  } catch (const itk::ExceptionObject& e) {
    fs::remove(tmp, ec);
    fail(path, std::string("cannot write: ") + e.GetDescription());
  }
  fs::rename(tmp, path, ec);
  if (ec) {
    const std::string why = ec.message();
    fs::remove(tmp, ec);
    fail(path, "cannot move the written file into place: " + why);
  }
}

void writeDicom(const std::string& folder, const Grid& g, const std::vector<float>& values, const DicomTags& tags) {
  quietItk();
  std::error_code ec;
  fs::create_directories(folder, ec);
  if (ec || !fs::is_directory(folder)) fail(folder, "cannot create the folder: " + ec.message());
  if (fs::directory_iterator(folder, ec) != fs::directory_iterator())
    fail(folder, "the folder is not empty; a DICOM series is written into a new or empty folder (one series per folder)");

  using ShortImage = itk::Image<short, 3>;
  using SliceImage = itk::Image<short, 2>;
  auto volume = makeImage<ShortImage>(g);
  short* dst = volume->GetBufferPointer();
  for (std::size_t v = 0; v < values.size(); ++v)
    dst[v] = static_cast<short>(std::clamp(std::lround(values[v]), -32768L, 32767L));
  const Vec3 row = {g.direction[0], g.direction[3], g.direction[6]}, column = {g.direction[1], g.direction[4], g.direction[7]};
  const Vec3 axis_k = {g.direction[2], g.direction[5], g.direction[8]};
  const Vec3 normal = cross(row, column);
  std::string orientation;
  for (const Vec3& d : {row, column})
    for (int r = 0; r < 3; ++r) orientation += (orientation.empty() ? "" : "\\") + dicomNumber(d[r]);

  auto io = itk::GDCMImageIO::New();
  io->KeepOriginalUIDOn();
  using Writer = itk::ImageSeriesWriter<ShortImage, SliceImage>;
  auto writer = Writer::New();
  writer->SetInput(volume);
  writer->SetImageIO(io);
  Writer::DictionaryArrayType dictionaries;
  std::vector<std::unique_ptr<itk::MetaDataDictionary>> owned;
  std::vector<std::string> files;
  for (long k = 0; k < g.size[2]; ++k) {
    auto d = std::make_unique<itk::MetaDataDictionary>();
    const auto put = [&](const std::string& tag, const std::string& value) { itk::EncapsulateMetaData<std::string>(*d, tag, value); };
    put("0008|0016", "1.2.840.10008.5.1.4.1.1.4");  // MR Image Storage: keeps position and orientation
    put("0008|0018", tags.series_uid + "." + std::to_string(k + 1));
    put("0008|0060", "MR");
    put("0028|0004", "MONOCHROME2");
    put("0008|0008", "DERIVED\\SECONDARY");
    put("0008|103e", tags.description);
    put("0010|0010", tags.patient_name);
    put("0010|0020", tags.patient_id);
    put("0020|000d", tags.study_uid);
    put("0020|000e", tags.series_uid);
    put("0020|0052", tags.frame_uid);
    put("0020|0011", std::to_string(tags.series_number));
    put("0020|0013", std::to_string(k + 1));
    put("0020|0037", orientation);
    Vec3 p;
    for (int r = 0; r < 3; ++r) p[r] = g.origin_mm[r] + axis_k[r] * g.spacing_mm[2] * static_cast<double>(k);
    put("0020|0032", dicomNumber(p[0]) + "\\" + dicomNumber(p[1]) + "\\" + dicomNumber(p[2]));
    put("0020|1041", dicomNumber(dot(normal, p)));
    put("0018|0050", dicomNumber(g.spacing_mm[2]));
    put("0018|0088", dicomNumber(g.spacing_mm[2]));
    dictionaries.push_back(d.get());
    owned.push_back(std::move(d));
    char name[32];
    std::snprintf(name, sizeof name, "IM%05ld.dcm", k + 1);
    files.push_back((fs::path(folder) / name).string());
  }
  writer->SetMetaDataDictionaryArray(&dictionaries);
  writer->SetFileNames(files);
  try {
    writer->Update();
  } catch (const itk::ExceptionObject& e) {
    fail(folder, std::string("cannot write the DICOM series: ") + e.GetDescription());
  }
}

}  // namespace breast_sim::core::itk_bridge
