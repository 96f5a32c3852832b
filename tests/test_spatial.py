"""The spatial queries (tpscore.spatial) against brute-force NumPy references and SciPy."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import tpscore
from tpscore import KDTree
from tpscore.reference import spatial as ref

# Distances from the core and from the reference are both sqrt(dx*dx + dy*dy + dz*dz) of
# the same float64 differences; they can differ only if a compiler fuses a multiply-add,
# i.e. by a few ulp of the squared distance: 1e-13 relative leaves a wide margin.
DIST_RTOL = 1e-13

POINT_KINDS = ["uniform", "clustered", "duplicates", "identical", "collinear", "grid", "single"]


def make_points(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Point sets that stress a kd-tree: clusters, exact duplicates, zero extent, ties."""
    if kind == "single":
        return rng.normal(size=(1, 3)) * 50
    if kind == "uniform":
        return rng.uniform(-100, 100, size=(n, 3))
    if kind == "clustered":
        centres = rng.uniform(-100, 100, size=(4, 3))
        return centres[rng.integers(0, 4, n)] + rng.normal(scale=0.01, size=(n, 3))
    if kind == "duplicates":
        base = rng.uniform(-10, 10, size=(max(1, n // 4), 3))
        return base[rng.integers(0, len(base), n)]
    if kind == "identical":
        return np.tile(rng.normal(size=(1, 3)), (n, 1))
    if kind == "collinear":
        return np.outer(rng.uniform(-5, 5, n), [1.0, 2.0, -0.5]) + [3.0, 0.0, 1.0]
    if kind == "grid":
        # Integer coordinates: many neighbours at exactly the same distance.
        return rng.integers(-3, 4, size=(n, 3)).astype(float)
    raise AssertionError(kind)


def make_queries(points: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """Queries near the data, exactly on data points, and far away."""
    lo, hi = points.min(axis=0) - 1, points.max(axis=0) + 1
    near = rng.uniform(lo, hi, size=(m, 3))
    on = points[rng.integers(0, len(points), m)]
    far = rng.normal(size=(max(1, m // 4), 3)) * 1e4
    if np.all(points == np.round(points)):
        near = np.round(near * 2) / 2  # half-integers tie exactly on a grid
    return np.concatenate([near, on, far])


def assert_neighbours_match(points, queries, got_d, got_i, want_d, want_i):
    """Same distances; same indices, except where a near-tie could flip the order."""
    n = len(points)
    np.testing.assert_allclose(got_d, want_d, rtol=DIST_RTOL, atol=0)
    assert np.array_equal(np.isinf(got_d), np.isinf(want_d))
    assert np.all(got_i[np.isinf(got_d)] == n)
    differ = got_i != want_i
    if differ.any():
        # Only a point at the same distance (to rounding) may take another's slot.
        rows, slots = np.nonzero(differ)
        actual = np.linalg.norm(queries[rows] - points[got_i[rows, slots]], axis=1)
        np.testing.assert_allclose(actual, want_d[rows, slots], rtol=1e-12)
    for row in got_i:
        found = row[row < n]
        assert len(np.unique(found)) == len(found)


# --------------------------------------------------------------------------- kd-tree


@settings(max_examples=80, deadline=None)
@given(
    kind=st.sampled_from(POINT_KINDS),
    n=st.integers(1, 300),
    m=st.integers(1, 40),
    k=st.sampled_from([1, 2, 3, 8, 17, 64, 65, 100, 400]),
    bound=st.sampled_from([np.inf, 0.0, 0.5, 3.0, 50.0]),
    leaf_size=st.sampled_from([1, 2, 16, 40]),
    seed=st.integers(0, 2**32 - 1),
)
def test_knn_matches_brute_force(kind, n, m, k, bound, leaf_size, seed):
    rng = np.random.default_rng(seed)
    points = make_points(kind, n, rng)
    queries = make_queries(points, m, rng)
    tree = KDTree(points, leaf_size=leaf_size)
    got_d, got_i = tree.query(queries, k, distance_upper_bound=bound)
    want_d, want_i = ref.knn(points, queries, k, bound)
    if k == 1:
        assert got_d.shape == got_i.shape == (len(queries),)
        got_d, got_i = got_d[:, None], got_i[:, None]
    else:
        assert got_d.shape == got_i.shape == (len(queries), k)
    assert got_i.dtype == np.int64
    assert_neighbours_match(points, queries, got_d, got_i, want_d, want_i)


@settings(max_examples=40, deadline=None)
@given(
    kind=st.sampled_from(POINT_KINDS),
    n=st.integers(1, 500),
    k=st.sampled_from([1, 4, 9, 70]),
    bound=st.sampled_from([np.inf, 1.0, 20.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_knn_matches_ckdtree(kind, n, k, bound, seed):
    rng = np.random.default_rng(seed)
    points = make_points(kind, n, rng)
    n = len(points)  # "single" ignores the requested size
    queries = make_queries(points, 30, rng)
    got_d, got_i = KDTree(points).query(queries, k, distance_upper_bound=bound)
    want_d, want_i = cKDTree(points).query(queries, k, distance_upper_bound=bound)
    assert got_d.shape == want_d.shape and got_i.shape == want_i.shape
    # cKDTree breaks ties by its own tree order, so only distances must agree, and
    # each returned index must sit at its reported distance.
    np.testing.assert_allclose(got_d, want_d, rtol=DIST_RTOL, atol=0)
    missing = np.isinf(got_d)
    assert np.array_equal(got_i == n, missing) and np.array_equal(want_i == n, missing)
    shaped_q = queries if k == 1 else queries[:, None, :]
    actual = np.linalg.norm(shaped_q - points[np.minimum(got_i, n - 1)], axis=-1)
    np.testing.assert_allclose(actual[~missing], got_d[~missing], rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    kind=st.sampled_from(POINT_KINDS),
    n=st.integers(1, 300),
    r=st.sampled_from([0.0, 0.01, 0.5, 1.0, 3.0, 30.0]),
    sort=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_radius_matches_brute_force_and_ckdtree(kind, n, r, sort, seed):
    rng = np.random.default_rng(seed)
    points = make_points(kind, n, rng)
    queries = make_queries(points, 25, rng)
    tree = KDTree(points, leaf_size=4)
    got_i, got_d = tree.query_radius(queries, r, return_distance=True, sort=sort)
    want = ref.radius_neighbors(points, queries, r)
    scipy_lists = cKDTree(points).query_ball_point(queries, r)
    assert len(got_i) == len(queries)
    # the count is what the query finds; with whole nodes of up to 8 points counted, an
    # upper bound of it (what the size checks of radius queries and CSRBF fits use)
    counts = tree.count_radius(queries, r)
    assert counts.dtype == np.int64 and counts.tolist() == [len(w[0]) for w in want]
    bound = tree._tree.count_radius(queries, r, 0, 8)
    assert np.all(bound >= counts) and np.all(bound <= n)
    for q, indices, distances, (want_i, want_d), scipy_i in zip(
        queries, got_i, got_d, want, scipy_lists
    ):
        # The set of neighbours is exact: a point exactly at distance r is in (<= r).
        assert sorted(indices.tolist()) == sorted(want_i.tolist())
        assert sorted(scipy_i) == sorted(want_i.tolist())
        np.testing.assert_allclose(distances, np.linalg.norm(points[indices] - q, axis=1),
                                   rtol=1e-12, atol=0)
        if sort:
            assert np.array_equal(indices, want_i)
            np.testing.assert_allclose(distances, want_d, rtol=DIST_RTOL, atol=0)


def test_count_radius_of_no_queries_and_bad_radii():
    tree = KDTree(np.eye(3))
    assert tree.count_radius(np.empty((0, 3)), 1.0).shape == (0,)
    assert tree.count_radius([[0.0, 0, 0]], 1.0, workers=1).tolist() == [3]
    with pytest.raises(ValueError, match="r must be finite"):
        tree.count_radius([[0.0, 0, 0]], np.inf)
    with pytest.raises(ValueError, match="r must be >= 0"):
        tree.count_radius([[0.0, 0, 0]], -1.0)


def test_radius_zero_finds_exact_duplicates_only():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [1e-9, 0, 0]], dtype=float)
    tree = KDTree(points)
    (found,) = tree.query_radius([[0, 0, 0]], 0.0, sort=True)
    assert found.tolist() == [0, 2]


def test_radius_csr_layout_agrees_with_lists():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 10, size=(2000, 3))
    queries = rng.uniform(0, 10, size=(700, 3))
    tree = KDTree(points)
    offsets, indices, distances = tree.query_radius_csr(queries, 1.0, sort=True)
    assert offsets.shape == (701,) and offsets[0] == 0 and np.all(np.diff(offsets) >= 0)
    assert len(indices) == len(distances) == offsets[-1]
    lists = tree.query_radius(queries, 1.0, sort=True)
    for i, found in enumerate(lists):
        assert np.array_equal(found, indices[offsets[i]:offsets[i + 1]])
    assert np.all(distances <= 1.0)


def test_k_larger_than_n_pads_like_ckdtree():
    points = np.array([[0.0, 0, 0], [3, 0, 0]])
    distances, indices = KDTree(points).query([[1.0, 0, 0]], k=4)
    assert indices.tolist() == [[0, 1, 2, 2]]
    assert distances[0, :2].tolist() == [1.0, 2.0] and np.all(np.isinf(distances[0, 2:]))


def test_distance_upper_bound_is_strict_like_ckdtree():
    points = np.array([[0.0, 0, 0], [2, 0, 0]])
    distances, indices = KDTree(points).query([[1.0, 0, 0]], k=2, distance_upper_bound=1.0)
    want_d, want_i = cKDTree(points).query([[1.0, 0, 0]], k=2, distance_upper_bound=1.0)
    assert np.isinf(distances).all() and indices.tolist() == [[2, 2]]
    assert np.array_equal(indices, want_i)
    distances, indices = KDTree(points).query([[1.0, 0, 0]], k=2, distance_upper_bound=1.5)
    assert indices.tolist() == [[0, 1]]  # equal distances: the smaller index first


def test_exact_ties_go_to_the_smaller_index():
    points = np.zeros((100, 3))
    distances, indices = KDTree(points, leaf_size=3).query([[1.0, 0, 0]], k=5)
    assert indices.tolist() == [[0, 1, 2, 3, 4]]
    assert np.all(distances == 1.0)


def test_results_do_not_depend_on_the_thread_count():
    rng = np.random.default_rng(7)
    points = make_points("clustered", 20000, rng)
    queries = make_queries(points, 6000, rng)
    tree = KDTree(points)
    tpscore.set_num_threads(2)  # make workers=-1 really use two threads, even on one core
    try:
        for k in (1, 8, 80):
            serial = tree.query(queries, k, workers=1)
            parallel = tree.query(queries, k, workers=-1)
            two = tree.query(queries, k, workers=2)
            for a, b, c in zip(serial, parallel, two):
                assert np.array_equal(a, b) and np.array_equal(a, c)
        serial = tree.query_radius_csr(queries, 0.02, workers=1)
        parallel = tree.query_radius_csr(queries, 0.02, workers=2)
        for a, b in zip(serial, parallel):
            assert np.array_equal(a, b)
        assert serial[0][-1] > 0
    finally:
        tpscore.set_num_threads(0)


def test_two_python_threads_query_one_tree():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(30000, 3))
    queries = rng.normal(size=(20000, 3))
    tree = KDTree(points)
    expected = tree.query(queries, 4, workers=1)
    results = [None, None]
    barrier = threading.Barrier(2)

    def work(slot):
        barrier.wait()
        results[slot] = tree.query(queries, 4)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for result in results:
        assert np.array_equal(result[0], expected[0])
        assert np.array_equal(result[1], expected[1])


def test_snap_returns_nearest_vertex_and_its_position():
    points = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    indices, positions = KDTree(points).snap([[9.0, 1, 0], [1, 8, 0], [-5, -5, 0]])
    assert indices.tolist() == [1, 2, 0]
    assert np.array_equal(positions, points[[1, 2, 0]])


def test_accepts_lists_float32_ints_and_non_contiguous_input():
    rng = np.random.default_rng(5)
    # Values exactly representable in float32, so the float32 copy holds the same points.
    points = rng.uniform(-5, 5, size=(200, 6)).astype(np.float32).astype(float)[:, ::2]
    assert not points.flags.c_contiguous
    queries = rng.integers(-5, 5, size=(30, 3))
    expected = KDTree(np.ascontiguousarray(points)).query(queries.astype(float), k=3)
    for p, q in [
        (points, queries),
        (points.tolist(), queries.tolist()),
        (points.astype(np.float32), queries.astype(np.int32)),
    ]:
        got = KDTree(p).query(q, k=3)
        assert np.array_equal(got[0], expected[0]) and np.array_equal(got[1], expected[1])
    assert KDTree(points.astype(np.float32)).points.dtype == np.float64


def test_empty_queries_give_empty_results_with_the_right_shapes():
    tree = KDTree(np.eye(3))
    empty = np.zeros((0, 3))
    d, i = tree.query(empty)
    assert d.shape == (0,) and i.shape == (0,) and i.dtype == np.int64
    d, i = tree.query(empty, k=5)
    assert d.shape == (0, 5) and i.shape == (0, 5)
    offsets, indices, distances = tree.query_radius_csr(empty, 1.0)
    assert offsets.tolist() == [0] and indices.shape == (0,) and distances.shape == (0,)
    assert tree.query_radius(empty, 1.0) == []
    indices, positions = tree.snap(empty)
    assert indices.shape == (0,) and positions.shape == (0, 3)


def test_properties_repr_and_immutability():
    points = np.arange(12, dtype=float).reshape(4, 3)
    tree = KDTree(points, leaf_size=2)
    assert len(tree) == tree.n == 4
    assert "n=4" in repr(tree) and "leaf_size=2" in repr(tree)
    assert np.array_equal(tree.points, points)
    with pytest.raises(ValueError):
        tree.points[0, 0] = 1.0  # read-only: the tree indexes exactly these points
    points[0, 0] = 99.0  # the tree holds its own copy
    assert tree.query([[0.0, 1, 2]])[0][0] == 0.0


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: KDTree(np.zeros((0, 3))), "points is empty"),
        (lambda: KDTree([[0.0, np.nan, 0]]), "points contains NaN"),
        (lambda: KDTree(np.zeros((4, 2))), r"points must have shape \(n, 3\)"),
        (lambda: KDTree(np.zeros(3)), r"points must have shape \(n, 3\)"),
        (lambda: KDTree(np.eye(3), leaf_size=0), "leaf_size must be >= 1"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, np.inf]]), "points contains NaN or infinite"),
        (lambda: KDTree(np.eye(3)).query([[0, 0]]), r"points must have shape \(n, 3\)"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, 0]], k=0), "k must be >= 1"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, 0]], k=1.5), "k must be an integer"),
        (lambda: KDTree(np.eye(3)).query(np.zeros((4, 3)), k=2**27), "output slots"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, 0]], distance_upper_bound=-1), "distance_upper_bound must be >= 0"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, 0]], distance_upper_bound=np.nan), "distance_upper_bound must be >= 0"),
        (lambda: KDTree(np.eye(3)).query([[0, 0, 0]], workers=0), "workers must be -1"),
        (lambda: KDTree(np.eye(3)).query_radius([[0, 0, 0]], -0.1), "r must be >= 0"),
        (lambda: KDTree(np.eye(3)).query_radius([[0, 0, 0]], np.inf), "r must be finite"),
        (lambda: KDTree(np.eye(3)).query_radius([["a", 0, 0]], 1.0), "points must be a numeric array"),
    ],
)
def test_bad_input_raises_value_error_naming_the_problem(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ------------------------------------------------------------------ mesh surfaces

MESH_KINDS = ["soup", "grid", "sphere", "with_degenerate"]


def grid_mesh(rows: int, cols: int, rng: np.random.Generator | None = None, spacing=1.0):
    """A height-field grid mesh like tpscore's faces: two triangles per quad."""
    y, x = np.mgrid[0:rows, 0:cols].astype(float) * spacing
    z = np.zeros_like(x) if rng is None else rng.normal(scale=0.3, size=x.shape)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, faces


def make_mesh(kind: str, rng: np.random.Generator):
    if kind == "soup":
        vertices = rng.normal(size=(60, 3)) * 10
        return vertices, rng.integers(0, 60, size=(120, 3))  # repeated indices: zero area
    if kind == "grid":
        return grid_mesh(8, 9, rng)
    if kind == "sphere":
        directions = rng.normal(size=(80, 3))
        vertices = 20 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
        from scipy.spatial import ConvexHull

        return vertices, ConvexHull(vertices).simplices
    if kind == "with_degenerate":
        vertices, faces = grid_mesh(5, 5, rng)
        extra = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [5, 5, 5], [5, 5, 5], [5, 5, 5]],
                         dtype=float) + [1.3, 0.2, 0.4]
        n = len(vertices)
        degenerate = np.array([[n, n + 1, n + 2], [n + 3, n + 4, n + 5], [n, n, n + 1]])
        return np.concatenate([vertices, extra]), np.concatenate([faces, degenerate])
    raise AssertionError(kind)


