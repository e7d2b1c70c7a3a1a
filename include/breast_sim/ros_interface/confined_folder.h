#pragma once
/// @file confined_folder.h
/// A folder the node reads or writes files in, and nowhere else: the node's file services
/// (~load_case, ~save_state, ~load_state, ~write_supine_mri) take names from requests, and a request
/// must not reach a file the node's user can reach outside the folders it was configured with
/// (docs/ros.md, "Files").
///
/// A request names a file relative to the folder, or by an absolute path inside it. Refused, each
/// with a reason that names the request and the folder: an empty name, a name with a `..` component
/// (even one that would stay inside), an absolute path outside the folder, and a name whose real
/// path (every symbolic link resolved, realpath) leaves the folder. A symbolic link that stays inside
/// is followed for reading; a file is never written through one.
///
/// Writes are atomic: the content goes to a temporary file in the target's folder, is flushed to
/// disk (fsync), renamed onto the name (renameat, openat-relative to the folder opened once, so a
/// folder swapped for a link meanwhile is not followed), and the folder is flushed too, so that a
/// crash at any moment leaves the old file or the new one, never half a file. An existing file is
/// replaced only when the caller says so; without it the rename refuses to replace one that appeared
/// meanwhile (renameat2 RENAME_NOREPLACE).
///
/// Not protected against: another process of the same user changing the folder's contents between
/// the check of a name and the read of its file (the folders belong to the node's user).
/// ROS-free; test/ros/test_confined_folder.cpp.

#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

namespace breast_sim::ros_interface {

/// A request refused by a ConfinedFolder; what() is the reason, naming the request and the folder.
class ConfinementError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class ConfinedFolder {
 public:
  /// @param path    the folder: absolute, or relative to the working directory
  /// @param what    how messages name it (e.g. "~state_folder")
  /// @param create  create it (with its missing parents, mode 0777 less the umask) when missing
  /// @throws std::runtime_error naming `what` and `path` when it is not a folder or cannot be made.
  ConfinedFolder(const std::string& path, const std::string& what, bool create);

  /// The folder's real path (absolute, every link resolved).
  const std::string& root() const { return root_; }

  /// The real path of an existing regular file inside the folder, for reading.
  /// @throws ConfinementError for a name refused (see the file comment), a missing file, or one that
  ///         is not a regular file (a folder, a device).
  std::string existingFile(const std::string& name) const;

  /// Writes the file `name` atomically (see the file comment). `write` puts the complete content at
  /// the temporary path it is given (a file of the same folder, which exists and is empty; `write`
  /// may replace it, e.g. by a rename of its own); an exception from it is passed on and the
  /// temporary removed. The folder the name lies in must exist inside this folder.
  /// @param replace  an existing file of that name is replaced; false: it is refused
  /// @return the real path written
  /// @throws ConfinementError for a refused name, an existing file without `replace`, a symbolic
  ///         link or a non-regular file at the name; std::runtime_error naming the file when a system
  ///         call fails (with its reason, e.g. no space left).
  std::string writeFile(const std::string& name, bool replace,
                        const std::function<void(const std::string& temp_path)>& write) const;

  /// Removes the file `name` (a regular file or a link, never a folder) when it exists.
  /// @return false when there was none
  /// @throws ConfinementError for a refused name; std::runtime_error when the removal fails.
  bool removeFile(const std::string& name) const;

  /// The regular files directly in the folder (links and temporaries left out) whose names start
  /// with `prefix` and end with `suffix`, newest modification first (ties: by name, descending).
  std::vector<std::string> newestFirst(const std::string& prefix, const std::string& suffix) const;

 private:
  /// The path a name stands for (lexically: inside the root, or an absolute path), after the
  /// checks of the name alone.
  std::string candidate(const std::string& name) const;
  bool inside(const std::string& real_path) const;
  [[noreturn]] void refuse(const std::string& name, const std::string& why) const;

  std::string root_;
  std::string what_;
};

}  // namespace breast_sim::ros_interface
