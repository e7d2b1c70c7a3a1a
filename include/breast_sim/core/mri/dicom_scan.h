#pragma once
/// @file dicom_scan.h
/// The structure of DICOM files checked before any DICOM library opens them. GDCM (which ITK reads
/// DICOM with) allocates the length a data element claims before it reads the value: one damaged 4 kB
/// file in a folder claiming 1.4 GB made GDCM allocate 1.4 GB while ITK scanned the folder. So
/// readMriVolume walks every element of every file of a DICOM folder here, reading only element headers,
/// and hands GDCM only files whose every length fits.

#include <map>
#include <string>
#include <vector>

namespace breast_sim::core {

/// What the walk of one file found.
struct DicomFileScan {
  bool is_dicom = false;        ///< a DICOM Part 10 file: a 128-byte preamble, then "DICM"
  std::string transfer_syntax;  ///< (0002,0010), e.g. "1.2.840.10008.1.2" (implicit VR little endian)
  std::string series_uid;       ///< (0020,000E) of the top-level data set; empty when absent
  bool has_pixel_data = false;  ///< the top-level data set holds Pixel Data (7FE0,0010): an image
};

/// Walks every data element of a DICOM Part 10 file by its headers alone: the meta information (group
/// 0002, explicit VR little endian), then the data set in its transfer syntax — implicit VR little
/// endian, explicit VR little endian (also every encapsulated, compressed syntax) or explicit VR big
/// endian. Each defined length must fit in what is left of the file (and of the item or sequence that
/// holds it); elements of undefined length (sequences, UN, encapsulated pixel data) are walked item by
/// item to their delimiters; a defined-length SQ, or a value in implicit VR or UN that starts with an
/// item tag, is walked as a sequence within its length (as GDCM parses it).
/// Sequences may nest at most kMaxDicomNesting deep.
/// @returns is_dicom = false, and nothing else read, for a file that is not DICOM Part 10 (shorter than
///          132 bytes, or no "DICM" at byte 128): such files are not DICOM here.
/// @throws std::runtime_error whose message starts with the path and says "damaged DICOM file" with the
///         element's tag, its byte offset, the length it claims and the bytes left, for: a length past
///         the end of the file (or of its item); an undefined length where none may be; an unknown VR;
///         an item or delimiter out of place; nesting deeper than the bound; a file that ends inside an
///         element's header. And for: a file that cannot be read; no transfer syntax in the meta
///         information; a data set in implicit VR whose first element is written with an explicit VR;
///         the deflated syntax (1.2.840.10008.1.2.1.99) or a transfer syntax that is not DICOM's.
DicomFileScan scanDicomFile(const std::string& path);

/// Deepest nesting of sequences scanDicomFile walks (real files nest a few levels).
constexpr int kMaxDicomNesting = 32;

/// The DICOM images of a folder by series.
struct DicomFolder {
  /// SeriesInstanceUID → the series' image files (paths), sorted by name.
  std::map<std::string, std::vector<std::string>> series;
};

/// Scans every regular file of `folder` (not its subfolders) with scanDicomFile and keeps the DICOM
/// Part 10 files that hold pixel data. Other files are skipped: those that are not DICOM Part 10 (notes,
/// thumbnails, files without the preamble) and DICOM files without an image (DICOMDIR, reports,
/// presentation states). A damaged DICOM file is an error, not skipped, because a skipped slice would
/// silently shorten or split the volume.
/// @throws std::runtime_error naming the file: what scanDicomFile throws; an image without a
///         SeriesInstanceUID. Naming the folder: a folder that cannot be listed.
DicomFolder scanDicomFolder(const std::string& folder);

}  // namespace breast_sim::core
