// A uniform cubic B-spline lattice: evaluating a field on it, and the normal equations
// of least-squares fits on it.
#pragma once

#include <cstdint>

namespace tpscore {

/// Neighbour offsets under which a node stores its couplings: two cubic stencils
/// (4 x 4 nodes each) share nodes at most 3 apart in rows and columns, and every
/// unordered node pair is kept once, under its lower-indexed node. The forward half of
/// the 7 x 7 window is (0, 0..3) then (1..3, -3..3): 25 offsets, stored in that order.
inline constexpr int kLatticeNeighbours = 25;

/// Unique entries of a symmetric 3 x 3 block, stored as xx, xy, xz, yy, yz, zz.
inline constexpr int kSymmetricBlock = 6;

/// Block Gram matrix of a 3-vector field sampled on the lattice:
///
///     G = sum_i (b_i b_i^T) (x) Q_i,
///
/// b_i holding the 16 B-spline weights of sample i over its stencil and Q_i a
/// symmetric 3 x 3 weight (e.g. w_i n_i n_i^T for a point-to-plane term).
///
/// Sample i's stencil is the 4 x 4 node block whose first node is first_node[i]:
/// stencil entry s = 4 a + b is node first_node[i] + a * columns + b, with weight
/// weights[16 i + s]. blocks holds Q_i as 6 values per sample (kSymmetricBlock order).
/// out receives G as (n_nodes, kLatticeNeighbours, kSymmetricBlock): the block coupling
/// node p with node p + (row offset) * columns + (column offset), for each forward
/// offset; entries are overwritten, not accumulated.
///
/// Runs on one thread: samples that share nodes would race, and the pass is a few
/// milliseconds for ten thousand samples. Throws std::invalid_argument when a stencil
/// leaves the lattice.
void lattice_block_gram(std::int64_t n_samples, const std::int64_t* first_node,
                        const double* weights, const double* blocks, std::int64_t rows,
                        std::int64_t columns, double* out);

/// The field of a uniform cubic B-spline lattice at points in the x-y plane:
///
///     out[i, c] = sum over the 4 x 4 stencil of point i of  w_row * w_column * values[node, c]
///
/// The lattice has `rows` x `columns` nodes (row-major node index), node (r, q) at
/// x = origin_x + q * spacing, y = origin_y + r * spacing. A point's stencil starts at
/// the cell below and left of it, clamped so that the stencil stays on the lattice
/// (a point beyond the edge takes the edge cell's polynomial at its clamped position),
/// exactly as tpscore.lattice.BSplineLattice places it. xy is (m, 2), values
/// (rows * columns, k) and out (m, k), all row-major. Rows are independent: the result
/// does not depend on the thread count. Non-finite points give NaN rows.
void lattice_evaluate(std::int64_t m, const double* xy, double origin_x, double origin_y, double spacing,
                      std::int64_t rows, std::int64_t columns, const double* values, std::int64_t k,
                      double* out);

}  // namespace tpscore
