"""Spatial queries: tpscore's kd-tree and mesh surface queries against SciPy, trimesh and
the NumPy reference, at the sizes of the face pipeline (a ~35k-point scan, a 150 x 150
grid of queries, a ~20k-triangle face mesh).

Each group compares like with like: the kd-tree groups fix the thread count of both
sides (workers=1 or workers=-1). Correctness is asserted inside every benchmark.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import tpscore
from tpscore.reference import spatial as ref

N_POINTS = 35_000
N_QUERIES = 22_500  # a 150 x 150 grid


def face_like_surface(u, v):
    """A smooth face-sized height field (mm): a dome with a ridge down the middle."""
    return 40 * np.exp(-(u**2 + v**2) / 5000) + 12 * np.exp(-(u**2) / 60 - (v / 40) ** 2)


@pytest.fixture(scope="module")
def scan():
    """~35k scan points near a face-like surface, and 22,500 grid queries near it."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-80, 80, size=(2, N_POINTS))
    points = np.stack([u, v, face_like_surface(u, v) + rng.normal(scale=0.2, size=N_POINTS)], 1)
    gu, gv = np.meshgrid(np.linspace(-80, 80, 150), np.linspace(-80, 80, 150))
    gu, gv = gu.ravel(), gv.ravel()
    queries = np.stack([gu, gv, face_like_surface(gu, gv) + rng.normal(scale=2.0, size=gu.size)], 1)
    return points, queries


@pytest.fixture(scope="module")
def face_mesh(scan):
    """A 101 x 101 grid mesh of the same surface: 20,000 triangles."""
    _, queries = scan
    side = 101
    gu, gv = np.meshgrid(np.linspace(-80, 80, side), np.linspace(-80, 80, side))
    vertices = np.stack([gu.ravel(), gv.ravel(), face_like_surface(gu, gv).ravel()], 1)
    index = np.arange(side * side).reshape(side, side)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, faces, queries


@pytest.fixture(scope="module")
def trees(scan):
    points, _ = scan
    return tpscore.KDTree(points), cKDTree(points)


# ------------------------------------------------------------------------ build


@pytest.mark.benchmark(group="kdtree build, 35k points")
def test_build_tpscore(benchmark, scan):
    points, _ = scan
    tree = benchmark(tpscore.KDTree, points)
    assert len(tree) == N_POINTS


@pytest.mark.benchmark(group="kdtree build, 35k points")
def test_build_scipy_ckdtree(benchmark, scan):
    points, _ = scan
    tree = benchmark(cKDTree, points)
    assert tree.n == N_POINTS


# ------------------------------------------------------------------------ queries

QUERY_CASES = [(k, workers) for k in (1, 8) for workers in (1, -1)]


def _group(k, workers):
    threads = "1 thread" if workers == 1 else "all threads"
    return f"kdtree k={k}, 22.5k queries on 35k, {threads}"


@pytest.mark.parametrize("k, workers", QUERY_CASES)
def test_query_tpscore(benchmark, scan, trees, k, workers):
    benchmark.group = _group(k, workers)
    _, queries = scan
    ours, theirs = trees
    distances, indices = benchmark(ours.query, queries, k, workers=workers)
    want_d, _ = theirs.query(queries, k)
    # Same distances to rounding (both compute sqrt of the same squared distance).
    np.testing.assert_allclose(distances, want_d, rtol=1e-13)
    assert indices.shape == want_d.shape


@pytest.mark.parametrize("k, workers", QUERY_CASES)
def test_query_scipy_ckdtree(benchmark, scan, trees, k, workers):
    benchmark.group = _group(k, workers)
    _, queries = scan
    ours, theirs = trees
    distances, _ = benchmark(theirs.query, queries, k, workers=workers)
    assert distances.shape == ((N_QUERIES,) if k == 1 else (N_QUERIES, k))


# The brute-force reference scans every point for every query: 200 queries keep a round
# near a second; tpscore runs the same 200 in the same group.
REFERENCE_QUERIES = 200


@pytest.mark.benchmark(group="kdtree k=8, 200 queries on 35k, vs NumPy brute force")
def test_query_small_tpscore(benchmark, scan, trees):
    points, queries = scan
    ours, _ = trees
    distances, indices = benchmark(ours.query, queries[:REFERENCE_QUERIES], 8, workers=1)
    want_d, want_i = ref.knn(points, queries[:REFERENCE_QUERIES], 8)
    np.testing.assert_allclose(distances, want_d, rtol=1e-13)
    assert np.array_equal(indices, want_i)  # random data: no ties


