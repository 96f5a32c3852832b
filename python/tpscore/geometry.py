"""Small geometric and statistical helpers that every method shares: a mesh's edges and
adjacency, the robust weights of the iterative fits (ICP, registration, adaptation), and
affine maps between frames with the least-squares similarity that fits them.

Normals come from the compiled mesh operators (:func:`tpscore.mesh.face_normals`,
:func:`tpscore.mesh.vertex_normals`), closest points from :class:`tpscore.MeshSurface`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ._validation import MAX_DENSE_ELEMENTS, as_array, as_points, as_vertex_count

__all__ = ["mesh_edges", "spread_vertices", "vertex_adjacency", "robust_scale", "tukey_weights", "off_surface", "FrameTransform",
           "paired_points", "similarity_transform"]

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
    """(n, n) symmetric 0/1 CSR matrix: 1 where two vertices share an edge.

    ``n_vertices`` is at most 2**28 (the matrix's row pointers alone take 8 bytes a
    vertex: 2 GiB), judged before anything is allocated; the faces' indices lie in
    [0, n_vertices)."""
    n_vertices = as_vertex_count(n_vertices, "n_vertices", most=MAX_DENSE_ELEMENTS,
                                 what="the adjacency matrix's row pointers alone would pass 2 GiB")
    edges = mesh_edges(faces)
    if edges.size and (edges.min() < 0 or edges.max() >= n_vertices):
        raise ValueError(f"faces refers to vertex indices outside [0, {n_vertices}): min {edges.min()}, "
                         f"max {edges.max()}")
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


@dataclass(frozen=True)
class FrameTransform:
    """An affine map between two frames, as a 4 x 4 homogeneous matrix.

    ``apply`` maps points from the source frame (e.g. the scan) to the target frame
    (e.g. the reference face); ``apply_inverse`` maps them back.
    """

    matrix: np.ndarray
    method: str = "affine"

    def __post_init__(self):
        m = np.array(as_array(self.matrix, "matrix"), dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise ValueError(f"matrix must be a finite 4 x 4 array, got shape {m.shape}")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError("matrix must be affine: its last row must be [0, 0, 0, 1]")
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise ValueError("matrix is singular: the transform collapses space")
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)

    @classmethod
    def identity(cls) -> "FrameTransform":
        return cls(np.eye(4), "none")

    @property
    def scale(self) -> float:
        """Mean linear scale factor (cube root of the determinant)."""
        return float(abs(np.linalg.det(self.matrix[:3, :3])) ** (1.0 / 3.0))

    def apply(self, points) -> np.ndarray:
        """Map (..., 3) points into the target frame (NaN rows stay NaN)."""
        p = as_array(points, "points")
        return p @ self.matrix[:3, :3].T + self.matrix[:3, 3]

    def apply_inverse(self, points) -> np.ndarray:
        """Map (..., 3) points from the target frame back to the source frame."""
        return self.inverse().apply(points)

    def apply_vectors(self, vectors) -> np.ndarray:
        """Map displacement vectors (no translation)."""
        return np.asarray(vectors, dtype=np.float64) @ self.matrix[:3, :3].T

    def inverse(self) -> "FrameTransform":
        return FrameTransform(np.linalg.inv(self.matrix), self.method)

    def then(self, other: "FrameTransform") -> "FrameTransform":
        """The transform that applies ``self`` first, then ``other``."""
        return FrameTransform(other.matrix @ self.matrix, f"{self.method}+{other.method}")


def paired_points(source, target, name: str = "source", target_name: str = "target"):
    """Two (n, 3) point sets as float64 and the rows finite in both."""
    lm = as_points(source, name, finite=False)
    ref = as_points(target, target_name, finite=False)
    if lm.shape != ref.shape:
        raise ValueError(f"{name} has shape {lm.shape} but {target_name} has {ref.shape}")
    both = np.isfinite(lm).all(axis=1) & np.isfinite(ref).all(axis=1)
    return lm, ref, both


def similarity_transform(source, target, *, scale: bool = True, weights=None) -> FrameTransform:
    """Least-squares similarity (rotation, optional uniform scale, translation) source -> target.

    Parameters
    ----------
    source, target : (n, 3) array_like
        Corresponding points (mm); rows with NaN in either are ignored.
    scale : bool
        Fit a uniform scale; False gives a rigid transform.
    weights : (n,) array_like, optional
        Non-negative weight per pair.

    Raises
    ------
    ValueError
        Fewer than 3 usable pairs, or pairs on one line (rotation undetermined).
    """
    src, dst, both = paired_points(source, target)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (len(src),) or not np.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"weights must be {len(src)} finite non-negative numbers")
    use = both & (w > 0)
    if use.sum() < 3:
        raise ValueError(
            f"a similarity transform needs at least 3 landmark pairs present in both faces, "
            f"got {int(use.sum())}"
        )
    return fit_similarity(src[use], dst[use], w[use], scale=scale)


def fit_similarity(source: np.ndarray, target: np.ndarray, weights: np.ndarray, *, scale: bool = True) -> FrameTransform:
    """:func:`similarity_transform` without its checks, for loops that refit the same
    points many times (a robust fit's iterations): (n, 3) float64 points, finite, and n
    positive weights, n >= 3. Pairs on one line still raise a ValueError."""
    w = weights / weights.sum()
    mu_s, mu_d = w @ source, w @ target
    xs, xd = source - mu_s, target - mu_d
    cov = (xd * w[:, None]).T @ xs
    u, sing, vt = np.linalg.svd(cov)
    if sing[1] < 1e-9 * max(sing[0], 1e-300):
        raise ValueError("the landmark pairs lie on one line: the rotation is undetermined")
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1.0  # a reflection is not a pose: flip the weakest axis instead
    rotation = u @ d @ vt
    s = 1.0
    if scale:
        s = float(np.trace(np.diag(sing) @ d) / float((w * (xs**2).sum(axis=1)).sum()))
    m = np.eye(4)
    m[:3, :3] = s * rotation
    m[:3, 3] = mu_d - s * rotation @ mu_s
    return FrameTransform(m, "similarity" if scale else "rigid")


def spread_vertices(vertices, spacing: float, candidates=None) -> np.ndarray:
    """About one vertex per cube of side `spacing`: evenly spread samples of a mesh.

    Parameters
    ----------
    vertices : (n, 3) array_like
        Points (mm).
    spacing : float
        Cube side (mm), > 0.
    candidates : (n,) bool array_like, optional
        Only these vertices may be chosen.

    Returns
    -------
    (k,) int64 indices, the vertex nearest the centre of each occupied cube.
    """
    vertices = as_points(vertices, "vertices")
    pool = np.arange(len(vertices)) if candidates is None else np.flatnonzero(candidates)
    if len(pool) == 0:
        return pool.astype(np.int64)
    scaled = vertices[pool] / spacing
    cells = np.floor(scaled).astype(np.int64)
    offset = np.linalg.norm(scaled - cells - 0.5, axis=1)
    order = np.lexsort((offset, cells[:, 2], cells[:, 1], cells[:, 0]))
    sorted_cells = cells[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(sorted_cells[1:] != sorted_cells[:-1], axis=1)
    return np.sort(pool[order[first]]).astype(np.int64)
