// The thread count of a time step from the machine's load (include/breast_sim/core/thread_budget.h): the rule
// on made-up samples, the sampler's bounds on this machine, and that the caller's count comes back.
#include <gtest/gtest.h>

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

TEST(LoadSampler, StaysWithinTheCallersCountOnThisMachine) {
  LoadSampler& s = LoadSampler::instance();
  EXPECT_GE(s.cores(), 1);
  for (int i = 0; i < 3 * kLoadWindow; ++i) {
    const int t = s.next(2);
    EXPECT_GE(t, 1);
    EXPECT_LE(t, 2);
    EXPECT_EQ(s.next(1), 1);
  }
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
          EXPECT_LE(chosen, callers);  // capped by the outermost caller's count, not the stage's
        }
        EXPECT_EQ(omp_get_max_threads(), chosen);  // the stage's work goes on with the step's count
      }
    }
    EXPECT_EQ(omp_get_max_threads(), callers);
  }
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
  load = 0;  // it ends: both threads at the next sample
  EXPECT_EQ(s.next(2), 2);
  EXPECT_EQ(s.latest(2), 2);
  load = -1;  // no sample (/proc unreadable): the caller's count
  EXPECT_EQ(s.next(2), 2);
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
