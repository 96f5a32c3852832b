#include "tpscore/rbf.hpp"

#include <Eigen/Householder>
#include <Eigen/LU>
#include <Eigen/QR>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "tpscore/dense_cholesky.hpp"
#include "tpscore/parallel.hpp"
#include "tpscore/simd.hpp"

// glibc declares the vector variants of log and exp (libmvec: _ZGVbN2v_log,
// _ZGVdN4v_log, _ZGVeN8v_log, ...) only under -ffast-math (bits/math-vector.h).
// Declaring them here lets the `#pragma omp simd` loops below call them without
// fast-math's other relaxations (NaN and infinity handling, reassociation).
// With them the tps loop at 22,500 x 60 went from 5.7 ms (scalar log) to 4.1 ms
// (SSE2 libmvec), 2.0 ms (AVX2 clone) and 1.3 ms (AVX-512 clone), one thread, on
// the development machine (an AMD EPYC with AVX-512).
#if defined(__GLIBC__) && defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
extern "C" {
double log(double) noexcept __attribute__((simd("notinbranch")));
double exp(double) noexcept __attribute__((simd("notinbranch")));
}
// The loops are built per instruction set (TPSCORE_DISPATCH, measured above:
// x86-64-v3 brings AVX2 + FMA, v4 AVX-512); the tps evaluation has hand-written
// AVX-512 and AVX2 loops besides (accumulate_tps_avx512, accumulate_tps_avx2).
#define TPSCORE_HAND_WRITTEN_TPS TPSCORE_MULTI_TARGET
#include <immintrin.h>
#else
#define TPSCORE_HAND_WRITTEN_TPS 0
#endif

