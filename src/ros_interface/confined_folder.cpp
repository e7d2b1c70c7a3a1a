// The node's file folders (confined_folder.h): names checked lexically, then by their real paths;
// writes through a temporary, fsync, rename and a flush of the folder, relative to the folder's
// descriptor.
#include "breast_sim/ros_interface/confined_folder.h"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <climits>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <system_error>
#include <utility>

#include <dirent.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

namespace breast_sim::ros_interface {

namespace {

std::string systemError(int error) { return std::strerror(error); }

/// The real path of `path`, or "" with errno set.
std::string realPath(const std::string& path) {
  char buffer[PATH_MAX];
  if (!::realpath(path.c_str(), buffer)) return {};
  return buffer;
}

/// A file descriptor closed on scope exit.
class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  int get() const { return fd_; }
  /// Closes it, returning close's errno (0 on success).
  int close() {
    const int result = fd_ >= 0 && ::close(fd_) != 0 ? errno : 0;
    fd_ = -1;
    return result;
  }

 private:
  int fd_;
};

bool lexicallyInside(const std::string& root, const std::string& path) {
  if (root == "/") return !path.empty() && path[0] == '/';
  return path == root || (path.size() > root.size() && path.compare(0, root.size(), root) == 0 && path[root.size()] == '/');
}

}  // namespace

ConfinedFolder::ConfinedFolder(const std::string& path, const std::string& what, bool create) : what_(what) {
  if (path.empty()) throw std::runtime_error(what + " is empty; give a folder");
  if (create) {
    std::error_code ec;
    std::filesystem::create_directories(path, ec);
    if (ec)
      throw std::runtime_error(what + " '" + path + "' cannot be created (" + ec.message() +
                               "); give a folder the node's user can write");
  }
  root_ = realPath(path);
  if (root_.empty())
    throw std::runtime_error(what + " '" + path + "' cannot be used (" + systemError(errno) + "); give an existing folder");
  struct stat st {};
  if (::stat(root_.c_str(), &st) != 0 || !S_ISDIR(st.st_mode))
    throw std::runtime_error(what + " '" + path + "' is not a folder");
}

void ConfinedFolder::refuse(const std::string& name, const std::string& why) const {
  throw ConfinementError("'" + name + "' " + why);
}

std::string ConfinedFolder::candidate(const std::string& name) const {
  if (name.empty()) throw ConfinementError("no file name given; name a file in " + what_ + " (" + root_ + ")");
  if (name.find('\0') != std::string::npos) refuse(name, "holds a NUL character");
  for (const auto& part : std::filesystem::path(name))
    if (part == "..")
      refuse(name, "has a '..' component, which is not allowed; name the file relative to " + what_ + " (" + root_ + ")");
  const std::filesystem::path p = name[0] == '/' ? std::filesystem::path(name) : std::filesystem::path(root_) / name;
  return p.lexically_normal().string();
}

bool ConfinedFolder::inside(const std::string& real_path) const { return lexicallyInside(root_, real_path); }

std::string ConfinedFolder::existingFile(const std::string& name) const {
  const std::string path = candidate(name);
  const std::string real = realPath(path);
  if (real.empty()) {
    const int error = errno;
    // Outside or missing: decided by the folder it would be in (the name may reach the root through a link).
    const std::string real_parent = realPath(std::filesystem::path(path).parent_path().string());
    if (real_parent.empty() ? !lexicallyInside(root_, path) : !inside(real_parent))
      refuse(name, "is outside " + what_ + " (" + root_ + "); name files relative to it");
    if (error == ENOENT || error == ENOTDIR) refuse(name, "does not exist in " + what_ + " (" + root_ + ")");
    refuse(name, "cannot be resolved (" + systemError(error) + ")");
  }
  if (!inside(real)) {
    if (lexicallyInside(root_, path))
      refuse(name, "resolves to " + real + ", outside " + what_ + " (" + root_ + "): a symbolic link leaves the folder");
    refuse(name, "is outside " + what_ + " (" + root_ + "); name files relative to it");
  }
  struct stat st {};
  if (::stat(real.c_str(), &st) != 0) refuse(name, "cannot be read (" + systemError(errno) + ")");
  if (S_ISDIR(st.st_mode)) refuse(name, "is a folder, not a file");
  if (!S_ISREG(st.st_mode)) refuse(name, "is not a regular file (a device or a pipe?)");
  return real;
}

