"""SciPy reference for the CSRBF fit in tpscore.csrbf.

The scipy route: neighbours from scipy.spatial.cKDTree, the matrix in
scipy.sparse, the solve by scipy.sparse.linalg.bicgstab (with an spilu or Jacobi
preconditioner), local quadrics by a plain per-centre least-squares loop. Same
method and conventions as the compiled core; see tpscore.csrbf.CSRBF.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.spatial import cKDTree

__all__ = ["wendland", "ReferenceCSRBF", "fit", "evaluate", "tangent_frame"]

RANK_THRESHOLD = 1e-6


def wendland(r):
    """phi(r) = (1 - r)^4 (4 r + 1) for r < 1, else 0."""
    r = np.asarray(r, dtype=float)
    return np.where(r < 1, (1 - r) ** 4 * (4 * r + 1), 0.0)


def tangent_frame(normal):
    """(t1, t2) orthonormal with t1 x t2 = normal; t1 from the least aligned axis."""
    axis = 0
    if abs(normal[1]) < abs(normal[axis]):
        axis = 1
    if abs(normal[2]) < abs(normal[axis]):
        axis = 2
    t1 = np.cross(normal, np.eye(3)[axis])
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(normal, t1)


@dataclass
class ReferenceCSRBF:
    centres: np.ndarray
    support: float
    coefficients: np.ndarray  # (n, k)
    tangents: np.ndarray | None  # (n, 2, 3)
    models: np.ndarray | None  # (n, k, 6)
    orders: np.ndarray | None  # (n,)
    normals: np.ndarray | None  # (n, 3)
    iterations: np.ndarray
    residuals: np.ndarray
    matrix: sp.csr_matrix
    rhs: np.ndarray  # (n, k) values minus the local models' part


def _local_basis(offsets, tangents, support):
    """[1, u, v, u^2, 2uv, v^2] for offsets x - p_j (m, 3) in the frame (2, 3), / support."""
    u = offsets @ tangents[0] / support
    v = offsets @ tangents[1] / support
    return np.stack([np.ones_like(u), u, v, u * u, 2 * u * v, v * v], axis=-1)


def _rank(matrix):
    if matrix.shape[0] == 0:
        return 0
    r = scipy.linalg.qr(matrix, mode="r", pivoting=True)[0]
    diagonal = np.abs(np.diag(r))
    return int(np.sum(diagonal > RANK_THRESHOLD * diagonal.max())) if diagonal.size else 0


def _fit_local_models(centres, values, support, normals, neighbourhoods):
    n, k = values.shape
    tangents = np.zeros((n, 2, 3))
    models = np.zeros((n, k, 6))
    orders = np.zeros(n, dtype=np.int64)
    used_normals = np.zeros((n, 3))
    for j, neighbours in enumerate(neighbourhoods):
        neighbours = np.asarray(neighbours)
        weights = wendland(np.linalg.norm(centres[neighbours] - centres[j], axis=1) / support)
        if normals is not None:
            normal = normals[j] / np.linalg.norm(normals[j])
        else:
            mean = weights @ centres[neighbours] / weights.sum()
            spread = centres[neighbours] - mean
            covariance = (weights[:, None] * spread).T @ spread
            normal = np.linalg.eigh(covariance)[1][:, 0]
        t1, t2 = tangent_frame(normal)
        tangents[j] = t1, t2
        used_normals[j] = normal
        root = np.sqrt(weights)[:, None]
        design = root * _local_basis(centres[neighbours] - centres[j], tangents[j], support)
        rhs = root * values[neighbours]
        for terms, order in ((6, 2), (3, 1)):
            if len(neighbours) >= terms and _rank(design[:, :terms]) == terms:
                models[j, :, :terms] = np.linalg.lstsq(design[:, :terms], rhs, rcond=None)[0].T
                orders[j] = order
                break
        else:
            models[j, :, 0] = design[:, 0] @ rhs / (design[:, 0] @ design[:, 0])
    return tangents, models, orders, used_normals


def fit(centres, values, support, *, normals=None, quadric=False, smoothing=0.0,
        preconditioner="ilu", tolerance=1e-10, max_iterations=1000) -> ReferenceCSRBF:
    """Fit the CSRBF field; inputs as tpscore.csrbf.CSRBF (validated arrays)."""
    centres = np.asarray(centres, dtype=float)
    values = np.asarray(values, dtype=float)
    values = values[:, None] if values.ndim == 1 else values
    n, k = values.shape
    tree = cKDTree(centres)
    # The COO output keeps the zero distances, so the diagonal phi(0) = 1 is included.
    distances = tree.sparse_distance_matrix(tree, support, output_type="coo_matrix")
    phi = sp.csr_matrix((wendland(distances.data / support), (distances.row, distances.col)), shape=(n, n))
    if smoothing:
        phi = (phi + sp.diags(np.full(n, smoothing))).tocsr()

    tangents = models = orders = used_normals = None
    rhs = values.copy()
    if quadric:
        neighbourhoods = tree.query_ball_point(centres, support)
        tangents, models, orders, used_normals = _fit_local_models(
            centres, values, support, None if normals is None else np.asarray(normals, float), neighbourhoods)
        pure = (phi - sp.diags(np.full(n, smoothing))).tocoo() if smoothing else phi.tocoo()
        # g_j(p_i) for every stored pair (i, j)
        u = np.einsum("md,md->m", centres[pure.row] - centres[pure.col], tangents[pure.col, 0]) / support
        v = np.einsum("md,md->m", centres[pure.row] - centres[pure.col], tangents[pure.col, 1]) / support
        basis = np.stack([np.ones_like(u), u, v, u * u, 2 * u * v, v * v], axis=-1)
        g = np.einsum("mt,mkt->mk", basis, models[pure.col])
        contribution = np.zeros((n, k))
        np.add.at(contribution, pure.row, g * pure.data[:, None])
        rhs -= contribution

    if preconditioner == "ilu":
        factor = sla.spilu(phi.tocsc())
        operator = sla.LinearOperator((n, n), factor.solve)
    elif preconditioner == "diagonal":
        inverse_diagonal = 1.0 / phi.diagonal()
        operator = sla.LinearOperator((n, n), lambda x: inverse_diagonal * x)
    else:
        raise ValueError(f"unknown preconditioner {preconditioner!r}")
    coefficients = np.zeros((n, k))
    iterations = np.zeros(k, dtype=np.int64)
    residuals = np.zeros(k)
    for column in range(k):
        b = rhs[:, column]
        if not np.any(b):
            continue
        count = [0]

        def callback(_, count=count):
            count[0] += 1

        x, _ = sla.bicgstab(phi, b, rtol=tolerance, atol=0.0, maxiter=max_iterations, M=operator,
                            callback=callback)
        coefficients[:, column] = x
        iterations[column] = count[0]
        residuals[column] = np.linalg.norm(b - phi @ x) / np.linalg.norm(b)
    return ReferenceCSRBF(centres, float(support), coefficients, tangents, models, orders, used_normals,
                          iterations, residuals, phi, rhs)


def evaluate(model: ReferenceCSRBF, points) -> np.ndarray:
    """The fitted field at points (m, 3): (m, k)."""
    points = np.asarray(points, dtype=float)
    tree = cKDTree(model.centres)
    result = np.zeros((len(points), model.coefficients.shape[1]))
    for q, neighbours in enumerate(tree.query_ball_point(points, model.support)):
        neighbours = np.asarray(neighbours, dtype=np.int64)
        if neighbours.size == 0:
            continue
        offsets = points[q] - model.centres[neighbours]
        weights = wendland(np.linalg.norm(offsets, axis=1) / model.support)
        terms = model.coefficients[neighbours].copy()
        if model.models is not None:
            u = np.einsum("md,md->m", offsets, model.tangents[neighbours, 0]) / model.support
            v = np.einsum("md,md->m", offsets, model.tangents[neighbours, 1]) / model.support
            basis = np.stack([np.ones_like(u), u, v, u * u, 2 * u * v, v * v], axis=-1)
            terms += np.einsum("mt,mkt->mk", basis, model.models[neighbours])
        result[q] = weights @ terms
    return result
