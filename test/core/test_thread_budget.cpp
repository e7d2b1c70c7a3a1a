// The thread count of the core's work from the machine's load (include/breast_sim/core/thread_budget.h):
// the rule on made-up samples, the /proc parsing, the sampler on a made-up load and on this machine,
// and that the caller's count comes back.
#include <gtest/gtest.h>

#include <sched.h>
#include <unistd.h>

#include <stdexcept>
#include <vector>

#include <omp.h>

#include "breast_sim/core/thread_budget.h"

using namespace breast_sim::core;

namespace {

int rule(std::vector<int> others, int cores, int cap) {
  return threadsForLoad(others.data(), static_cast<int>(others.size()), cores, cap);
}

std::vector<int> window(int value) { return std::vector<int>(kLoadWindow, value); }

}  // namespace

TEST(ThreadsForLoad, KeepsAllThreadsUntilTheWindowIsFull) {
  EXPECT_EQ(rule({}, 2, 2), 2);
  EXPECT_EQ(rule(std::vector<int>(kLoadWindow - 1, 1), 2, 2), 2);
  EXPECT_EQ(rule(window(1), 2, 2), 1);
}

TEST(ThreadsForLoad, TwoCores) {
  EXPECT_EQ(rule(window(0), 2, 2), 2);  // idle
  EXPECT_EQ(rule(window(1), 2, 2), 1);  // one busy process: one thread keeps a core
  EXPECT_EQ(rule(window(2), 2, 2), 1);  // every core taken: one thread, none spinning in the way
  EXPECT_EQ(rule(window(7), 2, 2), 1);
}

TEST(ThreadsForLoad, OneSampleWithFewerOthersBringsBackTheThreads) {
  std::vector<int> s = window(1);
  s.front() = 0;
  EXPECT_EQ(rule(s, 2, 2), 2);
  // Only the last kLoadWindow samples count.
  std::vector<int> older = window(1);
  older.insert(older.begin(), 0);
  EXPECT_EQ(rule(older, 2, 2), 1);
  // The least sample decides: 1 and 3 on 4 cores leave 3 cores.
  std::vector<int> mixed = window(3);
  mixed.back() = 1;
  EXPECT_EQ(rule(mixed, 4, 4), 3);
}

TEST(ThreadsForLoad, MoreCoresAndTheCallersCap) {
  EXPECT_EQ(rule(window(1), 4, 4), 3);
  EXPECT_EQ(rule(window(3), 4, 4), 1);
  EXPECT_EQ(rule(window(4), 4, 4), 1);
  EXPECT_EQ(rule(window(1), 4, 2), 2);  // never more than the caller's count
  EXPECT_EQ(rule(window(0), 4, 3), 3);
  EXPECT_EQ(rule(window(1), 2, 1), 1);
  EXPECT_EQ(rule(window(0), 2, 0), 1);  // never fewer than one
  EXPECT_EQ(rule(window(1), 1, 1), 1);  // one core: nothing to give up
}

TEST(LoadSampler, ReadsTheProcFiles) {
  EXPECT_EQ(parseRunnableThreads("0.17 0.05 0.01 3/123 4567\n"), 3);
  EXPECT_EQ(parseRunnableThreads("12.50 9.00 8.25 17/2048 99"), 17);
  EXPECT_EQ(parseRunnableThreads("0.17 0.05 0.01"), -1);
  EXPECT_EQ(parseRunnableThreads("0.17 0.05 0.01 /12 3"), -1);
  EXPECT_TRUE(statSaysRunnable("1234 (breast_sim_run) R 1 1234 1234 0 -1"));
  EXPECT_FALSE(statSaysRunnable("1234 (breast_sim_run) S 1 1234 1234 0 -1"));
  // A name may hold ") R " itself: the state follows the last parenthesis.
  EXPECT_FALSE(statSaysRunnable("1234 (a) R (b) S 1 1234"));
  EXPECT_TRUE(statSaysRunnable("1234 (a) S (b) R 1 1234"));
  EXPECT_FALSE(statSaysRunnable("1234 (truncated"));
}

TEST(LoadSampler, AppliesWhereTheProcessHasEveryCpuAndStaysWithinTheCallersCount) {
  LoadSampler& s = LoadSampler::instance();
  cpu_set_t set;
  CPU_ZERO(&set);
  ASSERT_EQ(sched_getaffinity(getpid(), sizeof set, &set), 0);
  const long online = sysconf(_SC_NPROCESSORS_ONLN);
  EXPECT_EQ(s.cores(), CPU_COUNT(&set));
  // /proc is there on Linux: the sampler applies exactly where the process may use every CPU.
  EXPECT_EQ(s.applies(), CPU_COUNT(&set) > 1 && CPU_COUNT(&set) == online);
  for (int i = 0; i < 3 * kLoadWindow; ++i) {
    const int t = s.next(2);
    EXPECT_GE(t, 1);
    EXPECT_LE(t, 2);
    EXPECT_EQ(s.next(1), 1);
  }
  // Off, the caller's count is used as it is.
  s.setEnabled(false);
  EXPECT_FALSE(s.applies());
  EXPECT_EQ(s.next(7), 7);
  EXPECT_EQ(s.latest(5), 5);
  s.setEnabled(true);
}

