// dicom_scan.h: a walk over DICOM data element headers (PS3.5 section 7), reading values only for the
// attributes of an image volume and skipping the rest by its length; native pixel data converted to
// float (PS3.5 section 8). Files are read through a window of 64 kB, so a folder of slices costs about
// one read per file for the walk plus one for the pixels.
#include "breast_sim/core/mri/dicom_scan.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <stdexcept>
#include <system_error>
#include <vector>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

namespace breast_sim::core {

namespace {

namespace fs = std::filesystem;

[[noreturn]] void fail(const std::string& path, const std::string& what) { throw std::runtime_error(path + ": " + what); }

constexpr std::uint32_t kUndefined = 0xFFFFFFFFu;
constexpr std::uint64_t kNoEnd = ~std::uint64_t{0};  // an item or sequence of undefined length

struct Tag {
  std::uint16_t group = 0, element = 0;
  bool operator==(const Tag& o) const { return group == o.group && element == o.element; }
};
constexpr Tag kItem{0xFFFE, 0xE000}, kItemEnd{0xFFFE, 0xE00D}, kSequenceEnd{0xFFFE, 0xE0DD};
constexpr Tag kTransferSyntax{0x0002, 0x0010}, kSeriesUid{0x0020, 0x000E}, kPixelData{0x7FE0, 0x0010};
constexpr std::uint64_t kMaxAttributeBytes = 1024;  // an attribute of DicomFileScan, as text or binary

std::string tagText(Tag t) {
  char s[16];
  std::snprintf(s, sizeof s, "(%04X,%04X)", t.group, t.element);
  return s;
}

enum class Syntax { kImplicitLittle, kExplicitLittle, kExplicitBig };

// The file, read through a window: element headers are small and mostly consecutive.
class FileWindow {
 public:
  explicit FileWindow(const std::string& path) : path_(path) {
    fd_ = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd_ < 0) fail(path, std::string("cannot open for reading (") + std::strerror(errno) + ")");
    struct stat st {};
    if (::fstat(fd_, &st) != 0 || !S_ISREG(st.st_mode)) {
      ::close(fd_);
      fail(path, "is not a regular file");
    }
    size_ = static_cast<std::uint64_t>(st.st_size);
  }
  ~FileWindow() { ::close(fd_); }
  FileWindow(const FileWindow&) = delete;
  FileWindow& operator=(const FileWindow&) = delete;

  std::uint64_t size() const { return size_; }

  /// n ≤ kWindow bytes at `offset`, which the caller has checked lie within the file.
  const unsigned char* at(std::uint64_t offset, std::size_t n) {
    if (offset < begin_ || offset + n > begin_ + filled_) {
      begin_ = offset;
      filled_ = 0;
      const std::size_t want = static_cast<std::size_t>(std::min<std::uint64_t>(kWindow, size_ - offset));
      while (filled_ < want) {
        const ssize_t got = ::pread(fd_, buffer_.get() + filled_, want - filled_, static_cast<off_t>(offset + filled_));
        if (got < 0 && errno == EINTR) continue;
        if (got <= 0) fail(path_, std::string("read error (") + (got < 0 ? std::strerror(errno) : "the file shrank") + ")");
        filled_ += static_cast<std::size_t>(got);
      }
    }
    return buffer_.get() + (offset - begin_);
  }

  static constexpr std::size_t kWindow = 64 * 1024;

 private:
  std::string path_;
  int fd_ = -1;
  std::uint64_t size_ = 0;
  std::uint64_t begin_ = 0;
  std::size_t filled_ = 0;
  std::unique_ptr<unsigned char[]> buffer_{new unsigned char[kWindow]};  // filled by pread before it is read
};

bool isLongVr(const char* vr) {
  static const char* const kLong[] = {"OB", "OD", "OF", "OL", "OV", "OW", "SQ", "SV", "UC", "UN", "UR", "UT", "UV"};
  return std::any_of(std::begin(kLong), std::end(kLong), [&](const char* v) { return vr[0] == v[0] && vr[1] == v[1]; });
}

bool isShortVr(const char* vr) {
  static const char* const kShort[] = {"AE", "AS", "AT", "CS", "DA", "DS", "DT", "FL", "FD", "IS", "LO",
                                       "LT", "PN", "SH", "SL", "SS", "ST", "TM", "UI", "UL", "US"};
  return std::any_of(std::begin(kShort), std::end(kShort), [&](const char* v) { return vr[0] == v[0] && vr[1] == v[1]; });
}

std::string trimmedUid(const unsigned char* p, std::size_t n) {
  std::string s(reinterpret_cast<const char*>(p), n);
  while (!s.empty() && (s.back() == '\0' || s.back() == ' ')) s.pop_back();
  return s;
}

class Walker {
 public:
  Walker(const std::string& path, FileWindow& file, DicomFileScan& out) : path_(path), file_(file), out_(out) {}

