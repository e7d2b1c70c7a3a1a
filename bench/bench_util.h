#pragma once
// Small functions shared by the benchmarks: wall and CPU time, the machine's load, medians and means
// of repeated runs, and comma-separated number lists from the command line.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <sstream>
#include <string>
#include <vector>

namespace breast_sim::bench {

using Clock = std::chrono::steady_clock;

/// Seconds since t0.
inline double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

/// CPU time of the whole process (all threads) [s]: on a machine shared with other jobs the wall
/// time depends on the load; CPU time / threads is what the work takes on free cores.
inline double cpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

/// The 1-minute load average (runnable processes, as `uptime` shows), −1 where unknown: the load a
/// figure was measured under.
inline double loadAverage() {
  double l[1];
  return getloadavg(l, 1) == 1 ? l[0] : -1.0;
}

/// Median (upper median for an even count); 0 for none.
inline double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

/// Mean; 0 for none.
inline double mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return v.empty() ? 0.0 : s / static_cast<double>(v.size());
}

/// "1e-1,2,3.5" → {0.1, 2, 3.5}; an empty text gives an empty list.
/// @throws std::invalid_argument (from std::stod) for an entry that is not a number.
inline std::vector<double> parseList(const std::string& text) {
  std::vector<double> out;
  std::stringstream ss(text);
  for (std::string t; std::getline(ss, t, ',');)
    if (!t.empty()) out.push_back(std::stod(t));
  return out;
}

/// The value after option argv[i] (advancing i); exits with status 2 and a message when it is missing.
inline std::string argValue(int argc, char** argv, int& i) {
  if (i + 1 >= argc) {
    std::fprintf(stderr, "%s needs a value\n", argv[i]);
    std::exit(2);
  }
  return argv[++i];
}

}  // namespace breast_sim::bench
