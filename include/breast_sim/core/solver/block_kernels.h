#pragma once
/// @file block_kernels.h
/// The solver's hottest loops over ranges of node rows: the multigrid's residual t = b − A x of a
/// level stored in 3×3 blocks of floats (one column node per block, nine row-major values), and
/// PCG's product with the double CSR matrix in block layout. Two versions of the same arithmetic: portable scalar code (the reference), and AVX2/FMA code that works on a
/// block's first eight values as two four-wide vectors, chosen at run time when the processor has
/// those instructions. Both sum each block entry's products in its own accumulator, in block
/// order, and add the three accumulators of a row at the end, so they differ only in rounding
/// (the AVX2 version fuses each multiply-add).

namespace breast_sim::core {

/// Whether this processor runs the AVX2/FMA version (checked once).
bool blockKernelsHaveSimd();

/// t_i = b_i − Σ_k A_k x_{col[k]} for node rows i in [i0, i1): blocks start[i] .. start[i+1] − 1,
/// block k's values val[9k .. 9k+8] row-major, its column node col[k]; b, x, t hold 3 values per node.
/// @param simd  use the AVX2/FMA version (only when blockKernelsHaveSimd(); otherwise ignored)
void blockResidualRows(const float* val, const int* col, const int* start, const double* b, const double* x,
                       double* t, int i0, int i1, bool simd);

/// PCG's products with the caller's double matrix in CSR 3×3-block layout (fem/block_pattern.h) over
/// node rows [i0, i1): `outer` its row starts, `val` its values, `start`/`col` the node columns of
/// each node row's blocks (one index per block). kResidual: y = b − A x, returns Σ y_r²; otherwise
/// y = A x, returns Σ x_r y_r (over the range's rows). One accumulator per block entry, added per
/// row at the end; the AVX2 version multiplies a block row's three values by (x0 x1 x2) as one
/// masked four-wide vector.
double blockProductRows(const int* outer, const double* val, const int* start, const int* col, const double* b,
                        const double* x, double* y, int i0, int i1, bool residual, bool simd);

}  // namespace breast_sim::core
