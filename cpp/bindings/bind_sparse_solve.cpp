// Bindings of the sparse direct solver. The matrix arrives validated from
// tpscore.sparse as the CSC arrays of its lower triangle (int64 indices, float64
// values); right-hand sides arrive Fortran-ordered so Eigen reads them in place.
// Factorisation and solves run with the GIL released.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>

#include <cstdint>
#include <stdexcept>

#include "tpscore/sparse_solve.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
using IndexArray = Eigen::Ref<const Eigen::Matrix<std::int64_t, Eigen::Dynamic, 1>>;
using ValueArray = Eigen::Ref<const Eigen::VectorXd>;
}  // namespace

void bind_sparse_solve(nb::module_& m) {
    using tpscore::PatternCholesky;
    using tpscore::SparseCholesky;

    nb::class_<SparseCholesky>(
        m, "SparseCholesky",
        "LDL^T factor of a sparse symmetric positive-definite matrix (use tpscore.SparseCholesky).")
        .def(
            "__init__",
            [](SparseCholesky* self, std::int64_t n, const IndexArray& indptr,
               const IndexArray& indices, const ValueArray& values, double pivot_tolerance) {
                nb::gil_scoped_release release;
                new (self) SparseCholesky(n, indptr.data(), indices.data(), values.data(),
                                          pivot_tolerance);
            },
            "n"_a, "indptr"_a, "indices"_a, "values"_a, "pivot_tolerance"_a)
        .def("solve", &SparseCholesky::solve, "rhs"_a, nb::call_guard<nb::gil_scoped_release>(),
             "Solve A X = B for B of shape (n, k); returns X (n, k).")
        .def_prop_ro("size", &SparseCholesky::size)
        .def_prop_ro("factor_nonzeros", &SparseCholesky::factor_nonzeros)
        .def_prop_ro("min_pivot", &SparseCholesky::min_pivot)
        .def_prop_ro("max_pivot", &SparseCholesky::max_pivot);

    nb::class_<PatternCholesky>(
        m, "PatternCholesky",
        "LDL^T factors of matrices sharing one sparsity pattern (use tpscore.PatternCholesky).")
        .def(
            "__init__",
            [](PatternCholesky* self, std::int64_t n, const IndexArray& indptr,
               const IndexArray& indices) {
                nb::gil_scoped_release release;
                new (self) PatternCholesky(n, indptr.data(), indices.data());
            },
            "n"_a, "indptr"_a, "indices"_a)
        .def(
            "factorize",
            [](PatternCholesky& self, const ValueArray& values, double pivot_tolerance) {
                if (values.size() != self.stored_entries())
                    throw std::invalid_argument("values must hold one value per stored entry");
                nb::gil_scoped_release release;
                self.factorize(values.data(), pivot_tolerance);
            },
            "values"_a, "pivot_tolerance"_a)
        .def("solve", &PatternCholesky::solve, "rhs"_a, nb::call_guard<nb::gil_scoped_release>(),
             "Solve A X = B with the last factor, for B of shape (n, k); returns X (n, k).")
        .def_prop_ro("size", &PatternCholesky::size)
        .def_prop_ro("stored_entries", &PatternCholesky::stored_entries)
        .def_prop_ro("factorised", &PatternCholesky::factorised)
        .def_prop_ro("min_pivot", &PatternCholesky::min_pivot)
        .def_prop_ro("max_pivot", &PatternCholesky::max_pivot);
}
