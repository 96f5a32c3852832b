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
  the pair pulls along the surface normal there (point-to-plane; optionally also toward
  the point itself, ``tangential_weight``). Pairs are weighted by a Tukey biweight of
  their distance, and pairs whose closest point is on the scan's outline or a hole's
  rim (the offset is not along the normal) get weight 0, so holes and the parts one
  scan does not cover do not pull;
* **landmarks**: each landmark pair pulls its neutral landmark toward the expressive
  one with a weight that reflects their labelling noise (a soft constraint, so two
  noisy landmarks cannot fold the field). Before that, each pair is refined by
  matching the neutral surface patch around the landmark onto the expressive surface
  (:func:`refine_landmark_motion`). A patch pins its shift down only in the directions
  its shape constrains (along the normal always, along the surface only where it is
  curved), so the refined pair is trusted per direction: where the patch fits and its
  shape holds the shift, it replaces the label and pulls harder; along directions it
  leaves loose, and for patches that deform, the labelled motion and weight stay;
* **smoothness**: the thin-plate bending energy of the field on the lattice (second
  differences), with a stiffness that decreases over the iterations, so the field
  first follows the large motions and then the fine ones.

Every iteration's normal equations share one sparsity pattern (:class:`LatticeSystem`):
the data term's block Gram matrix is assembled by a compiled kernel straight into that
pattern, and :class:`tpscore.PatternCholesky` analyses the pattern once and then only
refactorises.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .lattice import SYMMETRIC_ENTRIES, BSplineLattice, LatticeSystem
from .spatial import MeshSurface

