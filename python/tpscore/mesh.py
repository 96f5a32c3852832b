"""Discrete differential operators on triangle meshes.

Normals, the cotangent Laplacian, mixed Voronoi areas and mean curvature after
Meyer, Desbrun, Schroeder and Barr, "Discrete differential-geometry operators for
triangulated 2-manifolds" (2003). Units follow the vertices (mm): areas in mm^2,
curvature in 1/mm.

Conventions shared by every function here:

- ``vertices`` is (n, 3) array-like, ``faces`` (m, 3) integer vertex indices in
  [0, n). Faces are oriented by the right-hand rule: the normal of face (a, b, c)
  is along (b - a) x (c - a).
- A face that repeats a vertex index (a "collapsed" face) contributes nothing.
- Zero-area faces never produce NaN or inf: the cotangent of a corner angle is
  clamped to [-1e4, 1e4] (angles below about 1e-4 rad, which a well-formed mesh
  never has; the exact value there is infinite). Quantities next to such faces are
  finite but not meaningful.
- Non-manifold input (an edge with three or more faces) is accepted; each face adds
  its own cotangent term, and its vertices count as boundary vertices.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from . import _core
from ._validation import MAX_VERTICES, as_array, as_faces, as_points, as_vertex_count
from .spatial import MeshSurface

__all__ = [
    "MeanCurvature",
    "grid_triangles",
    "face_normals",
    "vertex_normals",
    "cotan_laplacian",
    "voronoi_areas",
    "mass_matrix",
    "boundary_vertices",
    "mean_curvature",
]

_NORMAL_WEIGHTINGS = {name: getattr(_core.NormalWeighting, name) for name in ("area", "angle", "uniform")}


def _mesh(vertices, faces):
    vertices = as_points(vertices, "vertices")
    faces = as_faces(faces, len(vertices), "faces")
    return vertices, faces


def face_normals(vertices, faces) -> np.ndarray:
    """Unit normal of every face.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions, mm.
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices.

    Returns
    -------
    ndarray, shape (m, 3)
        Unit normals along (b - a) x (c - a); zero rows for zero-area faces.
    """
    vertices, faces = _mesh(vertices, faces)
    return _core.face_normals(vertices, faces)


def vertex_normals(vertices, faces, *, weighting: str = "area") -> np.ndarray:
    """Unit normal of every vertex: a weighted mean of its faces' unit normals.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions, mm.
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices.
    weighting : {"area", "angle", "uniform"}
        Weight of each incident face: its area (default), its corner angle at the
        vertex, or 1.

    Returns
    -------
    ndarray, shape (n, 3)
        Unit normals. A vertex in no face, only in zero-area faces, or whose face
        normals cancel (e.g. two faces folded back onto each other) gets a zero row
        rather than NaN, so the result can be used directly in arithmetic;
        test ``np.linalg.norm(normals, axis=1) == 0`` to find such vertices.
    """
    if weighting not in _NORMAL_WEIGHTINGS:
        raise ValueError(f"weighting must be one of {sorted(_NORMAL_WEIGHTINGS)}, got {weighting!r}")
    vertices, faces = _mesh(vertices, faces)
    return _core.vertex_normals(vertices, faces, _NORMAL_WEIGHTINGS[weighting])


def cotan_laplacian(vertices, faces) -> sp.csr_matrix:
    """The cotangent Laplacian L, a sparse (n, n) matrix.

    L_ij = (cot alpha_ij + cot beta_ij) / 2 for every edge ij, with alpha and beta
    the angles opposite the edge (a single term on a boundary edge), and
    L_ii = -sum_j L_ij. This is the negative semi-definite convention: L is
    symmetric, L @ constant = 0, and the Laplace-Beltrami operator is
    Delta f ~= M^-1 L f with M = :func:`mass_matrix`. For a linear function on a
    flat mesh, (L f)_i = 0 at every interior vertex.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions, mm.
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)
        Dimensionless weights; sorted column indices; the diagonal is stored for
        every vertex (0 for a vertex in no face).
    """
    vertices, faces = _mesh(vertices, faces)
    # The core builds the CSR arrays itself (sorted, duplicates merged): handing
    # scipy the 6 m + n COO triplets instead costs more in coo.tocsr() alone (11 ms on a
    # 300 x 300 grid) than the whole compiled assembly (about 9 ms).
    data, indices, indptr = _core.cotan_laplacian(vertices, faces)
    n = len(vertices)
    return sp.csr_matrix((data, indices, indptr), shape=(n, n), copy=False)


def voronoi_areas(vertices, faces) -> np.ndarray:
    """Mixed Voronoi area of every vertex (Meyer et al.).

    Each non-obtuse face gives each corner its Voronoi region (bounded by the
    perpendicular bisectors of the edges); an obtuse face gives half its area to
    the obtuse corner and a quarter to each of the others. The areas sum to the
    total area of the mesh.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions, mm.
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices.

    Returns
    -------
    ndarray, shape (n,)
        Areas, mm^2; 0 for a vertex in no face.
    """
    vertices, faces = _mesh(vertices, faces)
    return _core.voronoi_areas(vertices, faces)


def mass_matrix(vertices, faces) -> sp.csr_matrix:
    """Diagonal (lumped) mass matrix M = diag(:func:`voronoi_areas`), sparse (n, n), mm^2."""
    areas = voronoi_areas(vertices, faces)
    return sp.diags(areas, format="csr")


def boundary_vertices(faces, n_vertices: int | None = None) -> np.ndarray:
    """Mask of the vertices on an edge that does not have exactly two faces.

    That is the open boundary of the mesh (edges with one face) and, for
    non-manifold input, vertices on edges with three or more faces: the vertices
    where a one-ring formula such as :func:`mean_curvature` does not hold.

    Parameters
    ----------
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices.
    n_vertices : int, optional
        Length of the mask, at most 2**31 - 1 (a mask of 2 GiB); by default one more
        than the largest index in faces.

    Returns
    -------
    ndarray of bool, shape (n_vertices,)
        False for vertices in no face.
    """
    faces_array = np.asarray(faces)
    if n_vertices is None:
        if faces_array.ndim != 2 or faces_array.shape[1] != 3:
            raise ValueError(f"faces must have shape (m, 3), got {faces_array.shape}")
        n_vertices = int(faces_array.max()) + 1 if faces_array.size else 0
        if n_vertices > MAX_VERTICES:
            raise ValueError(f"faces refers to vertex {n_vertices - 1:,}: a mask of {n_vertices:,} vertices is "
                             f"more than the {MAX_VERTICES:,} tpscore accepts (a C int; 2 GiB)")
    else:
        # judged before the mask is allocated (the core takes a C int64 and would try)
        n_vertices = as_vertex_count(n_vertices, "n_vertices", most=MAX_VERTICES,
                                     what="a C int; the mask alone would pass 2 GiB")
    faces_array = as_faces(faces_array, n_vertices, "faces")
    return _core.boundary_vertices(n_vertices, faces_array)


class MeanCurvature(NamedTuple):
    """Mean curvature at the vertices of a mesh (see :func:`mean_curvature`)."""

    values: np.ndarray
    """(n,) signed mean curvature H, 1/mm; NaN where undefined."""
    normals: np.ndarray
    """(n, 3) mean-curvature normal K = 2 H n, 1/mm; NaN where undefined."""
    boundary: np.ndarray
    """(n,) bool, the :func:`boundary_vertices` mask."""


def mean_curvature(vertices, faces) -> MeanCurvature:
    """Mean curvature and mean-curvature normal at every vertex (Meyer et al.).

    K(x_i) = 1 / (2 A_i) * sum_j (cot alpha_ij + cot beta_ij) (x_i - x_j) = 2 H n,
    with A_i the mixed Voronoi area (:func:`voronoi_areas`). |H| = |K| / 2, and H
    is positive where K points along the outward (area-weighted, right-hand-rule)
    vertex normal: a sphere of radius R with outward-oriented faces has H = +1/R,
    a plane H = 0, a saddle H of either sign. Where K is (nearly) tangent to the
    vertex normal, which only happens on rough or folded meshes, the sign is not
    meaningful.

    The one-ring formula holds only where the faces around a vertex close into a
    disc. On boundary vertices (:func:`boundary_vertices`, which includes
    non-manifold edges) and on vertices with zero Voronoi area (in no face, or only
    in zero-area faces) ``values`` and ``normals`` are NaN, so they cannot pass as
    real curvature; mask them with ``~result.boundary`` or use ``np.nanmax`` /
    ``np.nanargmax``.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions, mm.
    faces : array_like of int, shape (m, 3)
        Triangles as vertex indices, consistently oriented (outward normals).

    Returns
    -------
    MeanCurvature
        ``values`` (n,) H in 1/mm, ``normals`` (n, 3) K in 1/mm, ``boundary`` (n,)
        bool.
    """
    vertices, faces = _mesh(vertices, faces)
    values, normals, boundary = _core.mean_curvature(vertices, faces)
    return MeanCurvature(values, normals, boundary)


class HeightFieldMesh(NamedTuple):
    """A mesh resampled as a grid seen along -z (see :func:`height_field_remesh`)."""

    vertices: np.ndarray          # (k, 3) grid vertices that hit the surface, mm
    faces: np.ndarray             # (t, 3) triangles over them
    source_corners: np.ndarray    # (k, 3) vertex indices of the input triangle each lies on
    barycentric: np.ndarray       # (k, 3) its weights on that triangle


def height_field_remesh(vertices, faces, centre, *, shape=(150, 150), crop_mm: float = 100.0,
                        max_edge_cells: float = 4.0) -> HeightFieldMesh:
    """Resample a mesh as a regular grid of its front-most surface seen along -z.

    The grid spans, in x and y, the vertices within `crop_mm` of `centre`; each node is
    the first hit of a ray along -z on the triangles whose corners are all that close.
    Cells with a corner that misses, or an edge longer than `max_edge_cells` grid cells
    (a depth jump), get no triangle. This gives a mesh of the same surface with an
    unrelated structure, as a depth scanner would.
    """

    vertices, faces = _mesh(vertices, faces)
    centre = as_array(centre, "centre").reshape(3)
    rows, cols = shape
    near = np.linalg.norm(vertices - centre, axis=1) <= crop_mm
    cropped = faces[near[faces].all(axis=1)]
    if not len(cropped):
        raise ValueError(f"no triangle lies within crop_mm={crop_mm} of the centre")
    lo, hi = vertices[near, :2].min(axis=0), vertices[near, :2].max(axis=0)
    x, y = np.meshgrid(np.linspace(lo[0], hi[0], cols), np.linspace(hi[1], lo[1], rows))
    origins = np.stack([x.ravel(), y.ravel(), np.full(x.size, vertices[:, 2].max() + 100.0)], axis=1)
    hits = MeshSurface(vertices, cropped).intersect_rays(origins, np.tile([0.0, 0.0, -1.0], (x.size, 1)))
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    grid = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    grid = grid[hits.hit[grid].all(axis=1)]
    spacing = max((hi[0] - lo[0]) / (cols - 1), (hi[1] - lo[1]) / (rows - 1))
    edges = np.stack([np.linalg.norm(hits.points[grid[:, i]] - hits.points[grid[:, (i + 1) % 3]], axis=1)
                      for i in range(3)], axis=1)
    grid = grid[(edges < max_edge_cells * spacing).all(axis=1)]
    used = np.unique(grid)
    renumber = np.full(rows * cols, -1)
    renumber[used] = np.arange(len(used))
    return HeightFieldMesh(hits.points[used], renumber[grid], cropped[hits.triangles[used]],
                           hits.barycentric[used])


def grid_triangles(mask) -> np.ndarray:
    """Triangles over the valid vertices of an (H, W) grid, as flat row-major indices.

    Each quad whose four vertices are valid gives two triangles split along its
    (r, c)-(r+1, c+1) diagonal; a quad with exactly three valid vertices gives the one
    triangle they form. Triangles run counter-clockwise seen from +z, in row-major quad
    order (see :meth:`tpscore.face.grid.FaceGrid.triangles`).
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.bool_:
        raise ValueError(f"mask must be an (H, W) bool array, got {mask.dtype} of shape {mask.shape}")
    height, width = mask.shape
    return _core.grid_triangles(np.ascontiguousarray(mask).reshape(-1), height, width)
