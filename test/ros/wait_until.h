#pragma once
// Test fixture of the rostests: polls a condition on the client's recorded messages, under the mutex
// their callbacks hold, until it holds or the wall-clock time runs out (simulated time may stand still).
#include <chrono>
#include <mutex>
#include <thread>

namespace breast_sim::test_fixtures {

/// True as soon as `condition()` (called with `m` locked) holds, checked every 20 ms and once more
/// at the end of `timeout_s` seconds of wall-clock time.
template <class F>
bool waitUntil(std::mutex& m, F&& condition, double timeout_s) {
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
  while (std::chrono::steady_clock::now() < end) {
    {
      std::lock_guard<std::mutex> l(m);
      if (condition()) return true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::lock_guard<std::mutex> l(m);
  return condition();
}

}  // namespace breast_sim::test_fixtures
