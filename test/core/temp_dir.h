#pragma once
// A fresh directory under the system temp dir for a test's files, removed with them at the end.
#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>
#include <system_error>

namespace breast_sim::test {

class TempDir {
 public:
  /// @param prefix  start of the directory's name (mkdtemp adds six random characters)
  explicit TempDir(const std::string& prefix) {
    std::string pattern = (std::filesystem::temp_directory_path() / (prefix + "_XXXXXX")).string();
    if (!mkdtemp(pattern.data())) throw std::runtime_error("cannot create a temp dir from " + pattern);
    dir_ = pattern;
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(dir_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  /// The path of a file in the directory.
  std::string path(const std::string& name) const { return (dir_ / name).string(); }
  /// Writes `text` to the file `name` in the directory; returns its path.
  std::string write(const std::string& name, const std::string& text) const {
    const std::string p = path(name);
    std::ofstream(p) << text;
    return p;
  }

 private:
  std::filesystem::path dir_;
};

}  // namespace breast_sim::test
