// Bindings of the sparse direct solver. The matrix arrives validated from
// tpscore.sparse as the CSC arrays of its lower triangle (int64 indices, float64
// values); right-hand sides arrive Fortran-ordered so Eigen reads them in place.
// Factorisation and solves run with the GIL released; solutions are owning NumPy
// arrays (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>

#include <cstdint>
#include <stdexcept>
#include <string>

#include "arrays.hpp"
#include "tpscore/supernode_kernels.hpp"
#include "tpscore/sparse_solve.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {
using IndexArray = In<tpscore::IndexVector>;
using ValueArray = In<tpscore::VectorX>;
// Right-hand sides (n, k), column-major (Fortran order), one column per system.
using Columns = In<Eigen::MatrixXd>;

template <class Factor>
Eigen::MatrixXd solve(const Factor& factor, Columns rhs) {
    return factor.solve(rhs);
}
}  // namespace

void bind_sparse_solve(nb::module_& m) {
    using tpscore::PatternCholesky;
    using tpscore::SimplicialPatternCholesky;
    using tpscore::SparseCholesky;

    nb::class_<SparseCholesky>(
        m, "SparseCholesky",
        "LDL^T factor of a sparse symmetric positive-definite matrix (use tpscore.SparseCholesky).")
        .def(
            "__init__",
            [](SparseCholesky* self, std::int64_t n, IndexArray indptr,
               IndexArray indices, ValueArray values, double pivot_tolerance) {
                nb::gil_scoped_release release;
                new (self) SparseCholesky(n, indptr.data(), indices.data(), values.data(),
                                          pivot_tolerance);
            },
            "n"_a, "indptr"_a, "indices"_a, "values"_a, "pivot_tolerance"_a)
        .def("solve", &solve<SparseCholesky>, "rhs"_a, nb::call_guard<nb::gil_scoped_release>(),
             "Solve A X = B for B of shape (n, k); returns X (n, k).")
        .def_prop_ro("size", &SparseCholesky::size)
        .def_prop_ro("factor_nonzeros", &SparseCholesky::factor_nonzeros)
        .def_prop_ro("min_pivot", &SparseCholesky::min_pivot)
        .def_prop_ro("max_pivot", &SparseCholesky::max_pivot);

    nb::class_<PatternCholesky>(
        m, "PatternCholesky",
        "Supernodal LL^T factors of matrices sharing one sparsity pattern (use "
        "tpscore.PatternCholesky).")
        .def(
            "__init__",
            [](PatternCholesky* self, std::int64_t n, IndexArray indptr,
               IndexArray indices) {
                nb::gil_scoped_release release;
                new (self) PatternCholesky(n, indptr.data(), indices.data(), nullptr);
            },
            "n"_a, "indptr"_a, "indices"_a,
            "Order the unknowns by approximate minimum degree.")
        .def(
            "__init__",
            [](PatternCholesky* self, std::int64_t n, IndexArray indptr,
               IndexArray indices, IndexArray ordering) {
                if (ordering.size() != n)
                    throw std::invalid_argument("ordering must hold n entries");
                nb::gil_scoped_release release;
                new (self) PatternCholesky(n, indptr.data(), indices.data(), ordering.data());
            },
            "n"_a, "indptr"_a, "indices"_a, "ordering"_a,
            "Eliminate the unknowns in the given order (a permutation of 0 .. n-1).")
        .def(
            "factorize",
            [](PatternCholesky& self, ValueArray values, double pivot_tolerance, int workers) {
                if (values.size() != self.stored_entries())
                    throw std::invalid_argument("values must hold one value per stored entry");
                nb::gil_scoped_release release;
                self.factorize(values.data(), pivot_tolerance, workers);
            },
            "values"_a, "pivot_tolerance"_a, "workers"_a = 0)
        .def("solve", &solve<PatternCholesky>, "rhs"_a, nb::call_guard<nb::gil_scoped_release>(),
             "Solve A X = B with the last factor, for B of shape (n, k); returns X (n, k).")
        .def_prop_ro("size", &PatternCholesky::size)
        .def_prop_ro("stored_entries", &PatternCholesky::stored_entries)
        .def_prop_ro("factorised", &PatternCholesky::factorised)
        .def_prop_ro("min_pivot", &PatternCholesky::min_pivot)
        .def_prop_ro("max_pivot", &PatternCholesky::max_pivot)
        .def_prop_ro("factor_nonzeros", &PatternCholesky::factor_nonzeros)
        .def_prop_ro("supernodes", &PatternCholesky::supernodes)
        .def_prop_ro("thread_groups", &PatternCholesky::thread_groups)
        .def_prop_ro("factor_multiply_adds", &PatternCholesky::factor_multiply_adds)
        .def_prop_ro("ordering", [](const PatternCholesky& self) {
            const auto& order = self.ordering();
            return Eigen::Matrix<std::int64_t, Eigen::Dynamic, 1>(
                Eigen::Map<const Eigen::Matrix<std::int64_t, Eigen::Dynamic, 1>>(
                    order.data(), static_cast<Eigen::Index>(order.size())));
        });

    nb::class_<SimplicialPatternCholesky>(
        m, "SimplicialPatternCholesky",
        "Simplicial LDL^T factors of matrices sharing one sparsity pattern (the reference of "
        "PatternCholesky).")
        .def(
            "__init__",
            [](SimplicialPatternCholesky* self, std::int64_t n, IndexArray indptr,
               IndexArray indices) {
                nb::gil_scoped_release release;
                new (self) SimplicialPatternCholesky(n, indptr.data(), indices.data());
            },
            "n"_a, "indptr"_a, "indices"_a)
        .def(
            "factorize",
            [](SimplicialPatternCholesky& self, ValueArray values, double pivot_tolerance) {
                if (values.size() != self.stored_entries())
                    throw std::invalid_argument("values must hold one value per stored entry");
                nb::gil_scoped_release release;
                self.factorize(values.data(), pivot_tolerance);
            },
            "values"_a, "pivot_tolerance"_a)
        .def("solve", &solve<SimplicialPatternCholesky>, "rhs"_a,
             nb::call_guard<nb::gil_scoped_release>(),
             "Solve A X = B with the last factor, for B of shape (n, k); returns X (n, k).")
        .def_prop_ro("size", &SimplicialPatternCholesky::size)
        .def_prop_ro("stored_entries", &SimplicialPatternCholesky::stored_entries)
        .def_prop_ro("factorised", &SimplicialPatternCholesky::factorised)
        .def_prop_ro("min_pivot", &SimplicialPatternCholesky::min_pivot)
        .def_prop_ro("max_pivot", &SimplicialPatternCholesky::max_pivot);

    m.def(
        "dense_kernel_isa", []() { return std::string(tpscore::supernode_kernels().isa); },
        "Instruction set of the dense kernels the sparse factorisation uses on this CPU.");
}
