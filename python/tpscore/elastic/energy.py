"""The elastic energy and its basis: the operator -k_s L + k_b L M^-1 L, the fixed
region, and one precomputed displacement field per handle.

With the handles prescribed and the fixed region held, the minimiser is linear in the
handle displacements, so the free block is factorised once and any deformation is
``basis @ params``; see ``docs/elastic.md``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .._validation import as_points, as_positive, check_options
from ..face.normalise import face_frame
from ..geometry import vertex_adjacency
from ..mesh import cotan_laplacian, voronoi_areas
from ..sparse import SparseCholesky

__all__ = [
    "DEFAULT_FIXED_FACTOR",
    "ElasticOptions",
    "energy_matrix",
    "default_fixed_region",
    "ElasticBasis",
]

#: Default fixed-region radius, in multiples of the nose-tip-to-forehead distance. On
#: the ICT face the eyebrows lie within 1.55 of it and the chin within 1.4, while the
#: region beyond 1.8 (temples, ears, the neck below the jaw) carries under 15 % of the
#: motion energy of any brow or mouth shape.
DEFAULT_FIXED_FACTOR = 1.8


@dataclass(frozen=True)
class ElasticOptions:
    """The tuning of an :class:`~tpscore.elastic.ElasticFace`, in one place so that a
    face and the faces cloned from it can share it; the defaults are what
    ``benchmarks/bench_elastic.py`` measures.

    Attributes
    ----------
    stretching, bending : float, default 0 and 1
        k_s and k_b of the energy (-k_s L + k_b L M^-1 L); pure bending by default.
        L is dimensionless and L M^-1 L is in 1/mm^2, so k_s / k_b is an inverse squared
        length: stretching dominates above features wider than sqrt(k_b / k_s) mm.
    fixed_factor : float, default 1.8
        Radius of the default fixed region, in multiples of the nose-tip-to-forehead
        distance (:func:`~tpscore.elastic.default_fixed_region`).
    unanchored : {"error", "fix"}, default "error"
        What to do with a connected part of the mesh that has neither a control point
        nor a fixed vertex (its position would be undetermined): raise, or hold it
        still (scans often carry small islands of this kind, e.g. inside a nostril).
    """

    stretching: float = 0.0
    bending: float = 1.0
    fixed_factor: float = DEFAULT_FIXED_FACTOR
    unanchored: str = "error"

    def __post_init__(self):
        check_options(self, positive=("fixed_factor",), non_negative=("stretching", "bending"),
                      choices={"unanchored": ("error", "fix")})
        if self.stretching == 0 and self.bending == 0:
            raise ValueError("ElasticOptions: stretching and bending are both 0; there is no energy to minimise")


def energy_matrix(vertices: np.ndarray, faces: np.ndarray, stretching: float, bending: float) -> sp.csr_matrix:
    """The (n, n) operator -k_s L + k_b L M^-1 L (symmetric positive semi-definite) of
    validated vertices and faces, with L the cotangent Laplacian and M the Voronoi areas."""
    laplacian = cotan_laplacian(vertices, faces)
    areas = voronoi_areas(vertices, faces)
    # A vertex of zero area (degenerate triangles only) would make M^-1 infinite;
    # a floor of 1e-3 of the median area keeps the operator finite and barely
    # changes it (that vertex's bending term is still 1000 times stiffer).
    floor = 1e-3 * float(np.median(areas[areas > 0])) if (areas > 0).any() else 1.0
    areas = np.maximum(areas, floor)
    operator = sp.csr_matrix(laplacian.shape)
    if bending:
        operator = operator + bending * (laplacian @ sp.diags(1.0 / areas) @ laplacian)
    if stretching:
        operator = operator - stretching * laplacian
    operator = sp.csr_matrix(operator)
    # Remove the rounding asymmetry of the triple product before the symmetry check.
    return sp.csr_matrix((operator + operator.T) * 0.5)


def default_fixed_region(vertices, landmarks, factor: float = DEFAULT_FIXED_FACTOR) -> np.ndarray:
    """Mask of the vertices farther from the nose tip than ``factor`` times the distance
    from the nose tip to the forehead (the midpoint of the inner eyebrows).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    vertices = as_points(vertices, "vertices")
    factor = as_positive(factor, "fixed_factor")
    frame = face_frame(landmarks)
    radius = factor * float(np.linalg.norm(frame.forehead - frame.origin))
    return np.linalg.norm(vertices - frame.origin, axis=1) > radius


