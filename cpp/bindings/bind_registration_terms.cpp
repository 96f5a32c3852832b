// nanobind glue for the registration's data terms (tpscore/registration_terms.hpp).
// Inputs arrive C-contiguous float64 from tpscore.registration_terms; the terms come
// back as owning NumPy arrays (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <stdexcept>
#include <tuple>

#include "arrays.hpp"
#include "tpscore/registration_terms.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {
using tpscore::Points;
using tpscore::VectorX;
using Rows = In<Points>;
using Values = In<VectorX>;
using Blocks = Eigen::Matrix<double, Eigen::Dynamic, 6, Eigen::RowMajor>;

void require(bool same, const char* what) {
    if (!same) throw std::invalid_argument(what);
}
}  // namespace

void bind_registration_terms(nb::module_& m) {
    m.def(
        "point_to_plane_terms",
        [](Rows sample, Rows moved, Rows closest, Values distances, Rows normals, Values prior, double floor,
           double tukey_factor) {
            const Eigen::Index n = sample.rows();
            require(moved.rows() == n && closest.rows() == n && distances.size() == n && normals.rows() == n &&
                        prior.size() == n,
                    "the pairs' arrays differ in length");
            Blocks blocks(n, 6);
            Points rhs(n, 3);
            VectorX along(n), weight(n);
            tpscore::point_to_plane_terms(n, sample.data(), moved.data(), closest.data(), distances.data(),
                                          normals.data(), prior.data(), floor, tukey_factor, blocks.data(),
                                          rhs.data(), along.data(), weight.data());
            return std::make_tuple(std::move(blocks), std::move(rhs), std::move(along), std::move(weight));
        },
        "sample"_a, "moved"_a, "closest"_a, "distances"_a, "normals"_a, "prior"_a, "floor"_a, "tukey_factor"_a,
        nb::call_guard<nb::gil_scoped_release>(),
        "The point-to-plane blocks (m, 6), right-hand sides (m, 3), distances along the normal "
        "and weights (m,).");
    m.def(
        "texture_pull_terms",
        [](Rows sample, Rows moved, Rows targets, Rows normals, Values prior, double floor, double tukey_factor) {
            const Eigen::Index n = sample.rows();
            require(moved.rows() == n && targets.rows() == n && normals.rows() == n && prior.size() == n,
                    "the points' arrays differ in length");
            Blocks blocks(n, 6);
            Points rhs(n, 3);
            tpscore::texture_pull_terms(n, sample.data(), moved.data(), targets.data(), normals.data(),
                                        prior.data(), floor, tukey_factor, blocks.data(), rhs.data());
            return std::make_tuple(std::move(blocks), std::move(rhs));
        },
        "sample"_a, "moved"_a, "targets"_a, "normals"_a, "prior"_a, "floor"_a, "tukey_factor"_a,
        nb::call_guard<nb::gil_scoped_release>(),
        "The texture term's blocks (m, 6) and right-hand sides (m, 3).");
}
