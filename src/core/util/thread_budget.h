#pragma once
// How many OpenMP threads the next time step gets, from what else the machine runs (private to
// src/core). OpenMP's threads spin briefly before they sleep (src/openmp_wait): on an idle machine
// that halved the main job's time against sleeping at once, but a thread that spins on a core
// another process needs slows every barrier. Beside one busy process on 2 cores, two spinning
// threads took the main job 2.5x as long as one thread (docs/load.md, "The thread count"), so a
// step runs one thread per core that other work leaves free. Results do not depend on the thread
// count, so only time is at stake.

#include <array>

namespace breast_sim::core::util {

/// Samples over which the rule takes its least value: one step that sees fewer other threads
/// brings back the threads at once; giving one up takes kLoadWindow steps that all see the load.
inline constexpr int kLoadWindow = 4;

/// The rule. `others`: the last `count` samples of how many threads of other work were runnable,
/// any order. With fewer than kLoadWindow samples it returns `cap`; otherwise, with k the least of
/// the last kLoadWindow samples, cores − k, never more than `cap` nor less than 1.
int threadsForLoad(const int* others, int count, int cores, int cap);

/// The process-wide sampler. A sample is the machine's runnable threads (the fourth field of
/// /proc/loadavg) minus this process's own (state R in /proc/self/task/*/stat: the sampling thread,
/// OpenMP threads that spin, any other thread of ours that runs). It applies where that count says
/// something about our cores: the process may run on every online CPU (the count is the machine's,
/// not a cpuset's), there are at least 2, and /proc reads. Elsewhere it returns the caller's
/// thread count unchanged. Thread-safe; a sample costs two /proc reads per thread of the process
/// (tens of microseconds).
class LoadSampler {
 public:
  /// The process's sampler.
  static LoadSampler& instance();

  /// Takes a sample and returns the thread count for the next piece of work, at most `cap` (the
  /// caller's omp_get_max_threads()).
  int next(int cap);
  bool applies() const { return applies_; }
  int cores() const { return cores_; }

 private:
  LoadSampler();
  bool applies_ = false;
  int cores_ = 1;
  std::array<int, kLoadWindow> samples_{};
  int count_ = 0;
};

/// For its lifetime (a time step), the calling thread's OpenMP thread count is the sampler's
/// choice; the caller's count comes back on destruction (a library must not leave it changed).
/// A nested one on the same thread (the simulator's step inside a stiffening step) keeps the outer
/// choice and takes no sample.
class StepThreadCount {
 public:
  StepThreadCount();
  ~StepThreadCount();
  StepThreadCount(const StepThreadCount&) = delete;
  StepThreadCount& operator=(const StepThreadCount&) = delete;

 private:
  int saved_ = 0;
  bool outer_ = false;
};

}  // namespace breast_sim::core::util
