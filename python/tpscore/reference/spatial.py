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
    "closest_point_on_triangles",
    "closest_point_on_mesh",
    "intersect_rays",
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


# ------------------------------------------------------------------ surface queries

# (query, triangle) pairs per chunk: each of the ~40 temporaries of the region test then
# stays near 6 MiB.
_CHUNK_TRIANGLE_PAIRS = 2**18

# Same thresholds as the compiled core (see closest_point.cpp for why).
_DEGENERATE_SIN2 = 1e-20
_PARALLEL_SIN = 1e-12


def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a, b):
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _closest_on_segment(p, p0, p1):
    e = p1 - p0
    e2 = _dot(e, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(e2 > 0, _dot(p - p0, e) / np.where(e2 > 0, e2, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return p0 + s[..., None] * e, s


def closest_point_on_triangles(p, a, b, c):
    """Closest point of each triangle (a, b, c) to p, all broadcast over leading axes.

    Returns (points (..., 3), barycentric (..., 3), squared distances (...)). Voronoi
    region test, every region evaluated and the right one selected; degenerate
    (sliver or zero-area) triangles fall back to the closest of their three edges.
    """
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    ab, ac = b - a, c - a
    normal = _cross(ab, ac)
    n2 = _dot(normal, normal)
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_ab = d1 / (d1 - d3)
        s_ac = d2 / (d2 - d6)
        s_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w_b = _dot(_cross(ap, ac), normal) / n2
        w_c = _dot(_cross(ab, ap), normal) / n2
    # Regions in the order the core tests them; np.select takes the first true one.
    regions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    weights_b = np.select(regions, [zero, one, s_ab, zero, zero, 1 - s_bc], w_b)
    weights_c = np.select(regions, [zero, zero, zero, one, s_ac, s_bc], w_c)
    weights_a = np.select(regions, [one, zero, 1 - s_ab, zero, 1 - s_ac, zero], 1 - w_b - w_c)
    points = np.select(
        [r[..., None] for r in regions],
        [a, b, a + s_ab[..., None] * ab, c, a + s_ac[..., None] * ac, b + s_bc[..., None] * (c - b)],
        a + w_b[..., None] * ab + w_c[..., None] * ac,
    )
    barycentric = np.stack([weights_a, weights_b, weights_c], axis=-1)

    degenerate = ~(n2 > _DEGENERATE_SIN2 * _dot(ab, ab) * _dot(ac, ac))
    if degenerate.any():
        edge_points, edge_bary, edge_d2 = None, None, None
        for p0, p1, order in ((a, b, (0, 1, 2)), (b, c, (1, 2, 0)), (c, a, (2, 0, 1))):
            point, s = _closest_on_segment(p[degenerate], p0[degenerate], p1[degenerate])
            bary = np.zeros(point.shape)
            bary[:, order[0]] = 1 - s
            bary[:, order[1]] = s
            diff = p[degenerate] - point
            d2_edge = _dot(diff, diff)
            if edge_points is None:
                edge_points, edge_bary, edge_d2 = point, bary, d2_edge
            else:
                better = d2_edge < edge_d2  # strict: the first edge wins a tie
                edge_points = np.where(better[:, None], point, edge_points)
                edge_bary = np.where(better[:, None], bary, edge_bary)
                edge_d2 = np.where(better, d2_edge, edge_d2)
        points[degenerate] = edge_points
        barycentric[degenerate] = edge_bary
    diff = p - points
    return points, barycentric, _dot(diff, diff)


def closest_point_on_mesh(vertices: np.ndarray, faces: np.ndarray, queries: np.ndarray):
    """Brute-force closest point of a triangle mesh to each query.

    Returns (points (m, 3), triangles (m,), barycentric (m, 3), distances (m,)); ties go
    to the smaller triangle index.
    """
    a, b, c = (vertices[faces[:, j]] for j in range(3))
    m, t = len(queries), len(faces)
    points = np.empty((m, 3))
    triangles = np.empty(m, dtype=np.int64)
    barycentric = np.empty((m, 3))
    distances = np.empty(m)
    step = max(1, _CHUNK_TRIANGLE_PAIRS // max(t, 1))
    for start in range(0, m, step):
        stop = min(m, start + step)
        p = queries[start:stop, None, :]
        chunk_points, chunk_bary, d2 = closest_point_on_triangles(p, a[None], b[None], c[None])
        best = np.argmin(d2, axis=1)  # the first minimum: ties go to the smaller index
        rows = np.arange(stop - start)
        points[start:stop] = chunk_points[rows, best]
        barycentric[start:stop] = chunk_bary[rows, best]
        distances[start:stop] = np.sqrt(d2[rows, best])
        triangles[start:stop] = best
    return points, triangles, barycentric, distances


def intersect_rays(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray,
                   directions: np.ndarray, max_distance: float = np.inf,
                   both_directions: bool = False):
    """Brute-force nearest hit of each ray origins[i] + t directions[i] on the mesh.

    Hits need 0 <= t <= max_distance (|t| <= max_distance, nearest by |t|, with
    ``both_directions``); the triangle boundary counts; rays parallel to a triangle (to a
    relative 1e-12) miss it. Returns (hit (m,), t (m,), points (m, 3), triangles (m,),
    barycentric (m, 3)) with NaN / -1 for misses; ties go to the smaller index.
    """
    a, b, c = (vertices[faces[:, j]] for j in range(3))
    e1, e2 = b - a, c - a
    m, t_count = len(origins), len(faces)
    hit = np.zeros(m, dtype=bool)
    t_out = np.full(m, np.nan)
    points = np.full((m, 3), np.nan)
    triangles = np.full(m, -1, dtype=np.int64)
    barycentric = np.full((m, 3), np.nan)
    step = max(1, _CHUNK_TRIANGLE_PAIRS // max(t_count, 1))
    for start in range(0, m, step):
        stop = min(m, start + step)
        o = origins[start:stop, None, :]
        d = directions[start:stop, None, :]
        pvec = _cross(d, e2[None])
        det = _dot(e1[None], pvec)
        scale = np.sqrt(_dot(d, d) * _dot(e1, e1)[None] * _dot(e2, e2)[None])
        valid = np.abs(det) > _PARALLEL_SIN * scale
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_det = 1.0 / det
            s = o - a[None]
            u = _dot(s, pvec) * inv_det
            qvec = _cross(s, e1[None])
            v = _dot(d, qvec) * inv_det
            t = _dot(e2[None], qvec) * inv_det
            valid &= (u >= 0) & (v >= 0) & (u + v <= 1)
        if not both_directions:
            valid &= t >= 0
        key = np.abs(t) if both_directions else t
        valid &= key <= max_distance
        key = np.where(valid, key, np.inf)
        best = np.argmin(key, axis=1)
        rows = np.arange(stop - start)
        found = valid[rows, best]
        idx = np.flatnonzero(found) + start
        tri = best[found]
        bu, bv = u[rows, best][found], v[rows, best][found]
        hit[idx] = True
        t_out[idx] = t[rows, best][found]
        triangles[idx] = tri
        barycentric[idx] = np.stack([1 - bu - bv, bu, bv], axis=1)
        points[idx] = (barycentric[idx, 0:1] * a[tri] + barycentric[idx, 1:2] * b[tri]
                       + barycentric[idx, 2:3] * c[tri])
    return hit, t_out, points, triangles, barycentric