def surface_queries(vertices, faces, m, rng):
    """Random points near the mesh, its vertices, edge points, face points, far points."""
    lo, hi = vertices.min(0) - 2, vertices.max(0) + 2
    face = faces[rng.integers(0, len(faces), m)]
    weights = rng.dirichlet([1, 1, 1], size=m)
    s = rng.uniform(size=(m, 1))
    return np.concatenate([
        rng.uniform(lo, hi, size=(m, 3)),
        vertices[rng.integers(0, len(vertices), m)],
        s * vertices[face[:, 0]] + (1 - s) * vertices[face[:, 1]],
        np.einsum("mj,mjk->mk", weights, vertices[face]),
        rng.normal(size=(4, 3)) * 1e4,
    ])


def assert_closest_points_match(vertices, faces, queries, got, want):
    want_points, want_triangles, want_bary, want_distances = want
    scale = np.abs(vertices).max() + 1.0
    # Core and reference evaluate the same region formulas in the same order; only a
    # differently rounded region choice near a region boundary (where both candidate
    # formulas agree to rounding) can separate them: 1e-9 of the coordinate scale.
    tol = 1e-9 * scale
    np.testing.assert_allclose(got.distances, want_distances, rtol=0, atol=tol)
    corners = vertices[faces[got.triangles]]
    np.testing.assert_allclose(got.points, np.einsum("mj,mjk->mk", got.barycentric, corners),
                               atol=tol)
    np.testing.assert_allclose(got.barycentric.sum(axis=1), 1.0, atol=1e-9)
    assert np.all(got.barycentric >= -1e-9)
    np.testing.assert_allclose(np.linalg.norm(queries - got.points, axis=1), got.distances,
                               atol=tol)
    same = got.triangles == want_triangles
    # Where the triangle differs, it must be a tie: same distance, different triangle.
    assert same.mean() > 0.5
    np.testing.assert_allclose(got.points[same], want_points[same], atol=tol)
    np.testing.assert_allclose(got.barycentric[same], want_bary[same], atol=1e-6)
    assert np.isfinite(got.points).all() and np.isfinite(got.barycentric).all()


