#include "breast_sim/core/solver/block_kernels.h"

#include <algorithm>
#include <array>
#include <cstddef>

#include <omp.h>

#include "../util/ordered_sum.h"

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define BREAST_SIM_X86_SIMD 1
#endif

namespace breast_sim::core {

namespace {

void residualScalar(const float* val, const int* col, const int* start, const double* b, const double* x, double* t,
                    int i0, int i1) {
  for (int i = i0; i < i1; ++i) blockRowResidual(val, col, start[i], start[i + 1], b + 3 * i, x, t + 3 * i);
}

double floatProductScalar(const float* val, const int* col, const int* start, const double* x, double* y, int i0,
                          int i1) {
  static const double zero[3] = {0.0, 0.0, 0.0};
  double sum = 0.0;
  for (int i = i0; i < i1; ++i) {
    double t[3];
    blockRowResidual(val, col, start[i], start[i + 1], zero, x, t);
    const double y0 = -t[0], y1 = -t[1], y2 = -t[2];
    sum += x[3 * i] * y0 + x[3 * i + 1] * y1 + x[3 * i + 2] * y2;
    y[3 * i] = y0, y[3 * i + 1] = y1, y[3 * i + 2] = y2;
  }
  return sum;
}

// A node row's three sums s into y (PCG's products): b − s and Σ y² for a residual, s and Σ x·s
// otherwise, added to `sum`.
inline void finishProductRow(double s0, double s1, double s2, bool residual, const double* b, const double* x,
                             double* y, int i, double& sum) {
  if (residual) {
    s0 = b[3 * i] - s0, s1 = b[3 * i + 1] - s1, s2 = b[3 * i + 2] - s2;
    sum += s0 * s0 + s1 * s1 + s2 * s2;
  } else {
    sum += x[3 * i] * s0 + x[3 * i + 1] * s1 + x[3 * i + 2] * s2;
  }
  y[3 * i] = s0, y[3 * i + 1] = s1, y[3 * i + 2] = s2;
}

double productScalar(const int* outer, const double* val, const int* start, const int* col, const double* b,
                     const double* x, double* y, int i0, int i1, bool residual) {
  double sum = 0.0;
  for (int i = i0; i < i1; ++i) {
    const double* v0 = val + outer[3 * i];
    const double* v1 = val + outer[3 * i + 1];
    const double* v2 = val + outer[3 * i + 2];
    double a00 = 0, a01 = 0, a02 = 0, a10 = 0, a11 = 0, a12 = 0, a20 = 0, a21 = 0, a22 = 0;
    for (int k = start[i], m = 0; k < start[i + 1]; ++k, m += 3) {
      const double* xj = x + 3 * static_cast<size_t>(col[k]);
      const double x0 = xj[0], x1 = xj[1], x2 = xj[2];
      a00 += v0[m] * x0, a01 += v0[m + 1] * x1, a02 += v0[m + 2] * x2;
      a10 += v1[m] * x0, a11 += v1[m + 1] * x1, a12 += v1[m + 2] * x2;
      a20 += v2[m] * x0, a21 += v2[m + 1] * x1, a22 += v2[m + 2] * x2;
    }
    finishProductRow((a00 + a01) + a02, (a10 + a11) + a12, (a20 + a21) + a22, residual, b, x, y, i, sum);
  }
  return sum;
}

#ifdef BREAST_SIM_X86_SIMD
// A block's values a0..a7 as doubles [a0 a1 a2 a3] and [a4 a5 a6 a7] times [x0 x1 x2 x0] and
// [x1 x2 x0 x1] (x_J permuted), a8 times x2 on its own: the nine products of the scalar version in
// the same accumulator slots (lo = a00 a01 a02 a10, hi = a11 a12 a20 a21, a22).
__attribute__((target("avx2,fma"), always_inline)) inline void avx2Block(const float* val, const int* col,
                                                                          const double* x, int k, __m256d& lo,
                                                                          __m256d& hi, double& a22) {
  const float* a = val + 9 * static_cast<size_t>(k);
  const double* xj = x + 3 * static_cast<size_t>(col[k]);
  const __m256d xv = _mm256_maskload_pd(xj, _mm256_set_epi64x(0, -1, -1, -1));  // x0 x1 x2 0
  const __m256d x_lo = _mm256_permute4x64_pd(xv, 0b00100100);                    // x0 x1 x2 x0
  const __m256d x_hi = _mm256_permute4x64_pd(xv, 0b01001001);                    // x1 x2 x0 x1
  const __m256 a8 = _mm256_loadu_ps(a);                                          // a0 .. a7
  lo = _mm256_fmadd_pd(_mm256_cvtps_pd(_mm256_castps256_ps128(a8)), x_lo, lo);
  hi = _mm256_fmadd_pd(_mm256_cvtps_pd(_mm256_extractf128_ps(a8, 1)), x_hi, hi);
  a22 = __builtin_fma(static_cast<double>(a[8]), xj[2], a22);
}

// The end of a residual row: s holds the accumulators' eight lanes in avx2Block's order
// (a00 a01 a02 a10 | a11 a12 a20 a21), a22 the ninth.
inline void finishResidualRow(const double s[8], double a22, const double* b, double* t, int i) {
  t[3 * i] = b[3 * i] - ((s[0] + s[1]) + s[2]);
  t[3 * i + 1] = b[3 * i + 1] - ((s[3] + s[4]) + s[5]);
  t[3 * i + 2] = b[3 * i + 2] - ((s[6] + s[7]) + a22);
}

// The end of a product row (y_i = A_i x, Σ x·y added to `sum`), the sums as finishResidualRow's.
inline void finishFloatProductRow(const double s[8], double a22, const double* x, double* y, int i, double& sum) {
  const double y0 = (s[0] + s[1]) + s[2], y1 = (s[3] + s[4]) + s[5], y2 = (s[6] + s[7]) + a22;
  sum += x[3 * i] * y0 + x[3 * i + 1] * y1 + x[3 * i + 2] * y2;
  y[3 * i] = y0, y[3 * i + 1] = y1, y[3 * i + 2] = y2;
}

// The residual rows t_i = b_i − A_i x with the block kernel K (Avx2Blocks, Avx512Blocks), or with
// kProduct the product rows t_i = A_i x and the returned Σ x_i·t_i: two blocks per iteration into
// two sets of accumulators (even and odd blocks), added at the end, so the multiply-adds of
// consecutive blocks do not wait for each other. Inlined into each kernel's entry point
// (residualAvx2, floatProductAvx512, …), whose instruction set the kernel's members then inline into.
template <class K, bool kProduct = false>
__attribute__((always_inline)) inline double residualRowsWith(const K& kernel, const float* val, const int* col,
                                                             const int* start, const double* b, const double* x,
                                                             double* t, int i0, int i1) {
  double sum = 0.0;
  for (int i = i0; i < i1; ++i) {
    typename K::Acc acc0 = kernel.zero(), acc1 = kernel.zero();
    double a22_0 = 0.0, a22_1 = 0.0;
    int k = start[i];
    const int k1 = start[i + 1];
    for (; k + 1 < k1; k += 2) {
      kernel.block(val, col, x, k, acc0, a22_0);
      kernel.block(val, col, x, k + 1, acc1, a22_1);
    }
    if (k < k1) kernel.block(val, col, x, k, acc0, a22_0);
    alignas(64) double s[8];
    kernel.store(s, acc0, acc1);
    if constexpr (kProduct)
      finishFloatProductRow(s, a22_0 + a22_1, x, t, i, sum);
    else
      finishResidualRow(s, a22_0 + a22_1, b, t, i);
  }
  return sum;
}

// The members carry their instruction set but not always_inline: residualRowsWith, which calls
// them, has none until it is inlined into its entry point, and GCC refuses to force-inline a
// function with more instructions into one with fewer. They are inlined there all the same (no call
// is left in either entry point).
struct Avx2Blocks {
  struct Acc {
    __m256d lo, hi;
  };
  __attribute__((target("avx2,fma"))) Acc zero() const { return {_mm256_setzero_pd(), _mm256_setzero_pd()}; }
  __attribute__((target("avx2,fma"))) void block(const float* val, const int* col, const double* x, int k, Acc& acc,
                                                 double& a22) const {
    avx2Block(val, col, x, k, acc.lo, acc.hi, a22);
  }
  __attribute__((target("avx2,fma"))) void store(double* s, const Acc& a, const Acc& b) const {
    _mm256_store_pd(s, _mm256_add_pd(a.lo, b.lo));
    _mm256_store_pd(s + 4, _mm256_add_pd(a.hi, b.hi));
  }
};

__attribute__((target("avx2,fma"))) void residualAvx2(const float* val, const int* col, const int* start,
                                                       const double* b, const double* x, double* t, int i0, int i1) {
  residualRowsWith(Avx2Blocks{}, val, col, start, b, x, t, i0, i1);
}

__attribute__((target("avx2,fma"))) double floatProductAvx2(const float* val, const int* col, const int* start,
                                                             const double* x, double* y, int i0, int i1) {
  return residualRowsWith<Avx2Blocks, true>(Avx2Blocks{}, val, col, start, nullptr, x, y, i0, i1);
}

// GCC 12's AVX-512 headers leave the unused upper half of a conversion or permutation "undefined"
// by a self-initialisation that -Wmaybe-uninitialized reports at every inlined use.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
// The AVX2 kernel's arithmetic with AVX-512F: a block's values a0..a7 are one vector of eight
// doubles, times (x0 x1 x2 x0 x1 x2 x0 x1) in one multiply-add, in the same accumulator lanes as
// avx2Block's lo and hi (lanes 0–3 and 4–7), and a8 on its own: the same sums, bit for bit, in
// fewer instructions (one conversion, permutation and multiply-add per block instead of two).
struct Avx512Blocks {
  struct Acc {
    __m512d v;
  };
  __attribute__((target("avx512f,avx2,fma"))) Acc zero() const { return {_mm512_setzero_pd()}; }
  __attribute__((target("avx512f,avx2,fma"))) void block(const float* val, const int* col, const double* x, int k,
                                                         Acc& acc, double& a22) const {
    const float* a = val + 9 * static_cast<size_t>(k);
    const double* xj = x + 3 * static_cast<size_t>(col[k]);
    const __m256d xv = _mm256_maskload_pd(xj, _mm256_set_epi64x(0, -1, -1, -1));  // x0 x1 x2 0
    const __m512i spread = _mm512_set_epi64(1, 0, 2, 1, 0, 2, 1, 0);                // → x0 x1 x2 x0 x1 x2 x0 x1
    const __m512d xs = _mm512_permutexvar_pd(spread, _mm512_zextpd256_pd512(xv));
    acc.v = _mm512_fmadd_pd(_mm512_cvtps_pd(_mm256_loadu_ps(a)), xs, acc.v);
    a22 = __builtin_fma(static_cast<double>(a[8]), xj[2], a22);
  }
  __attribute__((target("avx512f,avx2,fma"))) void store(double* s, const Acc& a, const Acc& b) const {
    _mm512_store_pd(s, _mm512_add_pd(a.v, b.v));
  }
};

__attribute__((target("avx512f,avx2,fma"))) void residualAvx512(const float* val, const int* col, const int* start,
                                                                 const double* b, const double* x, double* t, int i0,
                                                                 int i1) {
  residualRowsWith(Avx512Blocks{}, val, col, start, b, x, t, i0, i1);
}

__attribute__((target("avx512f,avx2,fma"))) double floatProductAvx512(const float* val, const int* col,
                                                                       const int* start, const double* x, double* y,
                                                                       int i0, int i1) {
  return residualRowsWith<Avx512Blocks, true>(Avx512Blocks{}, val, col, start, nullptr, x, y, i0, i1);
}
#pragma GCC diagnostic pop

// Block row r's three values (v_r[m], v_r[m+1], v_r[m+2], and a masked-off fourth) times
// (x0 x1 x2 0): each lane is one accumulator of the scalar version (lane 3 stays zero).
__attribute__((target("avx2,fma"))) double productAvx2(const int* outer, const double* val, const int* start,
                                                        const int* col, const double* b, const double* x, double* y,
                                                        int i0, int i1, bool residual) {
  const __m256i first_three = _mm256_set_epi64x(0, -1, -1, -1);
  double sum = 0.0;
  for (int i = i0; i < i1; ++i) {
    const double* v0 = val + outer[3 * i];
    const double* v1 = val + outer[3 * i + 1];
    const double* v2 = val + outer[3 * i + 2];
    __m256d r0 = _mm256_setzero_pd(), r1 = _mm256_setzero_pd(), r2 = _mm256_setzero_pd();
    const int k_last = start[i + 1] - 1;
    int k = start[i], m = 0;
    // Before a row's last block the fourth lane reads the row's next value, times the masked zero.
    for (; k < k_last; ++k, m += 3) {
      const __m256d xv = _mm256_maskload_pd(x + 3 * static_cast<size_t>(col[k]), first_three);
      r0 = _mm256_fmadd_pd(_mm256_loadu_pd(v0 + m), xv, r0);
      r1 = _mm256_fmadd_pd(_mm256_loadu_pd(v1 + m), xv, r1);
      r2 = _mm256_fmadd_pd(_mm256_loadu_pd(v2 + m), xv, r2);
    }
    if (k == k_last) {  // the last block: nothing read past the row (nor past the matrix)
      const __m256d xv = _mm256_maskload_pd(x + 3 * static_cast<size_t>(col[k]), first_three);
      r0 = _mm256_fmadd_pd(_mm256_maskload_pd(v0 + m, first_three), xv, r0);
      r1 = _mm256_fmadd_pd(_mm256_maskload_pd(v1 + m, first_three), xv, r1);
      r2 = _mm256_fmadd_pd(_mm256_maskload_pd(v2 + m, first_three), xv, r2);
    }
    alignas(32) double a[4], c[4], d[4];
    _mm256_store_pd(a, r0);
    _mm256_store_pd(c, r1);
    _mm256_store_pd(d, r2);
    finishProductRow((a[0] + a[1]) + a[2], (c[0] + c[1]) + c[2], (d[0] + d[1]) + d[2], residual, b, x, y, i, sum);
  }
  return sum;
}
#endif

}  // namespace

bool blockKernelsHaveSimd() {
#ifdef BREAST_SIM_X86_SIMD
  static const bool has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has;
#else
  return false;
#endif
}

bool blockResidualHasAvx512() {
#ifdef BREAST_SIM_X86_SIMD
  static const bool has = __builtin_cpu_supports("avx512f") && blockKernelsHaveSimd();
  return has;
#else
  return false;
#endif
}

void blockResidualRowsAvx2(const float* val, const int* col, const int* start, const double* b, const double* x,
                           double* t, int i0, int i1) {
#ifdef BREAST_SIM_X86_SIMD
  if (blockKernelsHaveSimd()) {
    residualAvx2(val, col, start, b, x, t, i0, i1);
    return;
  }
#endif
  residualScalar(val, col, start, b, x, t, i0, i1);
}

void blockResidualRows(const float* val, const int* col, const int* start, const double* b, const double* x,
                       double* t, int i0, int i1, bool simd) {
#ifdef BREAST_SIM_X86_SIMD
  if (simd && blockResidualHasAvx512()) {
    residualAvx512(val, col, start, b, x, t, i0, i1);
    return;
  }
  if (simd && blockKernelsHaveSimd()) {
    residualAvx2(val, col, start, b, x, t, i0, i1);
    return;
  }
#endif
  residualScalar(val, col, start, b, x, t, i0, i1);
}

double floatBlockProductRows(const float* val, const int* col, const int* start, const double* x, double* y, int i0,
                             int i1, bool simd) {
#ifdef BREAST_SIM_X86_SIMD
  if (simd && blockResidualHasAvx512()) return floatProductAvx512(val, col, start, x, y, i0, i1);
  if (simd && blockKernelsHaveSimd()) return floatProductAvx2(val, col, start, x, y, i0, i1);
#endif
  return floatProductScalar(val, col, start, x, y, i0, i1);
}

double blockProductRows(const int* outer, const double* val, const int* start, const int* col, const double* b,
                        const double* x, double* y, int i0, int i1, bool residual, bool simd) {
#ifdef BREAST_SIM_X86_SIMD
  if (simd && blockKernelsHaveSimd()) return productAvx2(outer, val, start, col, b, x, y, i0, i1, residual);
#endif
  return productScalar(outer, val, start, col, b, x, y, i0, i1, residual);
}

namespace {
// Thread p's share [first, second) of n rows among np threads.
inline int shareStart(int n, int p, int np) { return static_cast<int>(static_cast<long>(n) * p / np); }
}  // namespace

void blockResidual(const float* val, const int* col, const int* start, const double* b, const double* x, double* t,
                   int nodes, bool simd, bool parallel) {
#pragma omp parallel if (parallel)
  {
    const int p = omp_get_thread_num(), np = omp_get_num_threads();
    blockResidualRows(val, col, start, b, x, t, shareStart(nodes, p, np), shareStart(nodes, p + 1, np), simd);
  }
}

namespace {
// The products' sums over fixed chunks of node rows, added in chunk order (util/ordered_sum.h): the
// same bits on any number of threads.
constexpr long kProductChunkRows = 256;

template <class Rows>
double orderedRowSum(int nodes, bool parallel, const Rows& rows) {
  return util::orderedRangeSums<1>(nodes, kProductChunkRows, parallel, [&](long i0, long i1) {
    return std::array<double, 1>{rows(static_cast<int>(i0), static_cast<int>(i1))};
  })[0];
}
}  // namespace

double blockProduct(const int* outer, const double* val, const int* start, const int* col, const double* b,
                    const double* x, double* y, int nodes, bool residual, bool simd, bool parallel) {
  return orderedRowSum(nodes, parallel, [&](int i0, int i1) {
    return blockProductRows(outer, val, start, col, b, x, y, i0, i1, residual, simd);
  });
}

double floatBlockProduct(const float* val, const int* col, const int* start, const double* x, double* y, int nodes,
                         bool simd, bool parallel) {
  return orderedRowSum(nodes, parallel,
                       [&](int i0, int i1) { return floatBlockProductRows(val, col, start, x, y, i0, i1, simd); });
}

}  // namespace breast_sim::core
