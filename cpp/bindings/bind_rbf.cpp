// nanobind glue for the dense RBF / thin-plate-spline kernels (tpscore/rbf.hpp).
// Inputs arrive validated, C-contiguous float64 from tpscore.rbf; every call
// releases the GIL. Results are owning NumPy arrays (arrays.hpp), except for the
// evaluation at query points, which fills an array Python allocated (see below).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include "arrays.hpp"
#include "tpscore/rbf.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {

// A writable C-contiguous float64 NumPy array, filled in place (never a copy).
using MatrixOut = nb::ndarray<double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;

Eigen::Map<tpscore::MatrixX> as_eigen(MatrixOut& out) {
    return {out.data(), static_cast<Eigen::Index>(out.shape(0)),
            static_cast<Eigen::Index>(out.shape(1))};
}

}  // namespace

void bind_rbf(nb::module_& m) {
    nb::enum_<tpscore::RbfKernel>(m, "RbfKernel", "Radial functions of the dense RBF kernels.")
        .value("tps", tpscore::RbfKernel::tps, "r^2 ln r^2")
        .value("biharmonic", tpscore::RbfKernel::biharmonic, "r")
        .value("triharmonic", tpscore::RbfKernel::triharmonic, "r^3")
        .value("multiquadric", tpscore::RbfKernel::multiquadric, "sqrt(1 + (epsilon r)^2)")
        .value("gaussian", tpscore::RbfKernel::gaussian, "exp(-(epsilon r)^2)");

    nb::class_<tpscore::RbfModel>(m, "RbfModel",
                                  "A fitted dense RBF (immutable; see tpscore.RBF).")
        .def_prop_ro("kernel", [](const tpscore::RbfModel& s) { return s.kernel; })
        .def_prop_ro("epsilon", [](const tpscore::RbfModel& s) { return s.epsilon; })
        .def_prop_ro("smoothing", [](const tpscore::RbfModel& s) { return s.smoothing; })
        // Copies, so Python never holds a writable view into the fitted model.
        .def_prop_ro("centres", [](const tpscore::RbfModel& s) { return tpscore::MatrixX(s.centres); })
        .def_prop_ro("weights", [](const tpscore::RbfModel& s) { return tpscore::MatrixX(s.weights); })
        .def_prop_ro("affine", [](const tpscore::RbfModel& s) { return tpscore::MatrixX(s.affine); })
        .def_prop_ro("bending_energy", [](const tpscore::RbfModel& s) { return s.bending_energy; })
        .def_prop_ro("rcond", [](const tpscore::RbfModel& s) { return s.rcond; })
        .def_prop_ro("scale", [](const tpscore::RbfModel& s) { return s.scale; })
        .def_prop_ro("size", [](const tpscore::RbfModel& s) { return s.size(); }, "Number of centres n.")
        // The one binding that fills a caller's buffer rather than returning an owning
        // array. The kernel starts the thread pool, whose threads stay alive and may take
        // the rest of a capped address space; an owning return then needs allocations
        // after the kernel, inside nanobind's conversion, which aborts (noexcept) where
        // one fails. With the result (up to 2 GiB) allocated by NumPy before the call,
        // a MemoryError if it does not fit, nothing is allocated afterwards
        // (tests/test_package.py, test_threads_that_cannot_start_do_not_abort_...).
        .def("evaluate_into",
             [](const tpscore::RbfModel& s, In<tpscore::Points> queries, MatrixOut out) {
                 return tpscore::rbf_evaluate(s, queries, false, as_eigen(out));
             },
             "queries"_a, "out"_a.noconvert(), nb::call_guard<nb::gil_scoped_release>(),
             "Write f at (m, 3) queries into out (m, k), C-contiguous float64; returns the first "
             "row that overflowed, or -1.")
        .def("displacement_into",
             [](const tpscore::RbfModel& s, In<tpscore::Points> queries, MatrixOut out) {
                 return tpscore::rbf_evaluate(s, queries, true, as_eigen(out));
             },
             "queries"_a, "out"_a.noconvert(), nb::call_guard<nb::gil_scoped_release>(),
             "Write f(x) - x at (m, 3) queries into out (m, 3); needs k == 3; returns the first "
             "row that overflowed, or -1.")
        .def("evaluation_matrix",
             [](const tpscore::RbfModel& s, In<tpscore::Points> queries) {
                 return tpscore::rbf_evaluation_matrix(s, queries);
             },
             "queries"_a, nb::call_guard<nb::gil_scoped_release>(),
             "[phi(|x - p_j|) | 1 x y z] at (m, 3) queries: (m, n + 4).");

    m.def("rbf_fit",
          [](In<tpscore::Points> centres, In<tpscore::MatrixX> values, tpscore::RbfKernel kernel,
             double epsilon, double smoothing) {
              return tpscore::rbf_fit(centres, values, kernel, epsilon, smoothing);
          },
          "centres"_a, "values"_a, "kernel"_a, "epsilon"_a, "smoothing"_a,
          nb::call_guard<nb::gil_scoped_release>(),
          "Fit a dense RBF with an affine part to (n, 3) centres and (n, k) values.");
}