@settings(max_examples=40, deadline=None)
@given(kind=st.sampled_from(MESH_KINDS), seed=st.integers(0, 2**32 - 1))
def test_closest_point_matches_brute_force(kind, seed):
    rng = np.random.default_rng(seed)
    vertices, faces = make_mesh(kind, rng)
    queries = surface_queries(vertices, faces, 40, rng)
    got = tpscore.MeshSurface(vertices, faces).closest_point(queries)
    want = ref.closest_point_on_mesh(vertices, faces.astype(np.int64), queries)
    assert_closest_points_match(vertices, faces, queries, got, want)


def test_closest_point_on_the_surface_is_the_point_itself():
    rng = np.random.default_rng(11)
    vertices, faces = grid_mesh(10, 10, rng)
    face = faces[rng.integers(0, len(faces), 300)]
    weights = rng.dirichlet([1, 1, 1], size=300)
    on_surface = np.einsum("mj,mjk->mk", weights, vertices[face])
    result = tpscore.MeshSurface(vertices, faces).closest_point(on_surface)
    # A point on a triangle is its own closest point, up to the rounding of its
    # construction (a few ulp of coordinates below 10).
    assert np.all(result.distances < 1e-12)
    np.testing.assert_allclose(result.points, on_surface, atol=1e-12)


