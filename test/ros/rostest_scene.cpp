// Integration test of the navigation node on a recorded scene (test/ros/scene.test) that was not
// made by the node's own tracker simulation: ros_interface::writeSceneBag, from the node's precomputed
// skin, with two sensors of its own (an organized FLOAT32 depth camera with rgb and padding, NaN where
// it sees nothing, and a FLOAT64 hand-held scanner that moves on tf), a hand over the skin, the torso
// around the breast, the patient's pose on tf only, bad inputs at known times, and a 20 mm slide of
// the skin along the chest wall at the end. On simulated time:
//  1. the node precomputes on request; its lesions then are the truth (the scene's skin is the
//     precomputed skin, so the lesions should stay where they are);
//  2. the bag plays (rosbag play --clock) while ~lesions, ~state and /rosout are recorded;
//  3. the node survives; outside the drift its valid lesions are within LESION_TOLERANCE_MM of the
//     truth and most clouds give valid lesions; every kind of bad input is refused with a warning
//     that names it, throttled; no lesion array is stamped in the future; the drift turns ~state
//     degraded and the lesions invalid within a few frames, and they stay invalid while it lasts.
// All waits are on wall time. Until the bag plays, this client drives the simulated clock (from 1 s at
// a tenth of wall speed, below the scene's 100 s): the node's timers need a running clock.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>
#include <thread>

#include <ros/ros.h>
#include <rosgraph_msgs/Log.h>
#include <std_srvs/Trigger.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/NodeState.h>
#include <breast_sim/StartPrecomputation.h>
#include <breast_sim/TetrahedralMesh.h>

#include "node_state_folder.h"
#include "simulated_clock.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/morphing/target_surface.h"
#include "breast_sim/ros_interface/conversions.h"
#include "breast_sim/ros_interface/scene_recording.h"
#include "wait_until.h"

using namespace breast_sim;
using ros_interface::SceneBadKind;

