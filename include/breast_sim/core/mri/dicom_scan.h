#pragma once
/// @file dicom_scan.h
/// DICOM files read by the core: each file's data elements walked by their headers, the attributes an
/// MRI volume needs decoded, and native pixel data converted to float. GDCM (which ITK reads DICOM with)
/// is not used to read: it allocates the length an element claims before reading it (1.4 GB for a
/// damaged 4 kB file), and Debian builds it with its 3,000-odd assertions active, so a value out of
/// its range (a SamplesPerPixel of 2) aborts the process. ITK and GDCM still write DICOM series
/// (mri_volume.h, writeDicomSeries).
///
/// Read: DICOM Part 10 files (a 128-byte preamble, then "DICM"), single-frame images of one sample per
/// pixel (MONOCHROME1 or MONOCHROME2; values as stored, MONOCHROME1 not inverted, as ITK reads them),
/// 8, 16 or 32 bits allocated, in implicit VR little endian, explicit VR little endian or explicit VR
/// big endian. Not read (a clear error): compressed transfer syntaxes (JPEG, JPEG-LS, JPEG 2000, RLE,
/// MPEG; convert with `gdcmconv --raw`), deflated data sets, multi-frame files (enhanced MR: export
/// classic single-frame images).

#include <cstdint>
#include <map>
#include <string>
#include <vector>

namespace breast_sim::core {

/// What the walk of one file found: whether it is DICOM, and the attributes of its top-level data set
/// that an image volume needs (each with a flag whether the file has it).
struct DicomFileScan {
  std::string path;
  bool is_dicom = false;        ///< a DICOM Part 10 file: a 128-byte preamble, then "DICM"
  std::string transfer_syntax;  ///< (0002,0010), e.g. "1.2.840.10008.1.2" (implicit VR little endian)
  bool big_endian = false;      ///< the data set's byte order (explicit VR big endian)
  std::string series_uid;       ///< (0020,000E); empty when absent
  std::string series_description;  ///< (0008,103E)
  bool has_pixel_data = false;  ///< Pixel Data (7FE0,0010): an image
  bool encapsulated = false;    ///< the pixel data are compressed fragments
  std::uint64_t pixel_offset = 0, pixel_length = 0;  ///< native pixel data: where in the file [bytes]
  long rows = 0, columns = 0;   ///< (0028,0010), (0028,0011); 0 when absent
  long frames = 1;              ///< (0028,0008), 1 when absent
  int samples_per_pixel = 1;    ///< (0028,0002)
  std::string photometric;      ///< (0028,0004), e.g. "MONOCHROME2"
  int bits_allocated = 0, bits_stored = 0, high_bit = -1;  ///< (0028,0100) … (0028,0102); 0 / −1 when absent
  bool is_signed = false;       ///< (0028,0103) pixel representation 1
  double rescale_slope = 1.0, rescale_intercept = 0.0;  ///< (0028,1053), (0028,1052)
  bool has_position = false, has_orientation = false, has_spacing = false;
  double position_mm[3] = {0, 0, 0};  ///< (0020,0032) ImagePositionPatient [mm, LPS]
  double orientation[6] = {1, 0, 0, 0, 1, 0};  ///< (0020,0037): the row direction (axis i), then the column direction (axis j)
  double pixel_spacing_mm[2] = {1, 1};  ///< (0028,0030): between rows (along j), between columns (along i) [mm]
  /// The first of these attributes whose value could not be decoded, e.g. "ImagePositionPatient
  /// (0020,0032) is '1\2': not 3 numbers"; empty when all could.
  std::string bad_value;
};

/// Walks every data element of a DICOM Part 10 file by its headers alone, reading only the values of
/// the attributes above: the meta information (group 0002, explicit VR little endian), then the data set
/// in its transfer syntax (implicit VR little endian; explicit VR little endian, also for the
/// compressed syntaxes; explicit VR big endian). Each defined length must fit in what is left of the
/// file (and of the item or sequence holding it); elements of undefined length (sequences, UN,
/// encapsulated pixel data) are walked item by item to their delimiters, and a defined-length SQ as a
/// sequence within its length. Sequences may nest at most kMaxDicomNesting deep. Two writer bugs are read
/// as GDCM reads them: an implicit-VR value of 13 bytes holds 10 (a GE writer), a UL of 6 bytes in group
/// 0009 holds 4 (a Siemens writer). An attribute's value is checked when it is used
/// (readDicomSeries), not here.
/// @returns is_dicom = false, and nothing else read, for a file that is not DICOM Part 10 (shorter than
///          132 bytes, or no "DICM" at byte 128): such files are not DICOM here.
/// @throws std::runtime_error whose message starts with the path and says "damaged DICOM file" with the
///         element's tag, its byte offset, the length it claims and the bytes left, for: a length past
///         the end of the file (or of its item); an undefined length where none may be; an unknown VR;
///         an item or delimiter out of place; nesting deeper than the bound; a file that ends inside an
///         element's header; an attribute of the list above longer than 1 kB. And for: a file that
///         cannot be read; no transfer syntax in the meta information; a data set in implicit VR whose
///         first element is written with an explicit VR; the deflated syntax (1.2.840.10008.1.2.1.99)
///         or a transfer syntax that is not DICOM's.
DicomFileScan scanDicomFile(const std::string& path);

/// Deepest nesting of sequences scanDicomFile walks (real files nest a few levels).
constexpr int kMaxDicomNesting = 32;

/// The DICOM images of a folder by series.
struct DicomFolder {
  /// SeriesInstanceUID → the series' images (their scans), sorted by file name.
  std::map<std::string, std::vector<DicomFileScan>> series;
};

/// Scans every regular file of `folder` (not its subfolders) with scanDicomFile and keeps the DICOM
/// Part 10 files that hold pixel data. Other files are skipped: those that are not DICOM Part 10 (notes,
/// thumbnails, files without the preamble) and DICOM files without an image (DICOMDIR, reports,
/// presentation states). A damaged DICOM file is an error, not skipped, because a skipped slice would
/// silently shorten or split the volume.
/// @throws std::runtime_error naming the file: what scanDicomFile throws; an image without a
///         SeriesInstanceUID. Naming the folder: a folder that cannot be listed.
DicomFolder scanDicomFolder(const std::string& folder);

/// The native pixel values of one scanned single-frame image as float, row by row (i fastest):
/// the stored bits (bits_stored below high_bit), sign-extended when signed, times rescale_slope plus
/// rescale_intercept.
/// @pre the scan's image attributes passed readDicomSeries's checks (native data, one sample, 8, 16 or
///      32 bits allocated, pixel_length ≥ rows · columns · bits_allocated / 8).
/// @throws std::runtime_error naming the file when it cannot be read (or changed since the scan).
void readDicomPixels(const DicomFileScan& scan, float* out);

}  // namespace breast_sim::core
