"""The default refinement levels: each a Wendland offset fitted point to plane onto the
scan (a regularised non-rigid ICP step).

Every visible template vertex is paired with its closest scan point, and each pair asks
only for its distance to the scan's tangent plane there: unlike the published scheme's
interpolation, no pair is told how far to slide, so the sliding stays what the feature
points gave (docs/adaptation.md has the measurements).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._validation import as_points
from ..csrbf import wendland
from ..mesh import vertex_normals
from ..spatial import KDTree
from ..geometry import spread_vertices
from .correspondence import closest_visible_pairs
from .levels import LevelFit
from .options import AdaptOptions
from .result import evaluate_fields
from .setup import AdaptSetup

__all__ = ["SurfaceLevels", "SurfaceOffset", "fit_surface_offset"]


class SurfaceLevels:
    """The ``"surface"`` refinement: level k fits a :class:`SurfaceOffset` of support
    sigma_k, on centres spread at ``centre_spacing * sigma_k``, in a few closest-point
    rounds, until sigma_k falls below ``min_support``."""

    def __init__(self, setup: AdaptSetup, options: AdaptOptions):
        self.setup = setup
        self.options = options
        width = setup.width
        self.smallest_support = options.min_support if options.min_support is not None else width / 10.0

    def finished(self, support: float) -> bool:
        """True once the supports are finer than the levels should go."""
        return support < self.smallest_support * (1 - 1e-9)

    def fit(self, level: int, support: float, fields, deformed: np.ndarray, normals: np.ndarray) -> LevelFit:
        """The offset of one level, moving the fit `deformed` (normals `normals`) of the
        levels `fields` onto the scan."""
        setup, options = self.setup, self.options
        template = setup.template_vertices
        spacing = max(support * options.centre_spacing, 1e-3 * setup.width)
        centres = template[spread_vertices(template, spacing)]
        offset = SurfaceOffset(centres, np.zeros((len(centres), 3)), support)
        landmarks_so_far = evaluate_fields(fields, setup.landmark_sources)
        current, current_normals = deformed, normals
        for _ in range(options.surface_iterations):
            rows, partners, partner_normals = closest_visible_pairs(
                current, current_normals, setup.template_faces, setup.target, setup.view,
                max_distance=setup.max_ray)
            coefficients = fit_surface_offset(
                offset, template[rows], current[rows], partners, partner_normals,
                landmark_template=setup.landmark_sources,
                landmark_current=landmarks_so_far + offset(setup.landmark_sources),
                landmark_targets=setup.landmark_targets, landmark_weight=options.landmark_weight,
                regularisation=options.regularisation)
            offset = offset.plus(coefficients)
            current = deformed + offset(template)
            current_normals = vertex_normals(current, setup.template_faces)
        pairs = (template[rows], partners, np.array(["surface"] * len(rows), dtype=object))
        return LevelFit("surface", support, offset, current, pairs, len(rows), rows)


class SurfaceOffset:
    """An offset field o(p) = sum_j c_j phi_sigma(|p - p_j|) fitted point to plane.

    Built by :func:`fit_surface_offset`; evaluates like the other level fields (a
    callable from (m, 3) template-frame points to (m, 3) offsets, mm).

    Attributes
    ----------
    centres : (n, 3) ndarray
        The centres p_j (template frame, mm).
    coefficients : (n, 3) ndarray
        c_j (mm).
    support : float
        sigma (mm).
    """

    def __init__(self, centres: np.ndarray, coefficients: np.ndarray, support: float):
        self.centres = centres
        self.coefficients = coefficients
        self.support = float(support)
        self._tree = KDTree(centres)

    def matrix(self, points: np.ndarray):
        """The sparse (m, n) matrix phi_sigma(|points_i - p_j|)."""
        offsets, indices, distances = self._tree.query_radius_csr(points, self.support)
        values = wendland(distances / self.support)
        return sp.csr_matrix((values, indices, offsets), shape=(len(points), len(self.centres)))

    def __call__(self, points) -> np.ndarray:
        points = as_points(points, "points")
        if len(points) == 0:
            return np.zeros((0, 3))
        return np.asarray(self.matrix(points) @ self.coefficients)

    def plus(self, coefficients: np.ndarray) -> "SurfaceOffset":
        """The same field with `coefficients` added (one more iteration of a level)."""
        return SurfaceOffset(self.centres, self.coefficients + coefficients, self.support)


def fit_surface_offset(field: SurfaceOffset, template_points, current, targets, scan_normals, *,
                       landmark_template=None, landmark_current=None, landmark_targets=None,
                       landmark_weight: float = 1.0, regularisation: float = 1.0) -> np.ndarray:
    """Coefficients of the offset that best moves the current fit onto the scan.

    Minimises, over the coefficients c (n, 3) of `field`'s basis,

        sum_i (m_i . (x_i + o(p_i) - q_i))^2
        + landmark_weight sum_l |x_l + o(p_l) - q_l|^2 + regularisation c^T Phi c

    (Phi: the centres' kernel matrix, so the last term is the field's native norm).
    The surface pairs constrain only the distance to the scan's tangent planes. In
    principle neighbouring pairs with different normals also fix the sliding along
    a curved surface; in practice the regulariser, which favours small offsets,
    prefers pushing a shifted feature along the normals to sliding it (a 1.5 mm
    shifted bump slides by about 0.4 mm), so the sliding stays mostly what level 0
    gave.

    Parameters
    ----------
    field : SurfaceOffset
        Supplies the centres and support (its coefficients are ignored).
    template_points : (m, 3) ndarray
        p_i, template frame (mm).
    current, targets, scan_normals : (m, 3) ndarray
        x_i (the fit so far at p_i), q_i (scan partners) and unit m_i.
    landmark_template, landmark_current, landmark_targets : (k, 3) ndarray, optional
        Feature points: template position, current fit and scan position.
    landmark_weight : float
        Their weight (each counts as this many surface pairs).
    regularisation : float
        lambda, > 0.

    Returns
    -------
    (n, 3) ndarray of coefficients.
    """
    n = len(field.centres)
    phi = field.matrix(template_points)
    residual = np.einsum("ij,ij->i", scan_normals, targets - current)
    blocks = [[None] * 3 for _ in range(3)]
    rhs = np.zeros(3 * n)
    for a in range(3):
        rhs[a * n:(a + 1) * n] = phi.T @ (scan_normals[:, a] * residual)
        for b in range(a, 3):
            diagonal = scan_normals[:, a] * scan_normals[:, b]
            block = (phi.T @ sp.diags(diagonal) @ phi).tocsr()
            blocks[a][b] = block
            if b != a:
                blocks[b][a] = block.T
    kernel = field.matrix(field.centres)
    extra = regularisation * kernel
    if landmark_template is not None and len(landmark_template):
        phi_l = field.matrix(landmark_template)
        extra = extra + landmark_weight * (phi_l.T @ phi_l)
        lm_gap = landmark_targets - landmark_current
        for a in range(3):
            rhs[a * n:(a + 1) * n] += landmark_weight * (phi_l.T @ lm_gap[:, a])
    for a in range(3):
        blocks[a][a] = blocks[a][a] + extra
    system = sp.bmat(blocks, format="csr")
    # Conjugate gradients with a Jacobi preconditioner: the system is symmetric positive
    # definite and well conditioned by the regulariser, and a direct factorisation fills in
    # badly (tens of seconds at the finer supports).
    inverse_diagonal = 1.0 / np.maximum(system.diagonal(), 1e-300)
    preconditioner = spla.LinearOperator(system.shape, matvec=lambda x: inverse_diagonal * x)
    solution, _ = spla.cg(system, rhs, M=preconditioner, rtol=1e-6, maxiter=2000)
    return solution.reshape(3, n).T.copy()
