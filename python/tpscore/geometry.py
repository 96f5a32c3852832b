"""Small geometric and statistical helpers that every method shares: a mesh's edges and
adjacency, and the robust weights of the iterative fits (ICP, registration, adaptation).

Normals come from the compiled mesh operators (:func:`tpscore.mesh.face_normals`,
:func:`tpscore.mesh.vertex_normals`), closest points from :class:`tpscore.MeshSurface`.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["mesh_edges", "vertex_adjacency", "robust_scale", "tukey_weights", "off_surface"]

# The median absolute deviation times this is the standard deviation of a normal
# distribution: the robust scales below are in the units of a standard deviation.
MAD_TO_SIGMA = 1.4826


def mesh_edges(faces) -> np.ndarray:
    """(e, 2) int64 unique undirected edges of (m, 3) triangles, each as (low, high),
    sorted."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def vertex_adjacency(n_vertices: int, faces) -> sp.csr_matrix:
    """(n, n) symmetric 0/1 CSR matrix: 1 where two vertices share an edge."""
    edges = mesh_edges(faces)
    ones = np.ones(2 * len(edges))
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    return sp.csr_matrix((ones, (rows, cols)), shape=(n_vertices, n_vertices))


def robust_scale(residuals, floor: float = 0.0, *, centred: bool = False) -> float:
    """A standard deviation of residuals that ignores outliers: 1.4826 times the median
    of their absolute values (``centred``: of their deviations from their median), and
    at least ``floor``. Without residuals it is ``floor``."""
    values = np.asarray(residuals, dtype=np.float64).reshape(-1)
    if values.size == 0:
        return float(floor)
    if centred:
        values = values - np.median(values)
    return max(MAD_TO_SIGMA * float(np.median(np.abs(values))), float(floor))


def tukey_weights(residuals, cutoff) -> np.ndarray:
    """Tukey's biweight (1 - (r / cutoff)^2)^2 of each residual, 0 beyond the cutoff."""
    u = np.abs(np.asarray(residuals, dtype=np.float64)) / cutoff
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


def off_surface(along, distances) -> np.ndarray:
    """Whether each closest point on a scan lies on its outline or a hole's rim rather
    than below the query point: the offset then leaves the surface sideways, not along
    its normal (``along``: the offset's component along the normal at the closest point;
    ``distances``: the offsets' lengths, mm). Such pairs say nothing about the surface."""
    return np.abs(along) < 0.8 * np.asarray(distances) - 0.05