__all__ = ["MotionOptions", "DenseMotion",
           "register_surfaces", "AdaptedMotion",
           "MirroredMotion", "adapt_motion", "curvature_image", "face_gradients",
           "refine_landmark_motion", "refined_pair_trust"]


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
        Weight of the point-to-point pull relative to the point-to-plane pull (0 = off,
        the default). The pull draws every point toward its closest point, that is
        toward no slide along the surface, which biases the slide the surfaces and
        landmarks do show; the pull toward rest (``rest_weight``) already keeps the
        field determined where they show none.
    tangential_decay : bool
        Let the point-to-point pull decrease with the stiffness: it steadies the first,
        stiff iterations, but it also pulls every point toward no slide along the
        surface, which the later iterations should leave to the landmarks.
    tukey_factor : float
        Pairs farther than this many times the robust scale get weight 0.
    min_scale_mm : float
        Lower bound of the robust scale (about the scanner noise) at the last iteration.
    min_scale_start_mm : float
        Lower bound of the robust scale at the first iteration, decreasing geometrically
        to ``min_scale_mm`` at the last like the stiffness (0 = ``min_scale_mm``
        throughout). When most of the face is still, the scale is the bound; a tight
        bound early cuts off the pairs of a region that moves by a few mm as a block
        (the chin under AU17) before the stiff field has come near them, and a loose
        one late lets noise and stray pairs pull.
    shape_weight : float
        Weight of the shape-matching term (0 = off): each data point pulls along the
        surface toward where the expressive surface's curvature equals the neutral
        surface's curvature at that point (the descriptor's gradient direction), so the
        field follows how features such as the lips, nose wings and brows slide.
        Relative to a point-to-plane pair, in curvature units of one robust standard
        deviation of the neutral curvature image.
    shape_sigma_mm : float
        Gaussian smoothing of the surfaces before their curvature is taken (mm).
    refine_radius_mm : float
        Radius of the neutral surface patch around each neutral landmark that is
        matched onto the expressive surface to refine the landmark pair (0 = raw pairs,
        see :func:`refine_landmark_motion`).
    refined_landmark_weight : float
        Weight of a refined landmark pair, along the directions it is trusted in (see
        ``refine_max_rms_mm``), relative to one data point; along the others the pair
        keeps ``landmark_weight`` and its labelled motion.
    refine_max_rms_mm : float
        A refined pair is trusted fully along a direction when its uncertainty there
        (the patch's rms distance to the expressive surface over the square root of the
        patch's normal-matrix eigenvalue in that direction) is below this, and not at
        all beyond twice it (a linear blend of refined and labelled pair, and of their
        weights, in between).
    membrane_weight : float
        Weight of the membrane (stretching) energy of the field over the neutral
        surface, per data point (0 = off): the linearised change of the surface's
        metric, so that where the surface bulges or sinks (which the data measure) the
        skin slides along it as an inextensible sheet would, rather than only as smooth
        as the bending energy allows. Rigid motions cost nothing.
    rest_weight : float
        Weight of a pull of every control node's displacement toward zero, relative to
        the bending energy's unit (0 = off): where neither the surfaces nor the
        landmarks say how the skin slides (a smooth forehead above a raised brow), the
        field fades away from the motion it is given instead of carrying it on unchanged.
        The point-to-point pull (``tangential_weight``) holds each data point instead,
        along the surface only, and so also where the surfaces do show a slide; this
        pull also fades normal motion over holes.
    rest_shape_ratio : float
        Let the pull toward rest give way where the neutral surface's own shape shows
        the slide (0 = the same pull everywhere): a node's pull is scaled by
        exp(-r / rest_shape_ratio), where r is the ratio of the second to the largest
        eigenvalue of the node's normal matrix (its data points' normals, weighted by
        the squared B-spline weights). A flat patch (forehead, cheek) has r near 0
        and keeps the whole pull; lips, nose and chin, whose normals turn, are left to
        the data and the landmarks.
    texture_weight : float
        Weight of a texture match (:func:`tpscore.texture.track_texture`) at full
        confidence, relative to a point-to-plane pair. A match pulls its data point
        along the expressive surface (its normal component is left to the
        point-to-plane pair) toward where the skin's pattern went.
    texture_min_scale_mm : float
        Lower bound of the texture matches' robust scale (about the flow's noise on
        still skin).
    texture_refine_after : int
        Match the texture again after this many iterations, with the expressive image
        warped back by the field found so far (:meth:`TextureMatches.refined`; 0 = never,
        the default). The stiff first iterations find the large motions that the flow
        alone misses (the chin under AU17, the mouth corners under AU14), so the second
        flow keeps more of them. It costs a second flow in both directions; on the
        benchmark it gains 0.006 of residual ratio and adds 0.008 mm of stray motion.
    """

    spacing_mm: float = 8.0
    sample_step: int = 2
    iterations: int = 10
    stiffness_start: float = 100.0
    stiffness_end: float = 1.0
    landmark_weight: float = 3.0
    tangential_weight: float = 0.0
    tangential_decay: bool = False
    tukey_factor: float = 3.0
    min_scale_mm: float = 0.5
    min_scale_start_mm: float = 1.0
    shape_weight: float = 0.0
    shape_sigma_mm: float = 2.5
    membrane_weight: float = 0.0
    refine_radius_mm: float = 10.0
    refined_landmark_weight: float = 10.0
    refine_max_rms_mm: float = 0.35
    rest_weight: float = 0.01
    rest_shape_ratio: float = 0.1
    texture_weight: float = 10.0
    texture_min_scale_mm: float = 0.3
    texture_refine_after: int = 0

    def __post_init__(self):
        for name in ("spacing_mm", "stiffness_start", "stiffness_end", "tukey_factor",
                     "min_scale_mm", "shape_sigma_mm", "texture_min_scale_mm"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        for name in ("landmark_weight", "tangential_weight", "shape_weight", "membrane_weight",
                     "refine_radius_mm", "refined_landmark_weight", "refine_max_rms_mm", "rest_weight",
                     "min_scale_start_mm", "rest_shape_ratio", "texture_weight"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if int(self.texture_refine_after) != self.texture_refine_after or self.texture_refine_after < 0:
            raise ValueError(f"texture_refine_after must be an integer >= 0, got {self.texture_refine_after!r}")
        for name in ("sample_step", "iterations"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


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
    texture : TextureMatches or None
        The texture matches the registration weighed (None: geometry alone).
    """

    lattice: BSplineLattice
    node_values: np.ndarray
    residual_rms_mm: float
    inlier_fraction: float
    texture: object = None

    def __call__(self, points) -> np.ndarray:
        """Displacement (m, 3) at points (m, 3) (their x, y decide; NaN rows give NaN)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=1)
        out[ok] = self.lattice.evaluate(p[ok, :2], self.node_values)
        return out


def _face_normals(surface: MeshSurface) -> np.ndarray:
    v, f = surface.vertices, surface.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1)
    return n / np.where(length > 0, length, 1.0)[:, None]


def _off_surface(along: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """Whether each closest point lies on the scan's outline or a hole's rim rather than
    below the query point: the offset then leaves the surface sideways, not along its
    normal (``along`` is the offset's normal component)."""
    return np.abs(along) < 0.8 * distances - 0.05


def _grid_spacing(points: np.ndarray, mask: np.ndarray) -> float:
    """Median distance between valid neighbours along the grid rows and columns (mm)."""
    edges = []
    for a, b in ((points[:, 1:], points[:, :-1]), (points[1:], points[:-1])):
        both = np.isfinite(a).all(axis=-1) & np.isfinite(b).all(axis=-1)
        if a.shape[:2] == mask[:, 1:].shape:
            both &= mask[:, 1:] & mask[:, :-1]
        else:
            both &= mask[1:] & mask[:-1]
        edges.append(np.linalg.norm(a[both] - b[both], axis=1))
    edges = np.concatenate(edges)
    return float(np.median(edges)) if len(edges) else 1.0


def curvature_image(points, mask, sigma_mm: float = 2.5) -> np.ndarray:
    """Mean curvature of a face grid after Gaussian smoothing of its surface.

    The curvature of the skin's features (lips, nose wings, brows, folds) travels with
    the skin when it slides, so two scans of one person can be matched along their
    surfaces by it. The grid's points are smoothed first (normalised convolution over
    the grid's valid vertices, ``sigma_mm`` wide), which removes the scanner noise that
    a second derivative would amplify.

    Parameters
    ----------
    points : (H, W, 3) ndarray
        Grid points (mm), NaN where invalid.
    mask : (H, W) bool ndarray
    sigma_mm : float
        Smoothing width (mm).

    Returns
    -------
    (H, W) ndarray
        Mean curvature (1/mm), NaN where invalid, on the rim of the grid's holes and
        outline, and where the smoothing saw mostly invalid vertices.
    """
    from scipy.ndimage import gaussian_filter

    from .mesh import mean_curvature
    from .face.grid import FaceGrid

    points = np.asarray(points, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool) & np.isfinite(points).all(axis=-1)
    sigma = float(sigma_mm) / _grid_spacing(points, mask)
    weight = gaussian_filter(mask.astype(np.float64), sigma, mode="constant")
    filled = np.where(mask[..., None], points, 0.0)
    smooth = np.stack([gaussian_filter(filled[..., k], sigma, mode="constant") for k in range(3)],
                      axis=-1) / np.maximum(weight, 1e-12)[..., None]
    # near the outline the normalised convolution leans toward one side: keep vertices
    # whose neighbourhood is mostly valid
    keep = mask & (weight > 0.6)
    grid = FaceGrid.from_points(np.where(keep[..., None], smooth, np.nan))
    mesh = grid.mesh()
    out = np.full(mask.shape, np.nan)
    if len(mesh.faces):
        curvature = mean_curvature(mesh.vertices, mesh.faces).values
        out.reshape(-1)[mesh.grid_index] = curvature
    return out


def face_gradients(vertices, faces, values) -> np.ndarray:
    """(m, 3) gradient of a piecewise-linear function on each triangle, in its plane.

    ``values`` (n,) at the vertices; the gradient g of triangle (a, b, c) satisfies
    g . (b - a) = f_b - f_a, g . (c - a) = f_c - f_a and g . normal = 0 (NaN where a
    value is NaN or the triangle is degenerate).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    normal = np.cross(e1, e2)
    area2 = np.einsum("ij,ij->i", normal, normal)
    df1 = values[f[:, 1]] - values[f[:, 0]]
    df2 = values[f[:, 2]] - values[f[:, 0]]
    # closed form of the 3 x 3 solve: g = (df1 (e2 x n) + df2 (n x e1)) / |n|^2
    g = (df1[:, None] * np.cross(e2, normal) + df2[:, None] * np.cross(normal, e1))
    ok = area2 > 1e-12
    g[ok] /= area2[ok, None]
    g[~ok] = np.nan
    return g


def _membrane_energy(lattice: BSplineLattice, points: np.ndarray, mask: np.ndarray,
                     sample_mask: np.ndarray, prior: np.ndarray) -> sp.csr_matrix:
    """(3 n_nodes, 3 n_nodes) sum over the data points of the squared linearised strain.

    The neutral surface is the height field X(x, y) = (x, y, z(x, y)); moved by the
    field u its metric changes by dX_i . du_j + dX_j . du_i (i, j in x, y), linear in
    u. The strain tensor's squared norm (xx, yy and twice xy) is summed over the data
    points, each weighted like its data pair's prior.
    """
    z = np.where(mask, points[..., 2], np.nan)
    x = np.where(mask, points[..., 0], np.nan)
    y = np.where(mask, points[..., 1], np.nan)
    # slopes of the height field from the grid's neighbours (central differences,
    # one-sided at the rims); NaN slopes (isolated vertices) count as flat
    slopes = []
    for axis in (1, 0):
        dz = np.gradient(z, axis=axis)
        dx = np.gradient(x, axis=axis)
        dy = np.gradient(y, axis=axis)
        slopes.append((dz, dx, dy))
    (dz_c, dx_c, dy_c), (dz_r, dx_r, dy_r) = slopes
    # solve [dx_c dy_c; dx_r dy_r] [z_x; z_y] = [dz_c; dz_r]
    det = dx_c * dy_r - dy_c * dx_r
    with np.errstate(invalid="ignore", divide="ignore"):
        zx = (dz_c * dy_r - dy_c * dz_r) / det
        zy = (dx_c * dz_r - dz_c * dx_r) / det
    zx = np.nan_to_num(zx[sample_mask], nan=0.0, posinf=0.0, neginf=0.0)
    zy = np.nan_to_num(zy[sample_mask], nan=0.0, posinf=0.0, neginf=0.0)
    xy = points[sample_mask][:, :2]
    bx, by = lattice.basis(xy, "x"), lattice.basis(xy, "y")
    zero = sp.csr_matrix(bx.shape)
    # rows over the component blocks [u_x; u_y; u_z]
    exx = sp.hstack([bx, zero, bx.multiply(zx[:, None])])
    eyy = sp.hstack([zero, by, by.multiply(zy[:, None])])
    exy = sp.hstack([by, bx, by.multiply(zx[:, None]) + bx.multiply(zy[:, None])]) * 0.5
    weight = sp.diags(np.asarray(prior, dtype=np.float64))
    energy = exx.T @ weight @ exx + eyy.T @ weight @ eyy + 2.0 * (exy.T @ weight @ exy)
    return energy.tocsr()


# Ridge of the patch fit per patch point (a unit normal gives 1 per point along it):
# directions in which the patch has less shape than this keep the labelled motion.
_REFINE_RIDGE = 0.03


def grid_normals(points) -> np.ndarray:
    """Unit normals of an (H, W, 3) grid from its row and column tangents (0 where a
    neighbour is missing); their orientation follows the grid's rows and columns."""
    normals = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.nan_to_num(normals)


def rest_pull_per_node(basis: sp.csr_matrix, normals, rest_weight: float, shape_ratio: float) -> np.ndarray:
    """The pull toward rest of each control node (see ``MotionOptions.rest_shape_ratio``),
    from the data points' B-spline weights ``basis`` (points x nodes) and unit normals
    (0 where unknown: no information; not read, and may be None, when ``shape_ratio``
    is 0)."""
    if shape_ratio <= 0:
        return np.full(basis.shape[1], rest_weight)
    normals = np.asarray(normals, dtype=np.float64)
    squared = basis.power(2).T.tocsr()
    # each node's normal matrix; its orientation does not matter for n n^T
    matrix = np.stack([squared @ (normals[:, a] * normals[:, b]) for a in range(3) for b in range(3)],
                      axis=1).reshape(-1, 3, 3)
    eigenvalues = np.linalg.eigvalsh(matrix)
    ratio = eigenvalues[:, 1] / np.maximum(eigenvalues[:, 2], 1e-12)
    return rest_weight * np.exp(-ratio / shape_ratio)


def refine_landmark_motion(neutral_points, neutral_mask, neutral_landmarks, expressive_surface: MeshSurface,
                           expressive_landmarks, radius_mm: float = 10.0, iterations: int = 8,
                           return_shape: bool = False):
    """Refine each landmark pair by matching the neutral surface around it onto the
    expressive surface.

    A labelled landmark is off by about a millimetre in each scan, so the motion a pair
    says (expressive - neutral) is off by more than the motion of the subtle AUs. Around
    a landmark the face has shape (eye corners, nose, mouth), and over a small patch the
    motion is nearly a translation: the patch of neutral vertices within ``radius_mm``
    of the neutral landmark is translated onto the expressive surface by point-to-plane
    ICP, starting from the labelled motion. Directions the patch's shape does not pin
    down (a flat brow along the surface) stay near the labelled motion.

    Parameters
    ----------
    neutral_points : (H, W, 3) ndarray
    neutral_mask : (H, W) bool ndarray
    neutral_landmarks, expressive_landmarks : (22, 3) ndarray
        In the frame of the expressive surface (NaN rows missing).
    expressive_surface : MeshSurface
    radius_mm : float
    iterations : int

    Returns
    -------
    refined : (22, 3) ndarray
        The neutral landmark's corresponding point on the expressive surface (NaN
        where either landmark is missing).
    fit_rms_mm : (22,) ndarray
        RMS distance of the moved patch to the expressive surface over the patch's
        points that land on it (NaN where not refined); a patch that deforms fits
        badly. Points over a hole or beyond the scan's outline do not count, and a
        patch with fewer than half of its points on the surface is not refined.
    shape : (22, 3, 3) ndarray
        Only with ``return_shape``: the mean of n n^T over the patch's fitted points
        (NaN where not refined). A shift e along a unit direction v changes the
        patch's rms distance by about e sqrt(v^T shape v): its eigenvalues say how
        firmly the patch pins each direction down (a flat patch only along its normal).
    """
    points = np.asarray(neutral_points, dtype=np.float64)
    valid = points[np.asarray(neutral_mask, dtype=bool)]
    lm_from = np.asarray(neutral_landmarks, dtype=np.float64)
    lm_to = np.asarray(expressive_landmarks, dtype=np.float64)
    refined = np.full(lm_from.shape, np.nan)
    fit_rms = np.full(len(lm_from), np.nan)
    both = np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1)
    shape = np.full((len(lm_from), 3, 3), np.nan)
    if not both.any() or len(valid) == 0:
        return (refined, fit_rms, shape) if return_shape else (refined, fit_rms)
    normals_of = _face_normals(expressive_surface)
    index = np.flatnonzero(both)
    patches = [valid[np.linalg.norm(valid - lm_from[k], axis=1) < radius_mm] for k in index]
    owner = np.concatenate([np.full(len(p), i) for i, p in enumerate(patches)])
    patch_points = np.concatenate(patches) if len(owner) else np.zeros((0, 3))
    shift = (lm_to - lm_from)[index]
    n_points = np.bincount(owner, minlength=len(index))
    counts = np.maximum(n_points, 1)

    def contact(shift):
        """Closest points of the shifted patches, their normals, the offsets' normal
        components, and 1 for the points that land on the surface (0 over a hole)."""
        closest = expressive_surface.closest_point(patch_points + shift[owner])
        normals = normals_of[closest.triangles]
        along = np.einsum("ij,ij->i", closest.points - patch_points - shift[owner], normals)
        return closest, normals, along, (~_off_surface(along, closest.distances)).astype(np.float64)

    for _ in range(iterations):
        # all patches in one closest-point query; one 3 x 3 solve per patch
        _, normals, along, w = contact(shift)
        outer = np.einsum("i,ij,ik->ijk", w, normals, normals)
        matrix = np.zeros((len(index), 3, 3))
        np.add.at(matrix, owner, outer)
        rhs = np.zeros((len(index), 3))
        np.add.at(rhs, owner, (w * along)[:, None] * normals)
        # a small ridge (per point) keeps directions the patch does not pin down
        matrix += _REFINE_RIDGE * counts[:, None, None] * np.eye(3)
        shift = shift + np.linalg.solve(matrix, rhs[..., None])[..., 0]
    # points over a hole or beyond the outline say nothing about how well the patch fits
    # (eye and lip holes cut into most landmark patches); a patch mostly off the surface
    # is not refined
    closest, _, _, on_surface = contact(shift)
    sq = np.bincount(owner, weights=on_surface * closest.distances ** 2, minlength=len(index))
    n_on = np.bincount(owner, weights=on_surface, minlength=len(index))
    fitted = (n_on > 0) & (n_on >= 0.5 * n_points)
    refined[index[fitted]] = lm_from[index[fitted]] + shift[fitted]
    fit_rms[index[fitted]] = np.sqrt(sq[fitted] / n_on[fitted])
    # the last iteration's normal matrix without its ridge, per fitted point
    shape[index[fitted]] = (matrix[fitted] - _REFINE_RIDGE * counts[fitted, None, None] * np.eye(3)) \
        / np.maximum(np.bincount(owner, weights=w, minlength=len(index))[fitted], 1.0)[:, None, None]
    return (refined, fit_rms, shape) if return_shape else (refined, fit_rms)


