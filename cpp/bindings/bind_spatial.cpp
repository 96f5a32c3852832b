// Bindings of the spatial queries: the kd-tree over points and the surface queries on
// a triangle mesh. Inputs arrive validated (C-contiguous float64 / int64) from
// tpscore.spatial; every kernel runs with the GIL released; outputs are owning NumPy
// arrays (arrays.hpp).
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <stdexcept>
#include <tuple>

#include "arrays.hpp"
#include "tpscore/closest_point.hpp"
#include "tpscore/kdtree.hpp"

namespace nb = nanobind;
using namespace nb::literals;
using tpscore_bindings::In;

namespace {

using tpscore::IndexVector;
using tpscore::Points;
using tpscore::VectorX;
using Queries = In<Points>;
using BoolVector = Eigen::Matrix<bool, Eigen::Dynamic, 1>;
template <class T>
using Table = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

}  // namespace

void bind_spatial(nb::module_& m) {
    using tpscore::KDTree;

    nb::class_<KDTree>(m, "KDTree", "Static kd-tree over (n, 3) points (use tpscore.KDTree).")
        .def(
            "__init__",
            [](KDTree* self, In<Points> points, int leaf_size) {
                nb::gil_scoped_release release;
                new (self) KDTree(points, leaf_size);
            },
            "points"_a, "leaf_size"_a = 16)
        .def_prop_ro("size", &KDTree::size)
        .def(
            "query",
            [](const KDTree& tree, Queries queries, int k, double max_distance, int workers) {
                Table<double> distances(queries.rows(), k);
                Table<std::int64_t> indices(queries.rows(), k);
                tree.query(queries, k, max_distance, distances.data(), indices.data(), workers);
                return std::make_tuple(std::move(distances), std::move(indices));
            },
            "queries"_a, "k"_a, "max_distance"_a, "workers"_a, nb::call_guard<nb::gil_scoped_release>(),
            "(distances (m, k), indices (m, k)); missing neighbours: inf and -1.")
        .def(
            "query_radius",
            [](const KDTree& tree, Queries queries, double radius, bool sort, int workers) {
                tpscore::RadiusNeighbours found = tree.query_radius(queries, radius, sort, workers);
                return std::make_tuple(std::move(found.offsets), std::move(found.indices),
                                       std::move(found.distances));
            },
            "queries"_a, "radius"_a, "sort"_a, "workers"_a, nb::call_guard<nb::gil_scoped_release>(),
            "(offsets (m + 1,), indices, distances) in CSR form.")
        .def(
            "count_radius",
            [](const KDTree& tree, Queries queries, double radius, int workers, std::int64_t whole_below) {
                IndexVector counts(queries.rows());
                tree.count_radius(queries, radius, counts.data(), workers, whole_below);
                return counts;
            },
            "queries"_a, "radius"_a, "workers"_a, "whole_below"_a = 0, nb::call_guard<nb::gil_scoped_release>(),
            "(m,) the number of points within radius of each query (what query_radius returns); "
            "with whole_below > 0 an upper bound (nodes of at most that many points count whole).");

    using tpscore::MeshSurface;
    nb::class_<MeshSurface>(m, "MeshSurface",
                            "Triangle mesh with a BVH for closest-point and ray queries "
                            "(use tpscore.MeshSurface).")
        .def(
            "__init__",
            [](MeshSurface* self, In<Points> vertices, In<tpscore::Faces> faces, int leaf_size) {
                nb::gil_scoped_release release;
                new (self) MeshSurface(vertices, faces, leaf_size);
            },
            "vertices"_a, "faces"_a, "leaf_size"_a = 8)
        .def(
            "moved",
            [](const MeshSurface& shape, In<Points> vertices, In<tpscore::Faces> faces) {
                nb::gil_scoped_release release;
                return new MeshSurface(shape, vertices, faces);
            },
            "vertices"_a, "faces"_a, nb::rv_policy::take_ownership,
            "The same triangles over moved vertices: this tree, its boxes fitted again.")
        .def_prop_ro("num_triangles", &MeshSurface::num_triangles)
        .def(
            "closest_point",
            [](const MeshSurface& mesh, Queries queries, int workers) {
                const Eigen::Index m = queries.rows();
                Points points(m, 3), barycentric(m, 3);
                IndexVector triangles(m);
                VectorX distances(m);
                mesh.closest_point(queries, points.data(), triangles.data(), barycentric.data(), distances.data(),
                                   workers);
                return std::make_tuple(std::move(points), std::move(triangles), std::move(barycentric),
                                       std::move(distances));
            },
            "queries"_a, "workers"_a, nb::call_guard<nb::gil_scoped_release>(),
            "(points (m, 3), triangles (m,), barycentric (m, 3), distances (m,)).")
        .def(
            "intersect_rays",
            [](const MeshSurface& mesh, Queries origins, Queries directions, double max_distance,
               bool both_directions, int workers) {
                const Eigen::Index m = origins.rows();
                if (directions.rows() != m) throw std::invalid_argument("origins and directions differ in length");
                BoolVector hit(m);
                VectorX t(m);
                Points points(m, 3), barycentric(m, 3);
                IndexVector triangles(m);
                mesh.intersect_rays(origins, directions, max_distance, both_directions, hit.data(), t.data(),
                                    points.data(), triangles.data(), barycentric.data(), workers);
                return std::make_tuple(std::move(hit), std::move(t), std::move(points), std::move(triangles),
                                       std::move(barycentric));
            },
            "origins"_a, "directions"_a, "max_distance"_a, "both_directions"_a, "workers"_a,
            nb::call_guard<nb::gil_scoped_release>(),
            "(hit, t, points, triangles, barycentric); misses: False, NaN, -1.");
}