def test_closest_point_analytic_cases_and_tie_breaking():
    # Two triangles sharing the edge (1,0,0)-(0,1,0) in the plane z = 0.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    surface = tpscore.MeshSurface(vertices, faces)
    queries = np.array([
        [0.25, 0.25, 2.0],   # above the first face
        [-1.0, -1.0, 0.0],   # beyond corner 0
        [0.5, 0.5, 1.0],     # above the shared edge: a tie, the smaller index wins
        [1.0, 0.0, 0.0],     # on a shared vertex
        [2.0, 0.5, 0.0],     # beside edge 1-3
    ])
    result = surface.closest_point(queries)
    np.testing.assert_allclose(result.points, [[0.25, 0.25, 0], [0, 0, 0], [0.5, 0.5, 0],
                                               [1, 0, 0], [1, 0.5, 0]], atol=1e-15)
    np.testing.assert_allclose(result.distances, [2.0, np.sqrt(2), 1.0, 0.0, 1.0], atol=1e-15)
    assert result.triangles.tolist() == [0, 0, 0, 0, 1]
    np.testing.assert_allclose(result.barycentric[0], [0.5, 0.25, 0.25], atol=1e-15)
    np.testing.assert_allclose(result.barycentric[4], [0.5, 0.5, 0.0], atol=1e-15)


