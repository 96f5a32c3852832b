// nanobind glue for the lattice kernels (tpscore/lattice_gram.hpp). Inputs arrive
// C-contiguous from tpscore.lattice (int64 stencil corners, float64 weights and
// blocks); Python allocates the output and the kernel fills it in place.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cstdint>
#include <stdexcept>

#include "tpscore/lattice_gram.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
template <class T, class Shape>
using Input = nb::ndarray<const T, Shape, nb::c_contig, nb::device::cpu>;
using GramOut = nb::ndarray<double, nb::ndim<3>, nb::c_contig, nb::device::cpu>;
using FieldOut = nb::ndarray<double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
}  // namespace

void bind_lattice_gram(nb::module_& m) {
    m.def(
        "lattice_block_gram_into",
        [](Input<std::int64_t, nb::shape<-1>> first_node, Input<double, nb::shape<-1, 16>> weights,
           Input<double, nb::shape<-1, tpscore::kSymmetricBlock>> blocks, std::int64_t rows,
           std::int64_t columns, GramOut out) {
            const std::size_t n = first_node.shape(0);
            if (weights.shape(0) != n || blocks.shape(0) != n)
                throw std::invalid_argument("first_node, weights and blocks differ in length");
            if (rows < 4 || columns < 4)
                throw std::invalid_argument("the lattice needs at least 4 x 4 nodes");
            if (out.shape(0) != static_cast<std::size_t>(rows * columns) ||
                out.shape(1) != static_cast<std::size_t>(tpscore::kLatticeNeighbours) ||
                out.shape(2) != static_cast<std::size_t>(tpscore::kSymmetricBlock))
                throw std::invalid_argument("out must have shape (rows * columns, 25, 6)");
            nb::gil_scoped_release release;
            tpscore::lattice_block_gram(static_cast<std::int64_t>(n), first_node.data(),
                                        weights.data(), blocks.data(), rows, columns, out.data());
        },
        "first_node"_a, "weights"_a, "blocks"_a, "rows"_a, "columns"_a, "out"_a.noconvert(),
        "Write the block Gram matrix sum_i (b_i b_i^T) (x) Q_i of lattice samples into out "
        "(n_nodes, 25, 6).");
    m.def(
        "lattice_evaluate_into",
        [](Input<double, nb::shape<-1, 2>> xy, double origin_x, double origin_y, double spacing,
           std::int64_t rows, std::int64_t columns, Input<double, nb::ndim<2>> values, FieldOut out) {
            const std::size_t m = xy.shape(0);
            if (values.shape(0) != static_cast<std::size_t>(rows * columns))
                throw std::invalid_argument("values must have one row per lattice node");
            if (out.shape(0) != m || out.shape(1) != values.shape(1))
                throw std::invalid_argument("out must have shape (len(xy), values.shape[1])");
            nb::gil_scoped_release release;
            tpscore::lattice_evaluate(static_cast<std::int64_t>(m), xy.data(), origin_x, origin_y, spacing, rows,
                                      columns, values.data(), static_cast<std::int64_t>(values.shape(1)),
                                      out.data());
        },
        "xy"_a, "origin_x"_a, "origin_y"_a, "spacing"_a, "rows"_a, "columns"_a, "values"_a,
        "out"_a.noconvert(), "Write the lattice field at points xy (m, 2) into out (m, k).");
}
