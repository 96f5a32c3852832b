"""Template adaptation: deform a template mesh onto a scan (method 2 of the design).

Given a template (any topology) with feature points and a scan (a mesh or a
Bosphorus grid, noisy, with holes) with the corresponding feature points,
:func:`adapt` returns the template's vertices moved onto the scan -- same topology,
the scan's shape -- and the error figures of each level:

1. calibration: the scan is brought into the template's frame (similarity over the
   feature pairs by default, or the method's axes calibration, or a given transform);
2. level 0: a global biharmonic RBF (phi(r) = r, affine part, K - rho I) maps the
   template's feature points onto the scan's;
3. levels k >= 1: f_k = f_{k-1} + o_k with CSRBF supports sigma_k = sigma_{k-1} / 2.
   By default (``refinement="surface"``) o_k is fitted point to plane to the closest
   scan points of every visible template vertex (a regularised non-rigid ICP step
   that asks each pair only for its distance to the scan's tangent plane);
   the method's own scheme (``refinement="interpolate"``) interpolates the residuals
   at the level's correspondences -- all feature-mesh pairs so far, plus curvature
   (and spread) vertices paired by rays from the current fit -- with a global RBF
   while the pairs are few and a CSRBF after;
4. after each level the distance error Ed, the marker error Em and E = alpha Ed +
   beta Em; the levels stop when E stops decreasing and the best level is returned;
5. with the surface refinement, the visible vertices are snapped along their normals
   onto the scan's tangent planes, and template vertices the scan never showed
   (nostrils, inner lips) take the harmonic fill, along the template mesh, of the
   paired vertices' displacements.

Defective data: noisy scans (rho and the CSRBF smoothing), missing feature points
(the curvature search and the feature mesh fill in), holes (rays that miss make no
pair; the coarse levels carry the fit across), and a wrong feature point (found by
leave-one-out prediction and left out) all run; a :class:`AdaptationWarning` says
where the result cannot be trusted.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ._validation import as_faces, as_points
from .calibration import calibrate
from .correspondence import (FeatureMesh, ScanTarget, curvature_features, match_shape_features, self_occluded,
                             shape_descriptor, spread_vertices)
from .csrbf import CSRBF, ConvergenceError, wendland
from .fit_error import combined_error, distance_error, marker_error, surface_noise
from .face.landmarks import N_LANDMARKS, landmark_index
from .mesh import vertex_normals, voronoi_areas
from .face.normalise import FrameTransform, similarity_transform
from .rbf import RBF
from .spatial import KDTree, MeshSurface

__all__ = [
    "AdaptationWarning",
    "AdaptLevel",
    "AdaptResult",
    "Correspondences",
    "SurfaceOffset",
    "adapt",
    "fill_unseen_offsets",
    "find_outlier_landmarks",
    "fit_surface_offset",
    "DEFAULT_FEATURE_BOX",
]

#: Landmarks whose bounding box (plus a margin) limits the curvature search: eyes to mouth.
DEFAULT_FEATURE_BOX = (
    "Outer left eye corner", "Outer right eye corner", "Inner left eye corner", "Inner right eye corner",
    "Nose tip", "Left mouth corner", "Right mouth corner", "Lower lip outer middle",
)


class AdaptationWarning(UserWarning):
    """Part of an adaptation cannot be trusted (holes, wrong or missing feature points, noise)."""


@dataclass(frozen=True)
class AdaptLevel:
    """The figures of one level of the multilevel fit (a row of the method's Tables 1-2)."""

    level: int
    method: str
    """"rbf" (global biharmonic) or "csrbf"."""
    support: float
    """CSRBF support sigma_k (mm, template frame); NaN for a global level."""
    pairs: int
    """Correspondences the level's offset was fitted to."""
    new_pairs: int
    """Of those, the pairs found at this level."""
    distance_error: float
    """Ed, mm^2 (scan frame)."""
    marker_error: float
    """Em, mm^2 (scan frame); NaN without held-out markers."""
    error: float
    """E = alpha Ed + beta Em."""
    coverage: float
    """Fraction of the template vertices in the feature points' bounding box that have a
    compatible scan vertex."""
    seconds: float
    """Time spent on the level (pairing, fit, evaluation and error)."""


@dataclass(frozen=True)
class Correspondences:
    """The template -> scan pairs the fit used, in the template frame."""

    template_points: np.ndarray
    """(n, 3) points on the undeformed template, mm."""
    scan_points: np.ndarray
    """(n, 3) the scan points they were paired with (calibrated frame), mm."""
    source: np.ndarray
    """(n,) str: "landmark", "feature-mesh", "curvature" or "spread"."""


@dataclass(frozen=True)
class AdaptResult:
    """The template fitted to a scan.

    Attributes
    ----------
    vertices : (n, 3) ndarray
        The deformed template, vertex for vertex, in the SCAN's frame (mm).
    template_frame_vertices : (n, 3) ndarray
        The same, in the template's frame (before undoing the calibration).
    transform : FrameTransform
        The calibration: scan frame -> template frame.
    levels : list of AdaptLevel
        Every level computed, including the one that made E rise (if any).
    best_level : int
        The level whose fit is returned (E at its minimum).
    correspondences : Correspondences
        The pairs of the returned level.
    outlier_landmarks : tuple of int
        Feature points left out of the fit as wrong.
    warnings : tuple of str
        The :class:`AdaptationWarning` messages given.
    """

    vertices: np.ndarray
    template_frame_vertices: np.ndarray
    transform: FrameTransform
    levels: list
    best_level: int
    correspondences: Correspondences
    outlier_landmarks: tuple = ()
    warnings: tuple = ()
    _fields: tuple = field(default=(), repr=False)

    def deform(self, points) -> np.ndarray:
        """Apply the fitted map (up to the best level) to template-frame points.

        Parameters
        ----------
        points : (m, 3) array_like
            Points in the template's frame (mm).

        Returns
        -------
        (m, 3) ndarray in the scan's frame (mm).
        """
        points = as_points(points, "points")
        return self.transform.apply_inverse(_evaluate(self._fields, points))

    def __repr__(self) -> str:
        best = next((lv for lv in self.levels if lv.level == self.best_level), None)
        error = f", E {best.error:.3g}" if best is not None else ""
        return (f"AdaptResult({len(self.vertices)} vertices, best level {self.best_level} of "
                f"{len(self.levels)}{error}, {len(self.correspondences.template_points)} pairs, "
                f"{len(self.outlier_landmarks)} outlier landmarks, {len(self.warnings)} warnings)")

    def table(self) -> str:
        """The per-level figures as a Markdown table."""
        rows = ["| level | method | sigma (mm) | pairs | Ed (mm^2) | Em (mm^2) | E | coverage | time (s) |",
                "|---|---|---|---|---|---|---|---|---|"]
        for lv in self.levels:
            mark = " *" if lv.level == self.best_level else ""
            rows.append(f"| {lv.level}{mark} | {lv.method} | {lv.support:.1f} | {lv.pairs} | "
                        f"{lv.distance_error:.3f} | {lv.marker_error:.3f} | {lv.error:.3f} | "
                        f"{lv.coverage:.2f} | {lv.seconds:.3f} |")
        return "\n".join(rows)


def _evaluate(fields, points: np.ndarray) -> np.ndarray:
    """f(points) = f_0(points) + sum of the offsets."""
    result = fields[0](points)
    for offset in fields[1:]:
        result = result + offset(points)
    return result


def _as_mesh(obj, name: str):
    """(vertices, faces) from a FaceGrid, GridMesh, BntScan, MeshSurface or (vertices, faces)."""
    from .face.io import BntScan
    from .face.grid import FaceGrid, GridMesh

    if isinstance(obj, FaceGrid):
        mesh = obj.mesh()
        return mesh.vertices, mesh.faces
    if isinstance(obj, GridMesh):
        return obj.vertices, obj.faces
    if isinstance(obj, BntScan):
        mesh = FaceGrid.from_points(obj.points).mesh()
        return mesh.vertices, mesh.faces
    if isinstance(obj, MeshSurface):
        return obj.vertices, obj.faces
    try:
        vertices, faces = obj
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a (vertices, faces) pair, a FaceGrid, a GridMesh or a BntScan, "
            f"got {type(obj).__name__}") from None
    vertices = as_points(vertices, f"{name} vertices", allow_empty=False)
    return vertices, as_faces(faces, len(vertices), f"{name} faces")