def test_degenerate_triangles_give_finite_results():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 3, 3]], dtype=float)
    faces = np.array([[0, 1, 2], [3, 3, 3], [0, 0, 2]])  # collinear, a point, an edge
    queries = np.array([[0.5, 1, 0], [3, 3, 4], [-1, 0, 0], [1.5, 0, -2]])
    result = tpscore.MeshSurface(vertices, faces).closest_point(queries)
    assert np.isfinite(result.points).all() and np.isfinite(result.barycentric).all()
    np.testing.assert_allclose(result.points, [[0.5, 0, 0], [3, 3, 3], [0, 0, 0], [1.5, 0, 0]])
    np.testing.assert_allclose(result.distances, [1, 1, 1, 2])
    want = ref.closest_point_on_mesh(vertices, faces, queries)
    assert_closest_points_match(vertices, faces, queries, result, want)
    # Rays never hit a zero-area triangle, and never produce NaN hits.
    hits = tpscore.MeshSurface(vertices, faces).intersect_rays(
        [[0.5, 0, 1]], [[0, 0, -1]], both_directions=True)
    assert not hits.hit[0] and np.isnan(hits.distances[0]) and hits.triangles[0] == -1


def test_closest_point_does_not_depend_on_query_order():
    # Each query starts from the leaf of the previous query's answer; that changes how
    # much of the tree it searches, never the answer (distance, then smaller index).
    rng = np.random.default_rng(23)
    vertices, faces = grid_mesh(60, 60, rng)
    rows, cols = np.meshgrid(np.linspace(-1, 60, 90), np.linspace(-1, 60, 90))
    grid_order = np.column_stack([rows.ravel(), cols.ravel(), rng.normal(scale=1.5, size=rows.size)])
    shuffle = rng.permutation(len(grid_order))
    surface = tpscore.MeshSurface(vertices, faces)
    ordered = surface.closest_point(grid_order, workers=1)
    shuffled = surface.closest_point(grid_order[shuffle], workers=1)
    for a, b in zip(ordered, shuffled):
        assert np.array_equal(a[shuffle], b)
    sample = rng.choice(len(grid_order), 300, replace=False)
    want = ref.closest_point_on_mesh(vertices, faces.astype(np.int64), grid_order[sample])
    assert_closest_points_match(vertices, faces, grid_order[sample],
                                type(ordered)(*(field[sample] for field in ordered)), want)