std::string ConfinedFolder::writeFile(const std::string& name, bool replace,
                                      const std::function<void(const std::string& temp_path)>& write) const {
  const std::string path = candidate(name);
  const std::filesystem::path p(path);
  const std::string leaf = p.filename().string();
  if (leaf.empty() || leaf == ".") refuse(name, "names a folder, not a file");
  const std::string parent = p.parent_path().string();
  const std::string real_parent = realPath(parent);
  if (real_parent.empty()) {
    const int error = errno;
    if (!lexicallyInside(root_, parent)) refuse(name, "is outside " + what_ + " (" + root_ + "); name files relative to it");
    refuse(name, "cannot be written: its folder " + parent + " does not exist (" + systemError(error) + ")");
  }
  if (!inside(real_parent)) {
    if (lexicallyInside(root_, parent))
      refuse(name, "lies in " + real_parent + ", outside " + what_ + " (" + root_ + "): a symbolic link leaves the folder");
    refuse(name, "is outside " + what_ + " (" + root_ + "); name files relative to it");
  }
  Fd dir(::open(real_parent.c_str(), O_DIRECTORY | O_RDONLY | O_CLOEXEC | O_NOFOLLOW));
  if (dir.get() < 0) throw std::runtime_error(real_parent + ": cannot open the folder (" + systemError(errno) + ")");
  // The folder opened is the one checked, even if a link was swapped in since.
  const std::string opened = realPath("/proc/self/fd/" + std::to_string(dir.get()));
  if (!opened.empty() && !inside(opened))
    refuse(name, "lies in " + opened + ", outside " + what_ + " (" + root_ + "): the folder changed while it was opened");

  struct stat st {};
  if (::fstatat(dir.get(), leaf.c_str(), &st, AT_SYMLINK_NOFOLLOW) == 0) {
    if (S_ISLNK(st.st_mode))
      refuse(name, "is a symbolic link; the node never writes through one (remove it, or choose another name)");
    if (!S_ISREG(st.st_mode)) refuse(name, "exists and is not a regular file");
    if (!replace) refuse(name, "exists; set replace to true to replace it");
  } else if (errno != ENOENT) {
    throw std::runtime_error(real_parent + "/" + leaf + ": cannot be checked (" + systemError(errno) + ")");
  }

  // The temporary: hidden, unique in the folder, created here so that no other file is taken over.
  static std::atomic<unsigned> counter{0};
  std::string temp;
  int created = -1;
  for (int attempt = 0; attempt < 100 && created < 0; ++attempt) {
    temp = "." + leaf + ".partial" + std::to_string(::getpid()) + "_" + std::to_string(counter++);
    created = ::openat(dir.get(), temp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0666);
    if (created < 0 && errno != EEXIST) break;
  }
  if (created < 0)
    throw std::runtime_error(real_parent + ": cannot create a temporary file (" + systemError(errno) +
                             "; check the folder is writable)");
  ::close(created);
  auto removeTemp = [&] { ::unlinkat(dir.get(), temp.c_str(), 0); };
  try {
    write(real_parent + "/" + temp);
  } catch (...) {
    removeTemp();
    throw;
  }
  int error = 0;
  {
    Fd written(::openat(dir.get(), temp.c_str(), O_RDONLY | O_NOFOLLOW | O_CLOEXEC));
    if (written.get() < 0) error = errno;
    else if (::fstat(written.get(), &st) != 0) error = errno;
    else if (!S_ISREG(st.st_mode)) error = EINVAL;
    else if (::fsync(written.get()) != 0) error = errno;
    if (error == 0) error = written.close();
  }
  if (error != 0) {
    removeTemp();
    throw std::runtime_error(real_parent + "/" + leaf + ": the written file cannot be flushed (" + systemError(error) + ")");
  }
  if (replace) {
    if (::renameat(dir.get(), temp.c_str(), dir.get(), leaf.c_str()) != 0) error = errno;
  } else if (::renameat2(dir.get(), temp.c_str(), dir.get(), leaf.c_str(), RENAME_NOREPLACE) != 0) {
    error = errno;
    if (error == EINVAL) {
      // A file system without RENAME_NOREPLACE: a hard link fails the same way on an existing name.
      error = ::linkat(dir.get(), temp.c_str(), dir.get(), leaf.c_str(), 0) == 0 ? 0 : errno;
    }
  }
  if (error != 0) {
    removeTemp();
    if (error == EEXIST) refuse(name, "exists (it appeared while the file was written); set replace to true to replace it");
    throw std::runtime_error(real_parent + "/" + leaf + ": cannot be written (" + systemError(error) + ")");
  }
  removeTemp();  // left only by the hard-link fallback; otherwise already gone
  // The rename itself reaches the disk with the folder's entry.
  if (::fsync(dir.get()) != 0)
    throw std::runtime_error(real_parent + ": the folder cannot be flushed after writing " + leaf + " (" +
                             systemError(errno) + ")");
  return real_parent + "/" + leaf;
}

