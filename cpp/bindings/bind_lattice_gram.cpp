// nanobind glue for the lattice kernels (tpscore/lattice_gram.hpp). Inputs arrive
// C-contiguous from tpscore.lattice (int64 stencil corners, float64 weights and
// blocks); the results come back as owning NumPy arrays (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>

#include <cstdint>
#include <stdexcept>

#include "arrays.hpp"
#include "tpscore/lattice_gram.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {
template <int Columns>
using Rows = Eigen::Matrix<double, Eigen::Dynamic, Columns, Eigen::RowMajor>;
}  // namespace

void bind_lattice_gram(nb::module_& m) {
    m.def(
        "lattice_block_gram",
        [](In<tpscore::IndexVector> first_node, In<Rows<16>> weights, In<Rows<tpscore::kSymmetricBlock>> blocks,
           std::int64_t rows, std::int64_t columns) {
            const Eigen::Index n = first_node.size();
            if (weights.rows() != n || blocks.rows() != n)
                throw std::invalid_argument("first_node, weights and blocks differ in length");
            if (rows < 4 || columns < 4)
                throw std::invalid_argument("the lattice needs at least 4 x 4 nodes");
            // one row per node: its 25 neighbour blocks of 6 entries each
            tpscore::MatrixX out(rows * columns, tpscore::kLatticeNeighbours * tpscore::kSymmetricBlock);
            tpscore::lattice_block_gram(n, first_node.data(), weights.data(), blocks.data(), rows, columns,
                                        out.data());
            return out;
        },
        "first_node"_a, "weights"_a, "blocks"_a, "rows"_a, "columns"_a, nb::call_guard<nb::gil_scoped_release>(),
        "The block Gram matrix sum_i (b_i b_i^T) (x) Q_i of lattice samples, (n_nodes, 25 * 6).");
    m.def(
        "lattice_evaluate",
        [](In<Rows<2>> xy, double origin_x, double origin_y, double spacing, std::int64_t rows,
           std::int64_t columns, In<tpscore::MatrixX> values) {
            if (values.rows() != rows * columns)
                throw std::invalid_argument("values must have one row per lattice node");
            tpscore::MatrixX out(xy.rows(), values.cols());
            tpscore::lattice_evaluate(xy.rows(), xy.data(), origin_x, origin_y, spacing, rows, columns,
                                      values.data(), values.cols(), out.data());
            return out;
        },
        "xy"_a, "origin_x"_a, "origin_y"_a, "spacing"_a, "rows"_a, "columns"_a, "values"_a,
        nb::call_guard<nb::gil_scoped_release>(), "The lattice field (m, k) at points xy (m, 2).");
}