  void run() {
    std::uint64_t p = 132;
    // The meta information: explicit VR little endian, as long as the group is 0002.
    if (!startsGroup(p, 0x0002)) damaged("no meta information (group 0002) follows 'DICM' at byte 132");
    in_meta_ = true;
    while (startsGroup(p, 0x0002)) p = element(p, file_.size(), Syntax::kExplicitLittle, 0);
    in_meta_ = false;
    const Syntax syntax = syntaxOf(out_.transfer_syntax);
    out_.big_endian = syntax == Syntax::kExplicitBig;
    // A writer bug (explicit VRs in a file that declares implicit VR): refused by name rather than
    // read as other elements.
    if (syntax == Syntax::kImplicitLittle && p + 6 <= file_.size()) {
      const unsigned char* h = file_.at(p, 6);
      const char vr[2] = {static_cast<char>(h[4]), static_cast<char>(h[5])};
      if (isLongVr(vr) || isShortVr(vr))
        damaged("the meta information gives implicit VR (1.2.840.10008.1.2), but the data set at byte " +
                std::to_string(p) + " is written with explicit VRs ('" + std::string(vr, 2) + "')");
    }
    dataSet(p, file_.size(), file_.size(), syntax, 0);
  }

 private:
  struct Header {
    Tag tag;
    char vr[2] = {0, 0};
    bool explicit_vr = false;
    std::uint32_t length = 0;
    std::uint64_t value = 0;  // offset of the value
  };

  [[noreturn]] void damaged(const std::string& what) const {
    fail(path_, "a damaged DICOM file (" + std::to_string(file_.size()) + " bytes): " + what +
                    "; the file is truncated or damaged: export the series again, or remove the file from the folder");
  }

  std::uint16_t u16(const unsigned char* p, bool big) const {
    return big ? static_cast<std::uint16_t>(p[0] << 8 | p[1]) : static_cast<std::uint16_t>(p[1] << 8 | p[0]);
  }
  std::uint32_t u32(const unsigned char* p, bool big) const {
    return big ? (std::uint32_t{p[0]} << 24 | std::uint32_t{p[1]} << 16 | std::uint32_t{p[2]} << 8 | p[3])
               : (std::uint32_t{p[3]} << 24 | std::uint32_t{p[2]} << 16 | std::uint32_t{p[1]} << 8 | p[0]);
  }

  bool startsGroup(std::uint64_t p, std::uint16_t group) {
    return p + 4 <= file_.size() && u16(file_.at(p, 2), false) == group;
  }

  // Where a container's content must end: the end of its item or sequence, or of the file.
  std::string within(std::uint64_t limit) const {
    return limit == file_.size() ? "in the file" : "before the end of its enclosing item at byte " + std::to_string(limit);
  }

  Tag tagAt(std::uint64_t p, std::uint64_t limit, Syntax s) {
    if (p + 4 > limit) damaged("the data end inside an element's tag at byte " + std::to_string(p) + ", " + within(limit));
    const unsigned char* h = file_.at(p, 4);
    const bool big = s == Syntax::kExplicitBig;
    return {u16(h, big), u16(h + 2, big)};
  }

