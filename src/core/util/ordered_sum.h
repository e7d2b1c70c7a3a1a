#pragma once
// Sums over an index range whose result does not depend on the thread count (private to src/core).
// An OpenMP reduction adds each thread's share in an order set by the number of threads, so one
// thread and two give sums that differ in the last bits, and a run's path (stiffening reversals,
// settle steps, PCG iterations) can part from there. Here the range is cut into fixed chunks of
// kOrderedSumChunk indices; each chunk is summed in index order by whichever thread takes it, and
// the chunk partials are added in chunk order: the same bits on any number of threads.

#include <algorithm>
#include <array>
#include <vector>

namespace breast_sim::core::util {

inline constexpr long kOrderedSumChunk = 1024;

/// The K sums Σ_{i<n} term(i)[k] (term returns std::array<double, K>), in the fixed order above.
/// term may also write per-index results (each i is visited once). `parallel`: an OpenMP if-clause.
/// Allocates only when a longer range than before is summed on the calling thread.
template <int K, class Term>
std::array<double, K> orderedSums(long n, bool parallel, Term&& term) {
  thread_local std::vector<std::array<double, K>> partials;
  const long chunks = (n + kOrderedSumChunk - 1) / kOrderedSumChunk;
  if (static_cast<long>(partials.size()) < chunks) partials.resize(static_cast<size_t>(chunks));
  std::array<double, K>* const part = partials.data();
#pragma omp parallel for schedule(static) if (parallel && chunks > 1)
  for (long c = 0; c < chunks; ++c) {
    std::array<double, K> s{};
    const long end = std::min(n, (c + 1) * kOrderedSumChunk);
    for (long i = c * kOrderedSumChunk; i < end; ++i) {
      const std::array<double, K> t = term(i);
      for (int k = 0; k < K; ++k) s[k] += t[k];
    }
    part[c] = s;
  }
  std::array<double, K> total{};
  for (long c = 0; c < chunks; ++c)
    for (int k = 0; k < K; ++k) total[k] += part[c][k];
  return total;
}

/// Σ_{i<n} term(i) (term returns double), in the fixed order above.
template <class Term>
double orderedSum(long n, bool parallel, Term&& term) {
  return orderedSums<1>(n, parallel, [&](long i) { return std::array<double, 1>{term(i)}; })[0];
}

}  // namespace breast_sim::core::util
