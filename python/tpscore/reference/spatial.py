"""Brute-force NumPy references for the spatial queries (tpscore.spatial).

Inputs are assumed validated: (n, 3) float64 points, (t, 3) int64 faces. Work is
chunked over query rows so that no temporary exceeds about ``_CHUNK_ELEMENTS`` values.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "squared_distances",
    "knn",
    "radius_neighbors",
]

# Pairs (query, point) per chunk: 2**22 pairs keep each float64 temporary near 32 MiB.
_CHUNK_PAIRS = 2**22


def _chunks(m: int, n: int):
    step = max(1, _CHUNK_PAIRS // max(n, 1))
    for start in range(0, m, step):
        yield start, min(m, start + step)


def squared_distances(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m, n) squared distances, summed x + y + z in that order.

    The summation order matches the compiled core, so exact ties are ties in both.
    """
    diff = queries[:, None, :] - points[None, :, :]
    return diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]


def knn(points: np.ndarray, queries: np.ndarray, k: int, distance_upper_bound: float = np.inf):
    """The k nearest points of each query: (distances (m, k), indices (m, k)).

    Neighbours are ranked by (squared distance, index); only points strictly closer than
    ``distance_upper_bound`` count; missing neighbours get distance inf and index n.
    """
    n, m = len(points), len(queries)
    distances = np.full((m, k), np.inf)
    indices = np.full((m, k), n, dtype=np.int64)
    bound2 = distance_upper_bound * distance_upper_bound
    take = min(k, n)
    for start, stop in _chunks(m, n):
        d2 = squared_distances(queries[start:stop], points)
        # lexsort's last key is the primary one: distance, then index on ties.
        order = np.lexsort((np.broadcast_to(np.arange(n), d2.shape), d2), axis=1)[:, :take]
        best = np.take_along_axis(d2, order, axis=1)
        valid = best < bound2
        distances[start:stop, :take] = np.where(valid, np.sqrt(best), np.inf)
        indices[start:stop, :take] = np.where(valid, order, n)
    return distances, indices


def radius_neighbors(points: np.ndarray, queries: np.ndarray, r: float):
    """For each query, (indices, distances) of the points with distance <= r, sorted by
    (distance, index)."""
    result = []
    r2 = r * r
    for start, stop in _chunks(len(queries), len(points)):
        d2 = squared_distances(queries[start:stop], points)
        for row in d2:
            inside = np.flatnonzero(row <= r2)
            order = np.lexsort((inside, row[inside]))
            result.append((inside[order], np.sqrt(row[inside][order])))
    return result