TEST(ThreadCountScope, GivesTheCallersCountBackAndNestedOnesSetTheirOwn) {
  const int threads = omp_get_max_threads();
  for (int callers : {1, 2, 3}) {
    omp_set_num_threads(callers);
    {
      const ThreadCountScope stage(ThreadCountScope::Sample::reuse);
      EXPECT_GE(omp_get_max_threads(), 1);
      EXPECT_LE(omp_get_max_threads(), callers);
      for (int step = 0; step < 2 * kLoadWindow; ++step) {
        int chosen = 0;
        {
          const ThreadCountScope inner(ThreadCountScope::Sample::take);
          chosen = omp_get_max_threads();
          EXPECT_GE(chosen, 1);
          EXPECT_LE(chosen, callers);
        }
        EXPECT_EQ(omp_get_max_threads(), chosen);  // the stage's work goes on with the step's count
      }
    }
    EXPECT_EQ(omp_get_max_threads(), callers);
  }
  omp_set_num_threads(threads);
}

TEST(ThreadCountScope, GivesTheCallersCountBackWhenTheWorkThrowsAndDoesNothingInAParallelRegion) {
  const int threads = omp_get_max_threads();
  for (int callers : {1, 3}) {
    omp_set_num_threads(callers);
    try {
      const ThreadCountScope stage(ThreadCountScope::Sample::take);
      throw std::runtime_error("a step failed");
    } catch (const std::runtime_error&) {
    }
    EXPECT_EQ(omp_get_max_threads(), callers);
    // The next outermost scope starts afresh: it gives this caller's count back too.
    omp_set_num_threads(callers + 1);
    { const ThreadCountScope again(ThreadCountScope::Sample::reuse); }
    EXPECT_EQ(omp_get_max_threads(), callers + 1);
  }
  omp_set_num_threads(2);
  int inside = 0;
#pragma omp parallel num_threads(2)
  {
#pragma omp master
    {
      const int before = omp_get_max_threads();
      {
        const ThreadCountScope nested(ThreadCountScope::Sample::take);
        inside = omp_get_max_threads() == before ? 1 : -1;
      }
      if (omp_get_max_threads() != before) inside = -2;
    }
  }
  EXPECT_EQ(inside, 1);
  omp_set_num_threads(threads);
}

TEST(LoadSampler, FollowsTheLoadAndReusingTheChoiceTakesNoSample) {
  int load = 0, taken = 0;
  LoadSampler s([&] { ++taken; return load; }, 2, std::chrono::nanoseconds(0));
  for (int i = 0; i < kLoadWindow; ++i) EXPECT_EQ(s.next(2), 2);
  load = 1;  // a busy process starts: one thread once the whole window has seen it
  for (int i = 0; i < kLoadWindow - 1; ++i) EXPECT_EQ(s.next(2), 2);
  EXPECT_EQ(s.next(2), 1);
  EXPECT_EQ(taken, 2 * kLoadWindow);
  for (int i = 0; i < 3; ++i) EXPECT_EQ(s.latest(2), 1);
  EXPECT_EQ(taken, 2 * kLoadWindow);  // latest() took none
  EXPECT_EQ(s.latest(1), 1);
  load = -1;  // a sample that cannot be read (/proc unreadable): the latest choice stays
  EXPECT_EQ(s.next(2), 1);
  EXPECT_EQ(taken, 2 * kLoadWindow + 1);
  load = 0;  // the busy process ends: both threads at the next sample
  EXPECT_EQ(s.next(2), 2);
  EXPECT_EQ(s.latest(2), 2);
  // Within the interval a step reuses the latest choice and takes no sample.
  LoadSampler slow([&] { ++taken; return load; }, 2, std::chrono::hours(1));
  load = 1;
  taken = 0;
  for (int i = 0; i < 5; ++i) EXPECT_EQ(slow.next(2), 2);
  EXPECT_EQ(taken, 1);
  // One core: nothing to choose.
  LoadSampler single([] { return 1; }, 1, std::chrono::nanoseconds(0));
  for (int i = 0; i < 2 * kLoadWindow; ++i) EXPECT_EQ(single.next(2), 2);
}
