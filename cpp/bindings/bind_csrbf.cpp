// Bindings of the CSRBF fit. Inputs arrive validated from tpscore.csrbf; the core
// throws std::invalid_argument (-> ValueError) for duplicate centres, which only the
// neighbour search can see. Arrays follow arrays.hpp: In<T> views in, owning values out.
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>

#include "arrays.hpp"
#include "tpscore/csrbf.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

void bind_csrbf(nb::module_& m) {
    using tpscore::CSRBF;
    using tpscore::MatrixX;
    using tpscore::Points;

    nb::enum_<tpscore::CSRBFPreconditioner>(m, "CSRBFPreconditioner", "Preconditioner of the BiCGSTAB solve.")
        .value("diagonal", tpscore::CSRBFPreconditioner::diagonal)
        .value("ilu", tpscore::CSRBFPreconditioner::ilu);
    nb::class_<CSRBF>(m, "CSRBF", "Fitted CSRBF field (use tpscore.CSRBF).")
        .def(
            "__init__",
            [](CSRBF* self, In<Points> centres, In<MatrixX> values, In<Points> normals,
               double support, double smoothing, bool quadric, tpscore::CSRBFPreconditioner preconditioner,
               double tolerance,
               std::int64_t max_iterations) {
                tpscore::CSRBFOptions options;
                options.support = support;
                options.smoothing = smoothing;
                options.quadric = quadric;
                options.preconditioner = preconditioner;
                options.tolerance = tolerance;
                options.max_iterations = max_iterations;
                nb::gil_scoped_release release;
                new (self) CSRBF(centres, values, normals, options);
            },
            "centres"_a, "values"_a, "normals"_a, "support"_a, "smoothing"_a, "quadric"_a,
            "preconditioner"_a, "tolerance"_a, "max_iterations"_a,
            "Fit; normals (0, 3) to estimate them.")
        .def("evaluate", [](const CSRBF& s, In<Points> queries) { return s.evaluate(queries); }, "queries"_a,
             nb::call_guard<nb::gil_scoped_release>(),
             "The field at (m, 3) queries: (m, k).")
        .def_prop_ro("coefficients", [](const CSRBF& s) { return tpscore::MatrixX(s.coefficients()); })
        .def_prop_ro("iterations", [](const CSRBF& s) { return tpscore::IndexVector(s.iterations()); })
        .def_prop_ro("residuals", [](const CSRBF& s) { return tpscore::VectorX(s.residuals()); })
        .def_prop_ro("converged", [](const CSRBF& s) { return Eigen::Matrix<bool, Eigen::Dynamic, 1>(s.converged()); })
        .def_prop_ro("quadric_orders", [](const CSRBF& s) { return tpscore::IndexVector(s.quadric_orders()); })
        .def_prop_ro("normals", [](const CSRBF& s) { return tpscore::Points(s.normals()); })
        .def_prop_ro("nnz", &CSRBF::nnz);
}
