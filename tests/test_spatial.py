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
