// The node's file folders (ros_interface/confined_folder.h): what a request may name and what it may
// not ('..', absolute paths outside, symbolic links leaving the folder), and writes that replace a
// file only when asked, atomically, never through a link.
#include <gtest/gtest.h>

#include <stdlib.h>
#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>

#include "breast_sim/ros_interface/confined_folder.h"

namespace fs = std::filesystem;
using breast_sim::ros_interface::ConfinedFolder;
using breast_sim::ros_interface::ConfinementError;

namespace {

/// A fresh temporary folder with `inside/` (the confined folder) and `outside/` beside it.
class Folders : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string pattern = (fs::temp_directory_path() / "confined_folder_XXXXXX").string();
    ASSERT_NE(::mkdtemp(pattern.data()), nullptr);
    base_ = fs::path(pattern);
    fs::create_directories(base_ / "inside" / "sub");
    fs::create_directories(base_ / "outside");
    folder_ = std::make_unique<ConfinedFolder>((base_ / "inside").string(), "~state_folder", false);
  }
  void TearDown() override {
    std::error_code ec;
    fs::remove_all(base_, ec);
  }
  std::string write(const fs::path& p, const std::string& text) const {
    std::ofstream(p) << text;
    return p.string();
  }
  static std::string read(const fs::path& p) {
    std::ifstream in(p);
    std::ostringstream s;
    s << in.rdbuf();
    return s.str();
  }
  /// A writer that puts `text` at the temporary path.
  static std::function<void(const std::string&)> writer(const std::string& text) {
    return [text](const std::string& temp) { std::ofstream(temp) << text; };
  }
  /// The reason a request is refused ("" when it is not).
  template <typename F>
  static std::string refusal(F f) {
    try {
      f();
    } catch (const ConfinementError& e) {
      return e.what();
    }
    return "";
  }
  fs::path in(const std::string& name) const { return base_ / "inside" / name; }

  fs::path base_;
  std::unique_ptr<ConfinedFolder> folder_;
};

TEST_F(Folders, RelativeAndAbsoluteNamesInsideAreRead) {
  const std::string a = write(in("a.state"), "A");
  write(in("sub/b.state"), "B");
  EXPECT_EQ(folder_->existingFile("a.state"), fs::canonical(a).string());
  EXPECT_EQ(folder_->existingFile("./sub/b.state"), fs::canonical(in("sub/b.state")).string());
  EXPECT_EQ(folder_->existingFile(a), fs::canonical(a).string());  // absolute, inside
  EXPECT_EQ(folder_->root(), fs::canonical(base_ / "inside").string());
}

TEST_F(Folders, DotDotIsRefusedEvenWhenItStaysInside) {
  write(in("a.state"), "A");
  write(base_ / "outside" / "secret", "S");
  const std::string up = refusal([&] { folder_->existingFile("../outside/secret"); });
  EXPECT_NE(up.find("'..'"), std::string::npos) << up;
  EXPECT_NE(up.find("~state_folder"), std::string::npos) << up;
  EXPECT_NE(refusal([&] { folder_->existingFile("sub/../a.state"); }).find("'..'"), std::string::npos);
  EXPECT_NE(refusal([&] { folder_->writeFile("../outside/new", true, writer("x")); }).find("'..'"), std::string::npos);
  EXPECT_FALSE(fs::exists(base_ / "outside" / "new"));
}

TEST_F(Folders, AbsolutePathsOutsideAreRefused) {
  const std::string secret = write(base_ / "outside" / "secret", "S");
  const std::string read_why = refusal([&] { folder_->existingFile(secret); });
  EXPECT_NE(read_why.find("is outside ~state_folder"), std::string::npos) << read_why;
  EXPECT_NE(refusal([&] { folder_->existingFile("/etc/passwd"); }).find("outside"), std::string::npos);
  const std::string write_why = refusal([&] { folder_->writeFile(secret, true, writer("overwritten")); });
  EXPECT_NE(write_why.find("is outside"), std::string::npos) << write_why;
  EXPECT_EQ(read(secret), "S");
  // A folder whose name starts like the root's is not inside it.
  fs::create_directories(base_ / "inside_not");
  const std::string sibling = write(base_ / "inside_not" / "f", "F");
  EXPECT_NE(refusal([&] { folder_->existingFile(sibling); }).find("outside"), std::string::npos);
}