@pytest.mark.benchmark(group="kdtree k=8, 200 queries on 35k, vs NumPy brute force")
def test_query_small_numpy_reference(benchmark, scan):
    points, queries = scan
    distances, _ = benchmark.pedantic(ref.knn, (points, queries[:REFERENCE_QUERIES], 8),
                                      rounds=3, iterations=1)
    assert distances.shape == (REFERENCE_QUERIES, 8)


@pytest.mark.benchmark(group="kdtree radius 2 mm, 22.5k queries on 35k, all threads")
def test_radius_tpscore(benchmark, scan, trees):
    _, queries = scan
    ours, theirs = trees
    offsets, indices, _ = benchmark(ours.query_radius_csr, queries, 2.0)
    want = theirs.query_ball_point(queries, 2.0, workers=-1, return_length=True)
    assert np.array_equal(np.diff(offsets), want)


@pytest.mark.benchmark(group="kdtree radius 2 mm, 22.5k queries on 35k, all threads")
def test_radius_scipy_ckdtree(benchmark, scan, trees):
    _, queries = scan
    _, theirs = trees
    result = benchmark(theirs.query_ball_point, queries, 2.0, workers=-1)
    assert len(result) == N_QUERIES


# --------------------------------------------------------------- mesh surface


@pytest.fixture(scope="module")
def surface(face_mesh):
    vertices, faces, _ = face_mesh
    return tpscore.MeshSurface(vertices, faces)


@pytest.mark.benchmark(group="closest point, 22.5k queries on 20k triangles")
def test_closest_point_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    # One thread: trimesh's query is serial, so like is compared with like.
    result = benchmark(surface.closest_point, queries, workers=1)
    sample = slice(0, N_QUERIES, 45)  # 500 rows checked against brute force
    want = ref.closest_point_on_mesh(vertices, faces, queries[sample])
    np.testing.assert_allclose(result.distances[sample], want[3], atol=1e-9)


@pytest.mark.benchmark(group="closest point, 22.5k queries on 20k triangles")
def test_closest_point_trimesh(benchmark, face_mesh):
    pytest.importorskip("rtree", reason="trimesh.proximity.closest_point needs rtree")
    import trimesh

    vertices, faces, queries = face_mesh
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.triangles_tree  # build its r-tree outside the timing, as MeshSurface is
    _, distances, _ = benchmark.pedantic(trimesh.proximity.closest_point, (mesh, queries),
                                         rounds=1, iterations=1)
    ours = tpscore.MeshSurface(vertices, faces).closest_point(queries).distances
    # trimesh computes the same exact distance, in float64.
    np.testing.assert_allclose(distances, ours, atol=1e-7)


@pytest.mark.benchmark(group="closest point, 500 queries on 20k triangles, vs NumPy brute force")
def test_closest_point_small_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    subset = queries[::45]
    result = benchmark(surface.closest_point, subset, workers=1)
    want = ref.closest_point_on_mesh(vertices, faces, subset)
    np.testing.assert_allclose(result.distances, want[3], atol=1e-9)


@pytest.mark.benchmark(group="closest point, 500 queries on 20k triangles, vs NumPy brute force")
def test_closest_point_small_numpy_reference(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    result = benchmark.pedantic(ref.closest_point_on_mesh, (vertices, faces, queries[::45]),
                                rounds=2, iterations=1)
    assert np.isfinite(result[3]).all()


@pytest.mark.benchmark(group="rays both ways, 500 rays on 20k triangles, vs NumPy brute force")
def test_rays_small_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    origins = queries[::45]
    directions = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    hits = benchmark(surface.intersect_rays, origins, directions, both_directions=True,
                     workers=1)
    want = ref.intersect_rays(vertices, faces, origins, directions, np.inf, True)
    assert np.array_equal(hits.hit, want[0]) and hits.hit.mean() > 0.9
    np.testing.assert_allclose(hits.distances[hits.hit], want[1][want[0]], atol=1e-9)


@pytest.mark.benchmark(group="rays both ways, 500 rays on 20k triangles, vs NumPy brute force")
def test_rays_small_numpy_reference(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    origins = queries[::45]
    directions = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    hits = benchmark.pedantic(ref.intersect_rays,
                              (vertices, faces, origins, directions, np.inf, True),
                              rounds=2, iterations=1)
    assert hits[0].mean() > 0.9
