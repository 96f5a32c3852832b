// nanobind glue for the registration's data terms (tpscore/registration_terms.hpp).
// Inputs arrive C-contiguous float64 from tpscore.expression.registration, which also
// allocates the outputs; the kernels fill them in place.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <cstdint>
#include <stdexcept>

#include "tpscore/registration_terms.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {
using Rows = nb::ndarray<const double, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using Values = nb::ndarray<const double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using BlocksOut = nb::ndarray<double, nb::shape<-1, 6>, nb::c_contig, nb::device::cpu>;
using RowsOut = nb::ndarray<double, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using ValuesOut = nb::ndarray<double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

void require(bool same, const char* what) {
    if (!same) throw std::invalid_argument(what);
}
}  // namespace

void bind_registration_terms(nb::module_& m) {
    m.def(
        "point_to_plane_terms_into",
        [](Rows sample, Rows moved, Rows closest, Values distances, Rows normals, Values prior, double floor,
           double tukey_factor, BlocksOut blocks, RowsOut rhs, ValuesOut along, ValuesOut weight) {
            const std::size_t n = sample.shape(0);
            require(moved.shape(0) == n && closest.shape(0) == n && distances.shape(0) == n &&
                        normals.shape(0) == n && prior.shape(0) == n && blocks.shape(0) == n &&
                        rhs.shape(0) == n && along.shape(0) == n && weight.shape(0) == n,
                    "the pairs' arrays differ in length");
            nb::gil_scoped_release release;
            tpscore::point_to_plane_terms(static_cast<std::int64_t>(n), sample.data(), moved.data(), closest.data(),
                                          distances.data(), normals.data(), prior.data(), floor, tukey_factor,
                                          blocks.data(), rhs.data(), along.data(), weight.data());
        },
        "sample"_a, "moved"_a, "closest"_a, "distances"_a, "normals"_a, "prior"_a, "floor"_a, "tukey_factor"_a,
        "blocks"_a.noconvert(), "rhs"_a.noconvert(), "along"_a.noconvert(), "weight"_a.noconvert(),
        "Write the point-to-plane blocks (m, 6), right-hand sides (m, 3), distances along the normal "
        "and weights (m,).");
    m.def(
        "texture_pull_terms_into",
        [](Rows sample, Rows moved, Rows targets, Rows normals, Values prior, double floor, double tukey_factor,
           BlocksOut blocks, RowsOut rhs) {
            const std::size_t n = sample.shape(0);
            require(moved.shape(0) == n && targets.shape(0) == n && normals.shape(0) == n && prior.shape(0) == n &&
                        blocks.shape(0) == n && rhs.shape(0) == n,
                    "the points' arrays differ in length");
            nb::gil_scoped_release release;
            tpscore::texture_pull_terms(static_cast<std::int64_t>(n), sample.data(), moved.data(), targets.data(),
                                        normals.data(), prior.data(), floor, tukey_factor, blocks.data(),
                                        rhs.data());
        },
        "sample"_a, "moved"_a, "targets"_a, "normals"_a, "prior"_a, "floor"_a, "tukey_factor"_a,
        "blocks"_a.noconvert(), "rhs"_a.noconvert(),
        "Write the texture term's blocks (m, 6) and right-hand sides (m, 3).");
}
