#pragma once
// DICOM files written byte by byte for the tests of the core's DICOM reader (test_dicom_scan) and the
// seeds of its fuzz target (fuzz_seeds): a data set in any of the three encodings, the Part 10 wrapper,
// and a whole small slice.

#include <cstdint>
#include <string>
#include <vector>

namespace breast_sim::test::dicom {

inline constexpr std::uint32_t kUndefined = 0xFFFFFFFFu;
inline constexpr const char* kImplicit = "1.2.840.10008.1.2";
inline constexpr const char* kExplicit = "1.2.840.10008.1.2.1";
inline constexpr const char* kBig = "1.2.840.10008.1.2.2";
inline constexpr const char* kJpeg = "1.2.840.10008.1.2.4.50";

/// Bytes of a data set, element by element, in one transfer syntax.
class Bytes {
 public:
  explicit Bytes(bool explicit_vr = false, bool big = false) : explicit_(explicit_vr), big_(big) {}
  Bytes& u16(std::uint16_t v) {
    if (big_) s_ += {static_cast<char>(v >> 8), static_cast<char>(v & 0xFF)};
    else s_ += {static_cast<char>(v & 0xFF), static_cast<char>(v >> 8)};
    return *this;
  }
  Bytes& u32(std::uint32_t v) {
    if (big_) return u16(static_cast<std::uint16_t>(v >> 16)).u16(static_cast<std::uint16_t>(v & 0xFFFF));
    return u16(static_cast<std::uint16_t>(v & 0xFFFF)).u16(static_cast<std::uint16_t>(v >> 16));
  }
  /// An element's header: tag, VR (explicit syntaxes) and length.
  Bytes& head(std::uint16_t group, std::uint16_t element, const std::string& vr, std::uint32_t length) {
    u16(group).u16(element);
    if (!explicit_ || group == 0xFFFE) return u32(length);
    s_ += vr;
    const bool long_vr = vr == "OB" || vr == "OW" || vr == "SQ" || vr == "UN" || vr == "UT" || vr == "OF";
    if (long_vr) return u16(0).u32(length);
    return u16(static_cast<std::uint16_t>(length));
  }
  /// A whole element with its value.
  Bytes& element(std::uint16_t group, std::uint16_t element, const std::string& vr, const std::string& value) {
    head(group, element, vr, static_cast<std::uint32_t>(value.size()));
    s_ += value;
    return *this;
  }
  Bytes& raw(const std::string& bytes) {
    s_ += bytes;
    return *this;
  }
  const std::string& str() const { return s_; }

 private:
  bool explicit_, big_;
  std::string s_;
};

/// A UID value padded to even length, as DICOM stores it.
inline std::string uid(const std::string& u) { return u.size() % 2 ? u + std::string(1, '\0') : u; }

/// A DICOM Part 10 file: preamble, "DICM", the meta information (explicit VR little endian), the data set.
inline std::string part10(const std::string& transfer_syntax, const std::string& data_set) {
  Bytes meta(true);
  meta.element(0x0002, 0x0010, "UI", uid(transfer_syntax));
  Bytes group_length(true);
  group_length.head(0x0002, 0x0000, "UL", 4).u32(static_cast<std::uint32_t>(meta.str().size()));
  return std::string(128, '\0') + "DICM" + group_length.str() + meta.str() + data_set;
}

/// A whole slice: the attributes readDicomSeries needs, then 2 x 3 pixels of `bits` bits (values as
/// given, already in the stored bit layout), at `z_mm` along the normal (0, 0, 1).
struct Slice {
  bool explicit_vr = false, big = false;
  int bits = 16, stored = 16, high = 15, sign = 0;
  double z_mm = 0;
  std::vector<std::uint32_t> pixels = {1, 2, 3, 4, 5, 6};
  std::string samples = "1", photometric = "MONOCHROME2", frames = "1", slope = "1", intercept = "0";
  bool position = true;
};

inline std::string us(std::uint16_t v, bool big) { return Bytes(false, big).u16(v).str(); }

inline std::string even(std::string text) { return text.size() % 2 ? text + " " : text; }

/// The data set of a slice (without the Part 10 wrapper).
inline std::string sliceDataSet(const Slice& c) {
  Bytes b(c.explicit_vr, c.big);
  b.element(0x0008, 0x103E, "LO", even("hand-made"));
  b.element(0x0020, 0x000E, "UI", uid("1.2.3.4"));
  if (c.position) b.element(0x0020, 0x0032, "DS", even("-10\\20.5\\" + std::to_string(c.z_mm)));
  b.element(0x0020, 0x0037, "DS", even("0\\1\\0\\-1\\0\\0"));
  b.element(0x0028, 0x0002, "US", us(static_cast<std::uint16_t>(std::stoi(c.samples)), c.big));
  b.element(0x0028, 0x0004, "CS", even(c.photometric));
  b.element(0x0028, 0x0008, "IS", even(c.frames));
  b.element(0x0028, 0x0010, "US", us(2, c.big));
  b.element(0x0028, 0x0011, "US", us(3, c.big));
  b.element(0x0028, 0x0030, "DS", even("0.5\\0.25"));
  b.element(0x0028, 0x0100, "US", us(static_cast<std::uint16_t>(c.bits), c.big));
  b.element(0x0028, 0x0101, "US", us(static_cast<std::uint16_t>(c.stored), c.big));
  b.element(0x0028, 0x0102, "US", us(static_cast<std::uint16_t>(c.high), c.big));
  b.element(0x0028, 0x0103, "US", us(static_cast<std::uint16_t>(c.sign), c.big));
  b.element(0x0028, 0x1052, "DS", even(c.intercept));
  b.element(0x0028, 0x1053, "DS", even(c.slope));
  std::string pixels;
  for (std::uint32_t v : c.pixels) {
    if (c.bits == 8) pixels += static_cast<char>(v);
    else if (c.bits == 16) pixels += us(static_cast<std::uint16_t>(v), c.big);
    else pixels += c.big ? us(static_cast<std::uint16_t>(v >> 16), true) + us(static_cast<std::uint16_t>(v), true)
                         : us(static_cast<std::uint16_t>(v), false) + us(static_cast<std::uint16_t>(v >> 16), false);
  }
  b.element(0x7FE0, 0x0010, c.bits == 8 ? "OB" : "OW", pixels);
  return b.str();
}

/// A slice as a DICOM Part 10 file.
inline std::string slice(const Slice& c) {
  return part10(c.big ? kBig : c.explicit_vr ? kExplicit : kImplicit, sliceDataSet(c));
}

}  // namespace breast_sim::test::dicom