bool ConfinedFolder::removeFile(const std::string& name) const {
  const std::string path = candidate(name);
  const std::filesystem::path p(path);
  const std::string leaf = p.filename().string();
  if (leaf.empty() || leaf == ".") refuse(name, "names a folder, not a file");
  const std::string real_parent = realPath(p.parent_path().string());
  if (real_parent.empty()) return false;
  if (!inside(real_parent)) refuse(name, "is outside " + what_ + " (" + root_ + ")");
  Fd dir(::open(real_parent.c_str(), O_DIRECTORY | O_RDONLY | O_CLOEXEC | O_NOFOLLOW));
  if (dir.get() < 0) throw std::runtime_error(real_parent + ": cannot open the folder (" + systemError(errno) + ")");
  if (::unlinkat(dir.get(), leaf.c_str(), 0) == 0) {
    ::fsync(dir.get());
    return true;
  }
  if (errno == ENOENT) return false;
  if (errno == EISDIR) refuse(name, "is a folder, not a file");
  throw std::runtime_error(real_parent + "/" + leaf + ": cannot be removed (" + systemError(errno) + ")");
}

std::vector<std::string> ConfinedFolder::newestFirst(const std::string& prefix, const std::string& suffix) const {
  std::vector<std::pair<struct timespec, std::string>> found;
  DIR* dir = ::opendir(root_.c_str());
  if (!dir) throw std::runtime_error(what_ + " (" + root_ + ") cannot be listed (" + systemError(errno) + ")");
  while (const dirent* entry = ::readdir(dir)) {
    const std::string n = entry->d_name;
    if (n.empty() || n[0] == '.' || n.size() < prefix.size() + suffix.size() || n.compare(0, prefix.size(), prefix) != 0 ||
        n.compare(n.size() - suffix.size(), suffix.size(), suffix) != 0)
      continue;
    struct stat st {};
    if (::fstatat(::dirfd(dir), n.c_str(), &st, AT_SYMLINK_NOFOLLOW) != 0 || !S_ISREG(st.st_mode)) continue;
    found.emplace_back(st.st_mtim, n);
  }
  ::closedir(dir);
  std::sort(found.begin(), found.end(), [](const auto& a, const auto& b) {
    if (a.first.tv_sec != b.first.tv_sec) return a.first.tv_sec > b.first.tv_sec;
    if (a.first.tv_nsec != b.first.tv_nsec) return a.first.tv_nsec > b.first.tv_nsec;
    return a.second > b.second;
  });
  std::vector<std::string> paths;
  for (const auto& f : found) paths.push_back(root_ + "/" + f.second);
  return paths;
}

}  // namespace breast_sim::ros_interface