namespace {

using Clock = std::chrono::steady_clock;

// Valid lesions outside the drift vs the precomputed ones. The scene's skin is the precomputed skin;
// what moves the lesions is the table's ±1° roll (gravity follows it past the node's 0.5° threshold),
// the sensors' noise (0.5 mm depth, 0.3 mm scanner), the hand's occlusion and the torso near the
// rim. Measured with the node's limits: 0.30-0.50 mm at most, 0.16-0.25 mm mean (3.6k elements);
// three times that.
constexpr double LESION_TOLERANCE_MM = 1.5;
// Share of the good clouds (before the drift) whose lesion array is valid. Measured: 0.986 where the
// node keeps tracking (210 of 213, at play rate 0.5). The 60 Hz burst is a quarter of the clouds, and
// a node on a loaded machine drops most of it (newest wins).
constexpr double MIN_TRACKED_SHARE = 0.7;
// Depth frames from the drift's start to the first invalid lesion array and to degraded ~state: the
// ramp (1.33 mm per frame) passes the node's 3 mm ICP correction limit at the 3rd-4th frame, then
// degraded_after_rejected (5) refused clouds in a row make the lesions invalid. Measured: 9 and 9;
// three frames of margin.
constexpr int MAX_FRAMES_TO_DEGRADED = 12;
// A lesion array's stamp may lead this client's clock at its arrival by one /clock period of rosbag
// play (10 ms at its 100 Hz) and the delivery jitter; the node refuses clouds 0.5 s ahead.
constexpr double FUTURE_SLACK_S = 0.1;
constexpr const char* kNodeName = "/breast_sim";

double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

struct Received {
  breast_sim::LesionArray::ConstPtr msg;
  double clock_s;  ///< this client's simulated clock at arrival
};

struct Recorder {
  std::mutex m;
  breast_sim::NodeState::ConstPtr state;
  breast_sim::LesionArray::ConstPtr lesions;
  breast_sim::TetrahedralMesh::ConstPtr mesh;
  bool recording = false;
  std::vector<Received> lesion_history;
  std::vector<breast_sim::NodeState::ConstPtr> state_history;
  std::vector<rosgraph_msgs::Log::ConstPtr> warnings;  ///< WARN and above from the node
};
Recorder rec;
breast_sim::test_fixtures::SimulatedClock* sim_clock = nullptr;  ///< set in main()

template <class F>
bool waitUntil(F&& condition, double timeout_s) {
  return breast_sim::test_fixtures::waitUntil(rec.m, std::forward<F>(condition), timeout_s);
}

std::string stateText() {
  std::lock_guard<std::mutex> l(rec.m);
  return rec.state ? rec.state->state_name + ": " + rec.state->message : "(no state)";
}

double maxLesionErrorMm(const breast_sim::LesionArray& msg, const breast_sim::LesionArray& truth) {
  double worst = 0;
  for (size_t i = 0; i < msg.lesions.size() && i < truth.lesions.size(); ++i) {
    const auto &p = msg.lesions[i].position, &q = truth.lesions[i].position;
    worst = std::max(worst, 1e3 * std::hypot(p.x - q.x, p.y - q.y, p.z - q.z));
  }
  return worst;
}

/// What a warning of the node says for each kind of bad input (its texts in breast_sim_node.cpp,
/// input_checks.cpp and conversions.cpp): every substring must occur.
std::vector<std::string> warningWords(SceneBadKind k, const ros_interface::SceneOptions& o) {
  switch (k) {
    case SceneBadKind::kPoseNearZeroQuaternion: return {"~patient_pose refused", "unit quaternion"};
    case SceneBadKind::kPoseFlipped: return {"~patient_pose refused", "jumped"};
    case SceneBadKind::kPoseFuture: return {"~patient_pose refused", "ahead of the clock"};
    case SceneBadKind::kCloudFuture: return {"cloud on ~surface_points refused", "ahead of the clock"};
    case SceneBadKind::kCloudPast: return {"cloud on ~surface_points refused", "behind the clock"};
    case SceneBadKind::kCloudTruncated: return {"malformed cloud", "truncated"};
    case SceneBadKind::kCloudAllNan: return {"NaN/inf"};
    case SceneBadKind::kCloudUnknownFrame: return {"cloud in frame '" + o.unknown_frame + "'"};
  }
  return {"?"};
}

// What the tests share: the truth, the scene and what the node published while it played.
struct Run {
  bool precomputed = false, played = false;
  breast_sim::LesionArray truth;
  ros_interface::SceneOptions options;
  ros_interface::SceneDescription scene;
  std::vector<Received> lesions;
  std::vector<breast_sim::NodeState::ConstPtr> states;
  std::vector<rosgraph_msgs::Log::ConstPtr> warnings;
  double play_wall_s = 0;
};
Run run;

bool isStamp(double a, double b) { return std::abs(a - b) < 1e-6; }

}  // namespace

TEST(Scene, Precomputes) {
  ASSERT_TRUE(ros::service::waitForService("/breast_sim/start_precomputation", ros::Duration(60.0)));
  ASSERT_TRUE(waitUntil([] { return rec.state && rec.state->model_loaded && rec.state->state == breast_sim::NodeState::IDLE; }, 120.0))
      << stateText();
  breast_sim::StartPrecomputation start;
  ASSERT_TRUE(ros::service::call("/breast_sim/start_precomputation", start));
  ASSERT_TRUE(start.response.accepted) << start.response.message;
  ASSERT_TRUE(waitUntil(
      [] {
        return rec.state && rec.state->precomputed && rec.state->state == breast_sim::NodeState::IDLE && rec.lesions &&
               rec.lesions->valid && rec.lesions->status == "precomputed" && rec.mesh;
      },
      120.0))
      << stateText();
  std::lock_guard<std::mutex> l(rec.m);
  run.truth = *rec.lesions;
  ASSERT_FALSE(run.truth.lesions.empty());
  run.precomputed = true;
}