def _as_feature_points(landmarks, vertices: np.ndarray, name: str) -> np.ndarray:
    """(k, 3) points with NaN rows; integer input (k,) are vertex indices (-1 missing)."""
    array = np.asarray(landmarks)
    if array.ndim == 1 and np.issubdtype(array.dtype, np.integer):
        index = array.astype(np.int64)
        if index.size and index.max() >= len(vertices):
            raise ValueError(f"{name}: vertex index {index.max()} is out of range ({len(vertices)} vertices)")
        points = np.full((len(index), 3), np.nan)
        points[index >= 0] = vertices[index[index >= 0]]
        return points
    return as_points(landmarks, name, finite=False)


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
        import scipy.sparse as sp

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
                       weights=None, point_weight: float = 0.0, landmark_template=None,
                       landmark_current=None, landmark_targets=None, landmark_weight: float = 1.0,
                       regularisation: float = 1.0) -> np.ndarray:
    """Coefficients of the offset that best moves the current fit onto the scan.

    Minimises, over the coefficients c (n, 3) of `field`'s basis,

        sum_i w_i (m_i . (x_i + o(p_i) - q_i))^2 + point_weight sum_i w_i |x_i + o(p_i) - q_i|^2
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
    weights : (m,) ndarray, optional
        w_i (default 1).
    point_weight : float
        eta, the weak point-to-point term (it keeps the sliding small where the
        surface does not fix it).
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
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = len(field.centres)
    phi = field.matrix(template_points)
    w = np.ones(len(template_points)) if weights is None else np.asarray(weights, dtype=np.float64)
    residual = np.einsum("ij,ij->i", scan_normals, targets - current)
    blocks = [[None] * 3 for _ in range(3)]
    rhs = np.zeros(3 * n)
    gap = targets - current
    for a in range(3):
        rhs[a * n:(a + 1) * n] = phi.T @ (w * (scan_normals[:, a] * residual + point_weight * gap[:, a]))
        for b in range(a, 3):
            diagonal = w * scan_normals[:, a] * scan_normals[:, b]
            if a == b:
                diagonal = diagonal + point_weight * w
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


def fill_unseen_offsets(template_vertices, template_faces, offsets, anchored, *, order: int = 2,
                        cotangent: bool = True) -> np.ndarray:
    """Offsets over the template with the unanchored vertices filled in along the mesh.

    The refinement levels know the scan only where the template was paired with it.
    Vertices the scanner could not see (inside the nostrils, between the lips, under
    the nose) are close in space to paired vertices of other parts of the face (the
    upper lip, the ala), so a field over 3D space hands them those parts' offsets.
    Along the mesh they are connected to their own rims instead: here their offsets
    are the (bi)harmonic interpolation of the anchored vertices' offsets, minimising
    ``|L d|^2`` (order 2) or ``d^T (-L) d`` (order 1) with the anchored offsets fixed.

    Parameters
    ----------
    template_vertices : (n, 3) ndarray
        The undeformed template (mm).
    template_faces : (m, 3) int ndarray
    offsets : (n, 3) ndarray
        Current offsets (mm); kept at the anchored vertices.
    anchored : (n,) bool
        Vertices whose offsets the scan determined.
    order : {1, 2}
        Harmonic (1) or biharmonic (2) fill.
    cotangent : bool
        Cotangent weights (True) or uniform (graph) weights.

    Returns
    -------
    (n, 3) ndarray.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from .mesh import cotan_laplacian

    n = len(template_vertices)
    free = ~anchored
    used = np.zeros(n, dtype=bool)
    used[np.unique(template_faces)] = True
    free &= used
    if not free.any() or not anchored.any():
        return offsets
    if cotangent:
        laplacian = cotan_laplacian(template_vertices, template_faces)
    else:
        edges = np.concatenate([template_faces[:, [0, 1]], template_faces[:, [1, 2]], template_faces[:, [2, 0]]])
        edges = np.unique(np.sort(edges, axis=1), axis=0)
        ones = np.ones(len(edges))
        adjacency = sp.coo_matrix((np.r_[ones, ones], (np.r_[edges[:, 0], edges[:, 1]],
                                                        np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
        laplacian = adjacency - sp.diags(np.asarray(adjacency.sum(axis=1)).ravel())
    operator = (laplacian.T @ laplacian) if order == 2 else -laplacian
    operator = operator.tocsr()
    free_rows = np.flatnonzero(free)
    fixed_rows = np.flatnonzero(~free)
    a_ff = operator[free_rows][:, free_rows].tocsc()
    a_fx = operator[free_rows][:, fixed_rows]
    rhs = -(a_fx @ offsets[fixed_rows])
    # A tiny diagonal keeps islands of free vertices with no anchored neighbour solvable.
    a_ff = a_ff + 1e-9 * sp.identity(len(free_rows), format="csc")
    filled = offsets.copy()
    filled[free_rows] = spla.splu(a_ff).solve(np.asarray(rhs))
    return filled


def find_outlier_landmarks(template_points, scan_points, *, threshold: float = 6.0,
                           smoothing: float = 1.0, max_outliers: int = 3) -> list[int]:
    """Feature points whose scan position disagrees with all the others.

    Each present pair is predicted from the others by a biharmonic RBF (leave one
    out); the pair with the largest miss is removed while its miss exceeds both
    `threshold` and three times the median miss, up to `max_outliers` times.

    Parameters
    ----------
    template_points, scan_points : (k, 3) array_like
        Corresponding points (mm, scan already calibrated); NaN rows missing.
    threshold : float
        Smallest miss (mm) that counts as wrong.

    Returns
    -------
    list of int, the rows judged wrong (worst first).
    """
    template = as_points(template_points, "template_points", finite=False)
    scan = as_points(scan_points, "scan_points", finite=False)
    active = np.isfinite(template).all(axis=1) & np.isfinite(scan).all(axis=1)
    outliers: list[int] = []
    while len(outliers) < max_outliers and active.sum() > 7:
        rows = np.flatnonzero(active)
        misses = np.empty(len(rows))
        for k, row in enumerate(rows):
            others = rows[rows != row]
            try:
                field_ = RBF(template[others], scan[others] - template[others], "biharmonic",
                             smoothing=smoothing)
            except ValueError:
                misses[k] = 0.0
                continue
            predicted = template[row] + field_(template[row][None])[0]
            misses[k] = np.linalg.norm(predicted - scan[row])
        worst = int(np.argmax(misses))
        if misses[worst] > threshold and misses[worst] > 3.0 * np.median(misses):
            outliers.append(int(rows[worst]))
            active[rows[worst]] = False
        else:
            break
    return outliers


def _dedupe(template_points, scan_points, sources, tolerance: float):
    """Keep the first of pairs whose template points are closer than `tolerance`."""
    if len(template_points) < 2:
        return template_points, scan_points, sources
    keys = np.floor(template_points / tolerance).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return template_points[first], scan_points[first], sources[first]


def adapt(template, scan, template_landmarks, scan_landmarks=None, *, levels: int = 6,
          calibration="similarity", rho: float = 30.0, dense_threshold: int = 500,
          initial_support: float | None = None, csrbf_smoothing: float = 2.0, quadric: bool = False,
          curvature_count: int = 300, feature_mesh_levels: int = 1, feature_box=DEFAULT_FEATURE_BOX, spread: bool = True,
          held_out_landmarks=(), markers=None, alpha: float = 1.0, beta: float = 1.0,
          distance_threshold: float | None = None, vertex_weights=None, rigid_parts=None,
          scan_view=(0.0, 0.0, 1.0), outlier_threshold: float = 15.0, stop_at_minimum: bool = True,
          noise_warning_mm: float = 0.6, refinement: str = "surface", surface_iterations: int = 2,
          regularisation: float = 5.0, point_weight: float = 0.0, landmark_weight: float = 0.3,
          centre_spacing: float = 1.0 / 3.0, min_support: float | None = None, fill_unseen: bool = True,
          shape_match_weight: float = 0.0, shape_match_radius: float = 3.0, shape_radii=(5.0, 10.0),
          shape_scale: float = 1.0, fill_blend: float = 1.0, fill_order: int = 1, fill_margin: int = 0,
          fill_cotangent: bool = True, fill_base: str = "none", incidence_power: float = 0.0,
          snap: bool = True, snap_rings: int = 1,
          progress: Callable[[AdaptLevel], None] | None = None) -> AdaptResult:
    """Fit a template mesh to a scan with a global RBF and multilevel CSRBF.

    Parameters
    ----------
    template : (vertices, faces), FaceGrid or GridMesh
        The template mesh (mm), any topology; faces consistently oriented with
        normals facing out of the face (toward +z in the template frame).
    scan : (vertices, faces), FaceGrid, GridMesh or BntScan
        The scan surface (mm), in its own frame; noise and holes allowed.
    template_landmarks : (k, 3) array_like, or (k,) int vertex indices
        Feature points on the template (NaN rows or -1 missing). With k = 22 they are
        the Bosphorus landmarks, which the defaults (calibration, curvature box)
        use by name.
    scan_landmarks : (k, 3) array_like, optional
        The corresponding scan points (NaN rows missing); defaults to the
        FaceGrid's landmarks when `scan` is a FaceGrid.
    levels : int
        Largest number of levels (level 0 is the landmark RBF), >= 1.
    calibration : {"similarity", "axes", "none"} or FrameTransform
        How the scan is brought into the template frame; a FrameTransform (scan ->
        template) is used as given, "none" skips calibration (scan and template
        already share a frame).
    rho : float
        Error coefficient of the global RBF levels, mm (K - rho I), >= 0. 30 smooths
        the level-0 landmark RBF against the feature points' annotation noise (0.8 mm
        per axis on the benchmark); 10 and 100 measured slightly worse.
    dense_threshold : int
        Global RBF while a level has fewer pairs than this, CSRBF after.
    initial_support : float, optional
        sigma_1 (mm, template frame); sigma_k = sigma_{k-1} / 2. Default: a fifth of
        the template's width.
    csrbf_smoothing : float
        Diagonal term of the CSRBF levels (>= 0), against scan noise.
    quadric : bool
        Fit the CSRBF local quadrics g_j in each centre's tangent frame. Off by
        default: on the ICT benchmark the quadrics, fitted to residual fields that are
        noisy at the scale of the support, raised the true error (see the README).
    curvature_count : int
        Curvature vertices paired at each level (0 switches the search off).
    feature_mesh_levels : int
        Levels at which the feature mesh is subdivided (its points carry the feature
        points' annotation error, so ever finer subdivision only adds that noise).
    feature_box : sequence of landmark names, or ((3,), (3,)) corners, or None
        Limits the curvature search (template frame); None: the whole template.
    spread : bool
        Also pair evenly spread template vertices (spacing sigma_k / 4) at every
        level, so the fit reaches beyond the feature points' hull.
    held_out_landmarks : sequence of names or indices
        Landmarks kept out of the fit and used as markers for Em.
    markers : (template_points (m, 3), scan_points (m, 3)), optional
        More marker pairs for Em (template frame, scan frame), never fitted.
    alpha, beta : float
        Weights of Ed and Em in E.
    distance_threshold : float, optional
        Ed's compatibility distance (mm); default a tenth of the template's width.
    vertex_weights : (n,) array_like, optional
        Per-vertex (region) weights of Ed, >= 0.
    rigid_parts : sequence of index arrays, optional
        Groups of template vertices (eyes, teeth) that move rigidly: each follows
        the similarity fitted to the six feature points nearest to it.
    scan_view : (3,) array_like or None
        Direction from the scan toward its scanner, in the scan frame (+z for
        Bosphorus); template points facing away cannot have been scanned and are
        not paired. None disables the test.
    outlier_threshold : float
        Leave-one-out miss (mm) above which a feature point is judged wrong. On the
        ICT development subjects correct landmarks miss by up to about 13 mm (chin,
        nose tip: identity differences the others do not predict), so errors below
        about 15 mm cannot be told from identity this way and are kept.
    stop_at_minimum : bool
        Stop at the first level where E rises (return the best level); False runs
        every level and still returns the best.
    noise_warning_mm : float
        Warn when the estimated scan noise exceeds this (mm).
    refinement : {"surface", "interpolate"}
        How the levels after level 0 use the scan. ``"surface"`` (default): each
        level is a CSRBF offset (support sigma_k, centres spread at
        ``centre_spacing * sigma_k``) fitted point to plane to the closest scan
        points of all visible template vertices, with the feature points as weak
        point-to-point terms and the offset's native norm as regulariser, iterated
        ``surface_iterations`` times per level (see :func:`fit_surface_offset`).
        It pairs every visible vertex, not a few hundred, and asks no pair to keep
        the sliding the feature points gave it. ``"interpolate"``: the method's pairs (feature mesh, curvature
        and spread vertices, rays along the normals) are interpolated by a global RBF
        below ``dense_threshold`` pairs and a CSRBF after; this ties every pair's
        sliding to the feature points. On the ICT benchmark ``"surface"`` lowered the
        true error from 1.55 to 1.17 mm on the tuning subjects (see the README).
    surface_iterations : int
        Closest-point / solve rounds per ``"surface"`` level.
    regularisation : float
        lambda of the ``"surface"`` levels (weight of the offset's native norm,
        relative to one surface pair), > 0. With the harmonic fill, 3, 5 and 7 measured 1.133,
        1.132 and 1.136 mm on the tuning subjects, 10 gave 1.143 and 20 1.177.
    point_weight : float
        Weight of a point-to-point term on the surface pairs (0: point to plane only).
    landmark_weight : float
        Weight of each feature point in the ``"surface"`` levels, in surface pairs.
        Small: the feature points carry about 1 mm of annotation error, which level
        0 has already spread over the face; the surface should override them.
    centre_spacing : float
        Spacing of the ``"surface"`` offset's centres, as a fraction of sigma_k.
    min_support : float, optional
        ``"surface"`` levels stop once sigma_k falls below this (mm, template
        frame); default a tenth of the template's width (finer levels cost seconds
        and gained under 0.01 mm on the benchmark).
    fill_unseen : bool
        After a ``"surface"`` fit, replace the displacement of template vertices
        that were never paired (the scanner could not see them: inside the
        nostrils, between the lips, under the nose; or over holes) by the
        biharmonic interpolation along the template mesh of the paired vertices'
        displacements (:func:`fill_unseen_offsets`). :meth:`AdaptResult.deform` does
        not include this step nor the snap (both are defined on the mesh, not in
        space).
    fill_order : {1, 2}
        Harmonic (1, default) or biharmonic (2) fill. On the tuning subjects the
        harmonic fill measured 1.14 mm against 1.17 mm: the biharmonic one carries
        the rims' slope into the holes and overshoots inside the nostrils.
    fill_cotangent : bool
        Cotangent (default) or uniform weights of the fill's Laplacian.
    fill_blend : float
        The unpaired vertices take ``fill_blend * filled + (1 - fill_blend) * fitted``
        (1: the fill alone; 0.5 measured 1.20 mm against 1.17 mm).
    fill_base : {"none", "level0"}
        What the fill interpolates: the whole displacement ("none", default) or only
        what lies beyond level 0's landmark RBF ("level0": 1.23 mm against 1.14 mm).
    fill_margin : int
        Rings of paired vertices next to unpaired ones that the fill also replaces
        (0; 1 measured 1.15 mm against 1.14 mm).
    incidence_power : float
        Weight each surface pair by (scan normal . view direction) ** this (0: all
        pairs equal, default; 1 measured 1.17 mm against 1.14 mm).
    snap : bool
        After a ``"surface"`` fit (before the fill), move every visible paired vertex
        along its normal by its (smoothed) distance to the scan's tangent plane at
        its closest point. The CSRBF levels stop at a support of a tenth of the
        width and leave fine relief (lip and alar creases, eyelids) a few tenths of
        a millimetre short; the snap closes that gap vertex by vertex (1.132 ->
        1.109 mm on the tuning subjects) without the seconds a third level costs.
        It moves nothing sideways. The vertices it moves are the fill's anchors.
    snap_rings : int
        One-ring averages of the snap distances over the paired neighbours, against
        scan noise (0 measured 1.105 mm, 1 1.109 mm, 3 1.114 mm).
    shape_match_weight : float
        Weight (in surface pairs, scaled by the match's confidence) of point-to-point
        terms that slide each closest-point partner to the nearby scan point whose
        shape descriptor matches the template's (:func:`~tpscore.correspondence.match_shape_features`).
        0 (default) switches it off: it measured no better (1.17 mm at 0.3, 1.28 mm
        at 1) and costs about 2.5 s per fit.
    shape_match_radius : float
        Search radius of the shape matching (mm, template frame).
    shape_radii : sequence of float
        Scales of the :func:`~tpscore.correspondence.shape_descriptor` (mm).
    shape_scale : float
        Descriptor difference counted as one unit of matching cost, in standard
        deviations of the scan's descriptor.
    progress : callable, optional
        Called with each finished :class:`AdaptLevel`.

    Returns
    -------
    AdaptResult

    Raises
    ------
    ValueError
        Bad arguments, or fewer than 5 usable feature pairs.
    """
    template_vertices, template_faces = _as_mesh(template, "template")
    scan_vertices, scan_faces = _as_mesh(scan, "scan")
    if scan_landmarks is None:
        from .face.grid import FaceGrid

        if not isinstance(scan, FaceGrid):
            raise ValueError("scan_landmarks is required unless scan is a FaceGrid with landmarks")
        scan_landmarks = scan.landmarks
    template_lm = _as_feature_points(template_landmarks, template_vertices, "template_landmarks")
    scan_lm = as_points(scan_landmarks, "scan_landmarks", finite=False)
    if scan_lm.shape != template_lm.shape:
        raise ValueError(f"scan_landmarks must have shape {template_lm.shape} like template_landmarks, "
                         f"got {scan_lm.shape}")
    if int(levels) != levels or levels < 1:
        raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
    for value, label in ((rho, "rho"), (csrbf_smoothing, "csrbf_smoothing"), (alpha, "alpha"),
                         (beta, "beta")):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{label} must be finite and >= 0, got {value!r}")
    if fill_base not in ("none", "level0"):
        raise ValueError(f"fill_base must be 'none' or 'level0', got {fill_base!r}")
    if fill_order not in (1, 2):
        raise ValueError(f"fill_order must be 1 or 2, got {fill_order!r}")
    if not 0.0 <= fill_blend <= 1.0:
        raise ValueError(f"fill_blend must be in [0, 1], got {fill_blend!r}")
    if int(snap_rings) != snap_rings or snap_rings < 0:
        raise ValueError(f"snap_rings must be an integer >= 0, got {snap_rings!r}")
    if int(fill_margin) != fill_margin or fill_margin < 0:
        raise ValueError(f"fill_margin must be an integer >= 0, got {fill_margin!r}")
    if refinement not in ("surface", "interpolate"):
        raise ValueError(f"refinement must be 'surface' or 'interpolate', got {refinement!r}")
    for value, label in ((regularisation, "regularisation"), (centre_spacing, "centre_spacing")):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{label} must be finite and > 0, got {value!r}")
    for value, label in ((point_weight, "point_weight"), (landmark_weight, "landmark_weight"),
                         (shape_match_weight, "shape_match_weight"), (shape_match_radius, "shape_match_radius"),
                         (shape_scale, "shape_scale"), (incidence_power, "incidence_power")):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{label} must be finite and >= 0, got {value!r}")
    if int(surface_iterations) != surface_iterations or surface_iterations < 1:
        raise ValueError(f"surface_iterations must be an integer >= 1, got {surface_iterations!r}")
    n_vertices = len(template_vertices)
    if vertex_weights is not None:
        vertex_weights = np.asarray(vertex_weights, dtype=np.float64)
        if vertex_weights.shape != (n_vertices,) or not np.isfinite(vertex_weights).all() \
                or (vertex_weights < 0).any():
            raise ValueError(f"vertex_weights must be {n_vertices} finite non-negative numbers")

    messages: list[str] = []

    def warn(message: str) -> None:
        messages.append(message)
        warnings.warn(message, AdaptationWarning, stacklevel=3)

    names = None
    if len(template_lm) == N_LANDMARKS:
        from .face.landmarks import LANDMARK_NAMES

        names = LANDMARK_NAMES
    label = (lambda i: names[i]) if names else (lambda i: f"feature point {i}")

    # --- feature points: which take part in the fit, which are markers ----------------
    held = set()
    for item in held_out_landmarks:
        held.add(landmark_index(item) if isinstance(item, str) else int(item))
    present = np.isfinite(template_lm).all(axis=1) & np.isfinite(scan_lm).all(axis=1)
    missing = [i for i in range(len(template_lm)) if not present[i]]
    if missing:
        warn(f"{len(missing)} feature point(s) missing ({', '.join(label(i) for i in missing)}); "
             "the feature mesh and the curvature search fill in around them")
    fit_mask = present.copy()
    fit_mask[list(held)] = False

    # --- calibration ------------------------------------------------------------------
    if isinstance(calibration, str) and calibration == "axes" and names is None:
        raise ValueError("calibration='axes' needs the 22 Bosphorus landmarks")
    calib_lm = np.where(fit_mask[:, None], scan_lm, np.nan)
    transform = calibrate(calib_lm, template_lm, calibration)
    scale = transform.scale
    scan_points = transform.apply(scan_vertices)
    scan_lm_t = transform.apply(scan_lm)
    outliers = find_outlier_landmarks(np.where(fit_mask[:, None], template_lm, np.nan), scan_lm_t,
                                      threshold=outlier_threshold * scale)
    if outliers:
        warn(f"feature point(s) {', '.join(label(i) for i in outliers)} disagree with the others by more "
             f"than {outlier_threshold:g} mm and were left out of the fit; check them")
        fit_mask[outliers] = False
        if calibration in ("similarity", "axes"):
            transform = calibrate(np.where(fit_mask[:, None], scan_lm, np.nan), template_lm, calibration)
            scale = transform.scale
            scan_points = transform.apply(scan_vertices)
            scan_lm_t = transform.apply(scan_lm)
    if fit_mask.sum() < 5:
        raise ValueError(f"adaptation needs at least 5 feature pairs present on both faces, got {int(fit_mask.sum())}")

    target = ScanTarget(scan_points, scan_faces)
    template_surface = MeshSurface(template_vertices, template_faces)
    scan_tree = KDTree(scan_points)
    view = None
    if scan_view is not None:
        view = transform.apply_vectors(np.asarray(scan_view, dtype=np.float64))
        view = view / np.linalg.norm(view)
    extent = template_vertices.max(axis=0) - template_vertices.min(axis=0)
    width = float(extent[0])
    threshold = distance_threshold if distance_threshold is not None else width / 10.0
    sigma = float(initial_support) if initial_support is not None else width / 5.0
    smallest_support = float(min_support) if min_support is not None else width / 10.0
    # Rays longer than this find another part of the face rather than the same one.
    max_ray = max(0.05 * width, 4.0)

    box = None
    if feature_box is not None:
        if names is not None and all(isinstance(n, str) for n in feature_box):
            rows = template_lm[[landmark_index(n) for n in feature_box]]
            rows = rows[np.isfinite(rows).all(axis=1)]
            if len(rows):
                margin = 0.05 * width
                box = (rows.min(axis=0) - margin, rows.max(axis=0) + margin)
        else:
            box = tuple(np.asarray(c, dtype=np.float64).reshape(3) for c in feature_box)

    # Landmarks lie on the scan only to within their annotation error: move each onto the
    # surface (its normal error is pure noise) when the surface is close.
    fit_rows = np.flatnonzero(fit_mask)
    landmark_targets = scan_lm_t[fit_rows].copy()
    closest = target.surface.closest_point(landmark_targets)
    near = closest.distances < 2.0 * max_ray
    landmark_targets[near] = closest.points[near]
    landmark_sources = template_lm[fit_rows]

    marker_template = []
    marker_scan = []
    for i in sorted(held):
        if present[i]:
            marker_template.append(template_lm[i])
            marker_scan.append(scan_lm_t[i])
    if markers is not None:
        mt, ms = markers
        mt = as_points(mt, "markers template points", finite=False)
        ms = as_points(ms, "markers scan points", finite=False)
        if mt.shape != ms.shape:
            raise ValueError("markers: template and scan points must have the same shape")
        marker_template.extend(mt)
        marker_scan.extend(transform.apply(ms))
    marker_template = np.asarray(marker_template, dtype=np.float64).reshape(-1, 3)
    marker_scan = np.asarray(marker_scan, dtype=np.float64).reshape(-1, 3)

    # Coverage is judged over the part of the template the feature points span: a
    # template may reach well beyond what any scan of the face shows (ears, neck).
    lm_rows = template_lm[fit_mask]
    hull_margin = 0.05 * width
    inside_features = np.all((template_vertices >= lm_rows.min(axis=0) - hull_margin)
                             & (template_vertices <= lm_rows.max(axis=0) + hull_margin), axis=1)

    def errors(fields, deformed):
        normals = vertex_normals(deformed, template_faces)
        ed = distance_error(deformed, normals, scan_tree, target.vertex_normals, threshold=threshold,
                            weights=vertex_weights, scan_rim=target.rim_vertices)
        em = marker_error(_evaluate(fields, marker_template), marker_scan) if len(marker_template) else np.nan
        weights = np.ones(n_vertices) if vertex_weights is None else vertex_weights
        active = inside_features & (weights > 0)
        coverage = float(np.isfinite(ed.distances[active]).mean()) if active.any() else 0.0
        ed_value, em_value = ed.value / scale**2, em / scale**2
        return ed_value, em_value, combined_error(ed_value, em_value, alpha, beta), coverage, normals

    # --- level 0: global RBF over the feature points ------------------------------------
    level_start = time.perf_counter()
    first = RBF(landmark_sources, landmark_targets, "biharmonic", smoothing=rho)
    fields = [first]
    deformed = first(template_vertices)
    ed, em, e, coverage, normals = errors(fields, deformed)
    report = AdaptLevel(0, "rbf", float("nan"), len(fit_rows), len(fit_rows), ed, em, e, coverage,
                        time.perf_counter() - level_start)
    reports = [report]
    if progress:
        progress(report)
    sources = np.array(["landmark"] * len(fit_rows), dtype=object)
    pairs_template, pairs_scan = landmark_sources.copy(), landmark_targets.copy()
    best = (e, 0, list(fields), deformed, (pairs_template, pairs_scan, sources))

    feature_mesh = None
    if len(fit_rows) >= 3:
        try:
            feature_mesh = FeatureMesh.build(landmark_sources, landmark_targets,
                                             view if view is not None else (0.0, 0.0, 1.0))
        except ValueError:
            feature_mesh = None
    curvature_vertices = np.zeros(0, dtype=np.int64)
    if curvature_count > 0 and refinement == "interpolate":
        curvature_vertices = curvature_features(template_vertices, template_faces, curvature_count,
                                                box=box, spacing=0.01 * width)
    fm_template = np.zeros((0, 3))
    fm_scan = np.zeros((0, 3))
    shape_radii = tuple(float(r) for r in shape_radii)
    scan_shape = shape_scale_k = None
    if refinement == "surface" and shape_match_weight > 0:
        scan_shape = shape_descriptor(scan_points, target.vertex_normals, scan_points,
                                      voronoi_areas(scan_points, scan_faces), shape_radii)
        shape_scale_k = shape_scale * np.nanstd(scan_shape, axis=0)
    best_anchors = np.zeros(0, dtype=np.int64)

    for level in range(1, int(levels)):
        level_start = time.perf_counter()
        if refinement == "surface":
            if sigma < smallest_support * (1 - 1e-9):
                break
            spacing = max(sigma * centre_spacing, 1e-3 * width)
            centres = template_vertices[spread_vertices(template_vertices, spacing)]
            offset = SurfaceOffset(centres, np.zeros((len(centres), 3)), sigma)
            current = deformed
            current_normals = normals
            for _ in range(int(surface_iterations)):
                candidates = np.ones(n_vertices, dtype=bool)
                if view is not None:
                    candidates &= current_normals @ view >= 0.2
                    candidates &= ~self_occluded(current, template_faces, view)
                rows = np.flatnonzero(candidates)
                hit, partners, partner_normals = target.closest(current[rows], current_normals[rows],
                                                                max_distance=max_ray)
                rows = rows[hit]
                pair_targets, pair_normals = partners[hit], partner_normals[hit]
                pair_point_weight = np.full(len(rows), float(point_weight))
                pair_weights = None
                if incidence_power > 0 and view is not None:
                    # Grazing scan samples are the sparsest and noisiest.
                    pair_weights = np.clip(pair_normals @ view, 0.05, 1.0) ** incidence_power
                if scan_shape is not None:
                    template_shape = shape_descriptor(current[rows], current_normals[rows], current,
                                                      voronoi_areas(current, template_faces), shape_radii)
                    pair_targets, confidence = match_shape_features(
                        template_shape, pair_targets, pair_normals, scan_points, scan_shape,
                        radius=shape_match_radius, scale=shape_scale_k)
                    pair_point_weight = pair_point_weight + shape_match_weight * confidence
                coefficients = fit_surface_offset(
                    offset, template_vertices[rows], current[rows], pair_targets, pair_normals,
                    weights=pair_weights, point_weight=pair_point_weight, landmark_template=landmark_sources,
                    landmark_current=_evaluate(fields, landmark_sources) + offset(landmark_sources),
                    landmark_targets=landmark_targets, landmark_weight=landmark_weight,
                    regularisation=regularisation)
                offset = offset.plus(coefficients)
                current = deformed + offset(template_vertices)
                current_normals = vertex_normals(current, template_faces)
            method, support = "surface", sigma
            all_template, all_scan = template_vertices[rows], pair_targets
            all_sources = np.array(["surface"] * len(rows), dtype=object)
            new = len(rows)
            candidate = fields + [offset]
            deformed_next = current
        else:
            new = 0
            if feature_mesh is not None and level <= feature_mesh_levels:
                feature_mesh, new_t, new_s = feature_mesh.subdivide(template_surface, target,
                                                                   max_distance=max_ray * 2)
                fm_template = np.vstack([fm_template, new_t])
                fm_scan = np.vstack([fm_scan, new_s])
                new += len(new_t)
            chosen = curvature_vertices
            kinds = ["curvature"] * len(chosen)
            use_spread = spread
            if use_spread:
                spacing = max(sigma / 4.0, 1e-3 * width)
                extra = spread_vertices(template_vertices, spacing)
                extra = np.setdiff1d(extra, chosen)
                chosen = np.concatenate([chosen, extra])
                kinds = kinds + ["spread"] * len(extra)
            hit, hit_points = target.cast(deformed[chosen], normals[chosen], max_distance=max_ray,
                                          view_direction=view)
            ray_template = template_vertices[chosen[hit]]
            ray_scan = hit_points[hit]
            ray_kinds = np.array(kinds, dtype=object)[hit]
            new += len(ray_template)

            all_template = np.vstack([landmark_sources, fm_template, ray_template])
            all_scan = np.vstack([landmark_targets, fm_scan, ray_scan])
            all_sources = np.concatenate([np.array(["landmark"] * len(landmark_sources), dtype=object),
                                          np.array(["feature-mesh"] * len(fm_template), dtype=object), ray_kinds])
            all_template, all_scan, all_sources = _dedupe(all_template, all_scan, all_sources, 1e-3 * width)
            residual = all_scan - _evaluate(fields, all_template)
            if len(all_template) < dense_threshold:
                method, support = "rbf", float("nan")
                offset = RBF(all_template, residual, "biharmonic", smoothing=rho)
            else:
                method, support = "csrbf", sigma
                try:
                    offset = CSRBF(all_template, residual, sigma, quadric=quadric, smoothing=csrbf_smoothing,
                                   tolerance=1e-8)
                except ConvergenceError:
                    warn(f"level {level}: the CSRBF solve did not converge; the fit stops at level {level - 1}")
                    break
            candidate = fields + [offset]
            deformed_next = deformed + offset(template_vertices)
        # the end of every level: errors, report, keep the best, stop past the minimum
        ed, em, e, coverage, normals_next = errors(candidate, deformed_next)
        report = AdaptLevel(level, method, support, len(all_template), new, ed, em, e, coverage,
                            time.perf_counter() - level_start)
        reports.append(report)
        if progress:
            progress(report)
        sigma /= 2.0
        if np.isfinite(e) and e < best[0] or not np.isfinite(best[0]):
            best = (e, level, candidate, deformed_next, (all_template, all_scan, all_sources))
            if refinement == "surface":
                best_anchors = rows
        elif stop_at_minimum:
            break
        fields, deformed, normals = candidate, deformed_next, normals_next

    _, best_level, fields, deformed, (pt, ps, src) = best
    deformed = deformed.copy()
    if snap and best_level > 0 and refinement == "surface":
        import scipy.sparse as sparse

        # Move the paired vertices the rest of the way to the scan along its normals.
        snap_normals = vertex_normals(deformed, template_faces)
        rows = np.arange(n_vertices)
        if view is not None:
            rows = rows[(snap_normals @ view >= 0.2) & ~self_occluded(deformed, template_faces, view)]
        hit, partners, partner_normals = target.closest(deformed[rows], snap_normals[rows], max_distance=max_ray)
        rows, partners, partner_normals = rows[hit], partners[hit], partner_normals[hit]
        gap = np.zeros(n_vertices)
        gap[rows] = np.einsum("ij,ij->i", partner_normals, partners - deformed[rows])
        counted = np.zeros(n_vertices)
        counted[rows] = 1.0
        edges = np.concatenate([template_faces[:, [0, 1]], template_faces[:, [1, 2]], template_faces[:, [2, 0]]])
        ring = sparse.coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]],
                                                         np.r_[edges[:, 1], edges[:, 0]])),
                             shape=(n_vertices, n_vertices)).tocsr()
        ring.data[:] = 1.0
        ring = ring + sparse.identity(n_vertices, format="csr")
        smooth = gap
        for _ in range(int(snap_rings)):
            # Average over the paired one-ring neighbours: the scan's noise (0.15 mm on the
            # benchmark) would otherwise go straight into the fit.
            smooth = (ring @ (smooth * counted)) / np.maximum(ring @ counted, 1.0)
        moved = np.zeros(n_vertices, dtype=bool)
        moved[rows] = True
        deformed[moved] += smooth[moved, None] * snap_normals[moved]
        best_anchors = rows
    if fill_unseen and best_level > 0 and refinement == "surface":
        # The whole displacement is filled, not only the refinement offsets: level 0's
        # field over 3D space carries the same fault (a nostril takes the upper lip's
        # displacement). Filling it measured better than filling only what lies beyond
        # level 0 (1.17 against 1.20 mm on the tuning subjects) or beyond level 0's
        # affine part (1.20 mm), at a price: a mesh fill does not reproduce a linear
        # field on a curved surface, so an affine map is no longer reproduced exactly
        # at the unpaired vertices (about 0.2 mm for a 5% shear; see the tests).
        anchored = np.zeros(n_vertices, dtype=bool)
        anchored[best_anchors] = True
        for _ in range(int(fill_margin)):
            # Paired vertices next to unpaired ones sit at rims (nostril, lip line) where the
            # closest points are least reliable: let the fill carry them too.
            touching = np.zeros(n_vertices, dtype=bool)
            touching[template_faces[(~anchored[template_faces]).any(axis=1)].ravel()] = True
            anchored &= ~touching
        base = template_vertices if fill_base == "none" else fields[0](template_vertices)
        filled = base + fill_unseen_offsets(template_vertices, template_faces, deformed - base, anchored,
                                            order=fill_order, cotangent=fill_cotangent)
        deformed = fill_blend * filled + (1.0 - fill_blend) * deformed

    if rigid_parts:
        lm_after = _evaluate(fields, landmark_sources)
        for part_index, part in enumerate(rigid_parts):
            part = np.asarray(part, dtype=np.int64).reshape(-1)
            if part.size == 0:
                continue
            if part.min() < 0 or part.max() >= n_vertices:
                raise ValueError(f"rigid_parts[{part_index}] has vertex indices outside [0, {n_vertices})")
            centre = template_vertices[part].mean(axis=0)
            nearest = np.argsort(np.linalg.norm(landmark_sources - centre, axis=1))[:6]
            motion = similarity_transform(landmark_sources[nearest], lm_after[nearest])
            deformed[part] = motion.apply(template_vertices[part])

    final = reports[best_level]
    if final.coverage < 0.75:
        warn(f"only {100 * final.coverage:.0f}% of the template has scan data near it (holes or a "
             "partial scan); the rest is interpolated and cannot be trusted")
    noise = surface_noise(scan_vertices, scan_faces, target.vertex_normals)
    if np.isfinite(noise) and noise > noise_warning_mm:
        warn(f"the scan is noisy (about {noise:.2f} mm along its normals); the fit follows it only "
             "as far as rho and csrbf_smoothing allow; raise them if the result is rough")
    if best_level == 0 and levels > 1:
        warn("no refinement level lowered the error; the result is the feature-point RBF alone")

    result_vertices = transform.apply_inverse(deformed)
    correspondences = Correspondences(pt.copy(), ps.copy(), np.asarray(src, dtype=str))
    return AdaptResult(result_vertices, deformed, transform, reports, best_level, correspondences,
                       tuple(outliers), tuple(messages), tuple(fields))