def test_closest_point_on_mesh_function_and_thread_independence():
    rng = np.random.default_rng(2)
    vertices, faces = grid_mesh(40, 40, rng)
    queries = rng.uniform(-3, 42, size=(5000, 3))
    surface = tpscore.MeshSurface(vertices, faces)
    tpscore.set_num_threads(2)
    try:
        serial = surface.closest_point(queries, workers=1)
        parallel = surface.closest_point(queries, workers=2)
        origins = queries
        directions = rng.normal(size=queries.shape)
        rays_serial = surface.intersect_rays(origins, directions, both_directions=True, workers=1)
        rays_parallel = surface.intersect_rays(origins, directions, both_directions=True)
    finally:
        tpscore.set_num_threads(0)
    for a, b in zip(serial, parallel):
        assert np.array_equal(a, b)
    for a, b in zip(rays_serial, rays_parallel):
        assert np.array_equal(a, b, equal_nan=True)
    assert rays_serial.hit.sum() > 1000
    once = tpscore.closest_point_on_mesh(vertices, faces, queries[:100])
    assert np.array_equal(once.points, serial.points[:100])


def check_rays(vertices, faces, origins, directions, max_distance, both):
    got = tpscore.MeshSurface(vertices, faces).intersect_rays(
        origins, directions, max_distance=max_distance, both_directions=both)
    # Normalised exactly as MeshSurface does, so both see bit-identical directions.
    unit = directions / np.sqrt(np.einsum("ij,ij->i", directions, directions))[:, None]
    want_hit, want_t, want_points, want_triangles, want_bary = ref.intersect_rays(
        vertices, faces.astype(np.int64), origins, unit, max_distance, both)
    # Same Moller-Trumbore arithmetic in the same order: random rays land on the same
    # side of every triangle edge and limit in both.
    assert np.array_equal(got.hit, want_hit)
    missed = ~got.hit
    assert np.isnan(got.distances[missed]).all() and np.isnan(got.points[missed]).all()
    assert np.isnan(got.barycentric[missed]).all() and np.all(got.triangles[missed] == -1)
    h = got.hit
    np.testing.assert_allclose(got.distances[h], want_t[h], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.points[h], want_points[h], rtol=1e-12, atol=1e-12)
    # The hit point lies on the ray, at the reported signed distance.
    np.testing.assert_allclose(got.points[h], origins[h] + got.distances[h, None] * unit[h],
                               atol=1e-9)
    # A different triangle is only allowed as a tie (origins on the surface, rays through
    # shared edges): the same t (checked above), and the hit lies on the reported triangle.
    corners = vertices[faces[got.triangles[h]]]
    np.testing.assert_allclose(got.points[h], np.einsum("mj,mjk->mk", got.barycentric[h], corners),
                               atol=1e-9)
    assert np.all(got.barycentric[h] >= -1e-12)
    same = got.triangles[h] == want_triangles[h]
    np.testing.assert_allclose(got.barycentric[h][same], want_bary[h][same], atol=1e-12)
    if both:
        assert np.all(np.abs(got.distances[h]) <= max_distance)
    else:
        assert np.all((got.distances[h] >= 0) & (got.distances[h] <= max_distance))
    return got


@settings(max_examples=40, deadline=None)
@given(
    kind=st.sampled_from(MESH_KINDS),
    both=st.booleans(),
    max_distance=st.sampled_from([np.inf, 5.0, 0.5]),
    seed=st.integers(0, 2**32 - 1),
)
def test_rays_match_brute_force(kind, both, max_distance, seed):
    rng = np.random.default_rng(seed)
    vertices, faces = make_mesh(kind, rng)
    origins = surface_queries(vertices, faces, 30, rng)
    directions = rng.normal(size=origins.shape)
    check_rays(vertices, faces, origins, directions, max_distance, both)