TEST(Scene, Plays) {
  ASSERT_TRUE(run.precomputed);
  ros::NodeHandle pnh("~");
  std::string case_file, bag;
  double play_rate = 0.5;
  int seed = 1;
  pnh.getParam("case_file", case_file);
  pnh.getParam("bag", bag);
  pnh.getParam("play_rate", play_rate);
  pnh.getParam("seed", seed);
  // The node's precomputed skin, from its latched mesh.
  breast_sim::TetrahedralMesh::ConstPtr mesh_msg;
  {
    std::lock_guard<std::mutex> l(rec.m);
    mesh_msg = rec.mesh;
  }
  const core::TetMesh mesh = ros_interface::meshFromMessage(*mesh_msg);
  const core::Points x = mesh.nodes() + ros_interface::displacementFromMessage(*mesh_msg);
  const core::Triangles skin = core::skinTriangles(mesh, mesh.nodeSet(core::node_sets::kSkin));
  run.options.seed = static_cast<unsigned>(seed);
  // Parts of the scene left out (scene.test's leave_out, for studying the node and for checking
  // that the assertions fail without what they test): torso, hand, drift, flipped_pose, bad_inputs.
  std::string leave_out;
  pnh.getParam("leave_out", leave_out);
  auto left_out = [&](const std::string& part) { return ("," + leave_out + ",").find("," + part + ",") != std::string::npos; };
  run.options.with_torso = !left_out("torso");
  run.options.with_hand = !left_out("hand");
  if (left_out("drift")) run.options.drift_m = 0.0;
  if (left_out("bad_inputs")) run.options.bad_bursts.clear();
  if (left_out("flipped_pose"))
    run.options.bad_bursts.erase(std::remove_if(run.options.bad_bursts.begin(), run.options.bad_bursts.end(),
                                                [](const ros_interface::SceneBadBurst& b) { return b.kind == SceneBadKind::kPoseFlipped; }),
                                 run.options.bad_bursts.end());
  if (!leave_out.empty()) std::printf("[ measure  ] left out of the scene: %s\n", leave_out.c_str());
  run.options.gravity_in_model = ros_interface::supineGravityDirection(core::loadModelCase(case_file));
  const auto t_write = Clock::now();
  run.scene = ros_interface::writeSceneBag(bag, x, skin, run.options);
  std::printf("[ measure  ] scene bag written in %.1f s: %zu good clouds, %zu bad inputs, %.0f s of scene time\n",
              since(t_write), run.scene.clouds.size(), run.scene.bad_inputs.size(), run.scene.end_s - run.scene.start_s);
  std::printf("%s", run.scene.toYaml().c_str());
  {
    std::lock_guard<std::mutex> l(rec.m);
    rec.lesion_history.clear();
    rec.state_history.clear();
    rec.warnings.clear();
    rec.recording = true;
  }
  sim_clock->stop();  // rosbag play --clock takes over
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const auto t0 = Clock::now();
  const int status =
      std::system(("rosbag play --clock -q -r " + std::to_string(play_rate) + " " + bag + " > /dev/null 2>&1").c_str());
  run.play_wall_s = since(t0);
  std::this_thread::sleep_for(std::chrono::milliseconds(1000));  // the last clouds' results
  std::remove(bag.c_str());
  ASSERT_EQ(status, 0) << "rosbag play failed";
  std::lock_guard<std::mutex> l(rec.m);
  rec.recording = false;
  run.lesions = rec.lesion_history;
  run.states = rec.state_history;
  run.warnings = rec.warnings;
  std::printf("[ measure  ] bag played in %.1f s (rate %.2f): %zu lesion arrays, %zu states, %zu warnings from the node\n",
              run.play_wall_s, play_rate, run.lesions.size(), run.states.size(), run.warnings.size());
  run.played = true;
  // The timeline, per second of scene time: lesion arrays valid / not valid, and ~state changes.
  for (double t = std::floor(run.scene.start_s); t < run.scene.end_s + 1; t += 1.0) {
    int v = 0, nv = 0;
    for (const auto& r : run.lesions) {
      const double st = r.msg->header.stamp.toSec();
      if (st >= t && st < t + 1) (r.msg->valid ? v : nv) += 1;
    }
    std::string states;
    for (const auto& st : run.states)
      if (st->header.stamp.toSec() >= t && st->header.stamp.toSec() < t + 1) states += " " + st->state_name;
    std::printf("[ timeline ] %.0f-%.0f s: %2d valid, %2d not valid arrays; states:%s\n", t, t + 1, v, nv, states.c_str());
  }
}