def refined_pair_trust(fit_rms, shape, max_rms_mm: float) -> np.ndarray:
    """How far each refined landmark pair is trusted, per direction.

    A patch that fits with rms r leaves its shift along an eigendirection of its normal
    matrix (eigenvalue l) uncertain by about r / sqrt(l). That direction is trusted
    fully while the uncertainty is below ``max_rms_mm``, and not at all beyond twice it
    (linear in between). Along the normal l is about 1, so the fit's rms itself decides;
    along a flat brow or a ridge l is about 0, and the labelled pair keeps the say.

    Parameters
    ----------
    fit_rms : (k,) ndarray
        From :func:`refine_landmark_motion` (NaN where not refined).
    shape : (k, 3, 3) ndarray
        From :func:`refine_landmark_motion` with ``return_shape``.
    max_rms_mm : float

    Returns
    -------
    (k, 3, 3) ndarray
        Symmetric matrices with eigenvalues in [0, 1]: T projects onto the trusted
        directions (0 where the pair was not refined).
    """
    fit_rms = np.asarray(fit_rms, dtype=np.float64)
    shape = np.asarray(shape, dtype=np.float64)
    trust = np.zeros((len(fit_rms), 3, 3))
    ok = np.isfinite(fit_rms) & np.isfinite(shape).all(axis=(1, 2))
    if ok.any():
        eigenvalues, vectors = np.linalg.eigh(shape[ok])
        error = fit_rms[ok, None] / np.sqrt(np.maximum(eigenvalues, 1e-12))
        c = np.clip(2.0 - error / max_rms_mm, 0.0, 1.0)
        trust[ok] = np.einsum("kij,kj,klj->kil", vectors, c, vectors)
    return trust


