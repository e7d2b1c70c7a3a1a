#pragma once
/// @file mesh_io_detail.h
/// Internal functions shared by the mesh readers and writers (src/core/mesh/*.cpp). Not part of the
/// public API: include mesh_io.h instead.

#include <cstddef>
#include <cstring>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/mesh_io.h"

namespace breast_sim::core {
namespace mesh_io_detail {

/// A whole file in memory with a read position, for text and binary parsing in linear time.
/// Errors name the path and the line (text) or byte offset (binary) of a position.
class FileCursor {
 public:
  /// Reads the whole file. @throws std::runtime_error naming the path if it cannot be read.
  explicit FileCursor(std::string path);

  const std::string& path() const { return path_; }
  const std::string& data() const { return data_; }
  std::size_t pos() const { return pos_; }
  void setPos(std::size_t pos) { pos_ = pos; }
  bool atEnd() const { return pos_ >= data_.size(); }
  /// 1-based line number of a byte position.
  int lineAt(std::size_t pos) const;

  /// Throws "<path>:<line of pos>: <what>".
  [[noreturn]] void failAtLine(std::size_t pos, const std::string& what) const;
  /// Throws "<path>:<line of the read position>: <what>".
  [[noreturn]] void fail(const std::string& what) const { failAtLine(pos_, what); }
  /// Throws "<path>: byte <offset>: <what>".
  [[noreturn]] void failAtByte(std::size_t offset, const std::string& what) const;

  // ---- text
  /// Skips spaces, tabs, carriage returns and newlines.
  void skipWhitespace();
  /// Next whitespace-separated token (skipping whitespace first); empty at the end of the file.
  std::string_view token();
  /// The rest of the current line without its line break; moves past the line break.
  std::string_view line();
  /// Whole-token number parses; fail() with "expected <what>, got '<token>'" otherwise.
  long long integerToken(const char* what);
  double realToken(const char* what);

  // ---- binary
  /// Reads sizeof(T) bytes in host (little-endian) order; failAtByte() with "truncated: expected
  /// <what>" when the file ends before.
  template <typename T>
  T binary(const char* what) {
    requireBytes(sizeof(T), what);
    T v;
    std::memcpy(&v, data_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return v;
  }
  /// Fails unless `n` more bytes are present.
  void requireBytes(std::size_t n, const char* what) const;

 private:
  std::string path_;
  std::string data_;
  std::size_t pos_ = 0;
};

/// Guards memory reserved from a count the file states: fails unless `count` records of at least
/// `min_bytes` bytes each (a separator after each included; the last may lack it) fit in the bytes
/// from `from` to the end of the file. Call it before reserving, so that "$Nodes 2000000000" in a
/// small file is an error naming the file rather than a bare std::bad_alloc.
/// @param count_pos  where the count stands: its line is named, or its byte offset when `binary`
/// @param what       the records, plural ("nodes")
/// Message: "<path>:<line>: header says 2000000000 nodes but the file can hold at most 5 (47 bytes
/// follow, each needs at least 8); is the file truncated or the count wrong?"
inline void checkCountFits(const FileCursor& f, long long count, std::size_t count_pos,
                           std::size_t from, std::size_t min_bytes, const char* what, bool binary) {
  const std::size_t size = f.data().size();
  const std::size_t left = from < size ? size - from : 0;
  const std::size_t most = (left + 1) / min_bytes;
  if (count >= 0 && static_cast<unsigned long long>(count) <= most) return;
  const std::string message = "header says " + std::to_string(count) + " " + what +
                              " but the file can hold at most " + std::to_string(most) + " (" +
                              std::to_string(left) + " bytes follow, each needs at least " +
                              std::to_string(min_bytes) + "); is the file truncated or the count wrong?";
  if (binary) f.failAtByte(count_pos, message);
  f.failAtLine(count_pos, message);
}

/// Whole-string number parses of a token (no surrounding whitespace allowed).
bool parseInteger(std::string_view s, long long& value);
bool parseReal(std::string_view s, double& value);
/// Splits a line into tokens: on whitespace, or when `commas` is true on commas (each token then
/// trimmed of whitespace; an empty field between two commas is kept empty, a trailing comma adds none).
void splitTokens(std::string_view line, bool commas, std::vector<std::string_view>& out);

/// Maps file node numbers to 0-based indices: a dense table for numbers below a bound that grows
/// with the count, a hash map beyond, so reading stays linear for any numbering.
class NumberMap {
 public:
  /// false if `number` was already present.
  bool insert(long long number, int index);
  /// -1 when absent.
  int find(long long number) const {
    if (number >= 0 && number < static_cast<long long>(dense_.size()) && dense_[number] >= 0)
      return dense_[number];
    if (sparse_.empty()) return -1;
    auto it = sparse_.find(number);
    return it == sparse_.end() ? -1 : it->second;
  }

 private:
  std::vector<int> dense_;
  std::unordered_map<long long, int> sparse_;
  std::size_t count_ = 0;
};

/// Shortest decimal text that reads back to exactly the same double.
void appendReal(std::string& out, double v);
void appendInteger(std::string& out, long long v);
/// Appends the bytes of a trivially copyable value.
template <typename T>
void appendBinary(std::string& out, const T& v) {
  out.append(reinterpret_cast<const char*>(&v), sizeof(T));
}
/// Writes bytes, replacing the file. @throws std::runtime_error naming the path.
void writeFile(const std::string& path, const std::string& bytes);

/// @throws std::invalid_argument unless length_unit_m is finite and > 0.
void checkLengthUnit(double length_unit_m, const char* function);
/// Builds the mesh, turning TetMesh's std::invalid_argument into std::runtime_error("<path>: …").
TetMesh makeMesh(const std::string& path, Points nodes_m, Tets tets, std::vector<int> labels);
/// Adds a node set, likewise turning std::invalid_argument into std::runtime_error("<path>: …").
void addNodeSet(const std::string& path, TetMesh& mesh, const std::string& name,
                std::vector<int> nodes);
/// Sorts tets and labels together by element number when not already sorted; fails (naming the path)
/// on a repeated number.
void sortByElementNumber(const std::string& path, std::vector<long long>& numbers, Tets& tets,
                         std::vector<int>& labels);

}  // namespace mesh_io_detail
}  // namespace breast_sim::core
