#pragma once
// How many OpenMP threads the core's parallel work gets, from what else the machine runs.
// OpenMP's threads spin briefly before they sleep (src/openmp_wait): on an idle machine that halved
// the main job's time against sleeping at once, but a thread that spins on a core another process
// needs slows every barrier. Beside one busy process on 2 cores, two spinning threads took the main
// job 2.5x as long as one thread (docs/load.md, "Choosing the spin count"), so a step runs one
// thread per core that other work leaves free. Results do not depend on the thread count, so only
// time is at stake.

#include <array>
#include <atomic>
#include <chrono>
#include <functional>
#include <mutex>

namespace breast_sim::core {

/// Samples over which the rule takes its least value: one sample that sees fewer other threads
/// brings back the threads at once; giving one up takes kLoadWindow samples (taken at least
/// kMinSampleInterval apart) that all see the load.
inline constexpr int kLoadWindow = 2;

/// The least time between two samples of the process's sampler.
inline constexpr std::chrono::milliseconds kMinSampleInterval{20};

/// The rule. `others`: the last `count` samples of how many threads of other work were runnable,
/// any order. With fewer than kLoadWindow samples it returns `cap`; otherwise, with k the least of
/// the last kLoadWindow samples, cores − k, never more than `cap` nor less than 1.
int threadsForLoad(const int* others, int count, int cores, int cap);

/// The machine's runnable threads from the text of /proc/loadavg ("0.17 0.05 0.01 3/123 4567": the
/// 3), or −1 if the text has no such field.
int parseRunnableThreads(const char* loadavg);
/// Whether the text of a /proc/<pid>/task/<tid>/stat file says the thread is runnable (state R,
/// the field after the name's closing parenthesis; a name may hold parentheses itself).
bool statSaysRunnable(const char* stat);

/// The process-wide sampler. A sample is the machine's runnable threads (/proc/loadavg) minus this
/// process's own (state R in /proc/self/task/*/stat: the sampling thread, OpenMP threads that spin,
/// any other thread of ours that runs; counted before and after the machine's, the larger count
/// taken, so that a thread of ours that stops in between is not taken for other work). It applies
/// where that count says something about our cores: the process may run on every online CPU (the
/// count is the machine's, not a cpuset's), there are at least 2, and /proc reads; and while it is
/// enabled. Elsewhere it returns the caller's thread count unchanged. A sample reads one /proc file
/// per thread of the process once or twice (about 0.1 ms for 2 threads here), so it is taken at
/// most every kMinSampleInterval; a step in between reuses the latest choice. Thread-safe.
class LoadSampler {
 public:
  /// The process's sampler.
  static LoadSampler& instance();
  /// A sampler whose samples come from `others` (how many threads of other work run now, −1 for
  /// none), on `cores` cores, at most every `interval`: for tests.
  LoadSampler(std::function<int()> others, int cores, std::chrono::nanoseconds interval);

  /// Takes a sample (unless the last one is younger than the interval) and returns the thread
  /// count for the next piece of work, at most `cap` (the caller's omp_get_max_threads()). A
  /// sample that cannot be read leaves the latest choice.
  int next(int cap);
  /// The thread count the samples taken so far give, at most `cap`; takes no sample.
  int latest(int cap);
  /// Off: the caller's thread count is used as it is (a measurement at a given thread count).
  void setEnabled(bool on) { enabled_ = on; }
  bool applies() const { return supported_ && enabled_; }
  int cores() const { return cores_; }

 private:
  LoadSampler();
  std::mutex mutex_;
  std::function<int()> others_;  // −1: no sample
  bool supported_ = false;
  std::atomic<bool> enabled_{true};
  int cores_ = 1;
  std::chrono::nanoseconds interval_{kMinSampleInterval};
  std::chrono::steady_clock::time_point last_sample_{};
  std::array<int, kLoadWindow> samples_{};
  int count_ = 0;
};

/// The thread count of the core's parallel work while it lives: the sampler's choice, capped by the
/// count the caller had when the outermost scope of this thread began, which comes back when that
/// scope ends, also when the work throws (a library must not leave it changed). A time step takes a
/// sample; the pipeline's entry points (a stage, a tracking iteration, a new target) and the node's
/// tracking frame reuse the latest choice, so the work between steps runs on as many threads as the
/// steps. A nested scope sets its count and leaves it for the enclosing scope's remaining work.
/// Inside an OpenMP parallel region a scope does nothing.
class ThreadCountScope {
 public:
  enum class Sample { take, reuse };
  explicit ThreadCountScope(Sample sample);
  ~ThreadCountScope();
  ThreadCountScope(const ThreadCountScope&) = delete;
  ThreadCountScope& operator=(const ThreadCountScope&) = delete;

 private:
  bool counted_ = false;  // entered the thread's scope depth
  bool outer_ = false;
};

}  // namespace breast_sim::core
