#include "tpscore/dense_cholesky.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <vector>

#include "tpscore/parallel.hpp"
#include "tpscore/simd.hpp"

// Everything below the driver is written once, as templates over a register tile
// shape, and instantiated three times inside functions compiled for AVX-512
// (x86-64-v4), AVX2 + FMA (x86-64-v3) and the baseline; the driver picks one set
// at load time. The templates are always inlined into those functions, so their
// code takes the functions' instruction set; nothing compiled for a wider set is
// shared with (or can be picked by the linker for) the baseline path.
#define TPSCORE_CHOLESKY_DISPATCH TPSCORE_MULTI_TARGET

#if defined(__GNUC__)
// GCC warns that passing the 32- and 64-byte vector types between functions built
// without AVX would change the ABI; every function that handles them is inlined
// into one built with the matching instruction set, so no such call exists.
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

namespace tpscore {

namespace {

// --- block sizes ---------------------------------------------------------------------
// Panel width of the blocked factorisation: the trailing update is a rank-128
// product, long enough to keep the micro-kernel busy, while the serial work on each
// panel's diagonal block (128^3 / 3 flops) stays a few percent of the whole at the
// sizes a face pipeline fits (n = 1000 to 5000). The panel is also one depth chunk
// (kDepth), so each trailing update packs its operands once.
constexpr std::int64_t kPanel = 128;
// Inside a diagonal block and a panel solve, columns are eliminated 16 at a time
// with plain vector code; the rest of their work is the tiled product. (16 factorised
// a 96-square matrix 20% faster than 32, a 296-square one 12%; 8 was no faster.)
constexpr std::int64_t kInner = 16;
// The product's inner dimension is cut into chunks of this many terms, so that one
// packed MR x kc and one NR x kc micro-panel (16 and 12 kB at kc = 128 with AVX-512)
// stay in the 32-48 kB level-1 data cache while a tile is computed.
constexpr std::int64_t kDepth = 128;
// Columns of the trailing matrix per parallel task, and rows per task of the panel
// solve: fixed, so the partition (and the result) does not depend on the thread count.
// Both are multiples of every tile's MR and NR (16 and 12, 8 and 6, 4 and 4), so a
// task's rows are whole packed panels.
constexpr std::int64_t kStripColumns = 96;
constexpr std::int64_t kSolveRows = 192;

// A register tile of MR = W * MV rows by NR columns: MV * NR vector accumulators.
template <int W, int MV, int NR_>
struct TileShape {
    typedef double Vector __attribute__((vector_size(W * sizeof(double))));
    static constexpr int kWidth = W;
    static constexpr int kVectors = MV;
    static constexpr int MR = W * MV;
    static constexpr int NR = NR_;
};
// AVX-512: 24 of the 32 zmm registers accumulate a 16 x 12 tile; per step of the
// inner loop, 2 loads and 12 broadcasts feed 24 FMAs (the two FMA ports' limit).
using TileAvx512 = TileShape<8, 2, 12>;
// AVX2: 12 of the 16 ymm registers hold an 8 x 6 tile (the shape BLIS uses on Haswell).
using TileAvx2 = TileShape<4, 2, 6>;
// SSE2 (and any other target): 8 of 16 xmm registers hold a 4 x 4 tile.
using TileBaseline = TileShape<2, 2, 4>;

template <class V>
TPSCORE_INLINE V load(const double* p) {
    V v;
    std::memcpy(&v, p, sizeof v);  // an unaligned vector load
    return v;
}

template <class V>
TPSCORE_INLINE void store(double* p, V v) {
    std::memcpy(p, &v, sizeof v);
}

// acc = sum over the kc steps of (MR values of a) x (NR values of b): a and b are
// packed micro-panels (see pack).
template <class S>
TPSCORE_INLINE void tile_product(std::int64_t kc, const double* __restrict a,
                                 const double* __restrict b,
                                 typename S::Vector (&acc)[S::kVectors][S::NR]) {
    using V = typename S::Vector;
#pragma GCC unroll 16
    for (int j = 0; j < S::NR; ++j)
#pragma GCC unroll 4
        for (int i = 0; i < S::kVectors; ++i) acc[i][j] = V{};
    for (std::int64_t p = 0; p < kc; ++p) {
        V column[S::kVectors];
#pragma GCC unroll 4
        for (int i = 0; i < S::kVectors; ++i) column[i] = load<V>(a + p * S::MR + i * S::kWidth);
#pragma GCC unroll 16
        for (int j = 0; j < S::NR; ++j) {
            // x - 0 == x for every x (-0 included), so this is a plain broadcast;
            // 0 + x would not be (it turns -0 into +0), and costs an add.
            const V broadcast = b[p * S::NR + j] - V{};
#pragma GCC unroll 4
            for (int i = 0; i < S::kVectors; ++i) acc[i][j] += column[i] * broadcast;
        }
    }
}

// Copies the m x kc block with element (r, p) at src[r * rs + p * cs] into panels of
// R rows: panel q holds, for p = 0..kc-1, rows qR..qR+R-1 of column p (zeros past m).
TPSCORE_INLINE void pack(int R, std::int64_t m, std::int64_t kc, const double* src, std::int64_t rs,
                         std::int64_t cs, double* dst) {
    for (std::int64_t r0 = 0; r0 < m; r0 += R) {
        const std::int64_t rows = std::min<std::int64_t>(R, m - r0);
        for (std::int64_t p = 0; p < kc; ++p) {
            const double* column = src + r0 * rs + p * cs;
            double* out = dst + p * R;
            if (rs == 1) {
                for (std::int64_t i = 0; i < rows; ++i) out[i] = column[i];
            } else {
                for (std::int64_t i = 0; i < rows; ++i) out[i] = column[i * rs];
            }
            for (std::int64_t i = rows; i < R; ++i) out[i] = 0.0;
        }
        dst += kc * R;
    }
}

// C -= A B^T for packed operands: A (m x kc) in MR-row panels, B (n x kc) in NR-row
// panels (see pack); C is m x n column-major (ldc). With `lower`, C is a block on the
// diagonal of a symmetric matrix and only its entries with row >= column are written.
// Each NR-row panel of B stays in the level-1 cache while the panels of A stream past
// it: the micro-kernel's broadcasts then come from level 1, its vector loads from the
// prefetched stream (15% faster at n = 3000 than keeping a panel of A in level 1).
template <class S>
TPSCORE_INLINE void multiply_packed(std::int64_t m, std::int64_t n, std::int64_t kc, const double* packed_a,
                                    const double* packed_b, double* c, std::int64_t ldc, bool lower) {
    using V = typename S::Vector;
    constexpr int MR = S::MR, NR = S::NR;
    const std::int64_t m_panels = (m + MR - 1) / MR;
    const std::int64_t n_panels = (n + NR - 1) / NR;
    for (std::int64_t jp = 0; jp < n_panels; ++jp) {
        const std::int64_t j0 = jp * NR;
        const std::int64_t cols = std::min<std::int64_t>(NR, n - j0);
        const double* panel_b = packed_b + jp * NR * kc;
        // Tiles wholly above the diagonal are skipped: rows i0 .. i0 + MR - 1 < j0.
        const std::int64_t first = lower ? j0 / MR : 0;
        for (std::int64_t ip = first; ip < m_panels; ++ip) {
            const std::int64_t i0 = ip * MR;
            const std::int64_t rows = std::min<std::int64_t>(MR, m - i0);
            V acc[S::kVectors][NR];
            tile_product<S>(kc, packed_a + ip * MR * kc, panel_b, acc);
            double* tile = c + i0 + j0 * ldc;
            const bool crosses_diagonal = lower && i0 < j0 + cols - 1;
            if (rows == MR && cols == NR && !crosses_diagonal) {
#pragma GCC unroll 16
                for (int j = 0; j < NR; ++j)
#pragma GCC unroll 4
                    for (int i = 0; i < S::kVectors; ++i) {
                        double* target = tile + j * ldc + i * S::kWidth;
                        store(target, load<V>(target) - acc[i][j]);
                    }
            } else {
                alignas(64) double values[MR * NR];
                for (int j = 0; j < NR; ++j)
                    for (int i = 0; i < S::kVectors; ++i) store(values + j * MR + i * S::kWidth, acc[i][j]);
                for (std::int64_t j = 0; j < cols; ++j) {
                    const std::int64_t top = lower ? std::max<std::int64_t>(0, j0 + j - i0) : 0;
                    for (std::int64_t i = top; i < rows; ++i) tile[j * ldc + i] -= values[j * MR + i];
                }
            }
        }
    }
}

// C -= A B^T: C is m x n column-major (ldc); A is m x k and B is n x k, element (r, p)
// at a[r * a_rs + p * a_cs] (and likewise for b). With `lower`, as above. `buffer` is
// scratch for the packed operands, grown as needed.
template <class S>
TPSCORE_INLINE void multiply_subtract(std::int64_t m, std::int64_t n, std::int64_t k, const double* a,
                                      std::int64_t a_rs, std::int64_t a_cs, const double* b,
                                      std::int64_t b_rs, std::int64_t b_cs, double* c,
                                      std::int64_t ldc, bool lower, std::vector<double>& buffer) {
    constexpr int MR = S::MR, NR = S::NR;
    if (m <= 0 || n <= 0 || k <= 0) return;
    const std::int64_t m_panels = (m + MR - 1) / MR;
    const std::int64_t n_panels = (n + NR - 1) / NR;
    const std::int64_t depth = std::min(k, kDepth);
    const std::size_t needed = static_cast<std::size_t>((m_panels * MR + n_panels * NR) * depth);
    if (buffer.size() < needed) buffer.resize(needed);
    double* packed_a = buffer.data();
    double* packed_b = packed_a + m_panels * MR * depth;
    for (std::int64_t p0 = 0; p0 < k; p0 += kDepth) {
        const std::int64_t kc = std::min(kDepth, k - p0);
        pack(MR, m, kc, a + p0 * a_cs, a_rs, a_cs, packed_a);
        pack(NR, n, kc, b + p0 * b_cs, b_rs, b_cs, packed_b);
        multiply_packed<S>(m, n, kc, packed_a, packed_b, c, ldc, lower);
    }
}

// X L^T = B for X (m x n, overwriting B, column-major ldb), L lower n x n (ldl), with
// plain vector code over the m rows: the base case of solve_rows.
TPSCORE_INLINE void solve_rows_unblocked(std::int64_t m, std::int64_t n, const double* l, std::int64_t ldl,
                                         double* b, std::int64_t ldb) {
    for (std::int64_t j = 0; j < n; ++j) {
        double* __restrict column = b + j * ldb;
        for (std::int64_t p = 0; p < j; ++p) {
            const double factor = l[j + p * ldl];
            const double* __restrict source = b + p * ldb;
#pragma omp simd
            for (std::int64_t i = 0; i < m; ++i) column[i] -= factor * source[i];
        }
        const double inverse = 1.0 / l[j + j * ldl];
#pragma omp simd
        for (std::int64_t i = 0; i < m; ++i) column[i] *= inverse;
    }
}

// X L^T = B, blocked: eliminate kInner columns, then update the rest with one product.
template <class S>
TPSCORE_INLINE void solve_rows(std::int64_t m, std::int64_t n, const double* l, std::int64_t ldl, double* b,
                               std::int64_t ldb, std::vector<double>& buffer) {
    for (std::int64_t j0 = 0; j0 < n; j0 += kInner) {
        const std::int64_t jb = std::min(kInner, n - j0);
        solve_rows_unblocked(m, jb, l + j0 + j0 * ldl, ldl, b + j0 * ldb, ldb);
        const std::int64_t rest = n - j0 - jb;
        if (rest > 0)
            multiply_subtract<S>(m, rest, jb, b + j0 * ldb, 1, ldb, l + (j0 + jb) + j0 * ldl, 1, ldl,
                                 b + (j0 + jb) * ldb, ldb, false, buffer);
    }
}

// Cholesky of a small block (n <= kInner) by columns, right-looking.
TPSCORE_INLINE std::int64_t factor_unblocked(std::int64_t n, double* a, std::int64_t lda) {
    for (std::int64_t j = 0; j < n; ++j) {
        double* __restrict column = a + j * lda;
        const double pivot = column[j];
        // !(pivot > 0) also catches NaN; an infinite pivot means overflow upstream.
        if (!(pivot > 0.0) || !std::isfinite(pivot)) return j;
        const double root = std::sqrt(pivot);
        column[j] = root;
        const double inverse = 1.0 / root;
        for (std::int64_t i = j + 1; i < n; ++i) column[i] *= inverse;
        for (std::int64_t c = j + 1; c < n; ++c) {
            const double factor = column[c];
            double* __restrict target = a + c * lda;
            for (std::int64_t i = c; i < n; ++i) target[i] -= factor * column[i];
        }
    }
    return -1;
}

// Cholesky of a diagonal block of the blocked factorisation (n <= kPanel), itself
// blocked by kInner columns.
template <class S>
TPSCORE_INLINE std::int64_t factor_block(std::int64_t n, double* a, std::int64_t lda,
                                         std::vector<double>& buffer) {
    for (std::int64_t j0 = 0; j0 < n; j0 += kInner) {
        const std::int64_t jb = std::min(kInner, n - j0);
        double* diagonal = a + j0 + j0 * lda;
        const std::int64_t failed = factor_unblocked(jb, diagonal, lda);
        if (failed >= 0) return j0 + failed;
        const std::int64_t rest = n - j0 - jb;
        if (rest == 0) break;
        double* below = diagonal + jb;
        solve_rows_unblocked(rest, jb, diagonal, lda, below, lda);
        multiply_subtract<S>(rest, rest, jb, below, 1, lda, below, 1, lda, below + jb * lda, lda, true,
                             buffer);
    }
    return -1;
}

// Y = L^{-1} B or L^{-T} B in place (B n x k). With a few right-hand sides these
// solves are bound by reading L from memory, so they read it once, in place (no
// packing), kSolveColumns columns at a time: forward, each block of columns updates
// the rows below it (a column-oriented axpy); backward, it takes dot products with
// the rows already solved.
constexpr std::int64_t kSolveColumns = 8;

// Substitution in a small diagonal block d (Size x Size, or `size` x `size` below,
// column-major with leading dimension ldl) of L or L^T, on `x` in place, with the
// reciprocals of its diagonal given. Column by column: each unknown, once known, is
// taken out of the others at once, so the chain of dependent operations is one
// multiply and one FMA per unknown (by rows it would be a sum as long as the row).
// A constant Size lets the compiler keep the block's unknowns in registers.
template <int Size>
TPSCORE_INLINE void block_substitution(const double* d, std::int64_t ldl, const double* inverse, bool transpose,
                                       double* x, int size = Size) {
    if (!transpose) {
#pragma GCC unroll 8
        for (int p = 0; p < size; ++p) {
            x[p] *= inverse[p];
#pragma GCC unroll 8
            for (int r = p + 1; r < size; ++r) x[r] -= d[r + p * ldl] * x[p];
        }
    } else {
#pragma GCC unroll 8
        for (int p = size - 1; p >= 0; --p) {
            x[p] *= inverse[p];
#pragma GCC unroll 8
            for (int r = 0; r < p; ++r) x[r] -= d[p + r * ldl] * x[p];
        }
    }
}

TPSCORE_INLINE void triangular_solve_impl(std::int64_t n, const double* l, std::int64_t ldl, bool transpose,
                                          double* b, std::int64_t ldb, std::int64_t k) {
    if (!transpose) {
        for (std::int64_t p0 = 0; p0 < n; p0 += kSolveColumns) {
            const std::int64_t pb = std::min(kSolveColumns, n - p0);
            const std::int64_t below = p0 + pb;
            const double* diagonal = l + p0 + p0 * ldl;
            double inverse_diagonal[kSolveColumns];
            for (std::int64_t p = 0; p < pb; ++p) inverse_diagonal[p] = 1.0 / diagonal[p + p * ldl];
            for (std::int64_t q = 0; q < k; ++q) {
                double* x = b + q * ldb;
                double solved[kSolveColumns];
                for (std::int64_t p = 0; p < pb; ++p) solved[p] = x[p0 + p];
                if (pb == kSolveColumns)
                    block_substitution<kSolveColumns>(diagonal, ldl, inverse_diagonal, false, solved);
                else
                    block_substitution<0>(diagonal, ldl, inverse_diagonal, false, solved, static_cast<int>(pb));
                for (std::int64_t p = 0; p < pb; ++p) x[p0 + p] = solved[p];
                if (pb == kSolveColumns) {
                    const double* c0 = l + p0 * ldl;
                    const double* c1 = c0 + ldl;
                    const double* c2 = c1 + ldl;
                    const double* c3 = c2 + ldl;
                    const double* c4 = c3 + ldl;
                    const double* c5 = c4 + ldl;
                    const double* c6 = c5 + ldl;
                    const double* c7 = c6 + ldl;
#pragma omp simd
                    for (std::int64_t i = below; i < n; ++i)
                        x[i] -= ((c0[i] * solved[0] + c1[i] * solved[1]) + (c2[i] * solved[2] + c3[i] * solved[3])) +
                                ((c4[i] * solved[4] + c5[i] * solved[5]) + (c6[i] * solved[6] + c7[i] * solved[7]));
                } else {
                    for (std::int64_t p = 0; p < pb; ++p) {
                        const double* column = l + (p0 + p) * ldl;
#pragma omp simd
                        for (std::int64_t i = below; i < n; ++i) x[i] -= column[i] * solved[p];
                    }
                }
            }
        }
    } else {
        const std::int64_t blocks = (n + kSolveColumns - 1) / kSolveColumns;
        for (std::int64_t block = blocks - 1; block >= 0; --block) {
            const std::int64_t p0 = block * kSolveColumns;
            const std::int64_t pb = std::min(kSolveColumns, n - p0);
            const std::int64_t below = p0 + pb;
            const double* diagonal = l + p0 + p0 * ldl;
            double inverse_diagonal[kSolveColumns];
            for (std::int64_t p = 0; p < pb; ++p) inverse_diagonal[p] = 1.0 / diagonal[p + p * ldl];
            for (std::int64_t q = 0; q < k; ++q) {
                double* x = b + q * ldb;
                double dots[kSolveColumns] = {};
                if (pb == kSolveColumns) {
                    // Eight dot products in one pass over the rows below.
                    const double* c0 = l + p0 * ldl;
                    const double *c1 = c0 + ldl, *c2 = c1 + ldl, *c3 = c2 + ldl, *c4 = c3 + ldl,
                                 *c5 = c4 + ldl, *c6 = c5 + ldl, *c7 = c6 + ldl;
                    double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0, s4 = 0.0, s5 = 0.0, s6 = 0.0, s7 = 0.0;
#pragma omp simd reduction(+ : s0, s1, s2, s3, s4, s5, s6, s7)
                    for (std::int64_t i = below; i < n; ++i) {
                        const double xi = x[i];
                        s0 += c0[i] * xi;
                        s1 += c1[i] * xi;
                        s2 += c2[i] * xi;
                        s3 += c3[i] * xi;
                        s4 += c4[i] * xi;
                        s5 += c5[i] * xi;
                        s6 += c6[i] * xi;
                        s7 += c7[i] * xi;
                    }
                    dots[0] = s0, dots[1] = s1, dots[2] = s2, dots[3] = s3;
                    dots[4] = s4, dots[5] = s5, dots[6] = s6, dots[7] = s7;
                } else {
                    for (std::int64_t p = 0; p < pb; ++p) {
                        const double* column = l + (p0 + p) * ldl;
                        double sum = 0.0;
#pragma omp simd reduction(+ : sum)
                        for (std::int64_t i = below; i < n; ++i) sum += column[i] * x[i];
                        dots[p] = sum;
                    }
                }
                double solved[kSolveColumns];
                for (std::int64_t p = 0; p < pb; ++p) solved[p] = x[p0 + p] - dots[p];
                if (pb == kSolveColumns)
                    block_substitution<kSolveColumns>(diagonal, ldl, inverse_diagonal, true, solved);
                else
                    block_substitution<0>(diagonal, ldl, inverse_diagonal, true, solved, static_cast<int>(pb));
                for (std::int64_t p = 0; p < pb; ++p) x[p0 + p] = solved[p];
            }
        }
    }
}

// Y = A X for symmetric A (n x n) given by its strict upper triangle (column-major,
// lda) and its diagonal; X and Y n x k (ldx, ldy). Column j of the triangle serves
// both Y[0:j] (as a column) and Y[j] (as a row) while it is in cache.
TPSCORE_INLINE void symmetric_multiply_impl(std::int64_t n, const double* a, std::int64_t lda,
                                            const double* diagonal, const double* x, std::int64_t ldx,
                                            double* y, std::int64_t ldy, std::int64_t k) {
    for (std::int64_t q = 0; q < k; ++q)
        for (std::int64_t i = 0; i < n; ++i) y[i + q * ldy] = diagonal[i] * x[i + q * ldx];
    for (std::int64_t j = 1; j < n; ++j) {
        const double* __restrict column = a + j * lda;
        for (std::int64_t q = 0; q < k; ++q) {
            const double* __restrict xq = x + q * ldx;
            double* __restrict yq = y + q * ldy;
            const double xj = xq[j];
            double dot = 0.0;
#pragma omp simd reduction(+ : dot)
            for (std::int64_t i = 0; i < j; ++i) {
                yq[i] += column[i] * xj;
                dot += column[i] * xq[i];
            }
            yq[j] += dot;
        }
    }
}

// The entry points of one instruction set.
struct Kernels {
    std::int64_t (*factor_block)(std::int64_t n, double* a, std::int64_t lda);
    void (*solve_rows)(std::int64_t m, std::int64_t n, const double* l, std::int64_t ldl, double* b,
                       std::int64_t ldb);
    // The trailing update of one strip: C (m x n, a diagonal block at its top) -= A B^T
    // for A and B packed in panels of mr and nr rows.
    void (*update)(std::int64_t m, std::int64_t n, std::int64_t kc, const double* packed_a,
                   const double* packed_b, double* c, std::int64_t ldc);
    void (*triangular_solve)(std::int64_t n, const double* l, std::int64_t ldl, bool transpose, double* b,
                             std::int64_t ldb, std::int64_t k);
    void (*symmetric_multiply)(std::int64_t n, const double* a, std::int64_t lda, const double* diagonal,
                               const double* x, std::int64_t ldx, double* y, std::int64_t ldy, std::int64_t k);
    int mr, nr;  // the packing's panel heights (the register tile's rows and columns)
};

// Scratch for the packed operands, one per thread, reused across calls.
std::vector<double>& scratch() {
    thread_local std::vector<double> buffer;
    return buffer;
}

#define TPSCORE_DEFINE_KERNELS(NAME, TARGET, SHAPE)                                                    \
    TARGET std::int64_t NAME##_factor_block(std::int64_t n, double* a, std::int64_t lda) {              \
        return factor_block<SHAPE>(n, a, lda, scratch());                                               \
    }                                                                                                   \
    TARGET void NAME##_solve_rows(std::int64_t m, std::int64_t n, const double* l, std::int64_t ldl,   \
                                  double* b, std::int64_t ldb) {                                        \
        solve_rows<SHAPE>(m, n, l, ldl, b, ldb, scratch());                                             \
    }                                                                                                   \
    TARGET void NAME##_update(std::int64_t m, std::int64_t n, std::int64_t kc, const double* packed_a, \
                              const double* packed_b, double* c, std::int64_t ldc) {                    \
        multiply_packed<SHAPE>(m, n, kc, packed_a, packed_b, c, ldc, true);                             \
    }                                                                                                   \
    TARGET void NAME##_triangular_solve(std::int64_t n, const double* l, std::int64_t ldl,             \
                                        bool transpose, double* b, std::int64_t ldb, std::int64_t k) {  \
        triangular_solve_impl(n, l, ldl, transpose, b, ldb, k);                                         \
    }                                                                                                   \
    TARGET void NAME##_symmetric_multiply(std::int64_t n, const double* a, std::int64_t lda,           \
                                          const double* diagonal, const double* x, std::int64_t ldx,    \
                                          double* y, std::int64_t ldy, std::int64_t k) {                \
        symmetric_multiply_impl(n, a, lda, diagonal, x, ldx, y, ldy, k);                                \
    }                                                                                                   \
    const Kernels NAME##_kernels = {NAME##_factor_block,       NAME##_solve_rows,                       \
                                    NAME##_update,             NAME##_triangular_solve,                 \
                                    NAME##_symmetric_multiply, SHAPE::MR,                               \
                                    SHAPE::NR};

