// Block Gram matrices on a cubic B-spline lattice (see tpscore/lattice_gram.hpp).
#include "tpscore/lattice_gram.hpp"

#include <algorithm>
#include <sstream>
#include <stdexcept>

namespace tpscore {

namespace {

// Storage slot of the forward offset (row_offset, column_offset), see kLatticeNeighbours.
constexpr int neighbour_slot(int row_offset, int column_offset) {
    return row_offset == 0 ? column_offset : 4 + (row_offset - 1) * 7 + (column_offset + 3);
}

}  // namespace

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
