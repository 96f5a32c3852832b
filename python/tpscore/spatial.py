"""Spatial queries: a kd-tree over points, and closest-point and ray queries on meshes.

Every query here is exact (no approximation parameter): the compiled core answers
what a brute-force search would, only faster. Distances are in the units of the
input coordinates (mm throughout tpscore).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import _core
from ._threads import as_workers
from ._validation import (Immutable, MAX_DENSE_ELEMENTS, MAX_POINTS, MAX_SPARSE_ENTRIES, as_count, as_faces, as_points,
                          check_rows, gib, row_count)

__all__ = [
    "KDTree",
    "MeshSurface",
    "ClosestPoints",
    "RayHits",
    "closest_point_on_mesh",
]


#: The most points a :class:`KDTree` indexes: 2 GiB of float64 coordinates.
MAX_TREE_POINTS = MAX_POINTS

#: The most (query, point) pairs :meth:`KDTree.query_radius_csr` returns: its int64
#: indices and float64 distances each stay within 2 GiB.
MAX_RADIUS_PAIRS = MAX_SPARSE_ENTRIES


# In the first, coarse count of a radius query's size, a node of the tree of at most
# this many points that the ball touches counts whole: an upper bound found in a few
# percent of the query's time (a ball of 50 neighbours touches some nodes of 256).
_COARSE_NODE_POINTS = 256


def _pairs_beyond(tree, queries: np.ndarray, radius: float, workers: int, limit: int) -> int | None:
    """The number of (query, point) pairs within `radius` on the core's kd-tree `tree`
    when it passes `limit`, else None, counted before anything is collected: nothing
    when m * n cannot pass it, then a cheap upper bound, the exact count only when the
    bound passes."""
    if len(queries) * tree.size <= limit:
        return None
    if int(tree.count_radius(queries, radius, workers, _COARSE_NODE_POINTS).sum()) <= limit:
        return None
    pairs = int(tree.count_radius(queries, radius, workers).sum())
    return pairs if pairs > limit else None


def _int64(array: np.ndarray) -> np.ndarray:
    """The core's int64 arrays as NumPy's canonical int64 type (a view, no copy).

    The core fills C ``int64_t`` buffers, which NumPy may label ``longlong``, a distinct
    (if identical) type from ``np.int64`` on some platforms.
    """
    return array.view(np.int64)


def _check_slots(m: int | None, k: int) -> None:
    """Refuse k neighbours of m query points beyond the dense-array budget."""
    if m is not None and m * k > MAX_DENSE_ELEMENTS:
        raise ValueError(
            f"points: k = {k} neighbours for {m:,} points would need {m * k:,} output slots "
            f"({gib(16.0 * m * k)} of distances and indices; limit {MAX_DENSE_ELEMENTS:,}); "
            "query fewer points at a time or use query_radius_csr")


def _radius(value, name: str = "r") -> float:
    try:
        radius = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if np.isnan(radius) or radius < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return radius


class KDTree(Immutable):
    """Exact nearest-neighbour and radius queries over a fixed set of 3D points.

    A static kd-tree (median split on the widest axis, leaves of ``leaf_size`` points)
    built once in the compiled core. The tree is immutable, so several threads may query
    it at once; every query releases the GIL.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        The points to index (mm), 1 <= n <= :data:`MAX_TREE_POINTS` (89,478,485: 2 GiB
        of coordinates, refused before anything is copied), finite. Copied.
    leaf_size : int, default 16
        Points per leaf; smaller leaves mean deeper trees and fewer distance tests.

    Notes
    -----
    Neighbours are ranked by distance and, among points at exactly the same distance, by
    index (smaller first); results are therefore deterministic and independent of the
    thread count. Output shapes follow :class:`scipy.spatial.cKDTree`.

    Examples
    --------
    >>> tree = KDTree([[0, 0, 0], [1, 0, 0], [0, 2, 0]])
    >>> tree.query([[0.9, 0, 0]])
    (array([0.1]), array([1]))
    """

    def __init__(self, points, leaf_size: int = 16):
        # judged before the points are converted: a broadcast view of 10^9 points costs
        # nothing until it is copied
        check_rows(points, "points", MAX_TREE_POINTS, "a kd-tree copies its points")
        # A private copy: as_points may return the caller's own array, which must stay
        # writable for them and must not change under the tree.
        points = as_points(points, "points", allow_empty=False).copy()
        self._leaf_size = as_count(leaf_size, "leaf_size")
        points.setflags(write=False)
        self._points = points
        self._tree = _core.KDTree(points, self._leaf_size)

    def __reduce__(self):
        # the tree is rebuilt from its points: the same build gives the same tree
        return KDTree, (self._points, self._leaf_size)

    @property
    def points(self) -> np.ndarray:
        """The indexed points, (n, 3) float64, read-only."""
        return self._points

    @property
    def n(self) -> int:
        """Number of indexed points."""
        return len(self._points)

    def __len__(self) -> int:
        return len(self._points)

    def __repr__(self) -> str:
        return f"KDTree(n={self.n}, leaf_size={self._leaf_size})"

    def query(self, points, k: int = 1, *, distance_upper_bound: float = np.inf,
              workers: int = -1):
        """The k nearest indexed points of each query point.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points (mm), finite.
        k : int, default 1
            Number of neighbours, >= 1. May exceed n (the extra slots are "missing").
        distance_upper_bound : float, default inf
            Only points strictly closer than this count as neighbours (mm), >= 0.
        workers : int, default -1
            Threads to use: -1 for all (``tpscore.num_threads()``), 1 for serial.

        Returns
        -------
        distances : ndarray, shape (m,) if k == 1 else (m, k)
            Euclidean distances (mm), ascending along each row.
        indices : ndarray of int64, shape (m,) if k == 1 else (m, k)
            Row indices into :attr:`points`.

        Missing neighbours (fewer than k points within the bound) have distance ``inf``
        and index ``n``, exactly as :meth:`scipy.spatial.cKDTree.query` reports them.
        """
        k = as_count(k, "k")
        _check_slots(row_count(points), k)  # before the points are converted
        queries = as_points(points, "points")
        bound = _radius(distance_upper_bound, "distance_upper_bound")
        _check_slots(len(queries), k)
        distances, indices = self._tree.query(queries, k, bound, as_workers(workers))
        indices = _int64(indices)
        # cKDTree's convention for a missing neighbour: index n, one past the last point.
        indices[indices < 0] = self.n
        if k == 1:
            return distances.reshape(-1), indices.reshape(-1)
        return distances, indices

    def query_radius_csr(self, points, r: float, *, sort: bool = False, workers: int = -1):
        """All indexed points within distance ``r`` of each query point, in CSR form.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points (mm), finite.
        r : float
            Radius (mm), >= 0; a point at distance exactly ``r`` is included.
        sort : bool, default False
            Sort each query's neighbours by distance (then index); otherwise their order
            is arbitrary but deterministic.
        workers : int, default -1
            Threads to use: -1 for all, 1 for serial.

        Returns
        -------
        offsets : ndarray of int64, shape (m + 1,)
            The neighbours of query i are ``indices[offsets[i]:offsets[i + 1]]``.
        indices : ndarray of int64, shape (offsets[-1],)
        distances : ndarray of float64, shape (offsets[-1],)
            Distances (mm) matching ``indices``.

        Raises
        ------
        ValueError
            If the query would return more than :data:`MAX_RADIUS_PAIRS` pairs (2**28:
            each of the two arrays within 2 GiB). They are counted before anything is
            collected (only when m * n passes the limit: a cheap upper bound first,
            then :meth:`count_radius`).
        """
        queries = as_points(points, "points")
        radius = _radius(r, "r")
        if not np.isfinite(radius):
            raise ValueError("r must be finite; use query with k=n for all points")
        workers = as_workers(workers)
        pairs = _pairs_beyond(self._tree, queries, radius, workers, MAX_RADIUS_PAIRS)
        if pairs is not None:
            raise ValueError(
                f"r: {len(queries):,} query points have {pairs:,} neighbours within r = {radius:g} mm, "
                f"more than the limit of {MAX_RADIUS_PAIRS:,} pairs a radius query returns (its index "
                f"and distance arrays would take {gib(8.0 * pairs)} each); use a smaller r or pass "
                "fewer points at a time")
        offsets, indices, distances = self._tree.query_radius(queries, radius, bool(sort),
                                                              workers)
        return _int64(offsets), _int64(indices), distances

    def count_radius(self, points, r: float, *, workers: int = -1) -> np.ndarray:
        """The number of indexed points within distance ``r`` of each query point.

        What :meth:`query_radius_csr` would find, counted without collecting it (like
        ``return_length=True`` of :meth:`scipy.spatial.cKDTree.query_ball_point`), so
        the size of a radius query can be judged before it is made.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points (mm), finite.
        r : float
            Radius (mm), >= 0, finite; a point at distance exactly ``r`` counts.
        workers : int, default -1
            Threads to use: -1 for all, 1 for serial.

        Returns
        -------
        ndarray of int64, shape (m,)
        """
        queries = as_points(points, "points")
        radius = _radius(r, "r")
        if not np.isfinite(radius):
            raise ValueError(f"r must be finite; every query point has all {self.n} points within r = inf")
        return _int64(self._tree.count_radius(queries, radius, as_workers(workers)))

    def query_radius(self, points, r: float, *, return_distance: bool = False,
                     sort: bool = False, workers: int = -1):
        """All indexed points within distance ``r`` of each query point.

        Parameters as in :meth:`query_radius_csr`.

        Returns
        -------
        indices : list of m int64 arrays
            The neighbours of each query point.
        distances : list of m float64 arrays
            Only with ``return_distance=True``: their distances (mm).
        """
        offsets, indices, distances = self.query_radius_csr(points, r, sort=sort, workers=workers)
        if len(offsets) == 1:  # no queries (np.split would return one empty piece)
            return ([], []) if return_distance else []
        split = offsets[1:-1]
        index_lists = np.split(indices, split)
        if return_distance:
            return index_lists, np.split(distances, split)
        return index_lists

    def snap(self, points, *, workers: int = -1):
        """Snap each query point to its nearest indexed point.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points (mm), finite.

        Returns
        -------
        indices : ndarray of int64, shape (m,)
            Index of the nearest indexed point (ties: the smaller index).
        positions : ndarray, shape (m, 3)
            Its coordinates (mm).
        """
        _, indices = self.query(points, 1, workers=workers)
        return indices, self._points[indices]


class ClosestPoints(NamedTuple):
    """Closest points on a mesh, one row per query point."""

    points: np.ndarray
    """(m, 3) the closest point of the surface (mm)."""
    triangles: np.ndarray
    """(m,) int64 index of the triangle it lies on (ties: the smaller index)."""
    barycentric: np.ndarray
    """(m, 3) its weights on that triangle's corners, in the order of ``faces``."""
    distances: np.ndarray
    """(m,) distance from the query point (mm)."""


