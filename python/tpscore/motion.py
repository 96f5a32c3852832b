"""Dense motion modelling: where every point of a neutral face goes in the expressive scan.

Twenty-two landmarks cannot say how the skin slides along the surface between them,
and their labelling noise (about 1.4 mm each, in both scans) is as large as the motion
of the subtle AUs. This stage registers the person's neutral surface onto the same
person's expressive surface (after :mod:`tpscore.alignment` has removed the head's
rigid motion) and returns a displacement at every vertex of the neutral grid.

The registration is a non-rigid iterative-closest-point fit of a smooth displacement
field u(x, y) (the faces look toward +z, so a field over the x-y plane covers them):

* **representation**: a uniform cubic B-spline over a lattice of control nodes in
  x, y (``spacing_mm`` apart), three values per node; it is C2 and each point depends
  on 16 nodes, so every system below is sparse;
* **data**: a sample of the neutral vertices, moved by the field, is paired with its
  closest point on the expressive surface (exact, :class:`tpscore.MeshSurface`);
  the pair pulls along the surface normal there (point-to-plane) and, weakly, toward
  the point itself. Pairs are weighted by a Tukey biweight of their distance, and pairs
  whose closest point is on the scan's outline or a hole's rim (the offset is not
  along the normal) get weight 0, so holes and the parts one scan does not cover
  do not pull;
* **landmarks**: each landmark pair pulls its neutral landmark toward the expressive
  one with a weight that reflects their labelling noise (a soft constraint, so two
  noisy landmarks cannot fold the field);
* **smoothness**: the thin-plate bending energy of the field on the lattice (second
  differences), with a stiffness that decreases over the iterations, so the field
  first follows the large motions and then the fine ones.

Each iteration solves the sparse normal equations with :class:`tpscore.SparseCholesky`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .sparse import SparseCholesky
from .spatial import MeshSurface

__all__ = ["MotionOptions", "DenseMotion", "BSplineLattice", "register_surfaces", "AdaptedMotion",
           "adapt_motion"]


@dataclass(frozen=True)
class MotionOptions:
    """Settings of the dense registration (:func:`register_surfaces`).

    Attributes
    ----------
    spacing_mm : float
        Control-node spacing of the B-spline field.
    sample_step : int
        Use every ``sample_step``-th row and column of the neutral grid as data points.
    iterations : int
        Closest-point iterations.
    stiffness_start, stiffness_end : float
        Weight of the bending energy at the first and the last iteration (geometric
        decrease in between), relative to the data term of one mm^2.
    landmark_weight : float
        Weight of a landmark pair relative to one data point.
    tangential_weight : float
        Weight of the point-to-point pull relative to the point-to-plane pull.
    tukey_factor : float
        Pairs farther than this many times the robust scale get weight 0.
    min_scale_mm : float
        Lower bound of the robust scale (about the scanner noise).
    """

    spacing_mm: float = 8.0
    sample_step: int = 2
    iterations: int = 6
    stiffness_start: float = 100.0
    stiffness_end: float = 1.0
    landmark_weight: float = 3.0
    tangential_weight: float = 0.05
    tukey_factor: float = 3.0
    min_scale_mm: float = 0.5

    def __post_init__(self):
        for name in ("spacing_mm", "stiffness_start", "stiffness_end", "tukey_factor",
                     "min_scale_mm"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        for name in ("landmark_weight", "tangential_weight"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("sample_step", "iterations"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def _cubic_bspline_weights(t: np.ndarray) -> np.ndarray:
    """(n, 4) uniform cubic B-spline weights of the nodes i-1, i, i+1, i+2 at t in [0, 1)."""
    s = 1.0 - t
    return np.stack([s ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1,
                     t ** 3], axis=1) / 6.0


class BSplineLattice:
    """A uniform cubic B-spline lattice over an x-y rectangle.

    Parameters
    ----------
    lower, upper : (2,) array_like
        Corners of the x-y rectangle the field must cover (mm).
    spacing : float
        Node spacing (mm).
    """

    def __init__(self, lower, upper, spacing: float):
        lower = np.asarray(lower, dtype=np.float64)
        upper = np.asarray(upper, dtype=np.float64)
        self.spacing = float(spacing)
        # one node beyond each side: a cubic B-spline needs the nodes i-1 .. i+2
        self.origin = lower - self.spacing
        cells = np.ceil((upper - lower) / self.spacing).astype(int) + 1
        self.shape = (int(cells[1]) + 3, int(cells[0]) + 3)   # (rows along y, columns along x)

    @property
    def n_nodes(self) -> int:
        return self.shape[0] * self.shape[1]

    def basis(self, xy) -> sp.csr_matrix:
        """(m, n_nodes) sparse matrix: the field at points (m, 2) is basis @ node_values."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        g = (xy - self.origin) / self.spacing
        cell = np.floor(g).astype(np.int64)
        cell[:, 0] = np.clip(cell[:, 0], 1, self.shape[1] - 3)
        cell[:, 1] = np.clip(cell[:, 1], 1, self.shape[0] - 3)
        t = np.clip(g - cell, 0.0, 1.0)
        wx = _cubic_bspline_weights(t[:, 0])
        wy = _cubic_bspline_weights(t[:, 1])
        offsets = np.arange(-1, 3)
        cols = (cell[:, 1, None, None] + offsets[None, :, None]) * self.shape[1] \
            + (cell[:, 0, None, None] + offsets[None, None, :])
        values = wy[:, :, None] * wx[:, None, :]
        rows = np.repeat(np.arange(len(xy)), 16)
        return sp.csr_matrix((values.ravel(), (rows, cols.ravel())), shape=(len(xy), self.n_nodes))

    def bending(self) -> sp.csr_matrix:
        """(n_nodes, n_nodes) thin-plate bending energy of the node values (second
        differences: xx, 2 xy, yy), scaled to mm^-2 so that it does not depend on the
        spacing."""
        rows, cols = self.shape
        index = np.arange(self.n_nodes).reshape(rows, cols)

        def operator(stencil):
            """Rows applying a 3 x 3 stencil at every interior node."""
            r, c = np.meshgrid(np.arange(1, rows - 1), np.arange(1, cols - 1), indexing="ij")
            centre = r.ravel(), c.ravel()
            entries_r, entries_c, entries_v = [], [], []
            for (dr, dc), v in stencil.items():
                entries_r.append(np.arange(len(centre[0])))
                entries_c.append(index[centre[0] + dr, centre[1] + dc])
                entries_v.append(np.full(len(centre[0]), v))
            return sp.csr_matrix((np.concatenate(entries_v),
                                  (np.concatenate(entries_r), np.concatenate(entries_c))),
                                 shape=(len(centre[0]), self.n_nodes))

        dxx = operator({(0, -1): 1.0, (0, 0): -2.0, (0, 1): 1.0})
        dyy = operator({(-1, 0): 1.0, (0, 0): -2.0, (1, 0): 1.0})
        dxy = operator({(-1, -1): 0.25, (-1, 1): -0.25, (1, -1): -0.25, (1, 1): 0.25})
        energy = dxx.T @ dxx + 2.0 * dxy.T @ dxy + dyy.T @ dyy
        return (energy / self.spacing ** 2).tocsr()


