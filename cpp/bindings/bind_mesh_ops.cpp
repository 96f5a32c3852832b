// Bindings of the mesh operators. Inputs arrive validated (C-contiguous float64
// vertices, int64 faces in range) from tpscore.mesh; outputs are owning NumPy arrays
// (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include "arrays.hpp"
#include "tpscore/mesh_ops.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

void bind_mesh_ops(nb::module_& m) {
    using tpscore::Faces;
    using tpscore::Points;
    using Vertices = In<Points>;
    using Triangles = In<Faces>;
    const auto release = nb::call_guard<nb::gil_scoped_release>();

    m.def(
        "face_normals", [](Vertices vertices, Triangles faces) { return tpscore::face_normals(vertices, faces); },
        "vertices"_a, "faces"_a, release,
        "Unit face normals (m, 3); zero for zero-area faces.");
    nb::enum_<tpscore::NormalWeighting>(m, "NormalWeighting", "How vertex_normals weights the faces' normals.")
        .value("area", tpscore::NormalWeighting::area)
        .value("angle", tpscore::NormalWeighting::angle)
        .value("uniform", tpscore::NormalWeighting::uniform);
    m.def(
        "vertex_normals",
        [](Vertices vertices, Triangles faces, tpscore::NormalWeighting weighting) {
            return tpscore::vertex_normals(vertices, faces, weighting);
        },
        "vertices"_a, "faces"_a, "weighting"_a, release,
        "Unit vertex normals (n, 3).");
    m.def(
        "cotan_laplacian",
        [](Vertices vertices, Triangles faces) {
            tpscore::CsrMatrix csr = tpscore::cotan_laplacian(vertices, faces);
            return std::make_tuple(std::move(csr.values), std::move(csr.indices),
                                   std::move(csr.indptr));
        },
        "vertices"_a, "faces"_a, release,
        "Cotangent Laplacian as CSR arrays (data, indices, indptr).");
    m.def(
        "voronoi_areas", [](Vertices vertices, Triangles faces) { return tpscore::voronoi_areas(vertices, faces); },
        "vertices"_a, "faces"_a, release,
        "Mixed Voronoi area per vertex (n,).");
    m.def(
        "boundary_vertices",
        [](std::int64_t n_vertices, Triangles faces) { return tpscore::boundary_vertices(n_vertices, faces); },
        "n_vertices"_a, "faces"_a, release,
        "Per-vertex mask: on an edge without exactly two faces.");
    m.def(
        "mean_curvature",
        [](Vertices vertices, Triangles faces) {
            tpscore::MeanCurvature result = tpscore::mean_curvature(vertices, faces);
            return std::make_tuple(std::move(result.values), std::move(result.normals),
                                   std::move(result.boundary));
        },
        "vertices"_a, "faces"_a, release,
        "Mean curvature H (n,), mean-curvature normal (n, 3), boundary mask (n,).");
    m.def(
        "grid_triangles",
        [](In<tpscore::BoolVector> valid, std::int64_t height, std::int64_t width) {
            return tpscore::grid_triangles(valid, height, width);
        },
        "valid"_a, "height"_a, "width"_a, release,
        "Triangles (m, 3) over a grid's valid vertices, as flat grid indices.");
}