def register_surfaces(neutral_points, neutral_mask, neutral_landmarks, expressive_surface: MeshSurface,
                      expressive_landmarks, options: MotionOptions = MotionOptions(),
                      weight=None, expressive_curvature=None, texture=None) -> DenseMotion:
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
    expressive_curvature : (n,) ndarray, optional
        :func:`curvature_image` of the expressive grid at the vertices of
        ``expressive_surface`` (NaN where unknown), with ``options.shape_sigma_mm``.
        Needed when ``options.shape_weight > 0``.
    texture : TextureMatches, optional
        Matches of the neutral grid's vertices on the expressive surface by their skin
        texture (:func:`tpscore.texture.track_texture`); without them the geometry alone
        says how the skin slides. With them, a landmark pair whose neutral landmark has
        a match takes the match as its expressive end (instead of the label refined by
        a patch fit, :func:`refine_landmark_motion`).

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
    if texture is not None:
        texture_targets, texture_prior = _texture_samples(texture, sample_mask, prior, options)
    valid = points[mask]
    lattice = BSplineLattice(valid[:, :2].min(axis=0), valid[:, :2].max(axis=0), options.spacing_mm)
    system = LatticeSystem(lattice, sample[:, :2])
    basis = system.basis
    bending = lattice.bending()
    n_nodes = lattice.n_nodes

    lm_from = np.asarray(neutral_landmarks, dtype=np.float64)
    lm_to = np.asarray(expressive_landmarks, dtype=np.float64)
    both = np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1)
    if texture is not None:
        lm_to = _texture_landmarks(points, mask, lm_from, lm_to, texture)
    # each landmark pair pulls the field at its neutral landmark toward a target with a
    # 3 x 3 weight: (u - t)^T W (u - t), W = lm_weight I for a labelled pair
    lm_weight = np.repeat(options.landmark_weight * np.eye(3)[None], int(both.sum()), axis=0)
    lm_pull = options.landmark_weight * (lm_to - lm_from)[both]          # W t
    if options.refine_radius_mm > 0 and texture is None:
        refined, fit_rms, shape = refine_landmark_motion(points, mask, lm_from, expressive_surface, lm_to,
                                                         options.refine_radius_mm, return_shape=True)
        trust = refined_pair_trust(fit_rms, shape, options.refine_max_rms_mm)[both]
        eye = np.eye(3)[None]
        lm_weight = options.landmark_weight * (eye - trust) + options.refined_landmark_weight * trust
        lm_pull = np.einsum("kij,kj->ki", options.landmark_weight * (eye - trust), (lm_to - lm_from)[both]) \
            + np.einsum("kij,kj->ki", options.refined_landmark_weight * trust,
                        (np.nan_to_num(refined) - lm_from)[both])
    lm_basis = lattice.basis(lm_from[both, :2])
    lm_normal = sp.bmat([[lm_basis.T @ lm_basis.multiply(lm_weight[:, a, b][:, None]) for b in range(3)]
                         for a in range(3)]).tocsr()

    normals_of = _face_normals(expressive_surface)
    membrane = sp.csr_matrix((3 * n_nodes, 3 * n_nodes))
    if options.membrane_weight > 0:
        membrane = options.membrane_weight * _membrane_energy(lattice, points, mask, sample_mask, prior)
    use_shape = options.shape_weight > 0
    if use_shape:
        if expressive_curvature is None:
            raise ValueError("expressive_curvature is needed when options.shape_weight > 0")
        expressive_curvature = np.asarray(expressive_curvature, dtype=np.float64)
        if expressive_curvature.shape != (len(expressive_surface.vertices),):
            raise ValueError(f"expressive_curvature must have shape ({len(expressive_surface.vertices)},), "
                             f"got {expressive_curvature.shape}")
        neutral_curvature = curvature_image(points, mask, options.shape_sigma_mm)[sample_mask]
        known = neutral_curvature[np.isfinite(neutral_curvature)]
        # one robust standard deviation of the curvature image is the unit of the term
        unit = 1.4826 * float(np.median(np.abs(known - np.median(known)))) if len(known) else 1.0
        unit = unit if unit > 0 else 1.0
        shape_of = expressive_curvature / unit
        neutral_shape = neutral_curvature / unit
        gradient_of = face_gradients(expressive_surface.vertices, expressive_surface.faces, shape_of)
    values = np.zeros((n_nodes, 3))
    # the pull toward rest, plus a tiny ridge that keeps nodes without data or bending
    # coupling determined when the pull is off
    # the grid's normals matter only to a shape-dependent pull
    data_normals = grid_normals(points)[sample_mask] if options.rest_shape_ratio > 0 else None
    rest = rest_pull_per_node(basis, data_normals, options.rest_weight, options.rest_shape_ratio)
    ridge = sp.diags(1e-8 + rest, format="csr")
    # the terms that do not change over the iterations, in the system's pattern
    bending_values = system.aligned(sp.block_diag([bending] * 3))
    fixed_values = system.aligned(lm_normal + membrane + sp.block_diag([ridge] * 3))
    lm_rhs = lm_basis.T @ lm_pull
    identity = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])      # I as symmetric entries
    upper_i, upper_j = np.array(SYMMETRIC_ENTRIES).T
    stiffness = np.geomspace(options.stiffness_start, options.stiffness_end, options.iterations)
    start = options.min_scale_start_mm if options.min_scale_start_mm > 0 else options.min_scale_mm
    floors = np.geomspace(start, options.min_scale_mm, options.iterations)
    residual_rms, inliers = float("nan"), 0.0
    for iteration, (alpha, floor) in enumerate(zip(stiffness, floors)):
        if texture is not None and iteration > 0 and iteration == options.texture_refine_after:
            # the stiff first iterations have found the large motions: match the texture
            # again with the expressive image warped back by them
            displacement = np.full(points.shape, np.nan)
            displacement[mask] = lattice.evaluate(points[mask][:, :2], values)
            texture = texture.refined(displacement)
            texture_targets, texture_prior = _texture_samples(texture, sample_mask, prior, options)
        moved = sample + basis @ values
        closest = expressive_surface.closest_point(moved)
        offset = moved - closest.points
        normals = normals_of[closest.triangles]
        along = np.einsum("ij,ij->i", offset, normals)
        rim = _off_surface(along, closest.distances)
        scale = max(1.4826 * float(np.median(closest.distances[~rim])) if (~rim).any() else 1.0,
                    floor)
        u = closest.distances / (options.tukey_factor * scale)
        w = np.where((u < 1.0) & ~rim, (1.0 - u * u) ** 2, 0.0) * prior
        inliers = float(np.mean(w > 0))
        residual_rms = float(np.sqrt(np.average(along ** 2, weights=w))) if w.sum() > 0 else float("nan")
        # normal equations in the node values: each pair weighs the field's offset
        # from its closest point with w (n n^T + pull I), point-to-plane plus the
        # optional pull toward the point itself
        pull = options.tangential_weight * (alpha / stiffness[0] if options.tangential_decay else 1.0)
        blocks = w[:, None] * (normals[:, upper_i] * normals[:, upper_j] + pull * identity)
        to_closest = closest.points - sample
        target_plane = np.einsum("ij,ij->i", to_closest, normals)
        per_sample_rhs = normals * (w * target_plane)[:, None] + to_closest * (pull * w)[:, None]
        if use_shape:
            # shape matching, linearised at the current field: the expressive curvature
            # at the moved point plus its surface gradient times the change of the
            # field should equal the neutral curvature of the point
            tri = expressive_surface.faces[closest.triangles]
            at = np.einsum("ij,ij->i", closest.barycentric, shape_of[tri])
            gradient = gradient_of[closest.triangles]
            current = moved - sample
            target_shape = neutral_shape - at + np.einsum("ij,ij->i", gradient, current)
            usable = np.isfinite(target_shape) & np.isfinite(gradient).all(axis=1) & (w > 0)
            mismatch = np.where(usable, neutral_shape - at, 0.0)
            shape_scale = max(1.4826 * float(np.median(np.abs(mismatch[usable]))) if usable.any() else 1.0,
                              0.05)
            v = np.abs(mismatch) / (options.tukey_factor * shape_scale)
            ws = np.where(usable & (v < 1.0), (1.0 - v * v) ** 2, 0.0) * w * options.shape_weight
            gradient = np.where(usable[:, None], gradient, 0.0)
            target_shape = np.where(usable, target_shape, 0.0)
            blocks = blocks + ws[:, None] * gradient[:, upper_i] * gradient[:, upper_j]
            per_sample_rhs = per_sample_rhs + gradient * (ws * target_shape)[:, None]
        if texture is not None:
            texture_blocks, texture_rhs = _texture_term(moved, sample, normals, texture_targets, texture_prior,
                                                        options)
            blocks = blocks + texture_blocks
            per_sample_rhs = per_sample_rhs + texture_rhs
        matrix_values = system.data_term(blocks) + alpha * bending_values + fixed_values
        rhs = (basis.T @ per_sample_rhs + lm_rhs).T.ravel()
        values = system.solve(matrix_values, rhs).reshape(3, n_nodes).T.copy()
    return DenseMotion(lattice, values, residual_rms, inliers, texture)



