"""Spatial queries: a kd-tree over points, and closest-point and ray queries on meshes.

Every query here is exact (no approximation parameter): the compiled core answers
what a brute-force search would, only faster. Distances are in the units of the
input coordinates (mm throughout tpscore).
"""
from __future__ import annotations

import numbers

import numpy as np

from . import _core
from ._validation import as_points

__all__ = [
    "KDTree",
]


def _int64(array: np.ndarray) -> np.ndarray:
    """The core's int64 arrays as NumPy's canonical int64 type (a view, no copy).

    The core fills C ``int64_t`` buffers, which NumPy may label ``longlong``, a distinct
    (if identical) type from ``np.int64`` on some platforms.
    """
    return array.view(np.int64)


def _workers(workers) -> int:
    """The thread count passed to the core: -1 (all) becomes 0, the core's 'default'."""
    if isinstance(workers, (bool, np.bool_)) or not isinstance(workers, numbers.Integral):
        raise ValueError(f"workers must be an integer (-1 for all threads), got {workers!r}")
    workers = int(workers)
    if workers == -1:
        return 0
    if workers < 1:
        raise ValueError(f"workers must be -1 (all threads) or >= 1, got {workers}")
    return workers


def _positive_int(value, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def _radius(value, name: str = "r") -> float:
    try:
        radius = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if np.isnan(radius) or radius < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return radius


class KDTree:
    """Exact nearest-neighbour and radius queries over a fixed set of 3D points.

    A static kd-tree (median split on the widest axis, leaves of ``leaf_size`` points)
    built once in the compiled core. The tree is immutable, so several threads may query
    it at once; every query releases the GIL.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        The points to index (mm), n >= 1, finite. Copied.
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
        # A private copy: as_points may return the caller's own array, which must stay
        # writable for them and must not change under the tree.
        points = as_points(points, "points", allow_empty=False).copy()
        self._leaf_size = _positive_int(leaf_size, "leaf_size")
        points.setflags(write=False)
        self._points = points
        self._tree = _core.KDTree(points, self._leaf_size)

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
        queries = as_points(points, "points")
        k = _positive_int(k, "k")
        bound = _radius(distance_upper_bound, "distance_upper_bound")
        distances, indices = self._tree.query(queries, k, bound, _workers(workers))
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
        """
        queries = as_points(points, "points")
        radius = _radius(r, "r")
        if not np.isfinite(radius):
            raise ValueError("r must be finite; use query with k=n for all points")
        offsets, indices, distances = self._tree.query_radius(queries, radius, bool(sort),
                                                              _workers(workers))
        return _int64(offsets), _int64(indices), distances

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
