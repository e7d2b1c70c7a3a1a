#pragma once
// Test fixture of the rostests that launch the node with a state folder of their own
// (state_folder: /tmp/..._$(anon ...) in the .test file), so that no checkpoint of another run is
// resumed: the folder is removed when the client ends.
#include <filesystem>
#include <string>
#include <system_error>

#include <ros/ros.h>

namespace breast_sim::test_fixtures {

/// Removes the node's ~state_folder (the parameter /breast_sim/state_folder) on destruction.
class NodeStateFolder {
 public:
  NodeStateFolder() { ros::NodeHandle("/breast_sim").getParam("state_folder", path_); }
  ~NodeStateFolder() {
    std::error_code ec;
    if (!path_.empty()) std::filesystem::remove_all(path_, ec);
  }
  NodeStateFolder(const NodeStateFolder&) = delete;
  NodeStateFolder& operator=(const NodeStateFolder&) = delete;
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

}  // namespace breast_sim::test_fixtures