TEST(Scene, NodeSurvives) {
  ASSERT_TRUE(run.played);
  std_srvs::Trigger cancel;
  EXPECT_TRUE(ros::service::call("/breast_sim/cancel_precomputation", cancel)) << "the node's services no longer answer";
  EXPECT_TRUE(ros::service::exists("/breast_sim/start_precomputation", false));
  EXPECT_FALSE(run.lesions.empty());
}

TEST(Scene, TracksTheGoodSegmentsWithinTolerance) {
  ASSERT_TRUE(run.played);
  const auto& s = run.scene;
  double worst = 0, sum = 0;
  int valid = 0, invalid = 0;
  std::map<std::string, std::pair<int, int>> share;  // sensor/segment → (valid arrays, clouds)
  std::string worst_at;
  for (const auto& r : run.lesions) {
    const double t = r.msg->header.stamp.toSec();
    if (t < s.start_s || t >= s.drift_begin_s) continue;
    if (!r.msg->valid) {
      ++invalid;
      continue;
    }
    const double e = maxLesionErrorMm(*r.msg, run.truth);
    if (e > worst) {
      worst = e;
      char b[64];
      std::snprintf(b, sizeof b, "t = %.3f s", t);
      worst_at = b;
    }
    sum += e;
    ++valid;
  }
  int clouds = 0, tracked = 0;
  for (const auto& c : s.clouds) {
    if (c.stamp_s >= s.drift_begin_s) continue;
    bool ok = false;
    for (const auto& r : run.lesions)
      if (isStamp(r.msg->header.stamp.toSec(), c.stamp_s) && r.msg->valid) ok = true;
    const bool burst = c.stamp_s >= s.segments[1].begin_s && c.stamp_s < s.segments[1].end_s;
    const std::string kind = !c.depth_camera ? "hand-held scanner" : burst ? "depth camera 60 Hz burst" : c.hand ? "depth camera, hand in view" : "depth camera";
    share[kind].first += ok;
    share[kind].second += 1;
    ++clouds;
    tracked += ok;
  }
  std::printf("[ measure  ] good segments: %d valid lesion arrays, max error %.3f mm (%s), mean %.3f mm (tolerance %.1f mm); %d invalid\n",
              valid, worst, worst_at.c_str(), valid ? sum / valid : 0.0, LESION_TOLERANCE_MM, invalid);
  for (const auto& [kind, n] : share)
    std::printf("[ measure  ]   %s: %d of %d clouds gave valid lesions\n", kind.c_str(), n.first, n.second);
  const double tracked_share = clouds ? static_cast<double>(tracked) / clouds : 0.0;
  std::printf("[ measure  ] tracked share of the good clouds: %.3f (%d of %d; at least %.2f)\n", tracked_share, tracked, clouds,
              MIN_TRACKED_SHARE);
  EXPECT_GT(valid, 0);
  EXPECT_LT(worst, LESION_TOLERANCE_MM) << "worst at " << worst_at;
  EXPECT_GE(tracked_share, MIN_TRACKED_SHARE);
}

