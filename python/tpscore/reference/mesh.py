"""NumPy reference for the mesh operators in tpscore.mesh.

Vectorised per-face formulas, scattered to vertices with np.add.at / bincount and
assembled with scipy.sparse (COO summed into CSR). Same conventions as the compiled
kernels: collapsed faces (a repeated vertex index) contribute nothing, cotangents
are clamped to [-MAX_COTANGENT, MAX_COTANGENT].
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = [
    "MAX_COTANGENT",
    "face_normals",
    "vertex_normals",
    "cotan_laplacian",
    "voronoi_areas",
    "boundary_vertices",
    "mean_curvature",
    "grid_triangles",
]

MAX_COTANGENT = 1e4
CANCELLATION = 1e-12


def _live_faces(faces):
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    collapsed = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    return faces[~collapsed]


def _corner_geometry(vertices, faces):
    """Per face: cross product (m, 3), corner dots (m, 3), clamped cotangents (m, 3)."""
    p = vertices[faces]  # (m, 3 corners, 3)
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    a = np.roll(p, -1, axis=1) - p  # corner k -> k+1
    b = np.roll(p, -2, axis=1) - p  # corner k -> k+2
    dot = np.einsum("mkd,mkd->mk", a, b)
    denominator = np.maximum(np.maximum(double_area[:, None], np.abs(dot) / MAX_COTANGENT),
                             np.finfo(float).tiny)
    return cross, dot, dot / denominator


def face_normals(vertices, faces):
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    p = vertices[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    collapsed = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    cross[collapsed] = 0
    norm = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)


def vertex_normals(vertices, faces, weighting="area"):
    total, total_weight = vertex_normal_sums(vertices, faces, weighting)
    norm = np.linalg.norm(total, axis=1, keepdims=True)
    # Normals that cancel to rounding noise give a zero normal, as in the core.
    keep = norm > CANCELLATION * total_weight[:, None]
    return np.divide(total, norm, out=np.zeros_like(total), where=keep)


def vertex_normal_sums(vertices, faces, weighting="area"):
    """Each vertex's weighted sum of its faces' unit normals (n, 3) and the sum of the
    weights (n,): the normal is the first over its length. Their ratio, total weight over
    the sum's length, is how much the normal amplifies rounding (large where the faces'
    normals nearly cancel, at a fold)."""
    faces = _live_faces(faces)
    cross, dot, _ = _corner_geometry(vertices, faces)
    double_area = np.linalg.norm(cross, axis=1)
    unit = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    if weighting == "area":
        weight = np.repeat(double_area[:, None], 3, axis=1)
    elif weighting == "angle":
        weight = np.arctan2(double_area[:, None], dot)
    elif weighting == "uniform":
        weight = np.ones_like(dot)
    else:
        raise ValueError(f"unknown weighting {weighting!r}")
    weight = np.where(double_area[:, None] > 0, weight, 0.0)
    contribution = weight[:, :, None] * unit[:, None, :]
    total = np.zeros_like(vertices)
    np.add.at(total, faces.reshape(-1), contribution.reshape(-1, 3))
    total_weight = np.bincount(faces.reshape(-1), weights=weight.reshape(-1), minlength=len(vertices))
    return total, total_weight


def cotan_laplacian(vertices, faces):
    n = len(vertices)
    faces = _live_faces(faces)
    _, _, cot = _corner_geometry(vertices, faces)
    # The edge opposite corner k joins corners k+1 and k+2.
    i = np.roll(faces, -1, axis=1).reshape(-1)
    j = np.roll(faces, -2, axis=1).reshape(-1)
    w = 0.5 * cot.reshape(-1)
    off = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))),
                        shape=(n, n)).tocsr()
    diagonal = -np.asarray(off.sum(axis=1)).ravel()
    return (off + sp.diags(diagonal)).tocsr()


def voronoi_areas(vertices, faces):
    faces = _live_faces(faces)
    cross, dot, cot = _corner_geometry(vertices, faces)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    p = vertices[faces]
    next_edge = np.sum((p - np.roll(p, -1, axis=1)) ** 2, axis=2)  # |x_k - x_{k+1}|^2
    prev_edge = np.sum((p - np.roll(p, -2, axis=1)) ** 2, axis=2)  # |x_k - x_{k+2}|^2
    # Corner k: edge to k+1 is opposite corner k+2, edge to k+2 opposite corner k+1.
    voronoi = (next_edge * np.roll(cot, -2, axis=1) + prev_edge * np.roll(cot, -1, axis=1)) / 8
    obtuse_face = (dot < 0).any(axis=1)
    mixed = np.where(dot < 0, area[:, None] / 2, area[:, None] / 4)
    corner_area = np.where(obtuse_face[:, None], mixed, voronoi)
    return np.bincount(faces.reshape(-1), weights=corner_area.reshape(-1), minlength=len(vertices))


def boundary_vertices(faces, n_vertices):
    faces = _live_faces(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    mask = np.zeros(n_vertices, dtype=bool)
    mask[unique[counts != 2].reshape(-1)] = True
    return mask


def mean_curvature(vertices, faces):
    """(H (n,), K (n, 3), boundary (n,)) with NaN on boundary and zero-area vertices."""
    n = len(vertices)
    laplacian = cotan_laplacian(vertices, faces)
    area = voronoi_areas(vertices, faces)
    boundary = boundary_vertices(faces, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        # (L x)_i = sum_j L_ij (x_j - x_i), so K_i = -(L x)_i / A_i.
        k = -(laplacian @ vertices) / area[:, None]
    live = _live_faces(faces)
    p = vertices[live]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal = np.zeros_like(vertices)
    np.add.at(normal, live.reshape(-1), np.repeat(cross[:, None, :], 3, axis=1).reshape(-1, 3))
    h = 0.5 * np.linalg.norm(k, axis=1)
    h = np.where(np.einsum("nd,nd->n", k, normal) >= 0, h, -h)
    undefined = boundary | ~(area > 0)
    h[undefined] = np.nan
    k[undefined] = np.nan
    return h, k, boundary


def grid_triangles(valid):
    """Triangles over the valid vertices of an (H, W) grid mask, as flat grid indices:
    two per quad of four valid vertices, one per quad of three (see
    :meth:`tpscore.FaceGrid.triangles`)."""
    valid = np.asarray(valid, dtype=bool)
    height, width = valid.shape
    index = np.arange(height * width, dtype=np.int64).reshape(height, width)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    flat = valid.reshape(-1)
    va, vb, vc, vd = flat[a], flat[b], flat[c], flat[d]
    n_valid = va.astype(np.int8) + vb + vc + vd
    full = n_valid == 4
    three = n_valid == 3
    first = np.stack([a, c, d], axis=1)  # full quads, and quads missing only b
    first = np.where((three & ~va)[:, None], np.stack([c, d, b], axis=1), first)
    first = np.where((three & ~vc)[:, None], np.stack([a, d, b], axis=1), first)
    first = np.where((three & ~vd)[:, None], np.stack([a, c, b], axis=1), first)
    second = np.stack([a, d, b], axis=1)
    both = np.stack([first, second], axis=1)            # (quads, 2, 3)
    keep = np.stack([full | three, full], axis=1)        # (quads, 2)
    return np.ascontiguousarray(both[keep]).reshape(-1, 3)