def _texture_samples(texture, sample_mask, prior, options: MotionOptions):
    """The data points' texture matches (zeros where none) and their weights."""
    targets = texture.targets[sample_mask]
    weight = options.texture_weight * texture.confidence[sample_mask] * prior
    weight[~np.isfinite(targets).all(axis=1)] = 0.0
    return np.nan_to_num(targets), weight


def _texture_landmarks(points, mask, lm_from, lm_to, texture) -> np.ndarray:
    """The expressive landmarks, each replaced by the texture match of its neutral
    landmark's grid vertex where there is one: the skin's pattern shows where a labelled
    point went more precisely than a second label (about a millimetre off in each scan)
    or a patch fit of the surface, which cannot follow skin that slides."""
    out = lm_to.copy()
    present = np.flatnonzero(np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1))
    if len(present) == 0:
        return out
    valid = np.flatnonzero(mask.reshape(-1))
    flat = points.reshape(-1, 3)[valid]
    # a neutral landmark sits on a grid vertex (it was snapped there): find that vertex
    nearest = valid[np.argmin(((flat[None, :, :] - lm_from[present, None, :]) ** 2).sum(axis=-1), axis=1)]
    matched = texture.confidence.reshape(-1)[nearest] > 0
    out[present[matched]] = texture.targets.reshape(-1, 3)[nearest[matched]]
    return out