TEST(Scene, RefusesAndLogsEveryBadInput) {
  ASSERT_TRUE(run.played);
  for (int k = 0; k < ros_interface::kSceneBadKinds; ++k) {
    const auto kind = static_cast<SceneBadKind>(k);
    const std::vector<std::string> words = warningWords(kind, run.options);
    int n = 0;
    std::string example;
    for (const auto& w : run.warnings) {
      bool all = true;
      for (const auto& word : words) all = all && w->msg.find(word) != std::string::npos;
      if (all) {
        ++n;
        if (example.empty()) example = w->msg;
      }
    }
    const int bursts = run.scene.bursts(kind);
    if (bursts == 0) continue;  // left out of this scene
    // Each burst (bad_burst_size messages within 0.4 s of scene time, < 1 s of wall time) falls within
    // one throttle period (tracking/warn_throttle_s = 5 s): at most one warning per burst.
    std::printf("[ measure  ] %-32s %d warnings for %d bursts of %d%s%s\n", ros_interface::sceneBadKindName(kind), n, bursts,
                run.options.bad_burst_size, example.empty() ? "" : ": ", example.substr(0, 160).c_str());
    EXPECT_GE(n, 1) << ros_interface::sceneBadKindName(kind) << ": no warning from the node names it";
    EXPECT_LE(n, bursts) << ros_interface::sceneBadKindName(kind) << ": more warnings than bursts (throttle)";
  }
}

TEST(Scene, NoLesionArrayStampedInTheFuture) {
  ASSERT_TRUE(run.played);
  double lead = -1e9;
  for (const auto& r : run.lesions) lead = std::max(lead, r.msg->header.stamp.toSec() - r.clock_s);
  double latest = 0;
  for (const auto& r : run.lesions) latest = std::max(latest, r.msg->header.stamp.toSec());
  std::printf("[ measure  ] largest lead of a lesion stamp over the clock at arrival: %.3f s (slack %.2f s); latest stamp %.3f s (scene end %.3f s)\n",
              lead, FUTURE_SLACK_S, latest, run.scene.end_s);
  EXPECT_LT(lead, FUTURE_SLACK_S);
  EXPECT_LT(latest, run.scene.end_s + 2.0);
}