def as_vertex_mask(value, n: int, name: str) -> np.ndarray:
    """A (n,) bool mask from a mask or an index list."""
    array = np.asarray(value)
    if array.dtype == bool:
        if array.shape != (n,):
            raise ValueError(f"{name} as a mask must have shape ({n},), got {array.shape}")
        return array.copy()
    if array.size == 0:
        return np.zeros(n, dtype=bool)
    if array.ndim != 1 or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"{name} must be a boolean mask of shape ({n},) or a 1-D array of vertex indices")
    if array.min() < 0 or array.max() >= n:
        raise ValueError(f"{name} refers to vertex indices outside [0, {n})")
    mask = np.zeros(n, dtype=bool)
    mask[array] = True
    return mask


def unanchored_parts(faces: np.ndarray, n: int, handles: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Label (n,) of each vertex's connected part of the mesh where that part holds
    neither a handle nor a fixed vertex (its position would be undetermined), else -1."""
    count, labels = connected_components(vertex_adjacency(n, faces), directed=False)
    anchored = np.zeros(count, dtype=bool)
    anchored[labels[handles]] = True
    anchored[labels[fixed]] = True
    return np.where(anchored[labels], -1, labels)


class ElasticBasis:
    """The factorised free block of the energy and one displacement field per handle.

    Parameters
    ----------
    operator : sparse matrix, shape (n, n)
        The energy operator (:func:`energy_matrix`).
    handles : ndarray of int64, shape (k,)
        Handle vertices, distinct and outside ``fixed``.
    fixed : ndarray of bool, shape (n,)
        Vertices held still.

    Attributes
    ----------
    matrix : ndarray, shape (n, k)
        The basis: column j is the displacement of every vertex when handle j moves by
        one unit alone; rows of handles are the identity, rows of fixed vertices 0.
    free : ndarray of int64
        The vertices neither handles nor fixed, whose block is factorised.
    timings : dict
        Seconds spent factorising (``factorisation_s``) and solving for the basis
        (``basis_s``).

    Notes
    -----
    ``basis`` is read-only and the factor's solve releases the GIL, so one basis can be
    used from several threads.
    """

    def __init__(self, operator: sp.csr_matrix, handles: np.ndarray, fixed: np.ndarray):
        n, k = operator.shape[0], len(handles)
        constrained = fixed.copy()
        constrained[handles] = True
        self.free = np.flatnonzero(~constrained)
        self.handles = handles
        self.timings: dict[str, float] = {}
        start = time.perf_counter()
        rows = operator[self.free]
        self.factor = SparseCholesky(rows[:, self.free]) if len(self.free) else None
        self.timings["factorisation_s"] = time.perf_counter() - start
        start = time.perf_counter()
        basis = np.zeros((n, k))
        basis[handles, np.arange(k)] = 1.0
        self.coupling = rows[:, handles].tocsr() if len(self.free) else None
        if len(self.free):
            basis[self.free] = self.factor.solve(-self.coupling.toarray())
        self.timings["basis_s"] = time.perf_counter() - start
        basis.setflags(write=False)
        self.matrix = basis

    def solve(self, params: np.ndarray) -> np.ndarray:
        """The displacement (n, 3) for handle displacements ``params`` (k, 3), by a fresh
        solve with the factor instead of the basis."""
        displacement = np.zeros((len(self.matrix), 3))
        displacement[self.handles] = params
        if len(self.free):
            displacement[self.free] = self.factor.solve(-(self.coupling @ params))
        return displacement