  Header header(std::uint64_t p, std::uint64_t limit, Syntax s) {
    Header h;
    h.tag = tagAt(p, limit, s);
    const bool big = s == Syntax::kExplicitBig;
    const auto need = [&](std::uint64_t n) {
      if (p + n > limit)
        damaged("element " + tagText(h.tag) + " at byte " + std::to_string(p) + " has a header of " + std::to_string(n) +
                " bytes, but only " + std::to_string(limit - p) + " follow " + within(limit));
    };
    need(8);
    const unsigned char* b = file_.at(p, 8);
    if (h.tag.group == 0xFFFE || s == Syntax::kImplicitLittle) {  // items and delimiters carry no VR
      h.length = u32(b + 4, big);
      h.value = p + 8;
      return h;
    }
    h.explicit_vr = true;
    h.vr[0] = static_cast<char>(b[4]);
    h.vr[1] = static_cast<char>(b[5]);
    if (isShortVr(h.vr)) {
      h.length = u16(b + 6, big);
      h.value = p + 8;
      // A Siemens writer's UL of 6 bytes holds 4; read as GDCM reads it.
      if (h.length == 6 && h.vr[0] == 'U' && h.vr[1] == 'L' && h.tag.group == 0x0009) h.length = 4;
    } else if (isLongVr(h.vr)) {
      need(12);
      h.length = u32(file_.at(p + 8, 4), big);
      h.value = p + 12;
    } else {
      char vr[8];
      std::snprintf(vr, sizeof vr, "%02X %02X", b[4], b[5]);
      damaged("element " + tagText(h.tag) + " at byte " + std::to_string(p) + " has the unknown VR bytes " + vr);
    }
    return h;
  }

  void requireFits(const Header& h, std::uint64_t limit) const {
    if (h.length > limit - h.value)
      damaged("data element " + tagText(h.tag) + " at byte " + std::to_string(h.value) + " claims " +
              std::to_string(h.length) + " bytes, but only " + std::to_string(limit - h.value) + " follow " + within(limit));
  }

  void requireDepth(int depth, std::uint64_t p) const {
    if (depth > kMaxDicomNesting)
      damaged("sequences nest deeper than " + std::to_string(kMaxDicomNesting) + " levels at byte " + std::to_string(p));
  }

  // One element at p; returns the offset after it.
  std::uint64_t element(std::uint64_t p, std::uint64_t limit, Syntax s, int depth) {
    Header h = header(p, limit, s);
    if (h.tag.group == 0xFFFE)
      damaged("an item tag " + tagText(h.tag) + " at byte " + std::to_string(p) + " where a data element belongs");
    // A GE writer's implicit-VR value of 13 bytes holds 10 (except in the two elements its fix left
    // alone); read as GDCM reads it.
    if (!h.explicit_vr && h.length == 13 && !(h.tag == Tag{0x0008, 0x0070}) && !(h.tag == Tag{0x0008, 0x0080})) h.length = 10;
    const bool sq = h.explicit_vr && h.vr[0] == 'S' && h.vr[1] == 'Q';
    const bool un = h.explicit_vr && h.vr[0] == 'U' && h.vr[1] == 'N';
    const bool ob_ow = h.explicit_vr && h.vr[0] == 'O' && (h.vr[1] == 'B' || h.vr[1] == 'W');
    // UN holds its sequence in implicit VR little endian (PS3.5 6.2.2).
    const Syntax nested = un ? Syntax::kImplicitLittle : s;
    if (depth == 0 && h.tag == kPixelData) out_.has_pixel_data = true;
    if (h.length == kUndefined) {
      if (sq) return sequence(h.value, kNoEnd, limit, nested, depth + 1);
      if (h.tag == kPixelData && (ob_ow || un || !h.explicit_vr)) {
        if (depth == 0) out_.encapsulated = true;
        return fragments(h.value, limit, s);
      }
      if (un || !h.explicit_vr) return sequence(h.value, kNoEnd, limit, nested, depth + 1);
      damaged("element " + tagText(h.tag) + " at byte " + std::to_string(p) + " of VR " + std::string(h.vr, 2) +
              " has an undefined length, which only sequences, UN and encapsulated pixel data may have");
    }
    requireFits(h, limit);
    const std::uint64_t end = h.value + h.length;
    if (sq) {
      sequence(h.value, end, end, nested, depth + 1);  // it stops exactly at `end` or throws
      return end;
    }
    if (in_meta_ && h.tag == kTransferSyntax) {
      out_.transfer_syntax = trimmedUid(valueBytes(h), h.length);
    } else if (!in_meta_ && depth == 0) {
      if (h.tag == kPixelData) {
        out_.pixel_offset = h.value;
        out_.pixel_length = h.length;
      } else {
        attribute(h, s);
      }
    }
    return end;
  }