TEST(Scene, DriftTurnsDegradedAndTheLesionsInvalid) {
  ASSERT_TRUE(run.played);
  const auto& s = run.scene;
  std::vector<double> drift_frames;  // depth clouds of the drift, by stamp
  for (const auto& c : s.clouds)
    if (c.depth_camera && c.stamp_s >= s.drift_begin_s) drift_frames.push_back(c.stamp_s);
  auto framesUntil = [&](double t) {
    return static_cast<int>(std::upper_bound(drift_frames.begin(), drift_frames.end(), t + 1e-6) - drift_frames.begin());
  };
  // What was in force when the drift began: the newest ~state and lesion array stamped before it.
  const breast_sim::NodeState* state_before = nullptr;
  const breast_sim::LesionArray* lesions_before = nullptr;
  for (const auto& st : run.states)
    if (st->header.stamp.toSec() < s.drift_begin_s) state_before = st.get();
  for (const auto& r : run.lesions)
    if (r.msg->header.stamp.toSec() < s.drift_begin_s) lesions_before = r.msg.get();
  double first_invalid = -1, first_degraded = -1;
  std::string reason;
  for (const auto& r : run.lesions) {
    const double t = r.msg->header.stamp.toSec();
    if (t >= s.drift_begin_s && !r.msg->valid) {
      first_invalid = t;
      break;
    }
  }
  for (const auto& st : run.states) {
    const double t = st->header.stamp.toSec();
    if (t >= s.drift_begin_s && st->state == breast_sim::NodeState::DEGRADED) {
      first_degraded = t;
      reason = st->message;
      break;
    }
  }
  std::printf("[ measure  ] when the drift began (t = %.3f s): ~state %s, lesions %s\n", s.drift_begin_s,
              state_before ? state_before->state_name.c_str() : "(none)",
              lesions_before ? (lesions_before->valid ? "valid" : "not valid") : "(none)");
  // The drift turns a tracking node degraded: it must be tracking with valid lesions before.
  EXPECT_TRUE(state_before && state_before->state == breast_sim::NodeState::TRACKING) << "not tracking when the drift began";
  EXPECT_TRUE(lesions_before && lesions_before->valid) << "the lesions were not valid when the drift began";
  ASSERT_GE(first_invalid, 0) << "no lesion array marked not valid during the drift";
  ASSERT_GE(first_degraded, 0) << "~state did not become degraded during the drift";
  const int frames_invalid = framesUntil(first_invalid), frames_degraded = framesUntil(first_degraded);
  // Through the rest of the drift: no valid lesions, no state back to tracking.
  int valid_after = 0, tracking_after = 0;
  for (const auto& r : run.lesions) {
    const double t = r.msg->header.stamp.toSec();
    if (t > first_invalid && t <= s.drift_end_s && r.msg->valid) ++valid_after;
  }
  for (const auto& st : run.states) {
    const double t = st->header.stamp.toSec();
    if (t > first_degraded && t <= s.drift_end_s && st->state == breast_sim::NodeState::TRACKING) ++tracking_after;
  }
  std::printf("[ measure  ] drift: lesions not valid after %d depth frames (t = %.3f s), ~state degraded after %d "
              "(t = %.3f s: %s); at most %d; afterwards %d valid arrays, %d tracking states\n",
              frames_invalid, first_invalid, frames_degraded, first_degraded, reason.substr(0, 200).c_str(),
              MAX_FRAMES_TO_DEGRADED, valid_after, tracking_after);
  EXPECT_LE(frames_invalid, MAX_FRAMES_TO_DEGRADED);
  EXPECT_LE(frames_degraded, MAX_FRAMES_TO_DEGRADED);
  EXPECT_EQ(valid_after, 0);
  EXPECT_EQ(tracking_after, 0);
}

namespace {
double clockNow() { return ros::Time::now().toSec(); }
void onState(const breast_sim::NodeState::ConstPtr& m) {
  std::lock_guard<std::mutex> l(rec.m);
  rec.state = m;
  if (rec.recording) rec.state_history.push_back(m);
}
void onMesh(const breast_sim::TetrahedralMesh::ConstPtr& m) {
  std::lock_guard<std::mutex> l(rec.m);
  rec.mesh = m;
}
void onLesions(const breast_sim::LesionArray::ConstPtr& m) {
  const double now = clockNow();
  std::lock_guard<std::mutex> l(rec.m);
  rec.lesions = m;
  if (rec.recording) rec.lesion_history.push_back({m, now});
}
void onLog(const rosgraph_msgs::Log::ConstPtr& m) {
  if (m->name != kNodeName || m->level < rosgraph_msgs::Log::WARN) return;
  std::lock_guard<std::mutex> l(rec.m);
  if (rec.recording) rec.warnings.push_back(m);
}
}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "scene_test");
  ros::NodeHandle nh;
  ros::Subscriber s1 = nh.subscribe("/breast_sim/state", 100, onState);
  ros::Subscriber s2 = nh.subscribe("/breast_sim/deformed_mesh", 2, onMesh);
  // Longer than the scene: an array lost here would read as a cloud the node did not track.
  ros::Subscriber s3 = nh.subscribe("/breast_sim/lesions", 2000, onLesions);
  ros::Subscriber s4 = nh.subscribe("/rosout", 1000, onLog);
  const breast_sim::test_fixtures::NodeStateFolder state_folder;
  breast_sim::test_fixtures::SimulatedClock clock(nh);
  sim_clock = &clock;
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int status = RUN_ALL_TESTS();
  clock.stop();
  return status;
}
