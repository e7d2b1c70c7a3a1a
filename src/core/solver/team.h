#pragma once
/// @file team.h
/// Small helpers for work shared inside one OpenMP parallel region (solver-internal): each thread
/// owns a contiguous range of rows or nodes, and reductions go through per-thread partial sums one
/// cache line apart that every thread adds up in the same order after a barrier.

#include <cstddef>

namespace breast_sim::core::team {

/// Doubles per thread in a partial-sum array: one 64-byte cache line, so that threads writing their
/// own partials do not share a line.
constexpr int kStride = 8;

/// [begin, end) of thread `tid` of `threads` when `n` items are split into contiguous, nearly equal
/// ranges of whole `unit`s (a node's three rows stay with one thread; n a multiple of unit).
template <typename Index>
inline void split(Index n, int tid, int threads, int unit, Index& begin, Index& end) {
  const Index units = n / unit;
  begin = unit * (units * tid / threads);
  end = unit * (units * (tid + 1) / threads);
  if (tid == threads - 1) end = n;
}

/// Sum over the team's threads of slot `slot` of a partial-sum array, in thread order (the same
/// bits on every thread). Call after a barrier that follows every thread's write.
inline double sum(const double* partial, int threads, int slot) {
  double s = 0.0;
  for (int t = 0; t < threads; ++t) s += partial[static_cast<std::size_t>(t) * kStride + slot];
  return s;
}

}  // namespace breast_sim::core::team
