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

/// The machine's runnable threads (/proc/loadavg), or −1.
int runnableThreads() {
  const int fd = ::open("/proc/loadavg", O_RDONLY | O_CLOEXEC);
  if (fd < 0) return -1;
  char buf[128];
  const ssize_t n = ::read(fd, buf, sizeof buf - 1);
  ::close(fd);
  if (n <= 0) return -1;
  buf[n] = '\0';
  return parseRunnableThreads(buf);
}

/// This process's runnable threads (/proc/self/task/*/stat), the calling one included, or −1.
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
    if (statSaysRunnable(buf)) ++running;
  }
  ::closedir(dir);
  return running;
}

/// Other work's runnable threads now, or −1.
int otherRunnableThreads() {
  const int own_before = ownRunnableThreads();
  const int running = runnableThreads();
  // A thread of ours that ran at the first count may have stopped since: count again and take the
  // larger. Only the sampling thread running at first: no thread of ours can have stopped.
  const int own = own_before > 1 ? std::max(own_before, ownRunnableThreads()) : own_before;
  return running < 1 || own < 1 ? -1 : std::max(0, running - own);
}

}  // namespace

int parseRunnableThreads(const char* loadavg) {
  const char* slash = std::strchr(loadavg, '/');
  if (!slash) return -1;
  const char* p = slash;
  while (p > loadavg && p[-1] >= '0' && p[-1] <= '9') --p;
  if (p == slash) return -1;
  return static_cast<int>(std::strtol(p, nullptr, 10));
}

bool statSaysRunnable(const char* stat) {
  const char* close_paren = std::strrchr(stat, ')');
  return close_paren && close_paren[1] == ' ' && close_paren[2] == 'R';
}

LoadSampler& LoadSampler::instance() {
  static LoadSampler sampler;
  return sampler;
}

LoadSampler::LoadSampler() : others_(otherRunnableThreads) {
  // The process's CPUs: those of its main thread (a thread of its own may be pinned narrower).
  cpu_set_t set;
  CPU_ZERO(&set);
  const long online = ::sysconf(_SC_NPROCESSORS_ONLN);
  const int allowed = ::sched_getaffinity(::getpid(), sizeof set, &set) == 0 ? CPU_COUNT(&set) : -1;
  cores_ = std::max(1, allowed);
  supported_ = allowed > 1 && allowed == online && others_() >= 0;
}

LoadSampler::LoadSampler(std::function<int()> others, int cores, std::chrono::nanoseconds interval)
    : others_(std::move(others)), supported_(cores > 1), cores_(std::max(1, cores)), interval_(interval) {}

int LoadSampler::next(int cap) {
  if (!applies()) return std::max(1, cap);
  const auto now = std::chrono::steady_clock::now();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (count_ > 0 && now - last_sample_ < interval_) return threadsForLoad(samples_.data(), count_, cores_, cap);
    last_sample_ = now;
  }
  const int others = others_();
  std::lock_guard<std::mutex> lock(mutex_);
  if (others >= 0) {
    if (count_ == kLoadWindow) std::rotate(samples_.begin(), samples_.begin() + 1, samples_.end());
    else ++count_;
    samples_[static_cast<size_t>(count_ - 1)] = others;
  }
  return threadsForLoad(samples_.data(), count_, cores_, cap);
}

int LoadSampler::latest(int cap) {
  if (!applies()) return std::max(1, cap);
  std::lock_guard<std::mutex> lock(mutex_);
  return threadsForLoad(samples_.data(), count_, cores_, cap);
}

namespace {
thread_local int scope_depth = 0;
thread_local int caller_threads = 1;  // the count before this thread's outermost scope
}  // namespace

ThreadCountScope::ThreadCountScope(Sample sample) {
  if (omp_in_parallel()) return;  // the enclosing region's team is the caller's business
  const bool outer = scope_depth == 0;
  const int cap = outer ? omp_get_max_threads() : caller_threads;
  LoadSampler& s = LoadSampler::instance();
  const int threads = sample == Sample::take ? s.next(cap) : s.latest(cap);
  // Counted in only once nothing can throw any more.
  if (outer) caller_threads = cap;
  ++scope_depth;
  counted_ = true;
  outer_ = outer;
  if (threads != omp_get_max_threads()) omp_set_num_threads(threads);
}

ThreadCountScope::~ThreadCountScope() {
  if (!counted_) return;
  --scope_depth;
  if (outer_ && omp_get_max_threads() != caller_threads) omp_set_num_threads(caller_threads);
}

}  // namespace breast_sim::core
