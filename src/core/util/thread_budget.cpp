#include "breast_sim/core/thread_budget.h"

#include <dirent.h>
#include <fcntl.h>
#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include <omp.h>

namespace breast_sim::core {

int threadsForLoad(const int* others, int count, int cores, int cap) {
  cap = std::max(1, cap);
  if (count < kLoadWindow) return cap;
  const int k = *std::min_element(others + count - kLoadWindow, others + count);
  return std::clamp(cores - std::max(0, k), 1, cap);
}

namespace {

/// The machine's runnable threads (fourth field of /proc/loadavg, "running/total"), or −1.
int runnableThreads() {
  const int fd = ::open("/proc/loadavg", O_RDONLY | O_CLOEXEC);
  if (fd < 0) return -1;
  char buf[128];
  const ssize_t n = ::read(fd, buf, sizeof buf - 1);
  ::close(fd);
  if (n <= 0) return -1;
  buf[n] = '\0';
  // "0.17 0.05 0.01 1/123 4567": the number before the slash.
  const char* slash = std::strchr(buf, '/');
  if (!slash) return -1;
  const char* p = slash;
  while (p > buf && p[-1] >= '0' && p[-1] <= '9') --p;
  if (p == slash) return -1;
  return static_cast<int>(std::strtol(p, nullptr, 10));
}

/// This process's runnable threads (state R in /proc/self/task/*/stat), the calling one included,
/// or −1. OpenMP's threads that spin while they wait are among them.
int ownRunnableThreads() {
  DIR* dir = ::opendir("/proc/self/task");
  if (!dir) return -1;
  int running = 0;
  char path[64], buf[512];
  while (const dirent* entry = ::readdir(dir)) {
    if (entry->d_name[0] < '0' || entry->d_name[0] > '9') continue;
    std::snprintf(path, sizeof path, "/proc/self/task/%.20s/stat", entry->d_name);
    const int fd = ::open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) continue;  // the thread ended meanwhile
    const ssize_t n = ::read(fd, buf, sizeof buf - 1);
    ::close(fd);
    if (n <= 0) continue;
    buf[n] = '\0';
    // "tid (name) S ...": the state follows the last ')' (a name may hold parentheses).
    const char* close_paren = std::strrchr(buf, ')');
    if (close_paren && close_paren[1] == ' ' && close_paren[2] == 'R') ++running;
  }
  ::closedir(dir);
  return running;
}

}  // namespace

LoadSampler& LoadSampler::instance() {
  static LoadSampler sampler;
  return sampler;
}

LoadSampler::LoadSampler() {
  cpu_set_t set;
  CPU_ZERO(&set);
  const long online = ::sysconf(_SC_NPROCESSORS_ONLN);
  const int allowed = ::sched_getaffinity(0, sizeof set, &set) == 0 ? CPU_COUNT(&set) : -1;
  cores_ = std::max(1, allowed);
  others_ = [] {
    const int running = runnableThreads(), own = ownRunnableThreads();
    return running < 1 || own < 1 ? -1 : std::max(0, running - own);
  };
  applies_ = allowed > 1 && allowed == online && others_() >= 0;
}

LoadSampler::LoadSampler(std::function<int()> others, int cores, std::chrono::nanoseconds interval)
    : others_(std::move(others)), applies_(cores > 1), cores_(std::max(1, cores)), interval_(interval) {}

int LoadSampler::next(int cap) {
  if (!applies_) return std::max(1, cap);
  const auto now = std::chrono::steady_clock::now();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (count_ > 0 && now - last_sample_ < interval_) return threadsForLoad(samples_.data(), count_, cores_, cap);
    last_sample_ = now;
  }
  const int others = others_();
  std::lock_guard<std::mutex> lock(mutex_);
  if (others < 0) return std::max(1, cap);
  if (count_ == kLoadWindow) std::rotate(samples_.begin(), samples_.begin() + 1, samples_.end());
  else ++count_;
  samples_[static_cast<size_t>(count_ - 1)] = others;
  return threadsForLoad(samples_.data(), count_, cores_, cap);
}

int LoadSampler::latest(int cap) {
  if (!applies_) return std::max(1, cap);
  std::lock_guard<std::mutex> lock(mutex_);
  return threadsForLoad(samples_.data(), count_, cores_, cap);
}

namespace {
thread_local int scope_depth = 0;
thread_local int caller_threads = 1;  // the count before this thread's outermost scope
}  // namespace

ThreadCountScope::ThreadCountScope(Sample sample) : outer_(scope_depth++ == 0) {
  if (outer_) caller_threads = omp_get_max_threads();
  LoadSampler& s = LoadSampler::instance();
  const int threads = sample == Sample::take ? s.next(caller_threads) : s.latest(caller_threads);
  if (threads != omp_get_max_threads()) omp_set_num_threads(threads);
}

ThreadCountScope::~ThreadCountScope() {
  --scope_depth;
  if (outer_ && omp_get_max_threads() != caller_threads) omp_set_num_threads(caller_threads);
}

}  // namespace breast_sim::core
