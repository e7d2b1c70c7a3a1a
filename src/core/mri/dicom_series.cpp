// dicom_series.h: the checks of each slice and of the series, sorting along the slice normal, and the
// voxels through readDicomPixels.
#include "dicom_series.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace breast_sim::core {

namespace {

[[noreturn]] void fail(const std::string& path, const std::string& what) { throw std::runtime_error(path + ": " + what); }

std::string fmt(double v, int precision) {
  char s[64];
  std::snprintf(s, sizeof s, "%.*f", precision, v);
  return s;
}

using Vec3 = std::array<double, 3>;
double dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
Vec3 minus(const Vec3& a, const Vec3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
Vec3 position(const DicomFileScan& s) { return {s.position_mm[0], s.position_mm[1], s.position_mm[2]}; }
Vec3 rowOf(const DicomFileScan& s) { return {s.orientation[0], s.orientation[1], s.orientation[2]}; }
Vec3 columnOf(const DicomFileScan& s) { return {s.orientation[3], s.orientation[4], s.orientation[5]}; }

bool compressed(const std::string& syntax) {
  return syntax != "1.2.840.10008.1.2" && syntax != "1.2.840.10008.1.2.1" && syntax != "1.2.840.10008.1.2.2";
}

// What one slice must have to be read; its file is named.
void checkSlice(DicomFileScan& s) {
  const std::string again = "; the file is damaged or was written wrongly: export the series again";
  if (compressed(s.transfer_syntax) || s.encapsulated)
    fail(s.path, "compressed DICOM (transfer syntax " + s.transfer_syntax +
                     "), which is not read; export the series uncompressed, or convert it with `gdcmconv --raw`");
  if (s.frames > 1)
    fail(s.path, "a multi-frame DICOM file (" + std::to_string(s.frames) +
                     " frames), which is not read; export the series as single-frame (classic) images");
  if (!s.bad_value.empty()) fail(s.path, s.bad_value + again);
  if (s.samples_per_pixel != 1)
    fail(s.path, "voxels with " + std::to_string(s.samples_per_pixel) +
                     " components (e.g. RGB); the MRI must be a scalar (magnitude) image");
  if (s.photometric != "MONOCHROME2" && s.photometric != "MONOCHROME1")
    fail(s.path, "PhotometricInterpretation (0028,0004) is '" + s.photometric +
                     "'; the MRI must be a greyscale image (MONOCHROME2)");
  if (s.rows < 1 || s.columns < 1)
    fail(s.path, "no image size: Rows (0028,0010) and Columns (0028,0011) are " + std::to_string(s.rows) + " and " +
                     std::to_string(s.columns) + again);
  if (s.bits_allocated != 8 && s.bits_allocated != 16 && s.bits_allocated != 32)
    fail(s.path, "BitsAllocated (0028,0100) is " + std::to_string(s.bits_allocated) + "; 8, 16 or 32 bits are read");
  if (s.bits_stored == 0) s.bits_stored = s.bits_allocated;
  if (s.high_bit < 0) s.high_bit = s.bits_stored - 1;
  if (s.bits_stored > s.bits_allocated || s.high_bit < s.bits_stored - 1 || s.high_bit >= s.bits_allocated)
    fail(s.path, "BitsStored (0028,0101) " + std::to_string(s.bits_stored) + " and HighBit (0028,0102) " +
                     std::to_string(s.high_bit) + " do not fit in BitsAllocated " + std::to_string(s.bits_allocated) + again);
  for (const auto& [has, what] : {std::pair<bool, const char*>{s.has_position, "ImagePositionPatient (0020,0032)"},
                                  {s.has_orientation, "ImageOrientationPatient (0020,0037)"},
                                  {s.has_spacing, "PixelSpacing (0028,0030)"}})
    if (!has) fail(s.path, std::string("no ") + what + ", which places the slice in the volume; export the series again");
  if (!(s.pixel_spacing_mm[0] > 0 && s.pixel_spacing_mm[1] > 0))
    fail(s.path, "PixelSpacing (0028,0030) is " + fmt(s.pixel_spacing_mm[0], 4) + "\\" + fmt(s.pixel_spacing_mm[1], 4) +
                     " mm; both must be positive");
  const std::uint64_t needed = static_cast<std::uint64_t>(s.rows) * static_cast<std::uint64_t>(s.columns) *
                               static_cast<std::uint64_t>(s.bits_allocated / 8);
  if (s.pixel_length < needed)
    fail(s.path, "the pixel data hold " + std::to_string(s.pixel_length) + " bytes, where " + std::to_string(s.rows) +
                     " rows x " + std::to_string(s.columns) + " columns x " + std::to_string(s.bits_allocated / 8) +
                     " bytes need " + std::to_string(needed) + again);
}

std::string typeName(const DicomFileScan& s) {
  const char* name = s.bits_allocated == 8 ? "char" : s.bits_allocated == 16 ? "short" : "int";
  return (s.is_signed ? "" : "unsigned_") + std::string(name);  // ITK's names
}

}  // namespace

MriVolume readDicomSeries(const std::string& folder, const std::string& uid, std::vector<DicomFileScan> slices,
                          long max_voxels, double tolerance) {
  const std::string where = folder + " (series " + uid + ")";
  std::string description;
  for (DicomFileScan& s : slices) {
    checkSlice(s);
    if (description.empty()) description = s.series_description;
  }
  const DicomFileScan first = slices.front();
  if (slices.size() == 1)
    fail(where, "a 2-D image (one slice of " + std::to_string(first.columns) + " x " + std::to_string(first.rows) +
                    " voxels); the MRI must be a 3-D volume: copy the whole series into the folder");
  const auto differs = [](const Vec3& a, const Vec3& b) {
    return std::max({std::abs(a[0] - b[0]), std::abs(a[1] - b[1]), std::abs(a[2] - b[2])}) > 1e-4;
  };
  for (const DicomFileScan& h : slices) {
    if (h.columns != first.columns || h.rows != first.rows)
      fail(h.path, "a slice of " + std::to_string(h.columns) + " x " + std::to_string(h.rows) + " voxels in " + where +
                       " whose first slice has " + std::to_string(first.columns) + " x " + std::to_string(first.rows) +
                       "; the series mixes acquisitions: give the series UID of one of them");
    if (differs(rowOf(h), rowOf(first)) || differs(columnOf(h), columnOf(first)))
      fail(h.path, "a slice orientation (ImageOrientationPatient) that differs from the first slice's in " + where +
                       "; the series mixes acquisitions (e.g. a localizer): give the series UID of one of them");
    if (std::abs(h.pixel_spacing_mm[0] - first.pixel_spacing_mm[0]) + std::abs(h.pixel_spacing_mm[1] - first.pixel_spacing_mm[1]) >
        1e-4 * std::max(first.pixel_spacing_mm[0], first.pixel_spacing_mm[1]))
      fail(h.path, "a pixel spacing that differs from the first slice's in " + where);
  }
  // Sort along the normal and check the spacing.
  const Vec3 row = rowOf(first), column = columnOf(first);
  Vec3 normal = cross(row, column);
  const double length = std::sqrt(dot(normal, normal));
  if (!(length >= 0.5)) fail(first.path, "ImageOrientationPatient does not give two orthogonal directions");
  for (double& x : normal) x /= length;
  std::stable_sort(slices.begin(), slices.end(), [&](const DicomFileScan& a, const DicomFileScan& b) {
    return dot(normal, position(a)) < dot(normal, position(b));
  });
  const int n = static_cast<int>(slices.size());
  std::vector<double> gaps(n - 1);
  for (int s = 0; s + 1 < n; ++s) gaps[s] = dot(normal, minus(position(slices[s + 1]), position(slices[s])));
  std::vector<double> sorted = gaps;
  std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
  const double spacing = sorted[sorted.size() / 2];
  const auto along = [&](int s) { return fmt(dot(normal, position(slices[s])), 2); };
  for (int s = 0; s + 1 < n; ++s)
    if (gaps[s] < 1e-3)
      fail(where, "slices " + std::to_string(s + 1) + " and " + std::to_string(s + 2) + " (" + slices[s].path + ", " +
                      slices[s + 1].path + ") lie at the same position (" + along(s) +
                      " mm along the slice normal): the series holds several volumes (echoes, phases or repeats); "
                      "export one volume");
  for (int s = 0; s + 1 < n; ++s)
    if (std::abs(gaps[s] - spacing) > tolerance * spacing)
      fail(where, "slices are not evenly spaced: slice " + std::to_string(s + 2) + " (" + slices[s + 1].path + ", at " +
                      along(s + 1) + " mm along the slice normal) follows slice " + std::to_string(s + 1) + " (at " +
                      along(s) + " mm) by " + fmt(gaps[s], 2) + " mm where the slices are " + fmt(spacing, 2) +
                      " mm apart: a slice is missing or the series mixes acquisitions; export the complete series");
  // The positions must lie on one line along the normal (no in-plane shift, i.e. no gantry tilt).
  for (int s = 1; s < n; ++s) {
    const Vec3 d = minus(position(slices[s]), position(slices[0]));
    const double a = dot(normal, d);
    const Vec3 off = {d[0] - a * normal[0], d[1] - a * normal[1], d[2] - a * normal[2]};
    if (std::sqrt(dot(off, off)) > 0.01 * std::max(spacing, 1.0) + 1e-3)
      fail(where, "slice " + std::to_string(s + 1) + " (" + slices[s].path +
                      ") is shifted within its plane against the first slice: a sheared grid (gantry tilt) is not "
                      "supported; resample the series onto an orthogonal grid first");
  }
  if (first.columns * first.rows > max_voxels / n)
    fail(where, std::to_string(first.columns) + " x " + std::to_string(first.rows) + " x " + std::to_string(n) +
                    " voxels, more than the " + std::to_string(max_voxels) +
                    " accepted (MriReadOptions::max_voxels); crop or resample the series first");

  MriVolume out;
  ImageGeometry& g = out.image.geometry;
  g.size = Eigen::Vector3i(static_cast<int>(first.columns), static_cast<int>(first.rows), n);
  // PixelSpacing lists the spacing between rows (along j) first, then between columns (along i).
  g.spacing_m = 1e-3 * Eigen::Vector3d(first.pixel_spacing_mm[1], first.pixel_spacing_mm[0], spacing);
  for (int r = 0; r < 3; ++r) {
    g.origin_m[r] = 1e-3 * slices.front().position_mm[r];
    g.direction(r, 0) = row[r];
    g.direction(r, 1) = column[r];
    g.direction(r, 2) = normal[r];
  }
  const std::size_t per_slice = static_cast<std::size_t>(first.columns) * static_cast<std::size_t>(first.rows);
  out.image.values.resize(per_slice * static_cast<std::size_t>(n));
  for (int s = 0; s < n; ++s) readDicomPixels(slices[s], out.image.values.data() + per_slice * static_cast<std::size_t>(s));
  out.info.format = "DICOM";
  out.info.series_uid = uid;
  out.info.series_description = description;
  out.info.files = n;
  out.info.pixel_type = typeName(first);
  return out;
}

}  // namespace breast_sim::core
