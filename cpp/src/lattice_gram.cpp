// Block Gram matrices on a cubic B-spline lattice (see tpscore/lattice_gram.hpp).
#include "tpscore/lattice_gram.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "tpscore/parallel.hpp"
#include "tpscore/simd.hpp"

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#include <immintrin.h>
#endif

namespace tpscore {

namespace {

// Storage slot of the forward offset (row_offset, column_offset), see kLatticeNeighbours.
constexpr int neighbour_slot(int row_offset, int column_offset) {
    return row_offset == 0 ? column_offset : 4 + (row_offset - 1) * 7 + (column_offset + 3);
}

// The four uniform cubic B-spline weights of the nodes i-1, i, i+1, i+2 at t in [0, 1].
inline void cubic_weights(double t, double w[4]) {
    const double s = 1.0 - t;
    const double t2 = t * t, t3 = t2 * t;
    w[0] = s * s * s / 6.0;
    w[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0;
    w[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0;
    w[3] = t3 / 6.0;
}

// The stencil's first cell along one axis (clamped to [1, nodes - 3]) and t in [0, 1].
inline std::int64_t cell_of(double g, std::int64_t nodes, double& t) {
    const double lo = 1.0, hi = static_cast<double>(nodes - 3);
    const double cell = std::clamp(std::floor(g), lo, hi);
    t = std::clamp(g - cell, 0.0, 1.0);
    return static_cast<std::int64_t>(cell);
}


// One sample's terms of the block Gram matrix: (b[s] b[t]) Q added to the block of
// node s's forward neighbour t, for the stencil pairs (s, t >= s). Pairs with t >= s
// are exactly the forward pairs: t's row is below s's, or the same row and not to the
// left. Each output entry gets at most one term per sample, so adding the samples in
// order fixes the rounding whichever of the two versions below adds them.
void add_sample_scalar(const double* b, const double* q, double* out, std::int64_t first,
                       std::int64_t columns) {
    for (int s = 0; s < 16; ++s) {
        if (b[s] == 0.0) continue;
        const int row_s = s / 4;
        const int column_s = s % 4;
        double* node_out = out + (first + row_s * columns + column_s) * kLatticeNeighbours * kSymmetricBlock;
        for (int t = s; t < 16; ++t) {
            const double bb = b[s] * b[t];
            double* slot = node_out + neighbour_slot(t / 4 - row_s, t % 4 - column_s) * kSymmetricBlock;
            for (int c = 0; c < kSymmetricBlock; ++c) slot[c] += bb * q[c];
        }
    }
}

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
// The same terms, a stencil row of t at a time where it holds four of them (every row
// below s's, and s's own when s begins it): their blocks lie side by side (24
// doubles), added as six 4-wide products. AVX2 without FMA, so each
// product is rounded before its sum exactly as in the scalar loop; bit-identical.
__attribute__((target("avx2"))) void add_sample_avx2(const double* b, const double* q, double* out,
                                                       std::int64_t first, std::int64_t columns) {
    // the block's six entries laid over 24 doubles: q0 q1 q2 q3 | q4 q5 q0 q1 | q2 q3 q4 q5 ...
    const __m256d q_a = _mm256_setr_pd(q[0], q[1], q[2], q[3]);
    const __m256d q_b = _mm256_setr_pd(q[4], q[5], q[0], q[1]);
    const __m256d q_c = _mm256_setr_pd(q[2], q[3], q[4], q[5]);
    for (int s = 0; s < 16; ++s) {
        if (b[s] == 0.0) continue;
        const int row_s = s / 4;
        const int column_s = s % 4;
        double* node_out = out + (first + row_s * columns + column_s) * kLatticeNeighbours * kSymmetricBlock;
        if (column_s > 0) {
            for (int t = s; t < 4 * row_s + 4; ++t) {  // the rest of s's own row, one by one
                const double bb = b[s] * b[t];
                double* slot = node_out + neighbour_slot(0, t % 4 - column_s) * kSymmetricBlock;
                for (int c = 0; c < kSymmetricBlock; ++c) slot[c] += bb * q[c];
            }
        }
        const __m256d b_s = _mm256_set1_pd(b[s]);
        // a whole row of neighbours: s's own when s begins it, and every row below
        for (int row_t = column_s > 0 ? row_s + 1 : row_s; row_t < 4; ++row_t) {
            const __m256d bb = _mm256_mul_pd(b_s, _mm256_loadu_pd(b + 4 * row_t));
            double* run = node_out + neighbour_slot(row_t - row_s, -column_s) * kSymmetricBlock;
            const __m256d factors[6] = {
                _mm256_permute4x64_pd(bb, 0x00), _mm256_permute4x64_pd(bb, 0x50),
                _mm256_permute4x64_pd(bb, 0x55), _mm256_permute4x64_pd(bb, 0xAA),
                _mm256_permute4x64_pd(bb, 0xFA), _mm256_permute4x64_pd(bb, 0xFF)};
            const __m256d entries[3] = {q_a, q_b, q_c};
            for (int k = 0; k < 6; ++k) {
                const __m256d term = _mm256_mul_pd(factors[k], entries[k % 3]);
                _mm256_storeu_pd(run + 4 * k, _mm256_add_pd(_mm256_loadu_pd(run + 4 * k), term));
            }
        }
    }
}

bool use_avx2() {
    static const bool avx2 = simd_level() >= SimdLevel::avx2;
    return avx2;
}
#else
constexpr auto add_sample_avx2 = add_sample_scalar;
bool use_avx2() { return false; }
#endif

}  // namespace

void lattice_evaluate(std::int64_t m, const double* xy, double origin_x, double origin_y, double spacing,
                      std::int64_t rows, std::int64_t columns, const double* values, std::int64_t k,
                      double* out) {
    if (rows < 4 || columns < 4) throw std::invalid_argument("the lattice needs at least 4 x 4 nodes");
    // About 50 ns a point for three components: chunks of a few thousand points.
    parallel_for(static_cast<std::size_t>(m), 2048, [&](std::size_t begin, std::size_t end) {
        for (std::size_t i = begin; i < end; ++i) {
            double* row_out = out + static_cast<std::int64_t>(i) * k;
            const double x = xy[2 * i], y = xy[2 * i + 1];
            if (!std::isfinite(x) || !std::isfinite(y)) {
                std::fill(row_out, row_out + k, std::numeric_limits<double>::quiet_NaN());
                continue;
            }
            double tx, ty, wx[4], wy[4];
            const std::int64_t cx = cell_of((x - origin_x) / spacing, columns, tx);
            const std::int64_t cy = cell_of((y - origin_y) / spacing, rows, ty);
            cubic_weights(tx, wx);
            cubic_weights(ty, wy);
            std::fill(row_out, row_out + k, 0.0);
            for (int a = 0; a < 4; ++a) {
                const double* node_row = values + ((cy - 1 + a) * columns + (cx - 1)) * k;
                for (int b = 0; b < 4; ++b) {
                    const double w = wy[a] * wx[b];
                    for (std::int64_t c = 0; c < k; ++c) row_out[c] += w * node_row[b * k + c];
                }
            }
        }
    });
}

void lattice_block_gram(std::int64_t n_samples, const std::int64_t* first_node,
                        const double* weights, const double* blocks, std::int64_t rows,
                        std::int64_t columns, double* out) {
    const std::int64_t n_nodes = rows * columns;
    for (std::int64_t i = 0; i < n_samples; ++i) {
        const std::int64_t first = first_node[i];
        if (first < 0 || first / columns + 3 >= rows || first % columns + 3 >= columns) {
            std::ostringstream message;
            message << "sample " << i << ": its stencil at node " << first
                    << " leaves the " << rows << " x " << columns << " lattice";
            throw std::invalid_argument(message.str());
        }
    }
    std::fill(out, out + n_nodes * kLatticeNeighbours * kSymmetricBlock, 0.0);
    if (use_avx2()) {
        for (std::int64_t i = 0; i < n_samples; ++i)
            add_sample_avx2(weights + 16 * i, blocks + kSymmetricBlock * i, out, first_node[i], columns);
    } else {
        for (std::int64_t i = 0; i < n_samples; ++i)
            add_sample_scalar(weights + 16 * i, blocks + kSymmetricBlock * i, out, first_node[i], columns);
    }
}

}  // namespace tpscore
