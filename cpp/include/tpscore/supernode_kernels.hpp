// Dense kernels of the supernodal Cholesky factorisation (tpscore/sparse_solve.hpp):
// the partial factorisation of one supernode's front and the supernode's share of the
// triangular solves.
//
// Almost all the arithmetic of a sparse Cholesky factorisation happens in these dense
// blocks, so they are compiled twice: once for the baseline instruction set the
// library is built for, and, on x86-64, once more for x86-64-v3 (AVX2 + FMA), which
// doubles the width of every multiply-add. supernode_kernels() picks the best set
// the CPU runs, so a wheel built for baseline x86-64 still uses AVX2 where it exists.
//
// This header includes no Eigen on purpose: the x86-64-v3 build of the kernels
// renames Eigen's namespace (see supernode_kernels.cpp), and only plain pointers may
// cross between the two builds.
#pragma once

#include <cstddef>

namespace tpscore {

/// One instruction set's build of the dense supernode kernels.
///
/// A supernode's panel is the column-major (rows, columns) block of L below and on
/// the diagonal of its `columns` consecutive columns (leading dimension `rows`): the
/// top (columns, columns) square is the diagonal block L11 (lower triangle; the
/// strict upper triangle is left as it was), the rest is L21.
struct SupernodeKernels {
    /// Name of the instruction set ("x86-64-v3" or "baseline").
    const char* isa;

    /// Factorises a supernode's front in place: on entry the panel holds the
    /// assembled columns of the matrix (A11; A21) and `update` the assembled
    /// (rows - columns) square lower triangle of the front's remaining block, column-
    /// major. On exit the panel holds (L11; L21) with A11 = L11 L11^T and
    /// L21 = A21 L11^-T, and update -= L21 L21^T (lower triangle only).
    /// pivots[j] receives the j-th pivot, the square of L11's j-th diagonal entry (the
    /// j-th entry of D in the equivalent L D L^T). Returns -1, or the index j of the
    /// first pivot that is not positive (then pivots[0..j] are set, nothing after j is
    /// meaningful and `update` is untouched).
    std::ptrdiff_t (*factor_front)(double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns,
                                   double* update, double* pivots);

    /// The supernode's step of the forward solve L y = b for one right-hand side:
    /// x (columns) := L11^-1 x, then below (rows - columns) := L21 x.
    void (*forward)(const double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns, double* x,
                    double* below);

    /// The supernode's step of the backward solve L^T x = y for one right-hand side:
    /// x (columns) := L11^-T (x - L21^T below), with `below` the (rows - columns)
    /// solution entries at the panel's lower rows.
    void (*backward)(const double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns, double* x,
                     const double* below);
};

/// The kernels for this CPU: the x86-64-v3 build when the CPU supports it and the
/// library has one, else the baseline build. TPSCORE_SIMD=baseline (see simd.hpp)
/// forces the baseline build, as it does for the other hand-dispatched kernels.
const SupernodeKernels& supernode_kernels();

/// The baseline build, always present.
const SupernodeKernels& supernode_kernels_baseline();

}  // namespace tpscore
