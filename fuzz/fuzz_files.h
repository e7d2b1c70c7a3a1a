#pragma once
/// @file fuzz_files.h
/// What every fuzz target shares: the fuzz input written as the files a reader takes by path, and
/// the check that a reader either succeeds or throws the error its header documents, naming the file.
///
/// Multi-file input: the input is split at each kNextFile marker; part i becomes the file names[i]
/// in a private temporary folder (under TMPDIR), and the files of parts the input lacks are removed,
/// so nothing carries over between inputs. A header names its other files by these names (an NRRD
/// `data file: data`, a case file's `base: b1.yaml`). The seed tool (fuzz_seeds.cpp) joins parts
/// the same way.

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>
#include <string_view>
#include <system_error>
#include <typeinfo>
#include <vector>

#include <unistd.h>

namespace breast_sim::fuzz {

/// Separates the files of one fuzz input.
inline constexpr std::string_view kNextFile = "\n--next-file--\n";

/// Splits a fuzz input into its files' contents.
inline std::vector<std::string_view> splitParts(std::string_view input) {
  std::vector<std::string_view> parts;
  while (true) {
    const std::size_t at = input.find(kNextFile);
    if (at == std::string_view::npos) {
      parts.push_back(input);
      return parts;
    }
    parts.push_back(input.substr(0, at));
    input.remove_prefix(at + kNextFile.size());
  }
}

/// The inverse of splitParts.
inline std::string joinParts(const std::vector<std::string>& parts) {
  std::string out;
  for (std::size_t i = 0; i < parts.size(); ++i) {
    if (i > 0) out += kNextFile;
    out += parts[i];
  }
  return out;
}

/// A private temporary folder holding the files of the current input; removed at exit.
class FuzzFiles {
 public:
  /// @param target  names the folder
  /// @param names   file names of the parts, the file the reader opens first
  FuzzFiles(const std::string& target, std::vector<std::string> names) : names_(std::move(names)) {
    std::string pattern =
        (std::filesystem::temp_directory_path() / ("breast_sim_" + target + "_XXXXXX")).string();
    if (!mkdtemp(pattern.data())) {
      std::perror(pattern.c_str());
      std::abort();
    }
    dir_ = pattern;
    folders().push_back(dir_);
    if (folders().size() == 1) std::atexit([] {
      for (const auto& d : folders()) {
        std::error_code ignored;
        std::filesystem::remove_all(d, ignored);
      }
    });
  }

  /// Writes the parts of `input`; returns the path of the first file.
  std::string write(const std::uint8_t* data, std::size_t size) {
    const auto parts = splitParts(std::string_view(reinterpret_cast<const char*>(data), size));
    for (std::size_t i = 0; i < names_.size(); ++i) {
      const std::string p = path(names_[i]);
      if (i < parts.size()) {
        std::ofstream out(p, std::ios::binary | std::ios::trunc);
        out.write(parts[i].data(), static_cast<std::streamsize>(parts[i].size()));
        if (!out) {
          std::perror(p.c_str());
          std::abort();
        }
      } else {
        std::remove(p.c_str());
      }
    }
    return path(names_[0]);
  }

  std::string path(const std::string& name) const { return (dir_ / name).string(); }
  const std::filesystem::path& dir() const { return dir_; }

 private:
  static std::vector<std::filesystem::path>& folders() {
    static std::vector<std::filesystem::path> f;
    return f;
  }
  std::vector<std::string> names_;
  std::filesystem::path dir_;
};

/// Runs a reader on the current input. The outcomes that are not findings: success, or a
/// std::runtime_error (the readers' documented error) whose message names the input's folder (each
/// error names its file). Anything else — another exception type (std::bad_alloc from a size the
/// file merely claims, std::length_error, std::logic_error, …) or a message without the file — is
/// reported and aborts, which libFuzzer records as a crash with its reproducer.
template <typename Read>
void expectCleanError(const FuzzFiles& files, Read&& read) {
  const std::string folder = files.dir().string();
  try {
    read();
  } catch (const std::runtime_error& e) {
    if (std::string(e.what()).find(folder) == std::string::npos) {
      std::fprintf(stderr, "error message does not name the file (%s): %s\n", typeid(e).name(), e.what());
      std::abort();
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "unexpected exception %s: %s\n", typeid(e).name(), e.what());
    std::abort();
  }
}

}  // namespace breast_sim::fuzz