def test_rays_edges_vertices_grazing_and_both_directions():
    # Integer grid in z = 0: every test below is exact in floating point.
    vertices, faces = grid_mesh(4, 4)
    surface = tpscore.MeshSurface(vertices, faces)
    origins = np.array([
        [1.0, 1.0, 5.0],   # straight down onto an interior vertex
        [1.5, 1.0, 5.0],   # onto an interior edge
        [3.0, 1.5, 5.0],   # onto the mesh's outer boundary edge
        [3.5, 1.5, 5.0],   # just beside the mesh: a miss
        [-1.0, 1.5, 0.0],  # grazing: in the plane of the mesh, never a hit
        [1.2, 1.7, -2.0],  # from below, looking down: the hit is behind
    ])
    directions = np.array([[0, 0, -2], [0, 0, -1], [0, 0, -1], [0, 0, -1], [1, 0, 0], [0, 0, -1]],
                          dtype=float)
    one_way = surface.intersect_rays(origins, directions)
    assert one_way.hit.tolist() == [True, True, True, False, False, False]
    np.testing.assert_array_equal(one_way.distances[:3], [5.0, 5.0, 5.0])
    np.testing.assert_array_equal(one_way.points[:3], [[1, 1, 0], [1.5, 1, 0], [3, 1.5, 0]])
    both = surface.intersect_rays(origins, directions, both_directions=True)
    assert both.hit.tolist() == [True, True, True, False, False, True]
    assert both.distances[5] == -2.0
    np.testing.assert_array_equal(both.points[5], [1.2, 1.7, 0.0])
    # Every triangle touching the hit vertex is at t = 5: the smallest index wins.
    touching = np.flatnonzero((faces == 5).any(axis=1))
    assert one_way.triangles[0] == touching.min()
    limited = surface.intersect_rays(origins, directions, max_distance=2.0, both_directions=True)
    assert limited.hit.tolist() == [False] * 5 + [True]  # |t| = 2 counts
    limited = surface.intersect_rays(origins, directions, max_distance=1.999, both_directions=True)
    assert not limited.hit.any()


def test_both_directions_takes_the_nearer_side():
    # Two parallel sheets, z = 0 and z = 3; the origin sits at z = 1.
    lower, faces = grid_mesh(3, 3)
    upper = lower + [0, 0, 3]
    vertices = np.concatenate([lower, upper])
    faces = np.concatenate([faces, faces + len(lower)])
    surface = tpscore.MeshSurface(vertices, faces)
    one_way = surface.intersect_rays([[0.5, 0.5, 1.0]], [[0, 0, 1.0]])
    both = surface.intersect_rays([[0.5, 0.5, 1.0]], [[0, 0, 1.0]], both_directions=True)
    assert one_way.distances.tolist() == [2.0] and one_way.points[0, 2] == 3.0
    assert both.distances.tolist() == [-1.0] and both.points[0, 2] == 0.0


def test_surface_accepts_array_likes_and_returns_empty_results():
    vertices, faces = grid_mesh(3, 3)
    surface = tpscore.MeshSurface(vertices.astype(np.float32).tolist(), faces.astype(np.int32))
    assert surface.faces.dtype == np.int64 and surface.vertices.dtype == np.float64
    assert "triangles=8" in repr(surface)
    queries = np.asfortranarray(np.array([[0.5, 0.5, 1.0], [1.5, 0.2, -1.0]]))
    result = surface.closest_point(queries)
    np.testing.assert_allclose(result.distances, [1.0, 1.0])
    empty = surface.closest_point(np.zeros((0, 3)))
    assert empty.points.shape == (0, 3) and empty.triangles.shape == (0,)
    assert empty.barycentric.shape == (0, 3) and empty.distances.shape == (0,)
    assert empty.triangles.dtype == np.int64
    rays = surface.intersect_rays(np.zeros((0, 3)), np.zeros((0, 3)))
    assert rays.hit.shape == (0,) and rays.hit.dtype == bool and rays.points.shape == (0, 3)
    assert rays.distances.shape == (0,) and rays.barycentric.shape == (0, 3)


def test_two_python_threads_query_one_surface():
    rng = np.random.default_rng(4)
    vertices, faces = grid_mesh(60, 60, rng)
    queries = rng.uniform(0, 60, size=(20000, 3))
    surface = tpscore.MeshSurface(vertices, faces)
    expected = surface.closest_point(queries, workers=1)
    results = [None, None]
    barrier = threading.Barrier(2)

    def work(slot):
        barrier.wait()
        results[slot] = surface.closest_point(queries)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for result in results:
        for a, b in zip(result, expected):
            assert np.array_equal(a, b)


def _same_answers(first, second, queries, origins, directions):
    for a, b in zip(first.closest_point(queries), second.closest_point(queries)):
        assert np.array_equal(a, b)
    for a, b in zip(first.intersect_rays(origins, directions, both_directions=True),
                    second.intersect_rays(origins, directions, both_directions=True)):
        assert np.array_equal(a, b, equal_nan=True)