class RayHits(NamedTuple):
    """Nearest ray-mesh intersections, one row per ray; misses hold NaN and -1."""

    hit: np.ndarray
    """(m,) bool, whether the ray met the mesh within the distance limit."""
    distances: np.ndarray
    """(m,) signed distance t along the unit direction (mm); negative for a hit behind the
    origin (only with ``both_directions``); NaN for a miss."""
    points: np.ndarray
    """(m, 3) the hit point (mm), NaN for a miss."""
    triangles: np.ndarray
    """(m,) int64 triangle hit, -1 for a miss."""
    barycentric: np.ndarray
    """(m, 3) the hit's weights on the triangle's corners, NaN for a miss."""


class MeshSurface(Immutable):
    """A triangle mesh prepared for exact closest-point and ray queries.

    Builds a bounding-volume hierarchy over the triangles once; queries then cost about
    log(number of triangles) each instead of a scan of every triangle. Answers are exact:
    the same as testing every triangle, with ties going to the smaller triangle index.
    Immutable, so several threads may query it at once; every query releases the GIL.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions (mm), finite. Copied.
    faces : array_like of int, shape (t, 3)
        Triangles as vertex indices in [0, n), t >= 1. Degenerate (zero-area) triangles
        are allowed: for closest points they act as their edges; rays never hit them.
    """

    def __init__(self, vertices, faces):
        vertices = as_points(vertices, "vertices", allow_empty=False).copy()
        faces = as_faces(faces, len(vertices), "faces").copy()
        if len(faces) == 0:
            raise ValueError("faces is empty; a mesh needs at least one triangle")
        if len(faces) >= 2**31:
            raise ValueError(f"faces has {len(faces)} triangles; at most 2**31 - 1 are supported")
        vertices.setflags(write=False)
        faces.setflags(write=False)
        self._vertices = vertices
        self._faces = faces
        self._surface = _core.MeshSurface(vertices, faces)

    def __reduce__(self):
        return MeshSurface, (self._vertices, self._faces)

    def moved(self, vertices) -> "MeshSurface":
        """The same triangles over moved vertices, without building a new tree.

        The tree's grouping of the triangles is kept and its boxes fitted around the
        new positions, at a fraction of a build's cost. Answers stay exact (the same as
        ``MeshSurface(vertices, self.faces)``'s, bit for bit) whatever the motion; queries
        slow down only as far as the motion scrambles the grouping, which a rigid,
        similarity or smooth motion (a frame change, a face's expression) does not.

        Parameters
        ----------
        vertices : array_like, shape (n, 3)
            The new positions (mm) of this surface's n vertices, finite. Copied.
        """
        vertices = as_points(vertices, "vertices", allow_empty=False).copy()
        if vertices.shape != self._vertices.shape:
            raise ValueError(f"vertices must have this surface's shape {self._vertices.shape}, "
                             f"got {vertices.shape}")
        vertices.setflags(write=False)
        moved = MeshSurface.__new__(MeshSurface)
        moved._vertices = vertices
        moved._faces = self._faces
        moved._surface = self._surface.moved(vertices, self._faces)
        return moved

    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) float64 vertex positions, read-only."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(t, 3) int64 triangles, read-only."""
        return self._faces

    def __repr__(self) -> str:
        return f"MeshSurface(vertices={len(self._vertices)}, triangles={len(self._faces)})"

    def closest_point(self, points, *, workers: int = -1) -> ClosestPoints:
        """The closest point of the surface to each query point.

        Parameters
        ----------
        points : array_like, shape (m, 3)
            Query points (mm), finite.
        workers : int, default -1
            Threads to use: -1 for all, 1 for serial.

        Returns
        -------
        ClosestPoints
            ``points`` (m, 3), ``triangles`` (m,), ``barycentric`` (m, 3),
            ``distances`` (m,).
        """
        queries = as_points(points, "points")
        closest, triangles, barycentric, distances = self._surface.closest_point(
            queries, as_workers(workers))
        return ClosestPoints(closest, _int64(triangles), barycentric, distances)

    def intersect_rays(self, origins, directions, *, max_distance: float = np.inf,
                       both_directions: bool = False, workers: int = -1) -> RayHits:
        """The nearest intersection of each ray with the surface.

        Parameters
        ----------
        origins : array_like, shape (m, 3)
            Ray origins (mm), finite.
        directions : array_like, shape (m, 3)
            Ray directions, finite and non-zero; normalised here, so distances are in mm
            whatever their length.
        max_distance : float, default inf
            Hits farther than this from the origin (mm) are ignored; >= 0.
        both_directions : bool, default False
            Also look behind the origin (negative distances) and take the hit nearest
            to the origin either side, as when a point is projected onto a surface along
            its normal without knowing on which side the surface lies.
        workers : int, default -1
            Threads to use: -1 for all, 1 for serial.

        Returns
        -------
        RayHits
            ``hit`` (m,), ``distances`` (m,), ``points`` (m, 3), ``triangles`` (m,),
            ``barycentric`` (m, 3); NaN (and triangle -1) where a ray misses.

        Notes
        -----
        The triangle boundary counts as inside, so a ray through a shared edge hits (the
        triangle with the smaller index on a tie). A ray lying in a triangle's plane does
        not hit that triangle.
        """
        origins = as_points(origins, "origins")
        directions = as_points(directions, "directions")
        if len(directions) != len(origins):
            raise ValueError(
                f"directions must have one row per origin: {len(directions)} rows for "
                f"{len(origins)} origins"
            )
        lengths = np.sqrt(np.einsum("ij,ij->i", directions, directions))
        zero = np.flatnonzero(~(lengths > 0))
        if len(zero):
            raise ValueError(
                f"directions has zero length at row {zero[0]} ({len(zero)} row(s) in all); "
                "a ray needs a direction"
            )
        unit = directions / lengths[:, None]
        limit = _radius(max_distance, "max_distance")
        hit, t, points, triangles, barycentric = self._surface.intersect_rays(
            origins, unit, limit, bool(both_directions), as_workers(workers))
        return RayHits(hit, t, points, _int64(triangles), barycentric)


def closest_point_on_mesh(vertices, faces, points, *, workers: int = -1) -> ClosestPoints:
    """The closest point of a triangle mesh to each query point.

    A one-off shortcut for ``MeshSurface(vertices, faces).closest_point(points)``; build a
    :class:`MeshSurface` once to query the same mesh repeatedly.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions (mm).
    faces : array_like of int, shape (t, 3)
        Triangles as vertex indices.
    points : array_like, shape (m, 3)
        Query points (mm).

    Returns
    -------
    ClosestPoints
        ``points`` (m, 3), ``triangles`` (m,), ``barycentric`` (m, 3), ``distances`` (m,).
    """
    return MeshSurface(vertices, faces).closest_point(points, workers=workers)