  const unsigned char* valueBytes(const Header& h) {
    if (h.length > kMaxAttributeBytes)
      damaged("the value of " + tagText(h.tag) + " at byte " + std::to_string(h.value) + " is " + std::to_string(h.length) +
              " bytes long; at most " + std::to_string(kMaxAttributeBytes) + " are expected");
    return file_.at(h.value, h.length);
  }

  // The value of one of DicomFileScan's attributes, decoded; anything else is skipped.
  void attribute(const Header& h, Syntax s) {
    const std::uint32_t key = std::uint32_t{h.tag.group} << 16 | h.tag.element;
    switch (key) {
      case 0x0020000E: case 0x0008103E: case 0x00280010: case 0x00280011: case 0x00280002: case 0x00280100:
      case 0x00280101: case 0x00280102: case 0x00280103: case 0x00280008: case 0x00280004: case 0x00200032:
      case 0x00200037: case 0x00280030: case 0x00281052: case 0x00281053: break;
      default: return;
    }
    const unsigned char* v = valueBytes(h);
    const std::string text = trimmedUid(v, h.length);  // the text value, its padding removed
    const auto us = [&](const char* name, long& into) {
      if (h.length < 2) return bad(name, h.tag, "holds " + std::to_string(h.length) + " bytes, not an unsigned short");
      into = u16(v, s == Syntax::kExplicitBig);
    };
    const auto ds = [&](const char* name, double* into, int count) {
      if (decimals(text, into, count)) return true;
      bad(name, h.tag, "is '" + printable(text) + "': not " + std::to_string(count) + " finite number" + (count > 1 ? "s" : ""));
      return false;
    };
    long n = 0;
    switch (key) {
      case 0x0020000E:
        if (h.length > 64) damaged("the UID (0020,000E) at byte " + std::to_string(h.value) + " is " + std::to_string(h.length) + " bytes long; a UID has at most 64");
        out_.series_uid = text;
        break;
      case 0x0008103E: out_.series_description = text; break;
      case 0x00280010: us("Rows", out_.rows); break;
      case 0x00280011: us("Columns", out_.columns); break;
      case 0x00280002: us("SamplesPerPixel", n), out_.samples_per_pixel = static_cast<int>(n); break;
      case 0x00280100: us("BitsAllocated", n), out_.bits_allocated = static_cast<int>(n); break;
      case 0x00280101: us("BitsStored", n), out_.bits_stored = static_cast<int>(n); break;
      case 0x00280102: n = -1, us("HighBit", n), out_.high_bit = static_cast<int>(n); break;
      case 0x00280103: us("PixelRepresentation", n), out_.is_signed = n == 1; break;
      case 0x00280004: out_.photometric = text; break;
      case 0x00280008: {
        double frames = 1;
        if (!decimals(text, &frames, 1) || frames != std::floor(frames) || frames < 1 || frames > 1e9)
          bad("NumberOfFrames", h.tag, "is '" + printable(text) + "': not a whole number from 1");
        else out_.frames = static_cast<long>(frames);
        break;
      }
      case 0x00200032: out_.has_position = ds("ImagePositionPatient", out_.position_mm, 3); break;
      case 0x00200037: out_.has_orientation = ds("ImageOrientationPatient", out_.orientation, 6); break;
      case 0x00280030: out_.has_spacing = ds("PixelSpacing", out_.pixel_spacing_mm, 2); break;
      case 0x00281052: ds("RescaleIntercept", &out_.rescale_intercept, 1); break;
      case 0x00281053: ds("RescaleSlope", &out_.rescale_slope, 1); break;
    }
  }

  void bad(const char* name, Tag t, const std::string& what) {
    if (out_.bad_value.empty()) out_.bad_value = std::string(name) + " " + tagText(t) + " " + what;
  }

