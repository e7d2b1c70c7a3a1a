#pragma once
// How many OpenMP threads the core's parallel work gets, from what else the machine runs.
// OpenMP's threads spin briefly before they sleep (src/openmp_wait): on an idle machine that halved
// the main job's time against sleeping at once, but a thread that spins on a core another process
// needs slows every barrier. Beside one busy process on 2 cores, two spinning threads took the main
// job 2.5x as long as one thread (docs/load.md, "Choosing the spin count"), so a step runs one
// thread per core that other work leaves free. Results do not depend on the thread count, so only
// time is at stake.

#include <array>
#include <chrono>
#include <functional>
#include <mutex>

namespace breast_sim::core {

/// Samples over which the rule takes its least value: one step that sees fewer other threads
/// brings back the threads at once; giving one up takes kLoadWindow steps that all see the load.
inline constexpr int kLoadWindow = 2;

/// The least time between two samples of the process's sampler.
inline constexpr std::chrono::milliseconds kMinSampleInterval{20};

/// The rule. `others`: the last `count` samples of how many threads of other work were runnable,
/// any order. With fewer than kLoadWindow samples it returns `cap`; otherwise, with k the least of
/// the last kLoadWindow samples, cores − k, never more than `cap` nor less than 1.
int threadsForLoad(const int* others, int count, int cores, int cap);

/// The process-wide sampler. A sample is the machine's runnable threads (the fourth field of
/// /proc/loadavg) minus this process's own (state R in /proc/self/task/*/stat: the sampling thread,
/// OpenMP threads that spin, any other thread of ours that runs). It applies where that count says
/// something about our cores: the process may run on every online CPU (the count is the machine's,
/// not a cpuset's), there are at least 2, and /proc reads. Elsewhere it returns the caller's
/// thread count unchanged. A sample reads one /proc file per thread of the process (about 0.1 ms
/// for 2 threads here), so it is taken at most every kMinSampleInterval; a step in between reuses
/// the latest choice. Thread-safe.
class LoadSampler {
 public:
  /// The process's sampler.
  static LoadSampler& instance();
  /// A sampler whose samples come from `others` (how many threads of other work run now, −1 for
  /// none), on `cores` cores, at most every `interval`: for tests.
  LoadSampler(std::function<int()> others, int cores, std::chrono::nanoseconds interval);

  /// Takes a sample (unless the last one is younger than the interval) and returns the thread
  /// count for the next piece of work, at most `cap` (the caller's omp_get_max_threads()).
  int next(int cap);
  /// The thread count the samples taken so far give, at most `cap`; takes no sample.
  int latest(int cap);
  bool applies() const { return applies_; }
  int cores() const { return cores_; }

 private:
  LoadSampler();
  std::mutex mutex_;
  std::function<int()> others_;  // −1: no sample
  bool applies_ = false;
  int cores_ = 1;
  std::chrono::nanoseconds interval_{kMinSampleInterval};
  std::chrono::steady_clock::time_point last_sample_{};
  std::array<int, kLoadWindow> samples_{};
  int count_ = 0;
};

/// The thread count of the core's parallel work while it lives: the sampler's choice, capped by the
/// count the caller had when the outermost scope of this thread began, which comes back when that
/// scope ends (a library must not leave it changed). A time step takes a sample; the pipeline's
/// entry points (a stage, a tracking iteration, a new target) and the node's tracking frame reuse
/// the latest choice, so the work between steps runs on as many threads as the steps. A nested
/// scope sets its count and leaves it for the enclosing scope's remaining work.
class ThreadCountScope {
 public:
  enum class Sample { take, reuse };
  explicit ThreadCountScope(Sample sample);
  ~ThreadCountScope();
  ThreadCountScope(const ThreadCountScope&) = delete;
  ThreadCountScope& operator=(const ThreadCountScope&) = delete;

 private:
  bool outer_ = false;
};

}  // namespace breast_sim::core
