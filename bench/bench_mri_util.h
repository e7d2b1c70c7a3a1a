#pragma once
// Shared by the MRI benchmarks: the process's CPU time and the machine's load, beside the wall times
// of bench_util.h.
#include <cstdio>
#include <ctime>

namespace breast_sim::bench {

/// CPU time of the whole process (all threads) [s]: on a machine shared with other jobs the wall time
/// depends on the load; CPU time / threads is what the run takes on free cores.
inline double cpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

/// The 1-minute load average (how busy the shared machine was); 0 when unknown.
inline double loadAverage() {
  double load = 0.0;
  if (std::FILE* f = std::fopen("/proc/loadavg", "r")) {
    if (std::fscanf(f, "%lf", &load) != 1) load = 0.0;
    std::fclose(f);
  }
  return load;
}

}  // namespace breast_sim::bench
