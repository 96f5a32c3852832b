// Block Gram matrices on a cubic B-spline lattice (see tpscore/lattice_gram.hpp).
#include "tpscore/lattice_gram.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "tpscore/parallel.hpp"

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

    // Pairs (s, t) of stencil entries with t >= s are exactly the forward pairs: t's
    // row is below s's, or the same row and not to the left.
    for (std::int64_t i = 0; i < n_samples; ++i) {
        const double* b = weights + 16 * i;
        const double* q = blocks + kSymmetricBlock * i;
        for (int s = 0; s < 16; ++s) {
            if (b[s] == 0.0) continue;
            const int row_s = s / 4;
            const int column_s = s % 4;
            const std::int64_t node = first_node[i] + row_s * columns + column_s;
            double* node_out = out + node * kLatticeNeighbours * kSymmetricBlock;
            for (int t = s; t < 16; ++t) {
                const double bb = b[s] * b[t];
                double* slot =
                    node_out + neighbour_slot(t / 4 - row_s, t % 4 - column_s) * kSymmetricBlock;
                for (int c = 0; c < kSymmetricBlock; ++c) slot[c] += bb * q[c];
            }
        }
    }
}

}  // namespace tpscore