  // `count` backslash-separated decimal numbers (DS, IS), each finite.
  static bool decimals(const std::string& text, double* into, int count) {
    std::size_t start = 0;
    for (int i = 0; i < count; ++i) {
      const std::size_t stop = i + 1 < count ? text.find('\\', start) : text.size();
      if (stop == std::string::npos) return false;
      std::string part = text.substr(start, stop - start);
      while (!part.empty() && part.front() == ' ') part.erase(part.begin());
      while (!part.empty() && part.back() == ' ') part.pop_back();
      char* end = nullptr;
      const double x = std::strtod(part.c_str(), &end);
      if (part.empty() || end != part.c_str() + part.size() || !std::isfinite(x)) return false;
      into[i] = x;
      start = stop + 1;
    }
    return true;
  }

  static std::string printable(const std::string& s) {
    std::string out = s.substr(0, 60);
    for (char& c : out)
      if (static_cast<unsigned char>(c) < 32 || static_cast<unsigned char>(c) > 126) c = '?';
    return out;
  }

  // The elements of a data set from p: to `end`, or (end = kNoEnd) to its item delimiter (FFFE,E00D).
  std::uint64_t dataSet(std::uint64_t p, std::uint64_t end, std::uint64_t limit, Syntax s, int depth) {
    for (;;) {
      if (end != kNoEnd && p == end) return p;
      if (end == kNoEnd && p >= limit)
        damaged("an item of undefined length at depth " + std::to_string(depth) + " has no item delimiter (FFFE,E00D) " +
                within(limit));
      const Tag t = tagAt(p, limit, s);
      if (t == kItemEnd) {
        if (end != kNoEnd)
          damaged("an item delimiter (FFFE,E00D) at byte " + std::to_string(p) + " inside an item of defined length");
        header(p, limit, s);  // its 8 bytes must be there
        return p + 8;
      }
      p = element(p, limit, s, depth);
    }
  }

  // The items of a sequence from p: to `end`, or (end = kNoEnd) to its delimiter (FFFE,E0DD).
  std::uint64_t sequence(std::uint64_t p, std::uint64_t end, std::uint64_t limit, Syntax s, int depth) {
    requireDepth(depth, p);
    for (;;) {
      if (end != kNoEnd && p == end) return p;
      const Header h = header(p, limit, s);
      if (h.tag == kSequenceEnd) {
        if (end != kNoEnd)
          damaged("a sequence delimiter (FFFE,E0DD) at byte " + std::to_string(p) + " inside a sequence of defined length");
        return h.value;
      }
      if (!(h.tag == kItem))
        damaged("a sequence holds " + tagText(h.tag) + " at byte " + std::to_string(p) + " where an item (FFFE,E000) belongs");
      if (h.length == kUndefined) {
        p = dataSet(h.value, kNoEnd, limit, s, depth);
      } else {
        requireFits(h, limit);
        p = dataSet(h.value, h.value + h.length, h.value + h.length, s, depth);
      }
    }
  }

  // Encapsulated pixel data: items of defined length (the offset table, the fragments) to (FFFE,E0DD).
  std::uint64_t fragments(std::uint64_t p, std::uint64_t limit, Syntax s) {
    for (;;) {
      const Header h = header(p, limit, s);
      if (h.tag == kSequenceEnd) return h.value;
      if (!(h.tag == kItem) || h.length == kUndefined)
        damaged("encapsulated pixel data hold " + tagText(h.tag) + (h.length == kUndefined ? " of undefined length" : "") +
                " at byte " + std::to_string(p) + " where a fragment item (FFFE,E000) of defined length belongs");
      requireFits(h, limit);
      p = h.value + h.length;
    }
  }

  Syntax syntaxOf(const std::string& uid) const {
    if (uid.empty())
      fail(path_, "a DICOM file without a transfer syntax (0002,0010) in its meta information; export the series again");
    if (uid == "1.2.840.10008.1.2") return Syntax::kImplicitLittle;
    if (uid == "1.2.840.10008.1.2.2") return Syntax::kExplicitBig;
    if (uid == "1.2.840.10008.1.2.1.99")
      fail(path_, "a DICOM file in the deflated transfer syntax (1.2.840.10008.1.2.1.99), which is not read; export the "
                  "series uncompressed or with image compression (JPEG, JPEG 2000, RLE)");
    // Every other transfer syntax of DICOM (explicit VR little endian, JPEG, JPEG-LS, JPEG 2000, RLE, MPEG,
    // HTJ2K) writes its data set in explicit VR little endian.
    if (uid == "1.2.840.10008.1.2.1" || uid.rfind("1.2.840.10008.1.2.4.", 0) == 0 || uid == "1.2.840.10008.1.2.5")
      return Syntax::kExplicitLittle;
    fail(path_, "a DICOM file in the transfer syntax '" + uid + "', which is not one of DICOM's; export the series again");
  }

