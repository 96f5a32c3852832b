// Bindings of the spatial queries: the kd-tree over points and the surface queries on
// a triangle mesh. Inputs arrive validated (C-contiguous float64 / int64) from
// tpscore.spatial; every kernel runs with the GIL released; outputs are new NumPy
// arrays that own their memory.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <cstdint>
#include <memory>
#include <vector>

#include "tpscore/closest_point.hpp"
#include "tpscore/kdtree.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {

using InPoints = nb::ndarray<const double, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using InFaces = nb::ndarray<const std::int64_t, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;

template <class T>
using OutArray = nb::ndarray<nb::numpy, T>;

Eigen::Map<const tpscore::Points> as_eigen(const InPoints& a) {
    return {a.data(), static_cast<Eigen::Index>(a.shape(0)), 3};
}

Eigen::Map<const tpscore::Faces> as_eigen(const InFaces& a) {
    return {a.data(), static_cast<Eigen::Index>(a.shape(0)), 3};
}

// Hands a heap buffer to NumPy: the capsule frees it with the array.
template <class T>
OutArray<T> to_numpy(std::unique_ptr<T[]> data, std::initializer_list<std::size_t> shape) {
    T* raw = data.release();
    nb::capsule owner(raw, [](void* p) noexcept { delete[] static_cast<T*>(p); });
    return OutArray<T>(raw, shape, owner);
}

template <class T>
OutArray<T> to_numpy(std::vector<T>&& values) {
    auto* holder = new std::vector<T>(std::move(values));
    nb::capsule owner(holder, [](void* p) noexcept { delete static_cast<std::vector<T>*>(p); });
    return OutArray<T>(holder->data(), {holder->size()}, owner);
}

}  // namespace

void bind_spatial(nb::module_& m) {
    using tpscore::KDTree;

    nb::class_<KDTree>(m, "KDTree", "Static kd-tree over (n, 3) points (use tpscore.KDTree).")
        .def(
            "__init__",
            [](KDTree* self, const InPoints& points, int leaf_size) {
                nb::gil_scoped_release release;
                new (self) KDTree(as_eigen(points), leaf_size);
            },
            "points"_a, "leaf_size"_a = 16)
        .def_prop_ro("size", &KDTree::size)
        .def(
            "query",
            [](const KDTree& tree, const InPoints& queries, int k, double max_distance, int workers) {
                const std::size_t m = queries.shape(0);
                const std::size_t kk = static_cast<std::size_t>(k);
                std::unique_ptr<double[]> distances(new double[m * kk]);
                std::unique_ptr<std::int64_t[]> indices(new std::int64_t[m * kk]);
                {
                    nb::gil_scoped_release release;
                    tree.query(as_eigen(queries), k, max_distance, distances.get(), indices.get(),
                               workers);
                }
                return nb::make_tuple(to_numpy(std::move(distances), {m, kk}),
                                      to_numpy(std::move(indices), {m, kk}));
            },
            "queries"_a, "k"_a, "max_distance"_a, "workers"_a,
            "(distances (m, k), indices (m, k)); missing neighbours: inf and -1.")
        .def(
            "query_radius",
            [](const KDTree& tree, const InPoints& queries, double radius, bool sort, int workers) {
                std::vector<std::int64_t> offsets, indices;
                std::vector<double> distances;
                {
                    nb::gil_scoped_release release;
                    tree.query_radius(as_eigen(queries), radius, sort, offsets, indices, distances,
                                      workers);
                }
                return nb::make_tuple(to_numpy(std::move(offsets)), to_numpy(std::move(indices)),
                                      to_numpy(std::move(distances)));
            },
            "queries"_a, "radius"_a, "sort"_a, "workers"_a,
            "(offsets (m + 1,), indices, distances) in CSR form.")
        .def(
            "count_radius",
            [](const KDTree& tree, const InPoints& queries, double radius, int workers,
               std::int64_t whole_below) {
                const std::size_t m = queries.shape(0);
                std::unique_ptr<std::int64_t[]> counts(new std::int64_t[m]);
                {
                    nb::gil_scoped_release release;
                    tree.count_radius(as_eigen(queries), radius, counts.get(), workers, whole_below);
                }
                return to_numpy(std::move(counts), {m});
            },
            "queries"_a, "radius"_a, "workers"_a, "whole_below"_a = 0,
            "(m,) the number of points within radius of each query (what query_radius returns); "
            "with whole_below > 0 an upper bound (nodes of at most that many points count whole).");

    using tpscore::MeshSurface;
    nb::class_<MeshSurface>(m, "MeshSurface",
                            "Triangle mesh with a BVH for closest-point and ray queries "
                            "(use tpscore.MeshSurface).")
        .def(
            "__init__",
            [](MeshSurface* self, const InPoints& vertices, const InFaces& faces, int leaf_size) {
                nb::gil_scoped_release release;
                new (self) MeshSurface(as_eigen(vertices), as_eigen(faces), leaf_size);
            },
            "vertices"_a, "faces"_a, "leaf_size"_a = 8)
        .def_prop_ro("num_triangles", &MeshSurface::num_triangles)
        .def(
            "closest_point",
            [](const MeshSurface& mesh, const InPoints& queries, int workers) {
                const std::size_t m = queries.shape(0);
                std::unique_ptr<double[]> points(new double[3 * m]);
                std::unique_ptr<std::int64_t[]> triangles(new std::int64_t[m]);
                std::unique_ptr<double[]> barycentric(new double[3 * m]);
                std::unique_ptr<double[]> distances(new double[m]);
                {
                    nb::gil_scoped_release release;
                    mesh.closest_point(as_eigen(queries), points.get(), triangles.get(),
                                       barycentric.get(), distances.get(), workers);
                }
                return nb::make_tuple(to_numpy(std::move(points), {m, 3}),
                                      to_numpy(std::move(triangles), {m}),
                                      to_numpy(std::move(barycentric), {m, 3}),
                                      to_numpy(std::move(distances), {m}));
            },
            "queries"_a, "workers"_a, "(points (m, 3), triangles (m,), barycentric (m, 3), distances (m,)).")
        .def(
            "intersect_rays",
            [](const MeshSurface& mesh, const InPoints& origins, const InPoints& directions,
               double max_distance, bool both_directions, int workers) {
                const std::size_t m = origins.shape(0);
                if (directions.shape(0) != m)
                    throw nb::value_error("origins and directions differ in length");
                std::unique_ptr<bool[]> hit(new bool[m]);
                std::unique_ptr<double[]> t(new double[m]);
                std::unique_ptr<double[]> points(new double[3 * m]);
                std::unique_ptr<std::int64_t[]> triangles(new std::int64_t[m]);
                std::unique_ptr<double[]> barycentric(new double[3 * m]);
                {
                    nb::gil_scoped_release release;
                    mesh.intersect_rays(as_eigen(origins), as_eigen(directions), max_distance,
                                        both_directions, hit.get(), t.get(), points.get(),
                                        triangles.get(), barycentric.get(), workers);
                }
                return nb::make_tuple(to_numpy(std::move(hit), {m}), to_numpy(std::move(t), {m}),
                                      to_numpy(std::move(points), {m, 3}),
                                      to_numpy(std::move(triangles), {m}),
                                      to_numpy(std::move(barycentric), {m, 3}));
            },
            "origins"_a, "directions"_a, "max_distance"_a, "both_directions"_a, "workers"_a,
            "(hit, t, points, triangles, barycentric); misses: False, NaN, -1.");
}
