// rostest client for node_files.test: the node's files and its restart.
//  1. ~save_state / ~load_state / ~load_case refuse '..', absolute paths outside their folders and
//     symbolic links leaving them, with the reason, and write nothing outside;
//  2. an existing state is replaced only when the request says so, by a rename (a new file, never
//     one rewritten in place), and no temporary is left behind; the node checkpointed its
//     precomputation;
//  3. killed with SIGKILL while it tracks, the node (respawned by roslaunch) resumes from its newest
//     checkpoint without precomputing and without meshing the multigrid levels (it kept them in its
//     state folder), tracks again within RESTART_BOUND_S of its launch, and its
//     lesions are those of a frame it published within one checkpoint period (and a frame) before
//     the kill, to LESION_TOLERANCE_M.
#include <gtest/gtest.h>

#include <signal.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <XmlRpc.h>
#include <ros/master.h>
#include <ros/network.h>
#include <ros/ros.h>
#include <sensor_msgs/PointCloud2.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/LoadCase.h>
#include <breast_sim/NodeState.h>
#include <breast_sim/StateFile.h>

#include "node_state_folder.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/state_file.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/tracker_simulation.h"
#include "wait_until.h"

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

namespace {

// From the launch of the respawned process to its first tracked frame [s].
constexpr double RESTART_BOUND_S = 5.0;
// The restored lesions against the array the killed node published from the same state: the state
// file holds the displacements as they were (float64), so they are the same numbers.
constexpr double LESION_TOLERANCE_M = 1e-9;
constexpr double CHECKPOINT_PERIOD_S = 1.0;  // node_files.test, checkpoint/period_s
constexpr double CLOUD_RATE_HZ = 10.0;

struct Received {
  Clock::time_point at;
  breast_sim::LesionArray::ConstPtr lesions;
};

struct Recorder {
  std::mutex m;
  breast_sim::NodeState::ConstPtr state;
  std::vector<breast_sim::NodeState::ConstPtr> states;  ///< every state since the last clear
  std::vector<Received> lesions;                        ///< every lesion array since the last clear
};
Recorder rec;
const breast_sim::test_fixtures::NodeStateFolder* state_folder = nullptr;  ///< set in main()

double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

template <class F>
bool waitUntil(F&& condition, double timeout_s) {
  return breast_sim::test_fixtures::waitUntil(rec.m, std::forward<F>(condition), timeout_s);
}

std::string stateText() {
  std::lock_guard<std::mutex> l(rec.m);
  return rec.state ? rec.state->state_name + ": " + rec.state->message : "(no state)";
}

bool precomputedAndIdle() {
  return rec.state && rec.state->precomputed && rec.state->state == breast_sim::NodeState::IDLE;
}

std::string fileText(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

/// The process id of /breast_sim, asked from the node itself (its XML-RPC getPid); -1 when it
/// does not answer (dead, or not registered yet).
int nodePid() {
  XmlRpc::XmlRpcValue args, result, payload;
  args[0] = ros::this_node::getName();
  args[1] = "/breast_sim";
  if (!ros::master::execute("lookupNode", args, result, payload, false)) return -1;
  std::string host;
  uint32_t port = 0;
  if (!ros::network::splitURI(static_cast<std::string>(payload), host, port)) return -1;
  XmlRpc::XmlRpcClient client(host.c_str(), static_cast<int>(port), "/");
  XmlRpc::XmlRpcValue request, response;
  request[0] = ros::this_node::getName();
  const bool ok = client.execute("getPid", request, response);
  client.close();
  if (!ok || response.getType() != XmlRpc::XmlRpcValue::TypeArray || response.size() < 3 ||
      static_cast<int>(response[0]) != 1)
    return -1;
  return static_cast<int>(response[2]);
}

/// Seconds since the process `pid` was started (its start time in /proc), or -1.
double processAge(int pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text;
  std::getline(stat, text);
  const size_t close = text.rfind(')');  // the command name may hold spaces
  if (close == std::string::npos) return -1;
  std::istringstream fields(text.substr(close + 2));
  std::string field;
  // Fields from the 3rd (state); the start time is the 22nd.
  for (int k = 3; k < 22 && fields >> field;) ++k;
  unsigned long long start_ticks = 0;
  if (!(fields >> start_ticks)) return -1;
  double uptime_s = 0;
  std::ifstream("/proc/uptime") >> uptime_s;
  return uptime_s - static_cast<double>(start_ticks) / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

double maxLesionDistanceM(const breast_sim::LesionArray& a, const breast_sim::LesionArray& b) {
  if (a.lesions.size() != b.lesions.size()) return INFINITY;
  double worst = 0;
  for (size_t i = 0; i < a.lesions.size(); ++i) {
    const auto& p = a.lesions[i].position;
    const auto& q = b.lesions[i].position;
    worst = std::max(worst, std::sqrt((p.x - q.x) * (p.x - q.x) + (p.y - q.y) * (p.y - q.y) + (p.z - q.z) * (p.z - q.z)));
  }
  return worst;
}

breast_sim::StateFile::Response saveState(const std::string& path, bool replace) {
  breast_sim::StateFile srv;
  srv.request.path = path;
  srv.request.replace = replace;
  EXPECT_TRUE(ros::service::call("/breast_sim/save_state", srv));
  return srv.response;
}

breast_sim::StateFile::Response loadState(const std::string& path) {
  breast_sim::StateFile srv;
  srv.request.path = path;
  EXPECT_TRUE(ros::service::call("/breast_sim/load_state", srv));
  return srv.response;
}

/// A temporary folder outside the node's folders, removed at the end.
struct OutsideFolder {
  OutsideFolder() {
    std::string pattern = (fs::temp_directory_path() / "breast_sim_outside_XXXXXX").string();
    if (::mkdtemp(pattern.data())) path = pattern;
  }
  ~OutsideFolder() {
    std::error_code ec;
    fs::remove_all(path, ec);
  }
  fs::path path;
};

}  // namespace

TEST(NodeFiles, RequestsCannotReachOutsideTheFolders) {
  ASSERT_TRUE(waitUntil(precomputedAndIdle, 300.0)) << stateText();
  const fs::path folder = state_folder->path();
  ASSERT_TRUE(fs::is_directory(folder)) << folder;
  OutsideFolder outside;
  ASSERT_FALSE(outside.path.empty());
  const fs::path target = outside.path / "target.state";
  std::ofstream(target) << "not to be overwritten";

  // '..' out of the folder.
  const auto up = saveState("../" + outside.path.filename().string() + "/escape.state", true);
  EXPECT_FALSE(up.success);
  EXPECT_NE(up.message.find("'..'"), std::string::npos) << up.message;
  EXPECT_FALSE(fs::exists(outside.path / "escape.state"));
  // An absolute path outside.
  const auto absolute = saveState(target.string(), true);
  EXPECT_FALSE(absolute.success);
  EXPECT_NE(absolute.message.find("is outside ~state_folder"), std::string::npos) << absolute.message;
  // A link in the folder to a file outside: neither written through nor read.
  fs::create_symlink(target, folder / "link.state");
  const auto through = saveState("link.state", true);
  EXPECT_FALSE(through.success);
  EXPECT_NE(through.message.find("symbolic link"), std::string::npos) << through.message;
  const auto read_link = loadState("link.state");
  EXPECT_FALSE(read_link.success);
  EXPECT_NE(read_link.message.find("a symbolic link leaves the folder"), std::string::npos) << read_link.message;
  EXPECT_EQ(fileText(target), "not to be overwritten");
  fs::remove(folder / "link.state");
  // Cases: only inside ~data_folder.
  std::ofstream(outside.path / "case.yaml") << "phantom: {}\n";
  breast_sim::LoadCase load;
  load.request.case_file = (outside.path / "case.yaml").string();
  ASSERT_TRUE(ros::service::call("/breast_sim/load_case", load));
  EXPECT_FALSE(load.response.success);
  EXPECT_NE(load.response.message.find("is outside ~data_folder"), std::string::npos) << load.response.message;
  load.request.case_file = "config/../../" + outside.path.filename().string() + "/case.yaml";
  ASSERT_TRUE(ros::service::call("/breast_sim/load_case", load));
  EXPECT_FALSE(load.response.success);
  EXPECT_NE(load.response.message.find("'..'"), std::string::npos) << load.response.message;
  // The model and its precomputed state are kept.
  EXPECT_TRUE(waitUntil(precomputedAndIdle, 5.0)) << stateText();
}

TEST(NodeFiles, AStateIsReplacedOnlyWhenAskedAndByARename) {
  ASSERT_TRUE(waitUntil(precomputedAndIdle, 60.0)) << stateText();
  const fs::path folder = state_folder->path();
  // The precomputation was checkpointed.
  int checkpoints = 0;
  for (const auto& entry : fs::directory_iterator(folder))
    checkpoints += entry.path().filename().string().rfind("checkpoint-", 0) == 0 ? 1 : 0;
  EXPECT_EQ(checkpoints, 1);
  // And the multigrid's coarse levels were kept beside it, for a restart.
  int levels = 0;
  for (const auto& entry : fs::directory_iterator(folder))
    levels += entry.path().filename().string().rfind("multigrid-", 0) == 0 ? 1 : 0;
  EXPECT_GE(levels, 1);

  const auto first = saveState("saved.state", false);
  ASSERT_TRUE(first.success) << first.message;
  const fs::path saved = folder / "saved.state";
  const std::string bytes = fileText(saved);
  struct stat before {};
  ASSERT_EQ(::stat(saved.c_str(), &before), 0);
  const auto again = saveState("saved.state", false);
  EXPECT_FALSE(again.success);
  EXPECT_NE(again.message.find("exists; set replace to true"), std::string::npos) << again.message;
  const auto replaced = saveState("saved.state", true);
  ASSERT_TRUE(replaced.success) << replaced.message;
  struct stat after {};
  ASSERT_EQ(::stat(saved.c_str(), &after), 0);
  EXPECT_NE(before.st_ino, after.st_ino) << "the file was rewritten in place, not replaced by a rename";
  EXPECT_EQ(fileText(saved), bytes);  // the same state, written again
  for (const auto& entry : fs::directory_iterator(folder))
    EXPECT_NE(entry.path().filename().string()[0], '.') << "a temporary was left: " << entry.path();
  EXPECT_NO_THROW(breast_sim::core::readStateFile(saved.string()));
  const auto load = loadState("saved.state");
  EXPECT_TRUE(load.success) << load.message;
}

TEST(NodeFiles, AfterSigkillTheRespawnedNodeTracksAgainWithTheSameLesions) {
  ASSERT_TRUE(waitUntil(precomputedAndIdle, 60.0)) << stateText();
  ros::NodeHandle pnh("~"), nh;
  std::string case_file;
  ASSERT_TRUE(pnh.getParam("case_file", case_file));
  // The phantom's simulated tracker: its supine skin, with noise, strays and breathing, on a table
  // that stays level (the node keeps the case's gravity: gravity/follow_patient_pose false).
  breast_sim::ros_interface::TrackerSimulationOptions options;
  options.tilt_amplitude_deg = 0.0;
  options.sway_amplitude_m = 0.0;
  breast_sim::ros_interface::TrackerSimulation tracker(breast_sim::core::loadModelCase(case_file), options);
  ros::Publisher clouds = nh.advertise<sensor_msgs::PointCloud2>("/breast_sim/surface_points", 2);
  std::atomic<bool> stop{false};
  const auto t_start = Clock::now();
  std::thread publisher([&] {
    ros::WallRate rate(CLOUD_RATE_HZ);
    while (!stop && ros::ok()) {
      clouds.publish(breast_sim::ros_interface::cloudToMessage(tracker.cloudInModel(since(t_start)), "breast_model",
                                                               ros::Time::now()));
      rate.sleep();
    }
  });
  struct Stopper {
    std::atomic<bool>& stop;
    std::thread& t;
    ~Stopper() {
      stop = true;
      if (t.joinable()) t.join();
    }
  } stopper{stop, publisher};

  ASSERT_TRUE(waitUntil([] { return rec.state && rec.state->state == breast_sim::NodeState::TRACKING; }, 30.0))
      << stateText();
  {
    std::lock_guard<std::mutex> l(rec.m);
    rec.lesions.clear();  // from here on: the arrays of tracked frames
  }
  // Several checkpoint periods of tracking.
  std::this_thread::sleep_for(std::chrono::duration<double>(3.5 * CHECKPOINT_PERIOD_S));
  const int pid = nodePid();
  ASSERT_GT(pid, 0) << "the node's process id is unknown";
  std::vector<Received> before;
  {
    std::lock_guard<std::mutex> l(rec.m);
    before.swap(rec.lesions);
    rec.states.clear();
    rec.state.reset();
  }
  ASSERT_FALSE(before.empty());
  const auto t_kill = Clock::now();
  ASSERT_EQ(::kill(pid, SIGKILL), 0);

  // roslaunch respawns it; it registers under the same name.
  int new_pid = -1;
  const auto t_wait = Clock::now();
  while (since(t_wait) < 30.0 && ((new_pid = nodePid()) <= 0 || new_pid == pid))
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  ASSERT_GT(new_pid, 0) << "the node was not respawned";
  ASSERT_NE(new_pid, pid);
  // Tracking again: a state that says the checkpoint was resumed, then a tracked frame.
  bool resumed = false;
  std::string resumed_message;
  ASSERT_TRUE(waitUntil([&] {
    for (const auto& s : rec.states) {
      if (!resumed && s->message.find("resumed case") != std::string::npos) {
        resumed = true;
        resumed_message = s->message;
      }
      if (resumed && s->state == breast_sim::NodeState::TRACKING) return true;
    }
    return false;
  }, 60.0)) << "the respawned node did not track again: " << stateText();
  const double kill_to_tracking_s = since(t_kill);
  const double launch_to_tracking_s = processAge(new_pid);  // the process is alive: measured now
  std::vector<breast_sim::NodeState::ConstPtr> states;
  std::vector<Received> after;
  {
    std::lock_guard<std::mutex> l(rec.m);
    states = rec.states;
    after = rec.lesions;
  }
  std::printf("[ measure  ] restart: killed -> tracking %.2f s, launch of the respawned node -> tracking %.2f s "
              "(bound %.1f s)\n", kill_to_tracking_s, launch_to_tracking_s, RESTART_BOUND_S);
  EXPECT_GT(launch_to_tracking_s, 0.0);
  EXPECT_LT(launch_to_tracking_s, RESTART_BOUND_S);
  EXPECT_NE(resumed_message.find("multigrid levels read from the state folder"), std::string::npos) << resumed_message;
  for (const auto& s : states)
    EXPECT_NE(s->state, breast_sim::NodeState::PRECOMPUTING) << "the respawned node precomputed: " << s->message;

  // The lesions it resumed with: those of the state it loaded, published before any new cloud.
  const Received* restored = nullptr;
  for (const auto& r : after)
    if (r.lesions->status.rfind("loaded state", 0) == 0) {
      restored = &r;
      break;
    }
  ASSERT_NE(restored, nullptr) << "no lesion array of the resumed state";
  EXPECT_TRUE(restored->lesions->valid);
  double best = INFINITY;
  const Received* match = nullptr;
  for (const auto& r : before) {
    const double d = maxLesionDistanceM(*r.lesions, *restored->lesions);
    if (d <= best) {  // the newest of equal ones
      best = d;
      match = &r;
    }
  }
  ASSERT_NE(match, nullptr);
  const double age_s = std::chrono::duration<double>(t_kill - match->at).count();
  double moved = 0;  // how far tracking moved the lesions before the kill: the match is not a coincidence
  for (const auto& r : before) moved = std::max(moved, maxLesionDistanceM(*r.lesions, *before.front().lesions));
  std::printf("[ measure  ] resumed lesions vs the nearest array published before the kill: %.3g m (tolerance %.0e m), "
              "that array received %.2f s before the kill; the tracked lesions moved up to %.3f mm before it\n",
              best, LESION_TOLERANCE_M, age_s, 1e3 * moved);
  EXPECT_LE(best, LESION_TOLERANCE_M);
  // The newest checkpoint: at most a period and a frame (and its latency) before the kill.
  EXPECT_LT(age_s, CHECKPOINT_PERIOD_S + 1.0);
  // And it tracks on: valid arrays of new clouds after the resumed one.
  int tracked = 0;
  for (const auto& r : after) tracked += (&r != restored && r.lesions->valid && r.at > restored->at) ? 1 : 0;
  EXPECT_GE(tracked, 1);
}

void onState(const breast_sim::NodeState::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(rec.m);
  rec.state = msg;
  rec.states.push_back(msg);
}

void onLesions(const breast_sim::LesionArray::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(rec.m);
  rec.lesions.push_back({Clock::now(), msg});
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "node_files_test");
  ros::NodeHandle nh;
  const breast_sim::test_fixtures::NodeStateFolder folder;
  state_folder = &folder;
  ros::Subscriber s1 = nh.subscribe("/breast_sim/state", 100, onState);
  ros::Subscriber s2 = nh.subscribe("/breast_sim/lesions", 1000, onLesions);
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