TEST_F(Folders, SymlinksLeavingTheFolderAreRefused) {
  const std::string secret = write(base_ / "outside" / "secret", "S");
  fs::create_symlink(secret, in("link_to_file"));
  fs::create_directory_symlink(base_ / "outside", in("link_to_folder"));
  const std::string file_why = refusal([&] { folder_->existingFile("link_to_file"); });
  EXPECT_NE(file_why.find("a symbolic link leaves the folder"), std::string::npos) << file_why;
  EXPECT_NE(refusal([&] { folder_->existingFile("link_to_folder/secret"); }).find("symbolic link"), std::string::npos);
  // Writing: not through a link at the name, not into a linked folder outside.
  const std::string over_link = refusal([&] { folder_->writeFile("link_to_file", true, writer("overwritten")); });
  EXPECT_NE(over_link.find("is a symbolic link"), std::string::npos) << over_link;
  const std::string into_folder = refusal([&] { folder_->writeFile("link_to_folder/new", true, writer("x")); });
  EXPECT_NE(into_folder.find("a symbolic link leaves the folder"), std::string::npos) << into_folder;
  EXPECT_EQ(read(secret), "S");
  EXPECT_FALSE(fs::exists(base_ / "outside" / "new"));
}

TEST_F(Folders, SymlinksStayingInsideAreReadButNeverWrittenThrough) {
  write(in("sub/real.state"), "R");
  fs::create_symlink(in("sub/real.state"), in("alias.state"));
  EXPECT_EQ(folder_->existingFile("alias.state"), fs::canonical(in("sub/real.state")).string());
  EXPECT_NE(refusal([&] { folder_->writeFile("alias.state", true, writer("x")); }).find("symbolic link"), std::string::npos);
  EXPECT_EQ(read(in("sub/real.state")), "R");
}

TEST_F(Folders, AnExistingFileIsReplacedOnlyWhenAsked) {
  write(in("a.state"), "old");
  const std::string why = refusal([&] { folder_->writeFile("a.state", false, writer("new")); });
  EXPECT_NE(why.find("exists; set replace to true"), std::string::npos) << why;
  EXPECT_EQ(read(in("a.state")), "old");
  const std::string replaced = folder_->writeFile("a.state", true, writer("new"));
  EXPECT_EQ(replaced, fs::canonical(in("a.state")).string());
  EXPECT_EQ(read(in("a.state")), "new");
  const std::string fresh = folder_->writeFile("fresh.state", false, writer("F"));
  EXPECT_EQ(fresh, fs::canonical(in("fresh.state")).string());
  EXPECT_EQ(read(in("fresh.state")), "F");
  // A folder at the name is never replaced.
  EXPECT_NE(refusal([&] { folder_->writeFile("sub", true, writer("x")); }).find("not a regular file"), std::string::npos);
}

TEST_F(Folders, AFailedWriteLeavesTheOldFileAndNoTemporary) {
  write(in("a.state"), "old");
  std::string temp_seen;
  EXPECT_THROW(folder_->writeFile("a.state", true,
                                  [&](const std::string& temp) {
                                    temp_seen = temp;
                                    std::ofstream(temp) << "half a fi";
                                    throw std::runtime_error("disk full");
                                  }),
               std::runtime_error);
  EXPECT_EQ(read(in("a.state")), "old");
  // The temporary was in the target's own folder (a rename never crosses file systems) and is gone.
  EXPECT_EQ(fs::path(temp_seen).parent_path(), fs::canonical(base_ / "inside"));
  EXPECT_FALSE(fs::exists(temp_seen));
  int entries = 0;
  for (const auto& e : fs::directory_iterator(base_ / "inside")) entries += e.is_regular_file() ? 1 : 0;
  EXPECT_EQ(entries, 1);
}

// A writer that needs a name of its own (ITK picks an image format by the extension, which the
// temporary lacks: ~write_supine_mri) writes beside the temporary and renames its file onto it.
TEST_F(Folders, AWriterMayRenameItsOwnFileOntoTheTemporary) {
  write(in("image.nii.gz"), "old");
  struct stat old {};
  ASSERT_EQ(::stat(in("image.nii.gz").c_str(), &old), 0);
  const std::string path = folder_->writeFile("image.nii.gz", true, [](const std::string& temp) {
    std::ofstream(temp + ".nii.gz") << "new image";
    fs::rename(temp + ".nii.gz", temp);
  });
  EXPECT_EQ(read(path), "new image");
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_NE(st.st_ino, old.st_ino);
  int entries = 0;
  for (const auto& e : fs::directory_iterator(base_ / "inside")) entries += e.is_regular_file() ? 1 : 0;
  EXPECT_EQ(entries, 1);  // no temporary, no file of the writer's left
}