#define TPSCORE_NO_TARGET
TPSCORE_DEFINE_KERNELS(baseline, TPSCORE_NO_TARGET, TileBaseline)
#if TPSCORE_CHOLESKY_DISPATCH
TPSCORE_DEFINE_KERNELS(avx2, TPSCORE_TARGET_V3, TileAvx2)
TPSCORE_DEFINE_KERNELS(avx512, TPSCORE_TARGET_V4, TileAvx512)
#endif

const Kernels& select_kernels() {
#if TPSCORE_CHOLESKY_DISPATCH
    switch (simd_level()) {
        case SimdLevel::avx512: return avx512_kernels;
        case SimdLevel::avx2: return avx2_kernels;
        default: break;
    }
#endif
    return baseline_kernels;
}

const Kernels& kernels() {
    static const Kernels& chosen = select_kernels();
    return chosen;
}

}  // namespace

std::int64_t cholesky_factor(std::int64_t n, double* a, std::int64_t lda) {
    const Kernels& k = kernels();
    std::vector<double> packed_a, packed_b;
    for (std::int64_t j0 = 0; j0 < n; j0 += kPanel) {
        const std::int64_t jb = std::min(kPanel, n - j0);
        double* diagonal = a + j0 + j0 * lda;
        const std::int64_t failed = k.factor_block(jb, diagonal, lda);
        if (failed >= 0) return j0 + failed;
        const std::int64_t m = n - j0 - jb;
        if (m == 0) break;
        double* panel = diagonal + jb;  // rows j0 + jb .. n - 1 of the block column
        // The panel below the diagonal block, L21 = A21 L11^{-T}, by blocks of rows; each
        // task then packs its rows for the trailing update, as the left operand (panels
        // of mr rows) and as the right one (panels of nr rows), in the same pass (one
        // wait for all threads per step fewer: on a busy machine every such wait can
        // cost a scheduler's time slice).
        const std::int64_t row_blocks = (m + kSolveRows - 1) / kSolveRows;
        packed_a.resize(static_cast<std::size_t>(((m + k.mr - 1) / k.mr) * k.mr * jb));
        packed_b.resize(static_cast<std::size_t>(((m + k.nr - 1) / k.nr) * k.nr * jb));
        parallel_for(static_cast<std::size_t>(row_blocks), 1, [&](std::size_t begin, std::size_t end) {
            for (std::size_t r = begin; r < end; ++r) {
                const std::int64_t r0 = static_cast<std::int64_t>(r) * kSolveRows;
                const std::int64_t rows = std::min(kSolveRows, m - r0);
                k.solve_rows(rows, jb, diagonal, lda, panel + r0, lda);
                pack(k.mr, rows, jb, panel + r0, 1, lda, packed_a.data() + r0 * jb);
                pack(k.nr, rows, jb, panel + r0, 1, lda, packed_b.data() + r0 * jb);
            }
        });
        // The trailing matrix, A22 -= L21 L21^T (its lower triangle), by strips of columns.
        // Strips are taken from a shared counter, widest work first, so a thread that
        // finishes early (or a core another process holds) does not leave the rest
        // waiting; each strip is computed wholly by one thread either way.
        double* trailing = panel + jb * lda;
        const std::int64_t strips = (m + kStripColumns - 1) / kStripColumns;
        // A strip is at least 96 x 96 x 128 x 2 flops (2.4 Mflop, ~50 us): one per
        // thread pays for handing it over.
        std::atomic<std::int64_t> next{0};
        parallel_for(static_cast<std::size_t>(strips), 1, [&](std::size_t, std::size_t) {
            for (;;) {
                const std::int64_t s = next.fetch_add(1, std::memory_order_relaxed);
                if (s >= strips) break;
                const std::int64_t c0 = s * kStripColumns;
                const std::int64_t width = std::min(kStripColumns, m - c0);
                k.update(m - c0, width, jb, packed_a.data() + c0 * jb, packed_b.data() + c0 * jb,
                         trailing + c0 + c0 * lda, lda);
            }
        });
    }
    return -1;
}

void triangular_solve(std::int64_t n, const double* l, std::int64_t ldl, bool transpose, double* b,
                      std::int64_t ldb, std::int64_t k) {
    if (n > 0 && k > 0) kernels().triangular_solve(n, l, ldl, transpose, b, ldb, k);
}

void symmetric_multiply(std::int64_t n, const double* a, std::int64_t lda, const double* diagonal,
                        const double* x, std::int64_t ldx, double* y, std::int64_t ldy, std::int64_t k) {
    if (n > 0 && k > 0) kernels().symmetric_multiply(n, a, lda, diagonal, x, ldx, y, ldy, k);
}

}  // namespace tpscore