@settings(max_examples=30, deadline=None)
@given(kind=st.sampled_from(MESH_KINDS), motion=st.sampled_from(["similarity", "smooth", "scrambled"]),
       seed=st.integers(0, 2**32 - 1))
def test_a_moved_surface_answers_as_a_new_build_bit_for_bit(kind, motion, seed):
    rng = np.random.default_rng(seed)
    vertices, faces = make_mesh(kind, rng)
    angle = rng.uniform(-np.pi, np.pi)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    if motion == "similarity":
        moved = 1.7 * vertices @ rotation.T + rng.normal(scale=50.0, size=3)
    elif motion == "smooth":
        moved = vertices + 0.2 * np.sin(vertices[:, [1, 2, 0]])
    else:  # every vertex somewhere else: the old grouping is no help, yet answers hold
        moved = rng.permutation(vertices) + rng.normal(size=vertices.shape)
    surface = tpscore.MeshSurface(vertices, faces)
    refitted = surface.moved(moved)
    rebuilt = tpscore.MeshSurface(moved, faces)
    queries = surface_queries(moved, faces, 40, rng)
    directions = rng.normal(size=queries.shape)
    _same_answers(refitted, rebuilt, queries, queries, directions)
    assert np.array_equal(refitted.vertices, moved) and refitted.faces is surface.faces
    # the original is untouched, and a moved surface moves again (back, here)
    _same_answers(refitted.moved(vertices), surface, queries, queries, directions)
    want = ref.closest_point_on_mesh(moved, faces.astype(np.int64), queries)
    assert_closest_points_match(moved, faces, queries, refitted.closest_point(queries), want)


def test_a_moved_surface_pickles_and_refuses_other_vertices():
    import pickle
    vertices, faces = grid_mesh(6, 5)
    surface = tpscore.MeshSurface(vertices, faces).moved(vertices + [0.0, 0.0, 2.0])
    again = pickle.loads(pickle.dumps(surface))
    queries = np.random.default_rng(3).uniform(-1, 6, size=(50, 3))
    _same_answers(surface, again, queries, queries, np.tile([0.0, 0.0, 1.0], (50, 1)))
    with pytest.raises(ValueError, match=r"vertices must have this surface's shape \(30, 3\)"):
        surface.moved(vertices[:-1])
    with pytest.raises(ValueError, match="vertices contains NaN"):
        surface.moved(np.where(np.arange(30)[:, None] == 4, np.nan, vertices))
    with pytest.raises(ValueError, match="vertices"):
        surface.moved(vertices + 1j)


_V, _F = grid_mesh(3, 3)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: tpscore.MeshSurface(_V, _F + 100), r"faces refers to vertex indices outside"),
        (lambda: tpscore.MeshSurface(_V, -_F - 1), r"faces refers to vertex indices outside"),
        (lambda: tpscore.MeshSurface(_V, _F[:, :2]), r"faces must have shape \(m, 3\)"),
        (lambda: tpscore.MeshSurface(_V, _F + 0.5), "faces must hold integer"),
        (lambda: tpscore.MeshSurface(_V, np.zeros((0, 3), int)), "faces is empty"),
        (lambda: tpscore.MeshSurface(np.zeros((0, 3)), _F), "vertices is empty"),
        (lambda: tpscore.MeshSurface(np.full((9, 3), np.nan), _F), "vertices contains NaN"),
        (lambda: tpscore.MeshSurface(_V, _F).closest_point([[0, 0]]), r"points must have shape"),
        (lambda: tpscore.MeshSurface(_V, _F).closest_point([[0, np.nan, 0]]), "points contains NaN"),
        (lambda: tpscore.MeshSurface(_V, _F).intersect_rays([[0, 0, 1]], [[0, 0, 0]]),
         "directions has zero length at row 0"),
        (lambda: tpscore.MeshSurface(_V, _F).intersect_rays([[0, 0, 1]], [[0, 0, 1], [0, 0, 1]]),
         "directions must have one row per origin"),
        (lambda: tpscore.MeshSurface(_V, _F).intersect_rays([[0, 0, 1]], [[0, 0, 1]], max_distance=-1),
         "max_distance must be >= 0"),
        (lambda: tpscore.MeshSurface(_V, _F).intersect_rays([[0, 0, np.inf]], [[0, 0, 1]]),
         "origins contains NaN or infinite"),
        (lambda: tpscore.closest_point_on_mesh(_V, _F, [[0, 0, 0]], workers=-2), "workers must be -1"),
    ],
)
def test_bad_surface_input_raises_value_error_naming_the_problem(call, match):
    with pytest.raises(ValueError, match=match):
        call()