def _texture_term(moved, sample, normals, targets, prior, options: MotionOptions):
    """Each data point's pull along the expressive surface toward its texture match: the
    energy w |P (s + u(s) - q)|^2 with P = I - n n^T (n: the expressive surface's normal
    at the point's current closest point) and w the match's weight times a Tukey biweight
    of its tangential residual. Returns the (m, 6) symmetric blocks w P and the (m, 3)
    right-hand sides w P (q - s)."""
    offset = moved - targets
    offset -= np.einsum("ij,ij->i", offset, normals)[:, None] * normals
    residual = np.linalg.norm(offset, axis=1)
    used = prior > 0
    scale = max(1.4826 * float(np.median(residual[used])) if used.any() else 0.0, options.texture_min_scale_mm)
    u = residual / (options.tukey_factor * scale)
    w = np.where(used & (u < 1.0), (1.0 - u * u) ** 2, 0.0) * prior
    upper_i, upper_j = np.array(SYMMETRIC_ENTRIES).T
    identity = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])
    blocks = w[:, None] * (identity - normals[:, upper_i] * normals[:, upper_j])
    to_target = targets - sample
    to_target -= np.einsum("ij,ij->i", to_target, normals)[:, None] * normals
    return blocks, w[:, None] * to_target


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


class MirroredMotion:
    """The mean of a displacement field and its mirror image: the motion of a bilateral
    expression, which moves both sides of the face alike.

    A point p takes the mean of its own displacement u(p) and of the displacement at its
    mirror point, reflected back: M u(S p), with S the face's mirror map (a plane
    reflection, :func:`tpscore.alignment.fit_mirror_symmetry`) and M its linear part.
    The two sides' independent errors (landmark labels, scanner noise, holes) average
    out. Each term is weighted by how well the registered face covers its point (full
    within ``reach_mm`` of a vertex of the face, none beyond twice that, measured in the
    x-y plane the face is a height field over), so a point whose mirror image falls off
    the scan, or into a hole, keeps its own motion, and a point in a hole takes its
    mirror's.

    Parameters
    ----------
    motion : callable
        The displacement field, (m, 3) points -> (m, 3) displacements.
    mirror : FrameTransform
        The face's mirror map (in the frame of the field).
    covered_points : (n, 3) array_like
        The vertices of the face the field was registered on.
    reach_mm : float
        Distance to the nearest vertex below which a point counts as covered.
    """

    def __init__(self, motion, mirror, covered_points, reach_mm: float = 3.0):
        from scipy.ndimage import distance_transform_edt

        covered = np.asarray(covered_points, dtype=np.float64).reshape(-1, 3)
        covered = covered[np.isfinite(covered).all(axis=1)]
        if len(covered) == 0:
            raise ValueError("covered_points has no finite point")
        if not np.isfinite(reach_mm) or reach_mm <= 0:
            raise ValueError(f"reach_mm must be finite and > 0, got {reach_mm!r}")
        self.motion = motion
        self.mirror = mirror
        self.reach_mm = float(reach_mm)
        # distance to the face over a raster of the x-y plane (a quarter of the reach per
        # cell): one lookup per point instead of a nearest-neighbour search
        self._cell = self.reach_mm / 4.0
        self._origin = covered[:, :2].min(axis=0) - 2.0 * self.reach_mm
        shape = np.ceil((covered[:, :2].max(axis=0) + 2.0 * self.reach_mm - self._origin)
                        / self._cell).astype(int) + 1
        occupied = np.zeros(shape, dtype=bool)
        cells = np.floor((covered[:, :2] - self._origin) / self._cell).astype(int)
        occupied[cells[:, 0], cells[:, 1]] = True
        self._distance = distance_transform_edt(~occupied) * self._cell

    def _coverage(self, points: np.ndarray) -> np.ndarray:
        cells = np.floor((points[:, :2] - self._origin) / self._cell).astype(int)
        inside = ((cells >= 0) & (cells < self._distance.shape)).all(axis=1)
        distance = np.full(len(points), np.inf)
        distance[inside] = self._distance[cells[inside, 0], cells[inside, 1]]
        return np.clip(2.0 - distance / self.reach_mm, 0.0, 1.0)

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            return out
        own_points = p[ok]
        mirrored_points = self.mirror.apply(own_points)
        own = self.motion(own_points)
        mirrored = self.mirror.apply_vectors(self.motion(mirrored_points))
        # a point nothing covers keeps its own (extrapolated) motion
        own_weight = np.maximum(self._coverage(own_points), 1e-6)
        mirrored_weight = self._coverage(mirrored_points)
        out[ok] = (own * own_weight[:, None] + mirrored * mirrored_weight[:, None]) \
            / (own_weight + mirrored_weight)[:, None]
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