@dataclass
class DenseMotion:
    """A smooth displacement field registered from a neutral onto an expressive surface.

    Attributes
    ----------
    lattice : BSplineLattice
    node_values : (n_nodes, 3) ndarray
        The field's B-spline coefficients (mm).
    residual_rms_mm : float
        RMS point-to-plane distance of the full-weight pairs at the end.
    inlier_fraction : float
        Share of the data points with a nonzero weight at the end.
    """

    lattice: BSplineLattice
    node_values: np.ndarray
    residual_rms_mm: float
    inlier_fraction: float

    def __call__(self, points) -> np.ndarray:
        """Displacement (m, 3) at points (m, 3) (their x, y decide; NaN rows give NaN)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=1)
        out[ok] = self.lattice.basis(p[ok, :2]) @ self.node_values
        return out


def _face_normals(surface: MeshSurface) -> np.ndarray:
    v, f = surface.vertices, surface.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1)
    return n / np.where(length > 0, length, 1.0)[:, None]


def register_surfaces(neutral_points, neutral_mask, neutral_landmarks, expressive_surface: MeshSurface,
                      expressive_landmarks, options: MotionOptions = MotionOptions(),
                      weight=None) -> DenseMotion:
    """Register a neutral face grid onto an expressive surface of the same person.

    Parameters
    ----------
    neutral_points : (H, W, 3) ndarray
        The neutral grid (mm), NaN where invalid, in the same frame as the expressive
        surface (rigidly aligned).
    neutral_mask : (H, W) bool ndarray
    neutral_landmarks, expressive_landmarks : (22, 3) ndarray
        Landmarks of the two scans in that frame (NaN rows missing).
    expressive_surface : MeshSurface
    options : MotionOptions
    weight : (H, W) ndarray, optional
        Extra weight of each neutral vertex as a data point (e.g. 0 where the field is
        known to be still); default 1.

    Returns
    -------
    DenseMotion
    """
    points = np.asarray(neutral_points, dtype=np.float64)
    mask = np.asarray(neutral_mask, dtype=bool)
    step = int(options.sample_step)
    sample_mask = np.zeros(mask.shape, dtype=bool)
    sample_mask[::step, ::step] = True
    sample_mask &= mask
    sample = points[sample_mask]
    prior = np.ones(len(sample)) if weight is None else np.asarray(weight, dtype=np.float64)[sample_mask]
    valid = points[mask]
    lattice = BSplineLattice(valid[:, :2].min(axis=0), valid[:, :2].max(axis=0), options.spacing_mm)
    basis = lattice.basis(sample[:, :2])
    bending = lattice.bending()
    n_nodes = lattice.n_nodes

    lm_from = np.asarray(neutral_landmarks, dtype=np.float64)
    lm_to = np.asarray(expressive_landmarks, dtype=np.float64)
    both = np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1)
    lm_basis = lattice.basis(lm_from[both, :2])
    lm_target = lm_to[both] - lm_from[both]
    lm_scale = options.landmark_weight
    lm_normal = lm_scale * (lm_basis.T @ lm_basis)

    normals_of = _face_normals(expressive_surface)
    values = np.zeros((n_nodes, 3))
    ridge = 1e-8 * sp.identity(n_nodes, format="csr")
    stiffness = np.geomspace(options.stiffness_start, options.stiffness_end, options.iterations)
    residual_rms, inliers = float("nan"), 0.0
    for alpha in stiffness:
        moved = sample + basis @ values
        closest = expressive_surface.closest_point(moved)
        offset = moved - closest.points
        normals = normals_of[closest.triangles]
        along = np.einsum("ij,ij->i", offset, normals)
        # a closest point on the outline or a hole's rim: the offset leaves the surface
        # sideways, not along its normal
        rim = np.abs(along) < 0.8 * closest.distances - 0.05
        scale = max(1.4826 * float(np.median(closest.distances[~rim])) if (~rim).any() else 1.0,
                    options.min_scale_mm)
        u = closest.distances / (options.tukey_factor * scale)
        w = np.where((u < 1.0) & ~rim, (1.0 - u * u) ** 2, 0.0) * prior
        inliers = float(np.mean(w > 0))
        residual_rms = float(np.sqrt(np.average(along ** 2, weights=w))) if w.sum() > 0 else float("nan")
        # normal equations in the node values, component blocks [x; y; z]
        plane_rows = sp.hstack([basis.multiply(normals[:, k:k + 1]) for k in range(3)]).tocsr()
        weighted_plane = plane_rows.multiply(w[:, None]).tocsr()
        target_plane = np.einsum("ij,ij->i", closest.points - sample, normals)
        point_normal = basis.T @ basis.multiply(w[:, None])
        block = alpha * bending + options.tangential_weight * point_normal + lm_normal + ridge
        matrix = (plane_rows.T @ weighted_plane) + sp.block_diag([block] * 3)
        rhs = plane_rows.T @ (w * target_plane)
        point_rhs = basis.T @ ((closest.points - sample) * (options.tangential_weight * w)[:, None])
        lm_rhs = lm_scale * (lm_basis.T @ lm_target)
        rhs = rhs + (point_rhs + lm_rhs).T.ravel()
        solution = SparseCholesky(sp.csc_matrix(matrix)).solve(rhs)
        values = solution.reshape(3, n_nodes).T.copy()
    return DenseMotion(lattice, values, residual_rms, inliers)



class AdaptedMotion:
    """A displacement field from :func:`tpscore.adapt` (multilevel RBF/CSRBF template
    adaptation of the neutral grid onto the expressive surface), callable like
    :class:`DenseMotion`."""

    def __init__(self, result):
        self.result = result

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=1)
        if ok.any():
            out[ok] = self.result.deform(p[ok]) - p[ok]
        return out


def adapt_motion(neutral_grid, expressive_grid, **adapt_options) -> AdaptedMotion:
    """Register a neutral face grid onto the same person's expressive grid with the
    template adaptation (both already in one frame: no calibration)."""
    import warnings

    from .adaptation import AdaptationWarning, adapt

    with warnings.catch_warnings():
        # its warnings concern fitting a template to a stranger's scan; here the two
        # surfaces are one person's, and the fidelity benchmark measures the outcome
        warnings.simplefilter("ignore", AdaptationWarning)
        result = adapt(neutral_grid, expressive_grid, neutral_grid.landmarks,
                       expressive_grid.landmarks, calibration="none", **adapt_options)
    return AdaptedMotion(result)