namespace tpscore {

namespace {

// Queries are evaluated in blocks of this many rows, laid out one array per axis, so
// the inner loop over a block is long, contiguous and has no remainder: every row
// goes through the same vector code whatever block or thread it falls in, which keeps
// the result independent of the thread count. 32..256 timed within 5% of each other
// (22,500 x 60, tps); 64 wastes the least on padding.
constexpr std::int64_t kBlock = 64;

// phi as a function of the squared distance d2 and e2 = epsilon^2 (same units).
template <RbfKernel Kernel>
TPSCORE_INLINE double phi_of_d2(double d2, double e2) {
    if constexpr (Kernel == RbfKernel::tps) {
        // U(0) = 0 without a comparison: 0 * log(DBL_MIN) = 0, and adding DBL_MIN
        // changes no d2 above 1e-290 mm^2. A `d2 > 0 ? ... : 0` select is a
        // possibly-trapping comparison to GCC, which then keeps it as a branch and
        // does not vectorise the loop (unless built with -fno-trapping-math).
        return d2 * std::log(d2 + std::numeric_limits<double>::min());
    } else if constexpr (Kernel == RbfKernel::biharmonic) {
        return std::sqrt(d2);
    } else if constexpr (Kernel == RbfKernel::triharmonic) {
        return d2 * std::sqrt(d2);
    } else if constexpr (Kernel == RbfKernel::multiquadric) {
        return std::sqrt(1.0 + e2 * d2);
    } else {
        return std::exp(-e2 * d2);
    }
}

// acc (Kdim rows of kBlock) += sum_j w_j phi(|q - c_j|) for one block of queries.
// Kdim > 0 fuses phi and the accumulation (k = 1, 2, 3 are the common cases);
// Kdim == 0 handles any k through a block of phi values.
template <RbfKernel Kernel, int Kdim>
TPSCORE_INLINE void accumulate_block_tile(double e2, const double* __restrict qx,
                                                 const double* __restrict qy,
                                                 const double* __restrict qz, const double* cx,
                                                 const double* cy, const double* cz,
                                                 std::int64_t n, const double* weights,
                                                 std::int64_t k, double* __restrict acc) {
    alignas(64) double u[kBlock];
    for (std::int64_t j = 0; j < n; ++j) {
        const double x = cx[j], y = cy[j], z = cz[j];
        if constexpr (Kdim > 0) {
            double w[Kdim];
            for (int c = 0; c < Kdim; ++c) w[c] = weights[c * n + j];
#pragma omp simd
            for (std::int64_t q = 0; q < kBlock; ++q) {
                const double dx = qx[q] - x, dy = qy[q] - y, dz = qz[q] - z;
                const double v = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
                for (int c = 0; c < Kdim; ++c) acc[c * kBlock + q] += w[c] * v;
            }
        } else {
#pragma omp simd
            for (std::int64_t q = 0; q < kBlock; ++q) {
                const double dx = qx[q] - x, dy = qy[q] - y, dz = qz[q] - z;
                u[q] = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
            }
            for (std::int64_t c = 0; c < k; ++c) {
                const double w = weights[c * n + j];
                double* __restrict a = acc + c * kBlock;
#pragma omp simd
                for (std::int64_t q = 0; q < kBlock; ++q) a[q] += w * u[q];
            }
        }
    }
}

template <RbfKernel Kernel>
TPSCORE_INLINE void accumulate_block_k(double e2, const double* qx, const double* qy,
                                              const double* qz, const double* cx,
                                              const double* cy, const double* cz,
                                              std::int64_t n, const double* weights,
                                              std::int64_t k, double* acc) {
    switch (k) {
        case 1: accumulate_block_tile<Kernel, 1>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        case 2: accumulate_block_tile<Kernel, 2>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        case 3: accumulate_block_tile<Kernel, 3>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        default: accumulate_block_tile<Kernel, 0>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
    }
}

TPSCORE_INLINE void accumulate_block_impl(RbfKernel kernel, double e2, const double* qx, const double* qy,
                                          const double* qz, const double* cx, const double* cy, const double* cz,
                                          std::int64_t n, const double* weights, std::int64_t k, double* acc) {
    switch (kernel) {
        case RbfKernel::tps:
            accumulate_block_k<RbfKernel::tps>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::biharmonic:
            accumulate_block_k<RbfKernel::biharmonic>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::triharmonic:
            accumulate_block_k<RbfKernel::triharmonic>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::multiquadric:
            accumulate_block_k<RbfKernel::multiquadric>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::gaussian:
            accumulate_block_k<RbfKernel::gaussian>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
    }
}

TPSCORE_DISPATCH(accumulate_block,
                 (RbfKernel kernel, double e2, const double* qx, const double* qy, const double* qz,
                  const double* cx, const double* cy, const double* cz, std::int64_t n, const double* weights,
                  std::int64_t k, double* acc),
                 (kernel, e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc))

#if TPSCORE_HAND_WRITTEN_TPS
// --- the tps evaluation, by hand for AVX-512 ------------------------------------------
//
// At 22,500 x 60 the tps evaluation is nearly all logarithms: glibc's vector log
// (libmvec) costs 0.89 ns per value on one AVX-512 core, the rest of the loop about
// 0.6 ns per pair. This log, for the arguments the kernel gives it (x >= DBL_MIN,
// finite or +inf), splits x = m 2^k with m in [1, 2) by the instructions made for it
// (getmant, getexp), looks up c ~ 1/m in a 16-entry table held in two registers, and
// sums k log 2 - log c + log1p(mc - 1) with |mc - 1| < 0.031, where ten Taylor terms
// leave an error below 1e-17. Its error is at most one unit in the last place of
// max(1, |log x|) (checked against std::log over 2^20 values from 1e-17 to 1e17):
// absolute, not relative, accuracy just below x = 1 (where -log 2 + log m cancel),
// which is what a sum of weighted kernel values needs; log 1 is exactly 0.

struct LogTable {
    alignas(64) double reciprocal[16];  // c_j: 1 / (centre of [1 + j/16, 1 + (j+1)/16)), rounded
    alignas(64) double minus_log[16];   // -log(c_j) for the rounded c_j
    LogTable() {
        for (int j = 0; j < 16; ++j) {
            reciprocal[j] = 1.0 / (1.0 + (j + 0.5) / 16.0);
            minus_log[j] = -std::log(reciprocal[j]);
        }
    }
};
const LogTable log_table;

struct LogConstants {
    __m512d reciprocal_low, reciprocal_high, minus_log_low, minus_log_high;
};

TPSCORE_TARGET_V4 TPSCORE_INLINE LogConstants log_constants() {
    return {_mm512_load_pd(log_table.reciprocal), _mm512_load_pd(log_table.reciprocal + 8),
            _mm512_load_pd(log_table.minus_log), _mm512_load_pd(log_table.minus_log + 8)};
}

TPSCORE_TARGET_V4 TPSCORE_INLINE __m512d log_avx512(__m512d x,
                                                                                   const LogConstants& t) {
    const __m512d one = _mm512_set1_pd(1.0);
    const __m512d m = _mm512_getmant_pd(x, _MM_MANT_NORM_1_2, _MM_MANT_SIGN_src);
    const __m512d k = _mm512_getexp_pd(x);  // floor(log2 x): x = m 2^k
    // The interval of m: trunc(16 m - 16) in 0..15 (16 m - 16 < 16 for every m < 2).
    const __m512d sixteen = _mm512_set1_pd(16.0);
    const __m512i j = _mm512_cvttpd_epi64(_mm512_fmsub_pd(m, sixteen, sixteen));
    const __m512d c = _mm512_permutex2var_pd(t.reciprocal_low, j, t.reciprocal_high);
    const __m512d minus_log_c = _mm512_permutex2var_pd(t.minus_log_low, j, t.minus_log_high);
    const __m512d r = _mm512_fmsub_pd(m, c, one);  // one rounding: m c - 1 to full precision
    __m512d p = _mm512_set1_pd(-1.0 / 10.0);
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 9.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(-1.0 / 8.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 7.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(-1.0 / 6.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 5.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(-1.0 / 4.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 3.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(-1.0 / 2.0));
    const __m512d log1p_r = _mm512_fmadd_pd(p, _mm512_mul_pd(r, r), r);
    return _mm512_add_pd(_mm512_fmadd_pd(k, _mm512_set1_pd(0.6931471805599453), minus_log_c), log1p_r);
}

// acc (Kdim rows of kBlock) += sum_j w_j phi(|q - c_j|) for the tps kernel, as
// accumulate_block_tile does, with the sums held in registers: 16 queries (two
// vectors) at a time meet every centre.
template <int Kdim>
TPSCORE_TARGET_V4 void accumulate_tps_avx512(const double* qx, const double* qy,
                                                                     const double* qz, const double* cx,
                                                                     const double* cy, const double* cz,
                                                                     std::int64_t n, const double* weights,
                                                                     double* acc) {
    const LogConstants table = log_constants();
    const __m512d tiny = _mm512_set1_pd(std::numeric_limits<double>::min());
    for (std::int64_t q = 0; q < kBlock; q += 16) {
        const __m512d x0 = _mm512_load_pd(qx + q), x1 = _mm512_load_pd(qx + q + 8);
        const __m512d y0 = _mm512_load_pd(qy + q), y1 = _mm512_load_pd(qy + q + 8);
        const __m512d z0 = _mm512_load_pd(qz + q), z1 = _mm512_load_pd(qz + q + 8);
        __m512d sum0[Kdim], sum1[Kdim];
        for (int c = 0; c < Kdim; ++c) {
            sum0[c] = _mm512_loadu_pd(acc + c * kBlock + q);
            sum1[c] = _mm512_loadu_pd(acc + c * kBlock + q + 8);
        }
        for (std::int64_t j = 0; j < n; ++j) {
            const __m512d px = _mm512_set1_pd(cx[j]), py = _mm512_set1_pd(cy[j]), pz = _mm512_set1_pd(cz[j]);
            const __m512d dx0 = _mm512_sub_pd(x0, px), dx1 = _mm512_sub_pd(x1, px);
            const __m512d dy0 = _mm512_sub_pd(y0, py), dy1 = _mm512_sub_pd(y1, py);
            const __m512d dz0 = _mm512_sub_pd(z0, pz), dz1 = _mm512_sub_pd(z1, pz);
            // d2 + DBL_MIN, which is d2 itself for any d2 above 1e-292 and keeps the log
            // finite at a centre, where U = DBL_MIN log(DBL_MIN) = -1.6e-305 stands for 0
            // (phi_of_d2 multiplies by d2 instead, one more operation a pair).
            const __m512d d0 = _mm512_fmadd_pd(dz0, dz0, _mm512_fmadd_pd(dy0, dy0, _mm512_fmadd_pd(dx0, dx0, tiny)));
            const __m512d d1 = _mm512_fmadd_pd(dz1, dz1, _mm512_fmadd_pd(dy1, dy1, _mm512_fmadd_pd(dx1, dx1, tiny)));
            const __m512d u0 = _mm512_mul_pd(d0, log_avx512(d0, table));
            const __m512d u1 = _mm512_mul_pd(d1, log_avx512(d1, table));
            for (int c = 0; c < Kdim; ++c) {
                const __m512d w = _mm512_set1_pd(weights[c * n + j]);
                sum0[c] = _mm512_fmadd_pd(w, u0, sum0[c]);
                sum1[c] = _mm512_fmadd_pd(w, u1, sum1[c]);
            }
        }
        for (int c = 0; c < Kdim; ++c) {
            _mm512_storeu_pd(acc + c * kBlock + q, sum0[c]);
            _mm512_storeu_pd(acc + c * kBlock + q + 8, sum1[c]);
        }
    }
}
static_assert(kBlock % 16 == 0, "accumulate_tps_avx512 takes 16 queries at a time");

// --- the tps evaluation, by hand for AVX2 ----------------------------------------------
//
// Through glibc's AVX2 vector log (which gathers its table from memory) the evaluation
// took 3.2 times its arithmetic limit at 22,500 x 60. AVX2 has neither getmant/getexp
// nor a two-register permute of doubles, so this log takes x = m 2^k apart by its bits
// (x >= DBL_MIN and finite or +inf: no sign, subnormal or NaN to handle) and looks up
// c ~ 1/m in an 8-entry table, indexed by the mantissa's top three bits, with 32-bit
// lane permutes: each table is held as its entries' low halves in one register and
// high halves in another, and c has 20 mantissa bits, so its low half is zero and one
// permute fetches it. It sums k log 2 - log c + log1p(r), r = mc - 1, |r| < 0.059,
// where log1p(r) = r + r^2 Q(r) and Q is the degree-8 Chebyshev fit of
// (log1p(r) - r) / r^2 on |r| <= 0.059 (mpmath.chebyfit at 40 digits: error 3.3e-15 in
// Q, 1.1e-17 in log1p; twelve Taylor terms would need two more multiply-adds, which
// was 8 % of the loop's time). Q runs as two Horner chains in r^2, interleaved. Its
// accuracy is log_avx512's: at most one unit in the last place of max(1, |log x|)
// from std::log (2^20 values from 1e-17 to 1e17 and 2^22 mantissas at 7 exponents).
// One thread, 22,500 x 60: 2.0 ns a pair through libmvec, 1.7 with the table as pairs
// of floats and a variable blend on the index's third bit, 1.6 with the halves, 1.47
// with the fit.

struct LogTableAvx2 {
    alignas(32) std::uint32_t reciprocal_high[8];  // c_j's high half (its low half is 0)
    alignas(32) std::uint32_t minus_log_low[8], minus_log_high[8];  // -log(c_j)'s halves
    LogTableAvx2() {
        for (int j = 0; j < 8; ++j) {
            // c_j ~ 1 / (the centre of [1 + j/8, 1 + (j+1)/8)), cut to 20 mantissa bits
            const double reciprocal = 1.0 / (1.0 + (j + 0.5) / 8.0);
            std::uint64_t c_bits;
            std::memcpy(&c_bits, &reciprocal, 8);
            c_bits &= 0xFFFFFFFF00000000ULL;
            double c;
            std::memcpy(&c, &c_bits, 8);
            const double minus_log = -std::log(c);
            std::uint64_t log_bits;
            std::memcpy(&log_bits, &minus_log, 8);
            reciprocal_high[j] = static_cast<std::uint32_t>(c_bits >> 32);
            minus_log_low[j] = static_cast<std::uint32_t>(log_bits);
            minus_log_high[j] = static_cast<std::uint32_t>(log_bits >> 32);
        }
    }
};
const LogTableAvx2 log_table_avx2;

struct LogConstantsAvx2 {
    __m256i reciprocal_high, minus_log_low, minus_log_high;
};

TPSCORE_TARGET_V3 TPSCORE_INLINE __m256i load_lanes(const std::uint32_t* lanes) {
    return _mm256_load_si256(reinterpret_cast<const __m256i*>(lanes));
}

TPSCORE_TARGET_V3 TPSCORE_INLINE LogConstantsAvx2 log_constants_avx2() {
    return {load_lanes(log_table_avx2.reciprocal_high), load_lanes(log_table_avx2.minus_log_low),
            load_lanes(log_table_avx2.minus_log_high)};
}

// log(x) of N vectors, each step taken for all N before the next: written so, the two
// logarithms of accumulate_tps_avx2 interleave their dependency chains (4 % faster on
// a Zen 3 core than two calls for one vector, whose chains the core overlapped less).
template <int N>
TPSCORE_TARGET_V3 TPSCORE_INLINE void log_avx2(const __m256d* x, const LogConstantsAvx2& t, __m256d* log_x) {
    __m256d k[N], m[N], c[N], minus_log_c[N];
    for (int v = 0; v < N; ++v) {
        const __m256i bits = _mm256_castpd_si256(x[v]);
        // k as a double: the 11 exponent bits put in the mantissa of 2^52 make 2^52 + e exactly.
        const __m256i biased =
            _mm256_or_si256(_mm256_srli_epi64(bits, 52), _mm256_set1_epi64x(0x4330000000000000));
        k[v] = _mm256_sub_pd(_mm256_castsi256_pd(biased), _mm256_set1_pd(4503599627370496.0 + 1023.0));
        m[v] = _mm256_castsi256_pd(_mm256_or_si256(_mm256_and_si256(bits, _mm256_set1_epi64x(0x000FFFFFFFFFFFFF)),
                                                   _mm256_set1_epi64x(0x3FF0000000000000)));
        // j (mantissa bits 51..49) in the low three bits of each double's low 32-bit lane
        // (shifted as 64 bits) and of its high lane (shifted as 32 bits): the permute
        // reads only those three bits of an index.
        const __m256i j_low = _mm256_srli_epi64(bits, 49), j_high = _mm256_srli_epi32(bits, 17);
        const __m256i high_lanes_of_c = _mm256_permutevar8x32_epi32(t.reciprocal_high, j_high);
        c[v] = _mm256_castsi256_pd(_mm256_blend_epi32(_mm256_setzero_si256(), high_lanes_of_c, 0xAA));
        minus_log_c[v] = _mm256_castsi256_pd(
            _mm256_blend_epi32(_mm256_permutevar8x32_epi32(t.minus_log_low, j_low),
                               _mm256_permutevar8x32_epi32(t.minus_log_high, j_high), 0xAA));
    }
    // Q(r) = even(s) + r odd(s): the fit's coefficients of even and of odd powers.
    constexpr double kEven[] = {-0.10065561993520983242, -0.12499828592574585559, -0.16666666832508468936,
                                -0.24999999999956693159, -0.5};
    constexpr double kOdd[] = {0.11182629172946546154, 0.14285527309924379806, 0.20000000180903257892,
                               0.33333333333286093578};
    __m256d r[N], s[N], even[N], odd[N];
    for (int v = 0; v < N; ++v) {
        r[v] = _mm256_fmsub_pd(m[v], c[v], _mm256_set1_pd(1.0));  // one rounding, as in log_avx512
        s[v] = _mm256_mul_pd(r[v], r[v]);
        even[v] = _mm256_set1_pd(kEven[0]);
        odd[v] = _mm256_set1_pd(kOdd[0]);
    }
    for (int i = 1; i < 4; ++i) {
        for (int v = 0; v < N; ++v) even[v] = _mm256_fmadd_pd(even[v], s[v], _mm256_set1_pd(kEven[i]));
        for (int v = 0; v < N; ++v) odd[v] = _mm256_fmadd_pd(odd[v], s[v], _mm256_set1_pd(kOdd[i]));
    }
    for (int v = 0; v < N; ++v) {
        even[v] = _mm256_fmadd_pd(even[v], s[v], _mm256_set1_pd(kEven[4]));
        const __m256d log1p_r = _mm256_fmadd_pd(_mm256_fmadd_pd(odd[v], r[v], even[v]), s[v], r[v]);
        log_x[v] = _mm256_add_pd(_mm256_fmadd_pd(k[v], _mm256_set1_pd(0.6931471805599453), minus_log_c[v]), log1p_r);
    }
}

// accumulate_tps_avx512 for AVX2, 8 queries (two vectors) at a time meeting every
// centre: the two vectors share each centre's and weight's broadcasts and give the
// core two independent logarithms to overlap. On a Zen 3 core this is 10 % faster than
// one vector at a time (1.60 against 1.77 ns a pair, one thread, 22,500 x 60; 12 or
// 16 queries were no better), and each lane's arithmetic is unchanged, so the results
// are the same bits. (On an AVX-512 core running this AVX2 code, one vector at a time
// had measured 4-7 % faster; a real AVX2 CPU is what this loop is for.)
template <int Kdim>
TPSCORE_TARGET_V3 void accumulate_tps_avx2(const double* qx, const double* qy, const double* qz,
                                           const double* cx, const double* cy, const double* cz,
                                           std::int64_t n, const double* weights, double* acc) {
    const LogConstantsAvx2 table = log_constants_avx2();
    const __m256d tiny = _mm256_set1_pd(std::numeric_limits<double>::min());
    for (std::int64_t q = 0; q < kBlock; q += 8) {
        const __m256d x0 = _mm256_load_pd(qx + q), y0 = _mm256_load_pd(qy + q), z0 = _mm256_load_pd(qz + q);
        const __m256d x1 = _mm256_load_pd(qx + q + 4), y1 = _mm256_load_pd(qy + q + 4),
                      z1 = _mm256_load_pd(qz + q + 4);
        __m256d sum0[Kdim], sum1[Kdim];
        for (int c = 0; c < Kdim; ++c) {
            sum0[c] = _mm256_loadu_pd(acc + c * kBlock + q);
            sum1[c] = _mm256_loadu_pd(acc + c * kBlock + q + 4);
        }
        for (std::int64_t j = 0; j < n; ++j) {
            const __m256d centre_x = _mm256_set1_pd(cx[j]), centre_y = _mm256_set1_pd(cy[j]),
                          centre_z = _mm256_set1_pd(cz[j]);
            // d2 + DBL_MIN, as in accumulate_tps_avx512
            __m256d dx = _mm256_sub_pd(x0, centre_x), dy = _mm256_sub_pd(y0, centre_y),
                    dz = _mm256_sub_pd(z0, centre_z);
            const __m256d d0 = _mm256_fmadd_pd(dz, dz, _mm256_fmadd_pd(dy, dy, _mm256_fmadd_pd(dx, dx, tiny)));
            dx = _mm256_sub_pd(x1, centre_x);
            dy = _mm256_sub_pd(y1, centre_y);
            dz = _mm256_sub_pd(z1, centre_z);
            const __m256d d1 = _mm256_fmadd_pd(dz, dz, _mm256_fmadd_pd(dy, dy, _mm256_fmadd_pd(dx, dx, tiny)));
            const __m256d d[2] = {d0, d1};
            __m256d log_d[2];
            log_avx2<2>(d, table, log_d);
            const __m256d u0 = _mm256_mul_pd(d0, log_d[0]);
            const __m256d u1 = _mm256_mul_pd(d1, log_d[1]);
            for (int c = 0; c < Kdim; ++c) {
                const __m256d w = _mm256_set1_pd(weights[c * n + j]);
                sum0[c] = _mm256_fmadd_pd(w, u0, sum0[c]);
                sum1[c] = _mm256_fmadd_pd(w, u1, sum1[c]);
            }
        }
        for (int c = 0; c < Kdim; ++c) {
            _mm256_storeu_pd(acc + c * kBlock + q, sum0[c]);
            _mm256_storeu_pd(acc + c * kBlock + q + 4, sum1[c]);
        }
    }
}
static_assert(kBlock % 8 == 0, "accumulate_tps_avx2 takes 8 queries at a time");

const bool has_avx512 = simd_level() == SimdLevel::avx512;
const bool has_avx2 = simd_level() == SimdLevel::avx2;

// The hand-written tps loop of this CPU's level (AVX-512 or AVX2).
template <int Kdim>
void accumulate_tps_by_hand(const double* qx, const double* qy, const double* qz, const double* cx,
                            const double* cy, const double* cz, std::int64_t n, const double* weights,
                            double* acc) {
    if (has_avx512)
        accumulate_tps_avx512<Kdim>(qx, qy, qz, cx, cy, cz, n, weights, acc);
    else
        accumulate_tps_avx2<Kdim>(qx, qy, qz, cx, cy, cz, n, weights, acc);
}
#endif

// One block of queries in the model's normalised coordinates, one array per axis:
// (row - shift) / scale for its count rows (stride doubles apart), the last row
// repeated to fill the block. Built per level (it took a third of a 22,500 x 6
// evaluation as scalar divisions); a division rounds the same in any width, so the
// coordinates are the same bits at every level.
// Stride > 0 fixes the rows' stride at compile time (3, contiguous points: the loads
// vectorise as shuffles, not gathers); 0 takes `stride` as given.
template <std::int64_t Stride>
TPSCORE_INLINE void normalise_rows(const double* rows, std::int64_t stride, std::int64_t count,
                                   const double* shift, double scale, double* __restrict qx,
                                   double* __restrict qy, double* __restrict qz) {
    const std::int64_t step = Stride > 0 ? Stride : stride;
    const double sx = shift[0], sy = shift[1], sz = shift[2];
#pragma omp simd
    for (std::int64_t q = 0; q < count; ++q) {
        qx[q] = (rows[step * q] - sx) / scale;
        qy[q] = (rows[step * q + 1] - sy) / scale;
        qz[q] = (rows[step * q + 2] - sz) / scale;
    }
}

TPSCORE_INLINE void normalise_block_impl(const double* rows, std::int64_t stride, std::int64_t count,
                                         const double* shift, double scale, double* qx, double* qy,
                                         double* qz) {
    if (stride == 3)
        normalise_rows<3>(rows, stride, count, shift, scale, qx, qy, qz);
    else
        normalise_rows<0>(rows, stride, count, shift, scale, qx, qy, qz);
    for (std::int64_t q = count; q < kBlock; ++q) {
        qx[q] = qx[count - 1];
        qy[q] = qy[count - 1];
        qz[q] = qz[count - 1];
    }
}

TPSCORE_DISPATCH(normalise_block,
                 (const double* rows, std::int64_t stride, std::int64_t count, const double* shift, double scale,
                  double* qx, double* qy, double* qz),
                 (rows, stride, count, shift, scale, qx, qy, qz))

// The block's sums (k rows of kBlock) written as count rows of out (stride doubles
// apart), counting into not_finite the values that are not finite. Built per level
// for the same reason.
TPSCORE_INLINE void store_block_impl(const double* acc, std::int64_t k, std::int64_t count, double* out,
                                     std::int64_t stride, std::int64_t* not_finite_count) {
    // |value| <= DBL_MAX is false for infinities and NaN alike; a sum of flags keeps
    // the loop free of branches.
    std::int64_t not_finite = 0;
    for (std::int64_t c = 0; c < k; ++c) {
        const double* a = acc + c * kBlock;
#pragma omp simd reduction(+ : not_finite)
        for (std::int64_t q = 0; q < count; ++q) {
            out[q * stride + c] = a[q];
            not_finite += !(std::abs(a[q]) <= std::numeric_limits<double>::max());
        }
    }
    *not_finite_count = not_finite;
}

TPSCORE_DISPATCH(store_block,
                 (const double* acc, std::int64_t k, std::int64_t count, double* out, std::int64_t stride,
                  std::int64_t* not_finite_count),
                 (acc, k, count, out, stride, not_finite_count))

// acc += sum_j w_j phi(|q - c_j|) for one block of queries, by the best loop this
// CPU runs.
void accumulate(RbfKernel kernel, double e2, const double* qx, const double* qy, const double* qz,
                const double* cx, const double* cy, const double* cz, std::int64_t n, const double* weights,
                std::int64_t k, double* acc) {
#if TPSCORE_HAND_WRITTEN_TPS
    if (kernel == RbfKernel::tps && (has_avx512 || has_avx2) && k <= 3) {
        switch (k) {
            case 1: accumulate_tps_by_hand<1>(qx, qy, qz, cx, cy, cz, n, weights, acc); return;
            case 2: accumulate_tps_by_hand<2>(qx, qy, qz, cx, cy, cz, n, weights, acc); return;
            default: accumulate_tps_by_hand<3>(qx, qy, qz, cx, cy, cz, n, weights, acc); return;
        }
    }
#endif
    accumulate_block(kernel, e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
}

template <RbfKernel Kernel>
TPSCORE_INLINE void phi_row_kernel(double e2, double x, double y, double z,
                                        const double* cx, const double* cy, const double* cz,
                                        std::int64_t n, double* __restrict out) {
#pragma omp simd
    for (std::int64_t j = 0; j < n; ++j) {
        const double dx = x - cx[j], dy = y - cy[j], dz = z - cz[j];
        out[j] = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
    }
}

// out[j] = phi(|(x, y, z) - c_j|) for j < n: one row of a kernel matrix.
TPSCORE_INLINE void phi_row_impl(RbfKernel kernel, double e2, double x, double y, double z, const double* cx,
                                 const double* cy, const double* cz, std::int64_t n, double* out) {
    switch (kernel) {
        case RbfKernel::tps: phi_row_kernel<RbfKernel::tps>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::biharmonic: phi_row_kernel<RbfKernel::biharmonic>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::triharmonic: phi_row_kernel<RbfKernel::triharmonic>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::multiquadric: phi_row_kernel<RbfKernel::multiquadric>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::gaussian: phi_row_kernel<RbfKernel::gaussian>(e2, x, y, z, cx, cy, cz, n, out); break;
    }
}

TPSCORE_DISPATCH(phi_row,
                 (RbfKernel kernel, double e2, double x, double y, double z, const double* cx, const double* cy,
                  const double* cz, std::int64_t n, double* out),
                 (kernel, e2, x, y, z, cx, cy, cz, n, out))

// What the fit needs from column j of K' (n values) while it is in cache: the sum and
// the largest of its absolute values (for ||S||_1 and the polynomial scale), and its
// products with the four columns of V (n x 4, column-major), out[2..5].
TPSCORE_INLINE void column_statistics_impl(const double* column, std::int64_t n, const double* v, double* out) {
    const double *v0 = v, *v1 = v + n, *v2 = v + 2 * n, *v3 = v + 3 * n;
    double sum = 0.0, largest = 0.0, d0 = 0.0, d1 = 0.0, d2 = 0.0, d3 = 0.0;
#pragma omp simd reduction(+ : sum, d0, d1, d2, d3) reduction(max : largest)
    for (std::int64_t i = 0; i < n; ++i) {
        const double value = column[i];
        sum += std::abs(value);
        largest = std::max(largest, std::abs(value));
        d0 += value * v0[i];
        d1 += value * v1[i];
        d2 += value * v2[i];
        d3 += value * v3[i];
    }
    out[0] = sum;
    out[1] = largest;
    out[2] = d0;
    out[3] = d1;
    out[4] = d2;
    out[5] = d3;
}

TPSCORE_DISPATCH(column_statistics, (const double* column, std::int64_t n, const double* v, double* out),
                 (column, n, v, out))

// Rows c..n-1 of column c of Q^T K' Q (times sign), in place over K':
// column[r] = sign (column[r] - Z(r,:) V(c,:)^T - V(r,:) Z(c,:)^T); V and Z are n x 4,
// column-major.
TPSCORE_INLINE void project_column_impl(double* column, std::int64_t c, std::int64_t n, const double* v,
                                        const double* z, double sign) {
    const double *v0 = v, *v1 = v + n, *v2 = v + 2 * n, *v3 = v + 3 * n;
    const double *z0 = z, *z1 = z + n, *z2 = z + 2 * n, *z3 = z + 3 * n;
    const double vc0 = v0[c], vc1 = v1[c], vc2 = v2[c], vc3 = v3[c];
    const double zc0 = z0[c], zc1 = z1[c], zc2 = z2[c], zc3 = z3[c];
#pragma omp simd
    for (std::int64_t r = c; r < n; ++r)
        column[r] = sign * (column[r] - ((z0[r] * vc0 + z1[r] * vc1) + (z2[r] * vc2 + z3[r] * vc3) +
                                         (v0[r] * zc0 + v1[r] * zc1) + (v2[r] * zc2 + v3[r] * zc3)));
}

TPSCORE_DISPATCH(project_column, (double* column, std::int64_t c, std::int64_t n, const double* v, const double* z,
                                  double sign),
                 (column, c, n, v, z, sign))

bool uses_epsilon(RbfKernel kernel) {
    return kernel == RbfKernel::multiquadric || kernel == RbfKernel::gaussian;
}

// phi(s r) = g(s) phi'(r) (+ for tps a term s^2 ln s^2 r^2, which the side conditions
// P^T W = 0 turn into a constant, see rbf_fit): the factor between the kernel in
// original and in normalised coordinates.
double kernel_scale_factor(RbfKernel kernel, double scale) {
    switch (kernel) {
        case RbfKernel::tps: return scale * scale;
        case RbfKernel::biharmonic: return scale;
        case RbfKernel::triharmonic: return scale * scale * scale;
        default: return 1.0;  // gaussian, multiquadric: epsilon absorbs the scale
    }
}

std::string format_number(double value) {
    char buffer[64];
    std::snprintf(buffer, sizeof buffer, "%.3g", value);
    return buffer;
}

// --- the fit's linear system ---------------------------------------------------------
//
// In normalised coordinates the fit solves the equilibrated saddle-point system
//
//   S [W; A / s] = [Y; 0],   S = [ K'   s P ]   K' = K + sign lambda' I (n x n),
//                                [ s P^T  0 ]   P = [1 x y z] (n x 4), s = max |K'_ij|,
//
// s scaling the polynomial rows and columns to the kernel block (without it, large
// smoothing makes S badly scaled, rcond ~ 1 / lambda'^2, while the problem is not).
//
// Every kernel here makes sign * K' positive definite on the null space of P^T:
// tps (r^2 log r^2) and triharmonic (r^3) are conditionally positive definite of
// order 2, biharmonic (r) and multiquadric conditionally negative definite of order 1,
// the gaussian positive definite, and lambda' >= 0 only adds to that. The fit uses it
// (the null-space method): with the QR factorisation P = Q [R; 0], Q = [Q1 Q2], any W
// with s P^T W = G is W = Q [z1; z2] with z1 = R^{-T} G / s, and
//
//   (Q2^T K' Q2) z2 = Q2^T Y - Q2^T K' Q1 z1,     R A = Q1^T (Y - K' W),
//
// where sign * Q2^T K' Q2 is symmetric positive definite: a Cholesky factorisation,
// n^3 / 3 flops, half of an LU of S, stable without pivoting. Should rounding make
// that matrix indefinite (centres that nearly coincide, a gaussian far too wide),
// the fit falls back to an LU of S, which then reports the singularity.
class ProjectedSystem {
public:
    /// Builds K' for the normalised centres (cx, cy, cz; n each) and projects it.
    ProjectedSystem(const double* cx, const double* cy, const double* cz, std::int64_t n, RbfKernel kernel,
                    double e2, double diagonal_shift)
        : n_(n), sign_(rbf_smoothing_sign(kernel)) {
        // Q as I - V T V^T (compact WY form of the 4 Householder reflections).
        Eigen::Matrix<double, Eigen::Dynamic, 4> polynomial(n, 4);
        for (std::int64_t i = 0; i < n; ++i) polynomial.row(i) << 1.0, cx[i], cy[i], cz[i];
        const Eigen::HouseholderQR<Eigen::MatrixXd> qr(polynomial);
        r_ = qr.matrixQR().topRows(4).triangularView<Eigen::Upper>();
        v_ = Eigen::MatrixXd::Zero(n, 4);
        for (int q = 0; q < 4; ++q) {
            v_(q, q) = 1.0;
            v_.col(q).tail(n - q - 1) = qr.matrixQR().col(q).tail(n - q - 1);
        }
        t_.setZero();
        for (int q = 0; q < 4; ++q) {
            const double tau = qr.hCoeffs()[q];
            t_(q, q) = tau;
            if (q > 0) {
                const Eigen::VectorXd products = v_.leftCols(q).transpose() * v_.col(q);
                const Eigen::VectorXd column = t_.topLeftCorner(q, q) * products;  // T is upper triangular
                t_.col(q).head(q) = -tau * column;
            }
        }

        // K' column by column (it is symmetric), with what the projection and the
        // condition estimate need from each column while it is in cache: K' V, the
        // column's absolute sum and largest entry. Each column is one task's, so the
        // sums do not depend on the thread count.
        matrix_.resize(n, n);
        diagonal_.resize(n);
        Eigen::MatrixXd kv(n, 4);
        Eigen::VectorXd column_sums(n), column_max(n);
        // A column costs about 2n ns (phi and the sums): at least ~100 us per thread.
        const auto min_columns = static_cast<std::size_t>(std::max<std::int64_t>(1, 50000 / n));
        parallel_for(static_cast<std::size_t>(n), min_columns, [&](std::size_t begin, std::size_t end) {
            for (std::size_t jj = begin; jj < end; ++jj) {
                const auto j = static_cast<std::int64_t>(jj);
                double* column = matrix_.col(j).data();
                phi_row(kernel, e2, cx[j], cy[j], cz[j], cx, cy, cz, n, column);
                column[j] += diagonal_shift;
                diagonal_[j] = column[j];
                double statistics[6];
                column_statistics(column, n, v_.data(), statistics);
                column_sums[j] = statistics[0];
                column_max[j] = statistics[1];
                // Row j of K' V is column j of K' times V (K' is symmetric).
                kv.row(j) << statistics[2], statistics[3], statistics[4], statistics[5];
            }
        });
        polynomial_scale_ = column_max.maxCoeff();
        if (!(polynomial_scale_ > 0.0) || !std::isfinite(polynomial_scale_)) polynomial_scale_ = 1.0;
        // ||S||_1: the largest absolute column sum, kernel columns and polynomial columns.
        norm1_ = 0.0;
        for (std::int64_t j = 0; j < n; ++j)
            norm1_ = std::max(norm1_, column_sums[j] + polynomial_scale_ * (1.0 + std::abs(cx[j]) +
                                                                            std::abs(cy[j]) + std::abs(cz[j])));
        norm1_ = std::max(norm1_, polynomial_scale_ * polynomial.cwiseAbs().colwise().sum().maxCoeff());

        // Q^T K' Q = K' - (Z V^T + V Z^T) with Z = K'V T - V (T^T V^T K'V T) / 2: one
        // symmetric rank-8 update, written (times sign) into the lower triangle while
        // the strict upper triangle keeps K' (for residuals and the LU fallback).
        const Eigen::Matrix4d m = v_.transpose() * kv;
        const Eigen::MatrixXd z = kv * t_ - 0.5 * v_ * (t_.transpose() * m * t_);
        const double sign = sign_;
        constexpr std::int64_t kColumns = 32;
        const std::int64_t blocks = (n + kColumns - 1) / kColumns;
        std::atomic<std::int64_t> next{0};
        // A block of columns costs about 8n ns: at least ~100 us per thread.
        const auto min_blocks = static_cast<std::size_t>(std::max<std::int64_t>(1, 12500 / n));
        parallel_for(static_cast<std::size_t>(blocks), min_blocks,
                     [&](std::size_t, std::size_t) {
                         for (;;) {
                             const std::int64_t b = next.fetch_add(1, std::memory_order_relaxed);
                             if (b >= blocks) break;
                             for (std::int64_t c = b * kColumns; c < std::min(n, (b + 1) * kColumns); ++c)
                                 project_column(matrix_.col(c).data(), c, n, v_.data(), z.data(), sign);
                         }
                     });
    }

    /// Factorises sign * Q2^T K' Q2; false if it is not numerically positive definite.
    bool factor() { return cholesky_factor(n_ - 4, projected_block(), n_) < 0; }

    double norm1() const { return norm1_; }
    double polynomial_scale() const { return polynomial_scale_; }

    /// Overwrites each column [f; g] of x ((n + 4) x c) with S^{-1} [f; g].
    ///
    /// The products with the n x 4 factors (V, Q2^T K' Q1) are written as loops over
    /// their 4 columns: Eigen's general matrix product costs microseconds of setup
    /// each, which at n = 100 was most of the fit.
    void solve(Eigen::MatrixXd& x) const {
        const std::int64_t n = n_;
        const std::int64_t m = n - 4;
        const std::int64_t columns = x.cols();
        const double s = polynomial_scale_;
        const double sign = sign_;
        const double* b21 = matrix_.data() + 4;  // sign Q2^T K' Q1: (m, 4), leading dimension n
        Eigen::Matrix<double, 4, Eigen::Dynamic> z1(4, columns), qf1(4, columns);
        for (std::int64_t col = 0; col < columns; ++col) {
            double* f = x.col(col).data();  // f = x[0:n], g = x[n:n+4]
            // z1 = R^{-T} g / s.
            Eigen::Vector4d z = Eigen::Map<const Eigen::Vector4d>(f + n) / s;
            r_.transpose().triangularView<Eigen::Lower>().solveInPlace(z);
            z1.col(col) = z;
            // f <- Q^T f; its tail becomes the right-hand side for z2:
            // sign (Q^T f)[4:] - sign Q2^T K' Q1 z1.
            apply_q(f, true);
            qf1.col(col) = Eigen::Map<const Eigen::Vector4d>(f);
            double* tail = f + 4;
#pragma omp simd
            for (std::int64_t i = 0; i < m; ++i)
                tail[i] = sign * tail[i] - (b21[i] * z[0] + b21[i + n] * z[1] + b21[i + 2 * n] * z[2] +
                                            b21[i + 3 * n] * z[3]);
        }
        // All columns at once: each pass reads the factor once.
        triangular_solve(m, projected_block(), n, false, x.data() + 4, x.rows(), columns);
        triangular_solve(m, projected_block(), n, true, x.data() + 4, x.rows(), columns);
        const Eigen::Matrix4d b11 = block11();
        for (std::int64_t col = 0; col < columns; ++col) {
            double* f = x.col(col).data();
            const double* z2 = f + 4;
            // R a = (Q^T f)[0:4] - sign (B11 z1 + B21^T z2).
            Eigen::Vector4d coupling = b11 * z1.col(col);
            for (int q = 0; q < 4; ++q) {
                const double* column = b21 + q * n;
                double dot = 0.0;
#pragma omp simd reduction(+ : dot)
                for (std::int64_t i = 0; i < m; ++i) dot += column[i] * z2[i];
                coupling[q] += dot;
            }
            Eigen::Vector4d affine = qf1.col(col) - sign * coupling;
            r_.triangularView<Eigen::Upper>().solveInPlace(affine);
            // W = Q [z1; z2].
            for (int q = 0; q < 4; ++q) f[q] = z1(q, col);
            apply_q(f, false);
            for (int q = 0; q < 4; ++q) f[n + q] = affine[q] / s;
        }
    }

    /// K' w for w (n x c), from the strict upper triangle and the diagonal.
    Eigen::MatrixXd kernel_times(const Eigen::MatrixXd& w) const {
        Eigen::MatrixXd product(n_, w.cols());
        symmetric_multiply(n_, matrix_.data(), n_, diagonal_.data(), w.data(), w.rows(), product.data(),
                           product.rows(), w.cols());
        return product;
    }

    /// S x for x ((n + 4) x c), given K' times x's top rows.
    Eigen::MatrixXd times(const Eigen::MatrixXd& x, const Eigen::MatrixXd& kernel_product,
                          const double* cx, const double* cy, const double* cz) const {
        const std::int64_t n = n_;
        const double s = polynomial_scale_;
        Eigen::MatrixXd product(n + 4, x.cols());
        for (std::int64_t q = 0; q < x.cols(); ++q) {
            const double a0 = x(n, q), a1 = x(n + 1, q), a2 = x(n + 2, q), a3 = x(n + 3, q);
            double g0 = 0.0, g1 = 0.0, g2 = 0.0, g3 = 0.0;
            for (std::int64_t i = 0; i < n; ++i) {
                const double wi = x(i, q);
                product(i, q) = kernel_product(i, q) + s * (a0 + cx[i] * a1 + cy[i] * a2 + cz[i] * a3);
                g0 += wi;
                g1 += cx[i] * wi;
                g2 += cy[i] * wi;
                g3 += cz[i] * wi;
            }
            product(n, q) = s * g0;
            product(n + 1, q) = s * g1;
            product(n + 2, q) = s * g2;
            product(n + 3, q) = s * g3;
        }
        return product;
    }

    /// S itself, for the LU fallback.
    Eigen::MatrixXd saddle_point_matrix(const double* cx, const double* cy, const double* cz) const {
        const std::int64_t n = n_;
        const double s = polynomial_scale_;
        Eigen::MatrixXd system(n + 4, n + 4);
        for (std::int64_t j = 0; j < n; ++j) {
            for (std::int64_t i = 0; i < j; ++i) system(i, j) = system(j, i) = matrix_(i, j);
            system(j, j) = diagonal_[j];
            const double row[4] = {s, s * cx[j], s * cy[j], s * cz[j]};
            for (int q = 0; q < 4; ++q) system(n + q, j) = system(j, n + q) = row[q];
        }
        system.bottomRightCorner(4, 4).setZero();
        return system;
    }

private:
    // y <- Q^T y (`transpose`) or Q y in place, y n values: y - V T^T V^T y or y - V T V^T y.
    void apply_q(double* y, bool transpose) const {
        const std::int64_t n = n_;
        const double *v0 = v_.col(0).data(), *v1 = v_.col(1).data(), *v2 = v_.col(2).data(),
                     *v3 = v_.col(3).data();
        double d0 = 0.0, d1 = 0.0, d2 = 0.0, d3 = 0.0;
#pragma omp simd reduction(+ : d0, d1, d2, d3)
        for (std::int64_t i = 0; i < n; ++i) {
            d0 += v0[i] * y[i];
            d1 += v1[i] * y[i];
            d2 += v2[i] * y[i];
            d3 += v3[i] * y[i];
        }
        const Eigen::Vector4d products(d0, d1, d2, d3);
        const Eigen::Vector4d c = transpose ? Eigen::Vector4d(t_.transpose() * products)
                                            : Eigen::Vector4d(t_ * products);
#pragma omp simd
        for (std::int64_t i = 0; i < n; ++i) y[i] -= v0[i] * c[0] + v1[i] * c[1] + v2[i] * c[2] + v3[i] * c[3];
    }

    double* projected_block() { return matrix_.data() + 4 + 4 * n_; }
    const double* projected_block() const { return matrix_.data() + 4 + 4 * n_; }
    // sign * Q1^T K' Q1, from the lower triangle.
    Eigen::Matrix4d block11() const {
        Eigen::Matrix4d b;
        for (int j = 0; j < 4; ++j)
            for (int i = j; i < 4; ++i) b(i, j) = b(j, i) = matrix_(i, j);
        return b;
    }

    std::int64_t n_;
    double sign_;
    Eigen::MatrixXd matrix_;     // lower: sign Q^T K' Q, then its factor; strict upper: K'
    Eigen::VectorXd diagonal_;   // the diagonal of K'
    Eigen::MatrixXd v_;          // (n, 4) Householder vectors, unit diagonal
    Eigen::Matrix4d t_;          // Q = I - V T V^T
    Eigen::Matrix4d r_;          // P = Q [R; 0]
    double polynomial_scale_ = 1.0;
    double norm1_ = 0.0;
};

// sign(x) as +-1, +1 for 0: the estimator's sign vectors.
Eigen::VectorXd signs(const Eigen::VectorXd& x) {
    return x.unaryExpr([](double v) { return v >= 0.0 ? 1.0 : -1.0; });
}

std::int64_t largest_magnitude(const Eigen::VectorXd& x) {
    Eigen::Index index = 0;
    x.cwiseAbs().maxCoeff(&index);
    return index;
}

// Solves S [W; A'] = [values; 0] by the null-space Cholesky: the solution, the
// estimate of rcond(S) (Hager and Higham's 1-norm estimator of ||S^{-1}||_1, as in
// LAPACK's dlacn2), and trace(W^T K' W) for the energy. Returns false when the
// projected matrix is not numerically positive definite (K' is then still whole, in
// the upper triangle, for the LU). The estimator's solves share passes over the factor
// with the solution and its refinement: a pass costs about as much for several
// right-hand sides as for one, since reading the factor is what takes the time.
bool solve_by_cholesky(ProjectedSystem& system, const Eigen::MatrixXd& rhs, const double* cx,
                       const double* cy, const double* cz, Eigen::MatrixXd& solution, double& rcond,
                       double& quadratic_form) {
    if (!system.factor()) return false;
    const std::int64_t size = rhs.rows();
    const std::int64_t n = size - 4;
    const std::int64_t k = rhs.cols();
    // Pass 1: the solution and the estimator's first vector, e / size.
    Eigen::MatrixXd batch(size, k + 1);
    batch.leftCols(k) = rhs;
    batch.col(k).setConstant(1.0 / static_cast<double>(size));
    system.solve(batch);
    solution = batch.leftCols(k);
    double estimate = batch.col(k).lpNorm<1>();
    Eigen::VectorXd sign_vector = signs(batch.col(k));

    // Pass 2: one step of iterative refinement (it recovers the digits lost to the
    // residual, which matters when values carry a large offset), and S^{-T} sign(v)
    // (S is symmetric).
    const Eigen::MatrixXd weights0 = solution.topRows(n);
    const Eigen::MatrixXd kernel0 = system.kernel_times(weights0);
    batch.leftCols(k) = rhs - system.times(solution, kernel0, cx, cy, cz);
    batch.col(k) = sign_vector;
    system.solve(batch);
    const Eigen::MatrixXd correction = batch.topLeftCorner(n, k);
    solution += batch.leftCols(k);
    // trace(W^T K' W) with W = W0 + dW, to first order in the correction:
    // W0^T K' W0 + 2 dW^T K' W0, leaving out dW^T K' dW, which is ~(cond eps)^2 relative.
    quadratic_form = ((weights0 + 2.0 * correction).cwiseProduct(kernel0)).sum();
    Eigen::VectorXd u = batch.col(k);

    // The estimator's loop (dlacn2): e_j for the largest |u_j|, until the sign vector
    // repeats, the estimate stops growing, or five iterations. The alternating vector
    // of its final safeguard rides along with the first e_j.
    Eigen::VectorXd alternating(size);
    for (std::int64_t i = 0; i < size; ++i)
        alternating[i] = (i % 2 == 0 ? 1.0 : -1.0) *
                         (1.0 + static_cast<double>(i) / static_cast<double>(std::max<std::int64_t>(1, size - 1)));
    double alternating_norm = -1.0;
    std::int64_t j = largest_magnitude(u);
    for (int iteration = 2;; ++iteration) {
        Eigen::MatrixXd probe = Eigen::MatrixXd::Zero(size, alternating_norm < 0.0 ? 2 : 1);
        probe(j, 0) = 1.0;
        if (alternating_norm < 0.0) probe.col(1) = alternating;
        system.solve(probe);
        if (alternating_norm < 0.0) alternating_norm = probe.col(1).lpNorm<1>();
        const Eigen::VectorXd v = probe.col(0);
        const double previous = estimate;
        estimate = v.lpNorm<1>();
        const Eigen::VectorXd new_signs = signs(v);
        if (new_signs == sign_vector || estimate <= previous) break;
        sign_vector = new_signs;
        Eigen::MatrixXd signed_probe = sign_vector;
        system.solve(signed_probe);
        u = signed_probe.col(0);
        const std::int64_t last = j;
        j = largest_magnitude(u);
        if (u[last] == std::abs(u[j]) || iteration >= 5) break;
    }
    estimate = std::max(estimate, 2.0 * alternating_norm / (3.0 * static_cast<double>(size)));
    rcond = 1.0 / (system.norm1() * estimate);
    return true;
}

}  // namespace

int rbf_smoothing_sign(RbfKernel kernel) {
    return (kernel == RbfKernel::biharmonic || kernel == RbfKernel::multiquadric) ? -1 : 1;
}

RbfModel rbf_fit(const PointsRef& centres, const MatrixRef& values, RbfKernel kernel,
                 double epsilon, double smoothing) {
    const std::int64_t n = centres.rows();
    const std::int64_t k = values.cols();
    if (n < 1) throw std::invalid_argument("rbf_fit: no centres");
    if (values.rows() != n)
        throw std::invalid_argument("rbf_fit: values must have one row per centre");
    if (k < 1) throw std::invalid_argument("rbf_fit: values need at least one column");
    if (static_cast<int>(kernel) < 0 || static_cast<int>(kernel) > 4)
        throw std::invalid_argument("rbf_fit: unknown kernel");
    if (uses_epsilon(kernel) && !(epsilon > 0.0 && std::isfinite(epsilon)))
        throw std::invalid_argument("rbf_fit: epsilon must be finite and > 0");
    if (!(smoothing >= 0.0 && std::isfinite(smoothing)))
        throw std::invalid_argument("rbf_fit: smoothing must be finite and >= 0");

    RbfModel model;
    model.kernel = kernel;
    model.epsilon = uses_epsilon(kernel) ? epsilon : 0.0;
    model.smoothing = smoothing;
    model.centres = centres;

    // Normalise: centre on the bounding box, scale into the unit ball. The kernel
    // matrix and P = [1 x y z] then have entries of order 1, whatever the units
    // and the offset of the data (1e4 mm offsets, 1e-3 mm extents).
    const Eigen::RowVector3d lo = centres.colwise().minCoeff();
    const Eigen::RowVector3d hi = centres.colwise().maxCoeff();
    model.shift = 0.5 * (lo + hi);
    double scale = 0.0;
    for (std::int64_t i = 0; i < n; ++i)
        scale = std::max(scale, (centres.row(i) - model.shift).norm());
    if (!(scale > 0.0) || !std::isfinite(scale))
        throw std::domain_error("the centres do not span any volume (all coincide or are not finite)");
    // Fewer than 5 centres leave no radial freedom (P has 4 columns); the caller
    // refuses them, and the null-space method needs n > 4.
    if (n < 5) throw std::domain_error("at least 5 centres are needed for an RBF with an affine part");
    model.scale = scale;
    model.epsilon_normalised = model.epsilon * scale;
    const double e2 = model.epsilon_normalised * model.epsilon_normalised;
    const double g = kernel_scale_factor(kernel, scale);
    // (K + sign lambda I) W + P A = Y in original units becomes, with K = g K' and
    // W = W' / g, (K' + sign (lambda / g) I) W' + P' A' = Y in normalised units.
    const double diagonal_shift = rbf_smoothing_sign(kernel) * smoothing / g;

    model.centre_x.resize(n);
    model.centre_y.resize(n);
    model.centre_z.resize(n);
    for (std::int64_t i = 0; i < n; ++i) {
        model.centre_x[i] = (centres(i, 0) - model.shift[0]) / scale;
        model.centre_y[i] = (centres(i, 1) - model.shift[1]) / scale;
        model.centre_z[i] = (centres(i, 2) - model.shift[2]) / scale;
    }
    const double* cx = model.centre_x.data();
    const double* cy = model.centre_y.data();
    const double* cz = model.centre_z.data();

    const std::int64_t size = n + 4;
    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(size, k);
    rhs.topRows(n) = values;

    ProjectedSystem system(cx, cy, cz, n, kernel, e2, diagonal_shift);
    const double polynomial_scale = system.polynomial_scale();
    Eigen::MatrixXd solution;
    double quadratic_form = 0.0;
    const bool definite = solve_by_cholesky(system, rhs, cx, cy, cz, solution, model.rcond, quadratic_form);
    std::optional<Eigen::MatrixXd> saddle_point;
    std::optional<Eigen::PartialPivLU<Eigen::MatrixXd>> lu;
    if (!definite) {
        // Partial pivoting rather than FullPivLU: the matrix is nonsingular whenever
        // the centres are distinct and not coplanar (checked by the caller), so full
        // pivoting's rank revelation buys nothing, while PartialPivLU is blocked. Its
        // rcond estimate below catches a near-singular system.
        saddle_point = system.saddle_point_matrix(cx, cy, cz);
        lu.emplace(*saddle_point);
        model.rcond = lu->rcond();
    }
    if (!(model.rcond > std::numeric_limits<double>::epsilon())) {
        throw std::domain_error(
            "the RBF system is numerically singular (reciprocal condition estimate " +
            format_number(model.rcond) +
            "): centres nearly coincide or nearly lie on a plane" +
            (uses_epsilon(kernel) ? std::string(", or epsilon is too small for the centres' spacing")
                                  : std::string()) +
            "; smoothing > 0 regularises it");
    }
    if (!definite) {
        solution = lu->solve(rhs);
        // One step of iterative refinement, as in the Cholesky path.
        solution += lu->solve(rhs - *saddle_point * solution);
        const Eigen::MatrixXd w = solution.topRows(n);
        quadratic_form = (saddle_point->topLeftCorner(n, n) * w).cwiseProduct(w).sum();
    }
    if (!solution.allFinite())
        throw std::domain_error("the RBF system could not be solved: the solution is not finite");

    model.weights_normalised = solution.topRows(n);
    model.affine_normalised = polynomial_scale * solution.bottomRows(4);
    const Eigen::MatrixXd& w = model.weights_normalised;

    // trace(W^T K W) = trace(W'^T K' W') / g (the tps term drops out: P^T W' = 0).
    const double energy_normalised = quadratic_form - diagonal_shift * w.squaredNorm();
    model.bending_energy = energy_normalised / g;

    // Back to original coordinates. f(x) = A'_0 + x' A'_xyz + sum W'_i phi'(r'_i) with
    // x' = (x - shift) / s and phi'(r') = (phi(r) - c(r)) / g, where c(r) = ln(s^2) r^2
    // for tps and 0 otherwise. Since P^T W' = 0, sum_i W'_i r_i^2 = s^2 sum_i W'_i |p'_i|^2
    // does not depend on x: it moves into the constant row of A.
    model.weights = MatrixX(w / g);
    model.affine = MatrixX(4, k);
    const Eigen::MatrixXd linear = model.affine_normalised.bottomRows(3) / scale;
    model.affine.bottomRows(3) = linear;
    Eigen::RowVectorXd constant = model.affine_normalised.row(0) - model.shift * linear;
    if (kernel == RbfKernel::tps) {
        const Eigen::VectorXd squared_norms =
            (model.centre_x.array().square() + model.centre_y.array().square() +
             model.centre_z.array().square())
                .matrix();
        constant -= std::log(scale * scale) * (squared_norms.transpose() * w);
    }
    model.affine.row(0) = constant;

    if (k == 3) {
        // f(x) - x with x = shift + s x': subtract the identity in normalised form.
        model.displacement_affine_normalised = model.affine_normalised;
        model.displacement_affine_normalised.row(0) -= model.shift;
        for (int axis = 0; axis < 3; ++axis)
            model.displacement_affine_normalised(1 + axis, axis) -= scale;
    }
    return model;
}

MatrixX rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement) {
    MatrixX out(queries.rows(), model.value_dim());
    rbf_evaluate(model, queries, displacement, out);
    return out;
}

std::int64_t rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement,
                          Eigen::Ref<MatrixX> out) {
    const std::int64_t m = queries.rows();
    const std::int64_t n = model.size();
    const std::int64_t k = model.value_dim();
    if (displacement && k != 3)
        throw std::invalid_argument("rbf_evaluate: the displacement needs 3 values per centre");
    if (out.rows() != m || out.cols() != k)
        throw std::invalid_argument("rbf_evaluate: out must have shape (m, k)");
    if (m == 0) return -1;

    const Eigen::MatrixXd& affine =
        displacement ? model.displacement_affine_normalised : model.affine_normalised;
    const double e2 = model.epsilon_normalised * model.epsilon_normalised;
    const double scale = model.scale;
    const Eigen::RowVector3d shift = model.shift;
    const std::int64_t blocks = (m + kBlock - 1) / kBlock;
    // About 200k kernel evaluations (~0.2 ms) per thread at least: below that,
    // starting a thread costs more than it saves.
    const std::int64_t min_blocks = std::max<std::int64_t>(1, 200000 / (kBlock * n));
    const std::int64_t workers =
        std::clamp<std::int64_t>(blocks / min_blocks, 1, std::max(1, num_threads()));
    // Workers take a few blocks at a time from a shared counter instead of one fixed
    // share each: when another process holds a core, the threads that do run take
    // over the rest rather than waiting for a descheduled one. Which thread computes
    // a row does not change how it is computed, so results stay thread-independent.
    constexpr std::int64_t kGrain = 4;
    std::atomic<std::int64_t> next_block{0};
    std::atomic<std::int64_t> first_overflow{m};

    auto evaluate_blocks = [&](std::size_t, std::size_t) {
        alignas(64) double qx[kBlock], qy[kBlock], qz[kBlock];
        std::vector<double> acc(static_cast<std::size_t>(k * kBlock));
        std::int64_t overflow = m;
        for (;;) {
            const std::int64_t begin = next_block.fetch_add(kGrain, std::memory_order_relaxed);
            if (begin >= blocks) break;
            const std::int64_t end = std::min(blocks, begin + kGrain);
            for (std::int64_t b = begin; b < end; ++b) {
                const std::int64_t first = b * kBlock;
                const std::int64_t count = std::min(kBlock, m - first);
                normalise_block(queries.data() + first * queries.outerStride(), queries.outerStride(), count,
                                shift.data(), scale, qx, qy, qz);
                for (std::int64_t c = 0; c < k; ++c) {
                    double* a = acc.data() + c * kBlock;
                    const double a0 = affine(0, c), ax = affine(1, c), ay = affine(2, c),
                                 az = affine(3, c);
                    for (std::int64_t q = 0; q < kBlock; ++q)
                        a[q] = a0 + ax * qx[q] + ay * qy[q] + az * qz[q];
                }
                accumulate(model.kernel, e2, qx, qy, qz, model.centre_x.data(), model.centre_y.data(),
                           model.centre_z.data(), n, model.weights_normalised.data(), k, acc.data());
                std::int64_t not_finite = 0;
                store_block(acc.data(), k, count, &out(first, 0), out.outerStride(), &not_finite);
                if (not_finite > 0)
                    for (std::int64_t q = 0; q < count; ++q)
                        for (std::int64_t c = 0; c < k; ++c)
                            if (!std::isfinite(acc[c * kBlock + q])) overflow = std::min(overflow, first + q);
            }
        }
        for (std::int64_t seen = first_overflow.load(); overflow < seen;)
            if (first_overflow.compare_exchange_weak(seen, overflow)) break;
    };
    // One chunk per worker: parallel_for provides the threads, the counter the work.
    parallel_for(static_cast<std::size_t>(workers), 1, evaluate_blocks);
    return first_overflow.load() < m ? first_overflow.load() : -1;
}

MatrixX rbf_evaluation_matrix(const RbfModel& model, const PointsRef& queries) {
    const std::int64_t m = queries.rows();
    const std::int64_t n = model.size();
    MatrixX out(m, n + 4);
    if (m == 0) return out;
    const Eigen::VectorXd cx = model.centres.col(0), cy = model.centres.col(1), cz = model.centres.col(2);
    const double e2 = model.epsilon * model.epsilon;
    const std::size_t min_rows = static_cast<std::size_t>(std::max<std::int64_t>(1, 100000 / (n + 4)));
    parallel_for(static_cast<std::size_t>(m), min_rows, [&](std::size_t begin, std::size_t end) {
        for (std::size_t ii = begin; ii < end; ++ii) {
            const auto i = static_cast<std::int64_t>(ii);
            double* row = out.row(i).data();
            const double x = queries(i, 0), y = queries(i, 1), z = queries(i, 2);
            phi_row(model.kernel, e2, x, y, z, cx.data(), cy.data(), cz.data(), n, row);
            row[n] = 1.0;
            row[n + 1] = x;
            row[n + 2] = y;
            row[n + 3] = z;
        }
    });
    return out;
}

}  // namespace tpscore
