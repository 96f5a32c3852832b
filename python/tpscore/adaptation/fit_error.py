"""Error estimates of a template fitted to a scan, without ground truth.

* the distance error Ed: the weighted mean squared distance from each template
  vertex to its nearest compatible scan vertex (normals within 90 degrees, closer
  than a threshold); a vertex with no compatible scan vertex (over a hole, beyond the
  scan) gets weight 0;
* the marker error Em: the mean squared distance between marker pairs that took no
  part in the fit (held-out landmarks, for example);
* E = alpha Ed + beta Em, which the multilevel fit follows to its minimum
  (:class:`LevelScorer` computes all three for each level).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..geometry import robust_scale, vertex_adjacency
from ..mesh import vertex_normals
from ..spatial import KDTree
from .result import evaluate_fields

__all__ = ["DistanceError", "LevelScore", "LevelScorer", "distance_error", "marker_error", "combined_error",
           "surface_noise"]

# Nearest scan vertices examined for a compatible one; beyond 8 the nearest compatible
# vertex is almost always farther than the threshold anyway.
_CANDIDATES = 8


class DistanceError(NamedTuple):
    """The distance error Ed and what went into it."""

    value: float
    """Ed, mm^2 (NaN when no vertex has a compatible scan vertex)."""
    distances: np.ndarray
    """(n,) distance to the nearest compatible scan vertex, mm; NaN where none."""
    coverage: float
    """Fraction of the (positively weighted) template vertices that have one."""


def distance_error(vertices, normals, scan_tree: KDTree, scan_normals, *, threshold: float,
                   weights=None, scan_rim=None) -> DistanceError:
    """Ed = sum_i w_i d_i^2 / sum_i w_i over vertices with a compatible scan vertex.

    Parameters
    ----------
    vertices, normals : (n, 3) ndarray
        Fitted template vertices (mm) and their unit normals.
    scan_tree : KDTree
        Over the scan vertices.
    scan_normals : (N, 3) ndarray
        Unit normals of the scan vertices.
    threshold : float
        Largest distance (mm) at which a scan vertex counts.
    weights : (n,) ndarray, optional
        Non-negative per-vertex (region) weights; 1 by default.
    scan_rim : (N,) bool ndarray, optional
        Scan vertices on its open boundary. A template vertex whose nearest compatible
        scan vertex is on the rim lies beyond the scan or over a hole: weight 0.
    """
    n = len(vertices)
    weights = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    k = min(_CANDIDATES, scan_tree.n)
    distances, indices = scan_tree.query(vertices, k=k, distance_upper_bound=threshold)
    distances, indices = distances.reshape(n, k), indices.reshape(n, k)
    found = np.isfinite(distances)
    safe = np.where(found, indices, 0)
    compatible = found & (np.einsum("ijk,ik->ij", scan_normals[safe], normals) > 0.0)
    first = np.argmax(compatible, axis=1)
    has = compatible[np.arange(n), first]
    if scan_rim is not None:
        has &= ~np.asarray(scan_rim, dtype=bool)[safe[np.arange(n), first]]
    nearest = np.where(has, distances[np.arange(n), first], np.nan)
    active = weights > 0
    used = has & active
    total = weights[used].sum()
    value = float((weights[used] * nearest[used] ** 2).sum() / total) if total > 0 else float("nan")
    coverage = float(used.sum() / max(active.sum(), 1))
    return DistanceError(value, nearest, coverage)


def marker_error(predicted, target) -> float:
    """Mean squared distance (mm^2) over marker pairs present in both; NaN if none."""
    predicted = np.asarray(predicted, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    both = np.isfinite(predicted).all(axis=1) & np.isfinite(target).all(axis=1)
    if not both.any():
        return float("nan")
    return float(np.mean(np.sum((predicted[both] - target[both]) ** 2, axis=1)))


def combined_error(distance: float, marker: float, alpha: float = 1.0, beta: float = 1.0) -> float:
    """E = alpha Ed + beta Em; a NaN term (nothing to measure) counts as absent."""
    terms = [w * v for w, v in ((alpha, distance), (beta, marker)) if np.isfinite(v) and w > 0]
    return float(sum(terms)) if terms else float("nan")


def surface_noise(vertices, faces, normals) -> float:
    """Robust estimate of the noise (mm, one standard deviation) along a mesh's normals.

    Each vertex is compared with the mean of its edge neighbours along its normal (the
    umbrella operator); for independent noise of deviation s that offset has deviation
    s * sqrt(1 + 1/deg). The median absolute offset (x 1.4826) ignores the few vertices
    on sharp features. On a smooth surface sampled finely the curvature adds little.
    """
    adjacency = vertex_adjacency(len(vertices), faces)
    if adjacency.nnz == 0:
        return float("nan")
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    inner = degree >= 3
    mean = (adjacency @ vertices)[inner] / degree[inner, None]
    offset = np.abs(np.einsum("ij,ij->i", vertices[inner] - mean, normals[inner]))
    offset /= np.sqrt(1.0 + 1.0 / degree[inner])
    return robust_scale(offset) if len(offset) else float("nan")


class LevelScore(NamedTuple):
    """The error figures of one level's fit (Ed and Em in the scan's mm^2)."""

    distance_error: float
    marker_error: float
    error: float
    coverage: float
    normals: np.ndarray
    """(n, 3) unit vertex normals of the fitted template (the next level pairs along them)."""


class LevelScorer:
    """Ed, Em, E and the coverage of a fitted template, the same way at every level.

    Parameters
    ----------
    template_faces : (m, 3) int ndarray
    scan_tree : KDTree
        Over the scan vertices (template frame).
    scan_normals : (N, 3) ndarray
        Their unit normals.
    scan_rim : (N,) bool ndarray
        Scan vertices on its open boundary.
    threshold : float
        Ed's compatibility distance (mm, template frame).
    vertex_weights : (n,) ndarray or None
        Ed's per-vertex weights.
    markers : ((m, 3), (m, 3)) ndarray
        Marker pairs (template points, calibrated scan points); m may be 0.
    covered : (n,) bool ndarray
        The vertices over which the coverage is judged.
    scale : float
        The calibration's scale: the errors are reported in the scan's mm^2.
    alpha, beta : float
        Weights of Ed and Em in E.
    """

    def __init__(self, template_faces, scan_tree: KDTree, scan_normals, scan_rim, *, threshold: float,
                 vertex_weights, markers, covered, scale: float, alpha: float, beta: float):
        self.template_faces = template_faces
        self.scan_tree = scan_tree
        self.scan_normals = scan_normals
        self.scan_rim = scan_rim
        self.threshold = threshold
        self.vertex_weights = vertex_weights
        self.marker_template, self.marker_scan = markers
        weights = np.ones(len(covered)) if vertex_weights is None else vertex_weights
        self.active = covered & (weights > 0)
        self.scale = scale
        self.alpha, self.beta = alpha, beta

    def __call__(self, fields, deformed: np.ndarray) -> LevelScore:
        """Score the fit `deformed` (the template's vertices) made by the level `fields`."""
        normals = vertex_normals(deformed, self.template_faces)
        ed = distance_error(deformed, normals, self.scan_tree, self.scan_normals, threshold=self.threshold,
                            weights=self.vertex_weights, scan_rim=self.scan_rim)
        em = (marker_error(evaluate_fields(fields, self.marker_template), self.marker_scan)
              if len(self.marker_template) else np.nan)
        coverage = float(np.isfinite(ed.distances[self.active]).mean()) if self.active.any() else 0.0
        ed_value, em_value = ed.value / self.scale**2, em / self.scale**2
        return LevelScore(ed_value, em_value, combined_error(ed_value, em_value, self.alpha, self.beta), coverage,
                          normals)
