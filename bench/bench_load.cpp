// Load study: how the Table-1 step, the tracking frame and the main job hold up when other processes
// take cores.
// The same work runs idle, beside one and beside two busy processes (busy loops this program forks
// and kills, each also ended by the kernel when this program dies and by an alarm after
// --busy-limit-s), with the program's OpenMP threads (from which each time step chooses its count by
// the load it sees, docs/load.md) and with one thread, printed side by side:
//   step      the seed's Table-1 step (bench_simulation): the phantom under supine gravity, chest
//             wall fixed, --steps implicit steps of the seed's co-rotated linear tetrahedra of dt
//             0.033 s, multigrid-PCG to the case's tolerance (1e-2), a fresh simulator per run
//             (mean and median step);
//   frame     the tracking frame's core (what ros_interface::SurfaceTracker::track does after the
//             cloud filters): a new point cloud as target (its distance field rebuilt) and one
//             morphing iteration at the tracker's PCG tolerance 0.3, on a model settled under supine
//             gravity (with sliding, as the node precomputes it) at --tracking-elements, the node's
//             3 mm distance field; every run starts from the same snapshot; the cloud is every k-th
//             vertex of the phantom's supine skin (about --cloud-points), shifted by 0.1 mm more
//             each frame (median and 95th percentile per frame);
//   main job  what `breast_sim_run --case config/phantom_default.yaml` computes (README's first
//             command): the pipeline built on the case's own mesh, its gravity, sliding and morphing
//             stages; the stages' seconds (breast_sim_run's "compute"), the set-up not included.
// --rounds times over, every round through every load level, each figure the median over the rounds.
// Ratios against the idle run with one thread less (the cores the program keeps when another
// process takes one) and against one thread under the same load come from the same run.
//   bench_load [--elements 47895] [--steps 25] [--tracking-elements 20000] [--frames 30]
//              [--cloud-points 10000] [--rounds 3] [--busy 0,1,2] [--busy-limit-s 600] [--json FILE]
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <omp.h>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

/// `count` busy processes (one spinning loop each) from construction to destruction. A child also
/// dies with this process (PR_SET_PDEATHSIG) and after `limit_s` seconds at the latest (alarm).
class BusyProcesses {
 public:
  BusyProcesses(int count, unsigned limit_s) {
    for (int i = 0; i < count; ++i) {
      const pid_t pid = fork();
      if (pid < 0) throw std::runtime_error(std::string("fork failed: ") + std::strerror(errno));
      if (pid == 0) {
        prctl(PR_SET_PDEATHSIG, SIGKILL);
        alarm(limit_s);
        volatile double x = 1.0;
        for (;;) x = x * 1.0000001 + 1e-9;
      }
      pids_.push_back(pid);
    }
    // Let the scheduler see them busy before anything is timed.
    if (count > 0) std::this_thread::sleep_for(std::chrono::milliseconds(300));
  }
  ~BusyProcesses() {
    for (pid_t pid : pids_) kill(pid, SIGKILL);
    for (pid_t pid : pids_) waitpid(pid, nullptr, 0);
  }
  BusyProcesses(const BusyProcesses&) = delete;
  BusyProcesses& operator=(const BusyProcesses&) = delete;

 private:
  std::vector<pid_t> pids_;
};

double percentile95(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(std::ceil(0.95 * static_cast<double>(v.size()))) - 1)];
}

/// What OpenMP was told about waiting, as libgomp read it at start: the process's OMP_WAIT_POLICY
/// and GOMP_SPINCOUNT ("-" where unset).
std::string waitSettings() {
  const char* policy = std::getenv("OMP_WAIT_POLICY");
  const char* spin = std::getenv("GOMP_SPINCOUNT");
  return std::string("OMP_WAIT_POLICY=") + (policy ? policy : "-") + " GOMP_SPINCOUNT=" + (spin ? spin : "-");
}

// The node's tracking settings (ros_interface::TrackerOptions::solver_relative_tolerance and the
// field_voxel_size_m parameter): this bench links the core alone.
constexpr double kTrackerTolerance = 0.3;
constexpr double kNodeFieldVoxelM = 0.003;

