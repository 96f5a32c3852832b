"""Spatial queries: tpscore's kd-tree and mesh surface queries against SciPy, libigl,
trimesh and the NumPy reference, at the sizes of the face pipeline (a ~35k-point scan,
a 150 x 150 grid of queries, a 150 x 150 face mesh of 44,402 triangles).

Each group compares like with like: the kd-tree groups fix the thread count of both
sides (workers=1 or workers=-1); the closest-point groups run tpscore and libigl on
all threads (libigl's AABB queries are threaded by its own parallel_for), and build
each side's tree once, outside the timing, except in the group that times the build.
The brute-force references scan every point or triangle for every query, so they run
on a few hundred queries, in groups of their own that hold tpscore and the peer too.
Correctness is asserted inside every benchmark.
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
def test_query_small_scipy_ckdtree(benchmark, scan, trees):
    points, queries = scan
    _, theirs = trees
    distances, _ = benchmark(theirs.query, queries[:REFERENCE_QUERIES], 8, workers=1)
    want_d, _ = ref.knn(points, queries[:REFERENCE_QUERIES], 8)
    np.testing.assert_allclose(distances, want_d, rtol=1e-13)


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


def face_grid_mesh(side):
    """A side x side grid mesh of a face-like height field (a broad dome and a nose),
    two triangles per quad, as the preprocessing stage produces."""
    x, y = np.meshgrid(np.linspace(-75, 75, side), np.linspace(-90, 90, side))
    z = 60 * np.exp(-(x**2 / (2 * 55**2) + y**2 / (2 * 70**2))) + 18 * np.exp(
        -(x**2 / (2 * 9**2) + (y + 5) ** 2 / (2 * 16**2)))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    index = np.arange(side * side).reshape(side, side)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return vertices, faces


@pytest.fixture(scope="module")
def face_mesh():
    """The 150 x 150 face mesh (44,402 triangles) and 22,500 queries near it: its own
    vertices moved by 2 mm of noise, in grid order (as a registration queries a scan)."""
    vertices, faces = face_grid_mesh(150)
    queries = vertices + np.random.default_rng(0).normal(scale=2.0, size=vertices.shape)
    return vertices, faces, queries


@pytest.fixture(scope="module")
def surface(face_mesh):
    vertices, faces, _ = face_mesh
    return tpscore.MeshSurface(vertices, faces)


def _igl():
    return pytest.importorskip("igl", reason="libigl (pip install libigl, the bench extra) is the peer")


CLOSEST = "closest point, 22.5k queries on a 150x150 face mesh (44k triangles), tree built"
CLOSEST_BUILD = "closest point, 22.5k queries on a 150x150 face mesh, building the tree included"
CLOSEST_SMALL = "closest point, 500 queries on a 150x150 face mesh, vs NumPy brute force"


def _check_distances(distances, vertices, faces, queries, rows=slice(0, N_QUERIES, 45)):
    want = ref.closest_point_on_mesh(vertices, faces, queries[rows])
    np.testing.assert_allclose(distances[rows], want[3], rtol=0, atol=1e-9)  # 500 rows


@pytest.mark.benchmark(group=CLOSEST)
def test_closest_point_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    result = benchmark(surface.closest_point, queries)
    _check_distances(result.distances, vertices, faces, queries)


@pytest.mark.benchmark(group=CLOSEST)
def test_closest_point_libigl_aabb(benchmark, face_mesh):
    igl = _igl()
    vertices, faces, queries = face_mesh
    tree = igl.AABB()
    tree.init(vertices, faces)
    squared, _, _ = benchmark(tree.squared_distance, vertices, faces, queries)
    _check_distances(np.sqrt(squared), vertices, faces, queries)


@pytest.mark.benchmark(group=CLOSEST)
def test_closest_point_trimesh(benchmark, face_mesh):
    pytest.importorskip("rtree", reason="trimesh.proximity.closest_point needs rtree")
    import trimesh

    vertices, faces, queries = face_mesh
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.triangles_tree  # build its r-tree outside the timing, as the others' trees are
    _, distances, _ = benchmark.pedantic(trimesh.proximity.closest_point, (mesh, queries),
                                         rounds=1, iterations=1)
    _check_distances(distances, vertices, faces, queries)


def _tpscore_build_and_query(vertices, faces, queries):
    return tpscore.MeshSurface(vertices, faces).closest_point(queries)


def _time_build_and_query_tpscore(benchmark, vertices, faces, queries):
    result = benchmark(_tpscore_build_and_query, vertices, faces, queries)
    _check_distances(result.distances, vertices, faces, queries)


def _time_build_and_query_libigl(benchmark, vertices, faces, queries):
    igl = _igl()
    squared, _, _ = benchmark(igl.point_mesh_squared_distance, queries, vertices, faces)
    _check_distances(np.sqrt(squared), vertices, faces, queries)


@pytest.mark.benchmark(group=CLOSEST_BUILD)
def test_closest_point_with_build_tpscore(benchmark, face_mesh):
    _time_build_and_query_tpscore(benchmark, *face_mesh)


@pytest.mark.benchmark(group=CLOSEST_BUILD)
def test_closest_point_with_build_libigl(benchmark, face_mesh):
    _time_build_and_query_libigl(benchmark, *face_mesh)


MOVED = "a tree for a moved 150x150 face mesh (an expression's frame), then 22.5k closest points"


def _moved_face(vertices):
    # an expression's worth of smooth motion (a few mm) with a small head turn
    turn = np.radians(3.0)
    rotation = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    return vertices @ rotation.T + 4.0 * np.sin(vertices[:, [1, 0, 2]] / 25.0)


@pytest.mark.benchmark(group=MOVED)
def test_moved_tree_refitted_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    moved = _moved_face(vertices)
    result = benchmark(lambda: surface.moved(moved).closest_point(queries))
    _check_distances(result.distances, moved, faces, queries)


@pytest.mark.benchmark(group=MOVED)
def test_moved_tree_rebuilt_tpscore(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    _time_build_and_query_tpscore(benchmark, _moved_face(vertices), faces, queries)


@pytest.mark.benchmark(group=MOVED)
def test_moved_tree_rebuilt_libigl(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    _time_build_and_query_libigl(benchmark, _moved_face(vertices), faces, queries)


@pytest.mark.benchmark(group=CLOSEST_SMALL)
def test_closest_point_small_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    subset = queries[::45]
    result = benchmark(surface.closest_point, subset)
    want = ref.closest_point_on_mesh(vertices, faces, subset)
    np.testing.assert_allclose(result.distances, want[3], rtol=0, atol=1e-9)


@pytest.mark.benchmark(group=CLOSEST_SMALL)
def test_closest_point_small_libigl_aabb(benchmark, face_mesh):
    igl = _igl()
    vertices, faces, queries = face_mesh
    subset = queries[::45]
    tree = igl.AABB()
    tree.init(vertices, faces)
    squared, _, _ = benchmark(tree.squared_distance, vertices, faces, subset)
    want = ref.closest_point_on_mesh(vertices, faces, subset)
    np.testing.assert_allclose(np.sqrt(squared), want[3], rtol=0, atol=1e-9)


@pytest.mark.benchmark(group=CLOSEST_SMALL)
def test_closest_point_small_numpy_reference(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    result = benchmark.pedantic(ref.closest_point_on_mesh, (vertices, faces, queries[::45]),
                                rounds=2, iterations=1)
    assert np.isfinite(result[3]).all()


@pytest.mark.benchmark(group="rays both ways, 500 rays on a 150x150 face mesh, vs NumPy brute force")
def test_rays_small_tpscore(benchmark, face_mesh, surface):
    vertices, faces, queries = face_mesh
    origins = queries[::45]
    directions = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    hits = benchmark(surface.intersect_rays, origins, directions, both_directions=True,
                     workers=1)
    want = ref.intersect_rays(vertices, faces, origins, directions, np.inf, True)
    assert np.array_equal(hits.hit, want[0]) and hits.hit.mean() > 0.9
    np.testing.assert_allclose(hits.distances[hits.hit], want[1][want[0]], atol=1e-9)


@pytest.mark.benchmark(group="rays both ways, 500 rays on a 150x150 face mesh, vs NumPy brute force")
def test_rays_small_numpy_reference(benchmark, face_mesh):
    vertices, faces, queries = face_mesh
    origins = queries[::45]
    directions = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    hits = benchmark.pedantic(ref.intersect_rays,
                              (vertices, faces, origins, directions, np.inf, True),
                              rounds=2, iterations=1)
    assert hits[0].mean() > 0.9
