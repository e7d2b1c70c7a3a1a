#pragma once
// Sums over an index range whose result does not depend on the thread count (private to src/core).
// An OpenMP reduction adds each thread's share in an order set by the number of threads, so one
// thread and two give sums that differ in the last bits, and a run's path (stiffening reversals,
// settle steps, PCG iterations) can part from there. Here the range is cut into fixed chunks
// (kOrderedSumChunk indices, or a caller's count); each chunk is summed in its own fixed order by
// whichever thread takes it, and the chunk partials are added in chunk order: the same bits on any
// number of threads.

#include <algorithm>
#include <array>
#include <vector>

namespace breast_sim::core::util {

inline constexpr long kOrderedSumChunk = 1024;

/// The K sums of range(i0, i1) (returns std::array<double, K>, the sums over [i0, i1) in an order
/// of its own) over [0, n) cut into fixed chunks of `chunk` indices, the chunks' sums added in
/// chunk order: for kernels that work on a range at a time (solver/block_kernels.h). range may
/// also write per-index results (each chunk is visited once). `parallel`: an OpenMP if-clause.
/// Allocates only when more chunks than before are summed on the calling thread.
template <int K, class Range>
std::array<double, K> orderedRangeSums(long n, long chunk, bool parallel, Range&& range) {
  thread_local std::vector<std::array<double, K>> partials;
  const long chunks = (n + chunk - 1) / chunk;
  if (static_cast<long>(partials.size()) < chunks) partials.resize(static_cast<size_t>(chunks));
  std::array<double, K>* const part = partials.data();
#pragma omp parallel for schedule(static) if (parallel && chunks > 1)
  for (long c = 0; c < chunks; ++c) part[c] = range(c * chunk, std::min(n, (c + 1) * chunk));
  std::array<double, K> total{};
  for (long c = 0; c < chunks; ++c)
    for (int k = 0; k < K; ++k) total[k] += part[c][k];
  return total;
}

/// The K sums Σ_{i<n} term(i)[k] (term returns std::array<double, K>), in the fixed order above.
/// term may also write per-index results (each i is visited once). `parallel`: an OpenMP if-clause.
template <int K, class Term>
std::array<double, K> orderedSums(long n, bool parallel, Term&& term) {
  return orderedRangeSums<K>(n, kOrderedSumChunk, parallel, [&](long i0, long i1) {
    std::array<double, K> s{};
    for (long i = i0; i < i1; ++i) {
      const std::array<double, K> t = term(i);
      for (int k = 0; k < K; ++k) s[k] += t[k];
    }
    return s;
  });
}

/// Σ_{i<n} term(i) (term returns double), in the fixed order above.
template <class Term>
double orderedSum(long n, bool parallel, Term&& term) {
  return orderedSums<1>(n, parallel, [&](long i) { return std::array<double, 1>{term(i)}; })[0];
}

}  // namespace breast_sim::core::util
