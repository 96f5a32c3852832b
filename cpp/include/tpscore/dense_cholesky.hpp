// Dense Cholesky factorisation A = L L^T of symmetric positive definite matrices,
// and solves with the factor: the linear algebra under the dense RBF fit.
//
// Blocked (right-looking, panels of 128 columns), threaded over the trailing update
// and the panel solve, with register-tiled SIMD micro-kernels compiled for AVX-512,
// AVX2 + FMA and baseline x86-64 and chosen once at load time (one binary for every
// CPU: no -march=native; see simd.hpp). Each output tile is computed by one thread with a fixed
// order of operations, so the factor does not depend on the thread count.
#pragma once

#include <cstdint>

namespace tpscore {

/// Factorises the n x n symmetric positive definite matrix whose lower triangle
/// (diagonal included) is stored column-major at `a` with leading dimension `lda`,
/// overwriting that lower triangle with L. The strict upper triangle is neither
/// read nor written, so a caller may keep the original matrix there.
///
/// Returns -1 on success, or the first column j whose pivot is not positive and
/// finite: the matrix is then not (numerically) positive definite, and the lower
/// triangle holds a partial factorisation.
std::int64_t cholesky_factor(std::int64_t n, double* a, std::int64_t lda);

/// Solves L Y = B (`transpose` false) or L^T Y = B (`transpose` true) in place, with
/// L the lower triangle at `l` (n x n, leading dimension ldl) and B n x k column-major
/// at `b` (leading dimension ldb). Serial; the caller passes all right-hand sides at
/// once, which reads L once for all of them.
void triangular_solve(std::int64_t n, const double* l, std::int64_t ldl, bool transpose, double* b,
                      std::int64_t ldb, std::int64_t k);

/// Y = A X for the symmetric n x n matrix A given by its strict upper triangle
/// (column-major at `a`, leading dimension lda) and its `diagonal` (n values); X and
/// Y are n x k column-major (ldx, ldy). Serial. With cholesky_factor this lets a
/// caller keep A in the upper triangle and compute residuals after factorising.
void symmetric_multiply(std::int64_t n, const double* a, std::int64_t lda, const double* diagonal,
                        const double* x, std::int64_t ldx, double* y, std::int64_t ldy, std::int64_t k);


}  // namespace tpscore