TEST_F(Folders, WritesGoOnlyIntoExistingFoldersInside) {
  const std::string why = refusal([&] { folder_->writeFile("no_such/a.state", true, writer("x")); });
  EXPECT_NE(why.find("does not exist"), std::string::npos) << why;
  EXPECT_NE(refusal([&] { folder_->writeFile("", true, writer("x")); }).find("no file name"), std::string::npos);
  EXPECT_NE(refusal([&] { folder_->writeFile("sub/", true, writer("x")); }).find("names a folder"), std::string::npos);
  EXPECT_EQ(read(folder_->writeFile("sub/b.state", false, writer("B"))), "B");
}

TEST_F(Folders, ReadingNamesWhatIsMissingOrNotAFile) {
  EXPECT_NE(refusal([&] { folder_->existingFile("none.state"); }).find("does not exist in ~state_folder"), std::string::npos);
  EXPECT_NE(refusal([&] { folder_->existingFile("sub"); }).find("is a folder"), std::string::npos);
}

TEST_F(Folders, NewestFirstListsRegularFilesByModificationTime) {
  write(in("checkpoint-1.state"), "1");
  write(in("checkpoint-2.state"), "2");
  write(in("other.state"), "o");
  write(in(".checkpoint-3.state.partial1_0"), "t");
  fs::create_symlink(in("checkpoint-1.state"), in("checkpoint-link.state"));
  const auto now = fs::file_time_type::clock::now();
  fs::last_write_time(in("checkpoint-2.state"), now - std::chrono::seconds(10));
  fs::last_write_time(in("checkpoint-1.state"), now);
  const auto list = folder_->newestFirst("checkpoint-", ".state");
  ASSERT_EQ(list.size(), 2u);
  EXPECT_EQ(list[0], fs::canonical(in("checkpoint-1.state")).string());
  EXPECT_EQ(list[1], fs::canonical(in("checkpoint-2.state")).string());
}

TEST_F(Folders, RemoveTakesFilesNotFolders) {
  write(in("a.state"), "A");
  EXPECT_TRUE(folder_->removeFile("a.state"));
  EXPECT_FALSE(fs::exists(in("a.state")));
  EXPECT_FALSE(folder_->removeFile("a.state"));
  EXPECT_NE(refusal([&] { folder_->removeFile("../outside/x"); }).find("'..'"), std::string::npos);
}

// The folder as the launch files name it: through a link (a catkin workspace's src/ links to the checkout).
TEST_F(Folders, NamesThroughALinkToTheFolderAreInside) {
  fs::create_directory_symlink(base_ / "inside", base_ / "alias");
  const std::string a = write(in("a.state"), "A");
  EXPECT_EQ(folder_->existingFile((base_ / "alias" / "a.state").string()), fs::canonical(a).string());
  const std::string missing = refusal([&] { folder_->existingFile((base_ / "alias" / "none.yaml").string()); });
  EXPECT_NE(missing.find("does not exist in ~state_folder"), std::string::npos) << missing;
  EXPECT_EQ(read(folder_->writeFile((base_ / "alias" / "b.state").string(), false, writer("B"))), "B");
}

TEST(ConfinedFolder, AMissingFolderIsCreatedOnlyWhenAsked) {
  const fs::path base = fs::temp_directory_path() / ("confined_folder_create_" + std::to_string(::getpid()));
  fs::remove_all(base);
  try {
    ConfinedFolder f((base / "a" / "b").string(), "~state_folder", false);
    ADD_FAILURE() << "a missing folder was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("~state_folder"), std::string::npos) << e.what();
  }
  const ConfinedFolder f((base / "a" / "b").string(), "~state_folder", true);
  EXPECT_TRUE(fs::is_directory(base / "a" / "b"));
  std::ofstream(base / "file") << "x";
  EXPECT_THROW(ConfinedFolder((base / "file").string(), "~data_folder", false), std::runtime_error);
  fs::remove_all(base);
}

}  // namespace