struct Timing {
  double mean_ms = 0, median_ms = 0, p95_ms = 0;
};

Timing summarise(const std::vector<double>& seconds) {
  std::vector<double> ms;
  for (double s : seconds) ms.push_back(1e3 * s);
  return {mean(ms), median(ms), percentile95(ms)};
}

}  // namespace

int main(int argc, char** argv) {
  int elements = 47895, steps = 25, tracking_elements = 20000, frames = 30, cloud_points = 10000, rounds = 3;
  unsigned busy_limit_s = 600;
  std::vector<double> busy_levels = {0, 1, 2};
  std::string json_path;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&] { return argValue(argc, argv, i); };
    if (a == "--elements") elements = std::stoi(next());
    else if (a == "--steps") steps = std::stoi(next());
    else if (a == "--tracking-elements") tracking_elements = std::stoi(next());
    else if (a == "--frames") frames = std::stoi(next());
    else if (a == "--cloud-points") cloud_points = std::stoi(next());
    else if (a == "--rounds") rounds = std::stoi(next());
    else if (a == "--busy") busy_levels = parseList(next());
    else if (a == "--busy-limit-s") busy_limit_s = static_cast<unsigned>(std::stoul(next()));
    else if (a == "--json") json_path = next();
    else {
      std::fprintf(stderr, "usage: bench_load [--elements 47895] [--steps 25] [--tracking-elements 20000] [--frames 30]\n"
                           "                  [--cloud-points 10000] [--rounds 3] [--busy 0,1,2] [--busy-limit-s 600] [--json FILE]\n");
      return 2;
    }
  }
  if (steps < 1 || frames < 1 || rounds < 1 || cloud_points < 1 || busy_levels.empty() || busy_limit_s < 1) {
    std::fprintf(stderr, "bench_load: --steps, --frames, --rounds, --cloud-points and --busy-limit-s must be at least 1, "
                         "--busy not empty\n");
    return 2;
  }
  for (double level : busy_levels)
    if (level < 0 || level > 64 || level != std::floor(level)) {
      std::fprintf(stderr, "bench_load: --busy takes whole numbers of processes from 0 to 64, not %g\n", level);
      return 2;
    }
  const int threads = omp_get_max_threads();
  std::vector<int> thread_counts = {threads};
  if (threads > 1) thread_counts.push_back(1);
  const std::string wait = waitSettings();
  std::printf("Load study: %d OpenMP threads (and 1), %u cores online, %s, load average %.2f at start\n", threads,
              std::thread::hardware_concurrency(), wait.c_str(), loadAverage());
  std::fflush(stdout);

  const std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  const ModelCase base = loadModelCase(case_path);
  const PipelineSettings job_settings = loadPipelineSettings(case_path);  // the main job's, as the case has them
  const Eigen::Vector3d g_supine = base.phantom->gravity_supine_mps2;

  // The step's model.
  ModelCase step_case = base;
  step_case.meshing.target_elements = elements;
  const SimulationModel step_model = buildSimulationModel(step_case);
  SimulationSettings step_settings;
  step_settings.element = SimulationSettings::Element::kLinearTet;  // the seed's Table-1 element
  step_settings.dynamics.gravity_mps2 = g_supine;

  // The frame's model, settled once; every run starts from this snapshot.
  ModelCase track_case = base;
  track_case.meshing.target_elements = tracking_elements;
  const SimulationModel track_model = buildSimulationModel(track_case);
  PipelineSettings track_settings = job_settings;
  track_settings.morphing.field.voxel_size_m = kNodeFieldVoxelM;
  ProneToSupinePipeline pipeline(track_case, track_model, track_settings);
  pipeline.runGravity();
  const PipelineState settled = pipeline.state();
  // The cloud: every k-th vertex of the phantom's supine skin, about --cloud-points of them.
  const Points& skin_vertices = pipeline.target().vertices_m;
  const Eigen::Index stride = std::max<Eigen::Index>(1, (skin_vertices.rows() + cloud_points - 1) / cloud_points);
  Points skin((skin_vertices.rows() + stride - 1) / stride, 3);
  for (Eigen::Index i = 0; i < skin.rows(); ++i) skin.row(i) = skin_vertices.row(i * stride);
  std::printf("step: %d elements, %d steps; frame: %d elements, a cloud of %ld points, %d frames\n",
              step_model.mesh.numTets(), steps, track_model.mesh.numTets(), static_cast<long>(skin.rows()), frames);
  std::fflush(stdout);

  auto runStep = [&]() {
    SimulatorBuild b = buildSimulator(step_case, step_model, step_settings);
    std::vector<double> t;
    b.simulator->step();  // the first step carries the solver's first set-up: not timed
    for (int s = 0; s < steps; ++s) t.push_back(b.simulator->step().total_seconds);
    return summarise(t);
  };
  auto runFrames = [&]() {
    pipeline.restore(settled);
    LinearSolver& solver = pipeline.simulator().solver();
    const double saved = solver.relativeTolerance();
    solver.setRelativeTolerance(kTrackerTolerance);
    pipeline.setTrackingMode(true);
    std::vector<double> t;
    TargetSurface cloud;
    for (int f = 0; f < frames; ++f) {
      cloud.vertices_m = skin;
      cloud.vertices_m.col(1).array() -= 1e-4 * (f + 1);
      const auto t0 = Clock::now();
      pipeline.setTarget(cloud);
      pipeline.iterate();
      t.push_back(since(t0));
    }
    pipeline.setTrackingMode(false);
    solver.setRelativeTolerance(saved);
    return summarise(t);
  };

  // The main job's model, meshed once (breast_sim_run meshes before it starts the clock, too).
  const SimulationModel job_model = buildSimulationModel(base);
  auto runJob = [&]() {
    ProneToSupinePipeline job(base, job_model, job_settings);
    const auto t0 = Clock::now();
    job.runGravity();
    job.runMorphing();
    return since(t0);
  };

  // Rounds: every round runs every load level once, so slow drifts of the machine's own load fall
  // on all levels alike; a cell's figure is the median over the rounds.
  struct Cell {
    int busy, threads;
    std::vector<double> step_ms, frame_ms, job_s, load_average;  // per round: mean step, median frame, main job
  };
  std::vector<Cell> cells;
  for (double level : busy_levels)
    for (int t : thread_counts) cells.push_back({static_cast<int>(level), t, {}, {}, {}, {}});
  auto find = [&](int busy, int t) -> Cell* {
    for (Cell& c : cells)
      if (c.busy == busy && c.threads == t) return &c;
    return nullptr;
  };
  nlohmann::json runs = nlohmann::json::array();
  for (int round = 0; round < rounds; ++round) {
    for (double level : busy_levels) {
      const int busy = static_cast<int>(level);
      BusyProcesses others(busy, busy_limit_s);
      for (int t : thread_counts) {
        omp_set_num_threads(t);
        const double load = loadAverage();
        const Timing step = runStep(), frame = runFrames();
        const double job = runJob();
        Cell& c = *find(busy, t);
        c.step_ms.push_back(step.mean_ms);
        c.frame_ms.push_back(frame.median_ms);
        c.job_s.push_back(job);
        c.load_average.push_back(load);
        std::printf("  round %d, %d busy, %d thread%s: step %.1f ms (median %.1f), frame %.1f ms (p95 %.1f), main job %.2f s, "
                    "load average %.2f\n",
                    round + 1, busy, t, t == 1 ? "" : "s", step.mean_ms, step.median_ms, frame.median_ms, frame.p95_ms, job, load);
        std::fflush(stdout);
        runs.push_back({{"round", round + 1},
                        {"busy_processes", busy},
                        {"threads", t},
                        {"load_average_at_start", load},
                        {"step_ms_mean", step.mean_ms},
                        {"step_ms_median", step.median_ms},
                        {"step_ms_p95", step.p95_ms},
                        {"frame_ms_mean", frame.mean_ms},
                        {"frame_ms_median", frame.median_ms},
                        {"frame_ms_p95", frame.p95_ms},
                        {"main_job_s", job}});
      }
      omp_set_num_threads(threads);
    }
  }

  const std::string over = "median over " + std::to_string(rounds) + (rounds == 1 ? " round" : " rounds");
  std::printf("\n%-38s %7s |", over.c_str(), "threads");
  for (double level : busy_levels) std::printf(" %9d busy", static_cast<int>(level));
  std::printf(" | 1 busy ÷ idle at 1 thread less |");
  for (double level : busy_levels)
    if (level > 0) std::printf(" ÷ 1 thread, %d busy", static_cast<int>(level));
  std::printf("\n");
  nlohmann::json rows = nlohmann::json::array();
  for (int work = 0; work < 3; ++work) {
    const char* name = work == 0 ? "step" : work == 1 ? "frame" : "main_job";
    auto value = [&](int busy, int t) {
      const Cell* c = find(busy, t);
      return c ? median(work == 0 ? c->step_ms : work == 1 ? c->frame_ms : c->job_s) : 0.0;
    };
    for (int t : thread_counts) {
      char label[64];
      if (work == 0) std::snprintf(label, sizeof label, "step, mean [ms], %d el.", step_model.mesh.numTets());
      else if (work == 1) std::snprintf(label, sizeof label, "frame, median [ms], %d el.", track_model.mesh.numTets());
      else std::snprintf(label, sizeof label, "main job, compute [s], %d el.", job_model.mesh.numTets());
      std::printf("%-38s %7d |", t == thread_counts.front() ? label : "", t);
      nlohmann::json row = {{"work", name}, {"threads", t}};
      for (double level : busy_levels) {
        const int busy = static_cast<int>(level);
        std::printf(work == 2 ? " %14.2f" : " %14.1f", value(busy, t));
        row[std::string(work == 2 ? "s_busy_" : "ms_busy_") + std::to_string(busy)] = value(busy, t);
      }
      // The program's thread count beside busy processes, against the idle run with one thread less
      // and against one thread beside the same processes.
      if (t == threads && threads > 1) {
        const double loaded = value(1, t), idle_less = value(0, t - 1);
        const double vs_idle = loaded > 0 && idle_less > 0 ? loaded / idle_less : 0.0;
        std::printf(" | %29.2fx |", vs_idle);
        row["one_busy_vs_idle_one_thread_less"] = vs_idle;
        for (double level : busy_levels) {
          const int busy = static_cast<int>(level);
          if (busy == 0) continue;
          const double vs_one = value(busy, 1) > 0 ? value(busy, t) / value(busy, 1) : 0.0;
          std::printf(" %17.2fx", vs_one);
          row["vs_one_thread_busy_" + std::to_string(busy)] = vs_one;
        }
      }
      std::printf("\n");
      rows.push_back(row);
    }
  }
  std::printf("(%d threads: the program's count, from which each time step chooses by the load it sees)\n", threads);
  std::printf("(targets: one busy process beside the program's %d threads at most 2.5x the idle run with one thread less, "
              "and never slower than one thread beside the same processes: at most 1x)\n",
              threads);
  std::printf("(main job: the pipeline's stages, breast_sim_run's \"compute\"; its set-up, mostly meshing, is not timed)\n");
  if (!json_path.empty()) {
    nlohmann::json out = {{"bench", "load"},
                          {"threads", threads},
                          {"cores_online", std::thread::hardware_concurrency()},
                          {"openmp_wait", wait},
                          {"step_elements", step_model.mesh.numTets()},
                          {"steps", steps},
                          {"frame_elements", track_model.mesh.numTets()},
                          {"frame_cloud_points", skin.rows()},
                          {"frames", frames},
                          {"main_job_case", "config/phantom_default.yaml"},
                          {"main_job_elements", job_model.mesh.numTets()},
                          {"tracker_relative_tolerance", kTrackerTolerance},
                          {"rounds", rounds},
                          {"table", rows},
                          {"runs", runs}};
    std::ofstream(json_path) << out.dump(2) << '\n';
  }
  return 0;
}
