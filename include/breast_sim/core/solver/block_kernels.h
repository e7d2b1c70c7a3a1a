#pragma once
/// @file block_kernels.h
/// The solver's hottest loops over ranges of node rows: the multigrid's residual t = b − A x of a
/// level stored in 3×3 blocks of floats (one column node per block, nine row-major values), and
/// PCG's product with the double CSR matrix in block layout. Two versions of the same arithmetic:
/// portable scalar code (the reference), and AVX2/FMA code chosen at run time when the processor
/// has those instructions (the residual also in AVX-512F, the same sums as its AVX2 version). Both sum each block entry's products in an accumulator of its own and
/// add the three of a row at the end; the AVX2 residual keeps two sets (even and odd blocks) and
/// every AVX2 multiply-add is fused, so the results differ in the last bits.

namespace breast_sim::core {

/// r = b_i − Σ_k A_k x_{col[k]} over the blocks [k0, k1) of one node row in float block storage
/// (the scalar kernel's row; also the Gauss–Seidel, Chebyshev and damping sweeps of the multigrid).
/// One accumulator per block entry (nine): each block's nine products are independent, so the loop
/// runs at the machine's multiply-add throughput instead of waiting out three dependent multiply-adds
/// per row and block.
inline void blockRowResidual(const float* val, const int* col, int k0, int k1, const double* b, const double* x,
                             double r[3]) {
  double a00 = 0, a01 = 0, a02 = 0, a10 = 0, a11 = 0, a12 = 0, a20 = 0, a21 = 0, a22 = 0;
  for (int k = k0; k < k1; ++k) {
    const float* a = val + 9 * static_cast<long>(k);
    const double* xj = x + 3 * static_cast<long>(col[k]);
    const double x0 = xj[0], x1 = xj[1], x2 = xj[2];
    a00 += a[0] * x0, a01 += a[1] * x1, a02 += a[2] * x2;
    a10 += a[3] * x0, a11 += a[4] * x1, a12 += a[5] * x2;
    a20 += a[6] * x0, a21 += a[7] * x1, a22 += a[8] * x2;
  }
  r[0] = b[0] - ((a00 + a01) + a02);
  r[1] = b[1] - ((a10 + a11) + a12);
  r[2] = b[2] - ((a20 + a21) + a22);
}

/// Whether this processor runs the AVX2/FMA version (checked once).
bool blockKernelsHaveSimd();

/// Whether this processor runs the AVX-512F version of the float-block residual (checked once).
bool blockResidualHasAvx512();

/// t_i = b_i − Σ_k A_k x_{col[k]} for node rows i in [i0, i1): blocks start[i] .. start[i+1] − 1,
/// block k's values val[9k .. 9k+8] row-major, its column node col[k]; b, x, t hold 3 values per node.
/// @param simd  use the AVX-512F version where the processor has it (blockResidualHasAvx512()), else
///        the AVX2/FMA one (blockKernelsHaveSimd()); ignored on a processor with neither. The
///        AVX-512F version does the AVX2 one's arithmetic in the same accumulators, one block per
///        eight-wide multiply-add instead of two four-wide ones: the same sums, bit for bit.
///        Measured (bench_solvers --variants mg:jacobi1 --morton, 48.8k, 1 thread, process CPU time,
///        three interleaved rounds): fine level per V-cycle 0.67–0.71 → 0.55–0.59 ms, level 1
///        0.26–0.28 → 0.21–0.22 ms.
void blockResidualRows(const float* val, const int* col, const int* start, const double* b, const double* x,
                       double* t, int i0, int i1, bool simd);
/// The AVX2/FMA version alone (the scalar one where the processor lacks AVX2/FMA): the reference
/// the tests hold the AVX-512F version to, bit for bit.
void blockResidualRowsAvx2(const float* val, const int* col, const int* start, const double* b, const double* x,
                           double* t, int i0, int i1);

/// PCG's products with the caller's double matrix in CSR 3×3-block layout (fem/block_pattern.h) over
/// node rows [i0, i1): `outer` its row starts, `val` its values, `start`/`col` the node columns of
/// each node row's blocks (one index per block). kResidual: y = b − A x, returns Σ y_r²; otherwise
/// y = A x, returns Σ x_r y_r (over the range's rows). One accumulator per block entry, added per
/// row at the end; the AVX2 version multiplies a block row's three values by (x0 x1 x2) as one
/// masked four-wide vector.
double blockProductRows(const int* outer, const double* val, const int* start, const int* col, const double* b,
                        const double* x, double* y, int i0, int i1, bool residual, bool simd);

/// y = A x over node rows [i0, i1) of a matrix in float block storage (as blockResidualRows), returns
/// Σ x_r y_r over them: PCG's iteration product with the float copy a preconditioner keeps. The
/// residual kernel's sums (simd as there): y is −(0 − A x) of blockResidualRows, bit for bit.
double floatBlockProductRows(const float* val, const int* col, const int* start, const double* x, double* y, int i0,
                             int i1, bool simd);

/// The same over all `nodes` node rows when `parallel` on the OpenMP team: blockResidual in one
/// contiguous range per thread (the static schedule's split); blockProduct and floatBlockProduct in
/// fixed chunks of 256 node rows whose sums are added in chunk order, so the returned sum has the
/// same bits on any number of threads.
void blockResidual(const float* val, const int* col, const int* start, const double* b, const double* x, double* t,
                   int nodes, bool simd, bool parallel);
double blockProduct(const int* outer, const double* val, const int* start, const int* col, const double* b,
                    const double* x, double* y, int nodes, bool residual, bool simd, bool parallel);
double floatBlockProduct(const float* val, const int* col, const int* start, const double* x, double* y, int nodes,
                         bool simd, bool parallel);

}  // namespace breast_sim::core