  const std::string& path_;
  FileWindow& file_;
  DicomFileScan& out_;
  bool in_meta_ = false;
};

}  // namespace

DicomFileScan scanDicomFile(const std::string& path) {
  DicomFileScan out;
  out.path = path;
  FileWindow file(path);
  if (file.size() < 132) return out;
  const unsigned char* magic = file.at(128, 4);
  if (std::memcmp(magic, "DICM", 4) != 0) return out;
  out.is_dicom = true;
  Walker(path, file, out).run();
  return out;
}

DicomFolder scanDicomFolder(const std::string& folder) {
  std::vector<std::string> files;
  std::error_code ec;
  for (fs::directory_iterator it(folder, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code kind;
    if (it->is_regular_file(kind)) files.push_back(it->path().string());
  }
  if (ec) fail(folder, "cannot list the folder (" + ec.message() + ")");
  std::sort(files.begin(), files.end());
  DicomFolder out;
  for (const std::string& f : files) {
    const DicomFileScan scan = scanDicomFile(f);
    if (!scan.is_dicom || !scan.has_pixel_data) continue;
    if (scan.series_uid.empty())
      fail(f, "a DICOM image without a SeriesInstanceUID (0020,000E), so it belongs to no series; export the series "
              "again, or remove the file from the folder");
    out.series[scan.series_uid].push_back(scan);
  }
  return out;
}

namespace {

template <typename T>
T load(const unsigned char* p, bool swap) {
  unsigned char b[sizeof(T)];
  for (std::size_t i = 0; i < sizeof(T); ++i) b[i] = swap ? p[sizeof(T) - 1 - i] : p[i];
  T v;
  std::memcpy(&v, b, sizeof(T));
  return v;
}

}  // namespace

void readDicomPixels(const DicomFileScan& scan, float* out) {
  const std::size_t bytes = static_cast<std::size_t>(scan.bits_allocated / 8);
  const std::uint64_t count = static_cast<std::uint64_t>(scan.rows) * static_cast<std::uint64_t>(scan.columns);
  FileWindow file(scan.path);
  if (scan.pixel_offset + count * bytes > file.size()) fail(scan.path, "the file changed since it was checked; read it again");
  // PS3.5 8.1.1: the value is bits_stored bits ending at high_bit; the bits around it are not the value.
  const int shift = scan.high_bit - scan.bits_stored + 1;
  const std::uint32_t mask = scan.bits_stored >= 32 ? 0xFFFFFFFFu : (std::uint32_t{1} << scan.bits_stored) - 1;
  const bool swap = scan.big_endian;
  const std::uint64_t chunk = FileWindow::kWindow / bytes;
  for (std::uint64_t first = 0; first < count; first += chunk) {
    const std::uint64_t n = std::min(chunk, count - first);
    const unsigned char* p = file.at(scan.pixel_offset + first * bytes, static_cast<std::size_t>(n * bytes));
    for (std::uint64_t v = 0; v < n; ++v, p += bytes) {
      std::uint32_t raw = bytes == 1 ? *p : bytes == 2 ? load<std::uint16_t>(p, swap) : load<std::uint32_t>(p, swap);
      raw = (raw >> shift) & mask;
      double value = static_cast<double>(raw);
      if (scan.is_signed && scan.bits_stored < 32 && (raw >> (scan.bits_stored - 1)) & 1u)
        value -= static_cast<double>(std::uint64_t{1} << scan.bits_stored);
      else if (scan.is_signed && scan.bits_stored == 32)
        value = static_cast<double>(static_cast<std::int32_t>(raw));
      out[first + v] = static_cast<float>(value * scan.rescale_slope + scan.rescale_intercept);
    }
  }
}

}  // namespace breast_sim::core
