"""Dense motion: where every point of a neutral face goes in the same person's
expressive scan.

Twenty-two landmarks cannot say how the skin slides along the surface between them, and
their labelling noise (about a millimetre in each scan) is as large as the motion of the
subtle AUs. This stage registers the neutral surface onto the expressive one (after the
rigid alignment of :mod:`tpscore.expression.alignment`) and returns a displacement at every
point of the neutral face.

The registration is a non-rigid iterative-closest-point fit of a smooth field u(x, y)
(the faces look toward +z, so a field over the x-y plane covers them): a uniform cubic
B-spline on a lattice of nodes ``spacing_mm`` apart (:mod:`tpscore.lattice`). Each
iteration solves one least-squares problem, the sum of these terms:

* **geometry**: each data point (a sample of the neutral vertices), moved by the field,
  pulls along the normal toward its closest point on the expressive surface
  (point-to-plane), with a Tukey weight of its distance; pairs on the scan's outline or
  a hole's rim do not pull (:func:`_point_to_plane`);
* **texture**: with the scans' colour images, each data point also pulls along the
  surface toward where its skin's pattern went (:mod:`tpscore.expression.texture`,
  :func:`_texture_pull`);
* **landmarks**: soft pairs from the labels, refined by the texture or by a patch fit
  (:mod:`tpscore.expression.landmark_pairs`);
* **rest**: a weak pull of every node toward no motion, which lets motion the data do
  not show fade away instead of carrying on; it gives way where the neutral surface's
  own shape shows the slide (:func:`rest_pull_per_node`);
* **bending**: the field's thin-plate bending energy, with a stiffness that falls over
  the iterations, so the field follows the large motions first and the fine ones last.

Every term adds to one sparsity pattern (:class:`tpscore.lattice.LatticeSystem`), so the
data terms are filled by a compiled kernel and each iteration only refactorises. A new
term is a function that returns per-data-point 3 x 3 blocks and right-hand sides (a data
term) or a matrix in the lattice's unknowns (a fixed term). How each term was chosen is
in ``benchmarks/FIDELITY.md``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..registration_terms import point_to_plane_terms, texture_pull_terms
from .._validation import check_options
from ..lattice import BSplineLattice, LatticeSystem
from ..mesh import face_normals
from ..spatial import MeshSurface
from .landmark_pairs import landmark_term

__all__ = ["MotionOptions", "DenseMotion", "RegistrationGrid", "prepare_registration", "register_surfaces",
           "grid_normals", "rest_pull_per_node", "soft_pairs"]

#: Pairs farther than this many robust scales from their target do not pull.
TUKEY_FACTOR = 3.0
#: The geometry pairs' robust scale is at least this (mm), falling geometrically over the
#: iterations like the stiffness: a loose bound early keeps the pairs of a region that
#: moves as a block (AU17's chin) until the stiff field reaches them; a tight one late
#: keeps noise and stray pairs out.
SCALE_FLOOR_START_MM = 1.0
SCALE_FLOOR_END_MM = 0.5
#: The texture pulls' robust scale is at least this (mm) at the first iteration, falling
#: geometrically to :data:`TEXTURE_SCALE_FLOOR_END_MM` at the last, as the geometry's floor
#: does: on still skin the scale is the flow's noise, and a cut-off of three times that
#: would drop the largest motions' matches while the stiff field is still far from them
#: (a lip corner 5 mm off at the first iteration); they joined only in the softer late
#: iterations, and stretched skin was registered short (benchmarks/FIDELITY.md, "The
#: texture's robust scale").
TEXTURE_SCALE_FLOOR_START_MM = 1.0
#: The texture pulls' robust scale at the last iteration is at least this (mm): the
#: flow's noise on still skin.
TEXTURE_SCALE_FLOOR_END_MM = 0.3
#: A node's pull toward rest is scaled by exp(-r / REST_SHAPE_RATIO), r the ratio of the
#: second to the largest eigenvalue of its data points' normal matrix: flat forehead and
#: cheeks keep the whole pull, the lips, nose and chin are left to the data.
REST_SHAPE_RATIO = 0.1
# A tiny ridge keeps nodes without data or bending coupling determined.
_RIDGE = 1e-8


@dataclass(frozen=True)
class MotionOptions:
    """Settings of the dense registration (:func:`register_surfaces`).

    Attributes
    ----------
    spacing_mm : float
        Node spacing of the B-spline field.
    sample_step : int
        Every ``sample_step``-th row and column of the neutral grid is a data point.
    iterations : int
        Closest-point iterations.
    stiffness_start, stiffness_end : float
        Weight of the bending energy at the first and the last iteration (geometric in
        between), relative to the data term of one mm^2.
    landmark_weight : float
        Weight of a labelled landmark pair relative to one data point.
    rest_weight : float
        Weight of every node's pull toward no motion, relative to the bending energy's
        unit: where neither the surfaces, the texture nor the landmarks say how the skin
        slides, the field fades away instead of carrying motion on.
    texture_weight : float
        Weight of a texture match at full confidence, relative to a point-to-plane pair.
    texture_refine_after : int
        Match the texture again after this many iterations, with the expressive image
        warped back by the field found so far (default 4; 0 = never, one pass). The
        second pass finds more of the large, deforming motions (the wide-open jaw, the
        mouth corners under AU14, skin that stretches far) for about a quarter more
        time a transfer: benchmarks/FIDELITY.md, "A second pass of the texture".
    """

    spacing_mm: float = 8.0
    sample_step: int = 2
    iterations: int = 10
    stiffness_start: float = 100.0
    stiffness_end: float = 1.0
    landmark_weight: float = 3.0
    rest_weight: float = 0.01
    texture_weight: float = 10.0
    texture_refine_after: int = 4

    def __post_init__(self):
        check_options(self, positive=("spacing_mm", "stiffness_start", "stiffness_end"),
                      non_negative=("landmark_weight", "rest_weight", "texture_weight"),
                      counts=("sample_step", "iterations", ("texture_refine_after", 0)))


@dataclass
class DenseMotion:
    """A smooth displacement field registered from a neutral onto an expressive surface.

    Attributes
    ----------
    lattice : BSplineLattice
    node_values : (n_nodes, 3) ndarray
        The field's B-spline coefficients (mm).
    residual_rms_mm : float
        RMS point-to-plane distance of the weighted pairs at the end.
    inlier_fraction : float
        Share of the data points with a nonzero weight at the end.
    texture : TextureMatches or None
        The texture matches the registration weighed last (None: geometry alone).
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


def soft_pairs(lattice: BSplineLattice, from_points, to_points, weights):
    """The normal-equation term (3 n_nodes x 3 n_nodes, component blocks [x; y; z]) and
    right-hand side (n_nodes, 3) of soft pairs: sum_k w_k |u(f_k) - (t_k - f_k)|^2."""
    from_points = np.asarray(from_points, dtype=np.float64).reshape(-1, 3)
    weights = np.asarray(weights, dtype=np.float64).reshape(-1)
    basis = lattice.basis(from_points[:, :2])
    gram = basis.T @ basis.multiply(weights[:, None])
    pull = (np.asarray(to_points, dtype=np.float64).reshape(-1, 3) - from_points) * weights[:, None]
    return sp.block_diag([gram] * 3, format="csr"), basis.T @ pull


def grid_normals(points) -> np.ndarray:
    """Unit normals of an (H, W, 3) grid from its row and column tangents (0 where a
    neighbour is missing); their orientation follows the grid's rows and columns."""
    normals = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.nan_to_num(normals)


def rest_pull_per_node(basis: sp.csr_matrix, normals, rest_weight: float,
                       shape_ratio: float = REST_SHAPE_RATIO) -> np.ndarray:
    """The pull toward rest of each node, from the data points' B-spline weights
    ``basis`` (points x nodes) and unit normals (0 where unknown): ``rest_weight``
    scaled by exp(-r / shape_ratio), r the ratio of the second to the largest eigenvalue
    of the node's normal matrix (``shape_ratio`` 0: the same pull everywhere, and
    ``normals`` is not read)."""
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


@dataclass
class _Pairs:
    """One iteration's closest points of the moved data points on the expressive surface."""

    moved: np.ndarray       # (m, 3) data points moved by the current field
    points: np.ndarray      # (m, 3) their closest points
    distances: np.ndarray   # (m,)
    normals: np.ndarray     # (m, 3) the surface's normal there


def _point_to_plane(sample, pairs: _Pairs, prior, floor):
    """The geometry term: each pair pulls along the normal toward its closest point,
    with a Tukey weight of its distance (scale: the robust scale of the distances, at
    least ``floor``), 0 for pairs off the surface. Returns the (m, 6) blocks w n n^T,
    the (m, 3) right-hand sides, and each pair's distance along the normal and weight
    (for :func:`_fit_measures`). A compiled kernel; NumPy reference:
    :func:`tpscore.reference.registration.point_to_plane_terms`."""
    return point_to_plane_terms(sample, pairs.moved, pairs.points, pairs.distances, pairs.normals, prior,
                                float(floor), TUKEY_FACTOR)


def _fit_measures(along, w) -> tuple[float, float]:
    """The weighted rms distance of the pairs and the share of them that pull."""
    rms = float(np.sqrt(np.average(along ** 2, weights=w))) if w.sum() > 0 else float("nan")
    return rms, float(np.mean(w > 0))


def _texture_pull(sample, pairs: _Pairs, targets, prior, floor):
    """The texture term: each data point pulls along the expressive surface toward its
    texture match q, the energy w |P (s + u(s) - q)|^2 with P = I - n n^T and w the
    match's weight times a Tukey weight of its tangential residual (scale: the robust
    scale of the residuals, at least ``floor``). Returns the (m, 6) blocks w P and the
    (m, 3) right-hand sides w P (q - s). A compiled kernel; NumPy reference:
    :func:`tpscore.reference.registration.texture_pull_terms`."""
    return texture_pull_terms(sample, pairs.moved, targets, pairs.normals, prior, float(floor), TUKEY_FACTOR)


def _texture_samples(texture, sample_mask, prior, options: MotionOptions):
    """The data points' texture matches (zeros where none) and their weights."""
    targets = texture.targets[sample_mask]
    weight = options.texture_weight * texture.confidence[sample_mask] * prior
    weight[~np.isfinite(targets).all(axis=1)] = 0.0
    return np.nan_to_num(targets), weight


@dataclass
class RegistrationGrid:
    """What a registration needs from the neutral face alone (:func:`prepare_registration`):
    the data points, the lattice and its system, and the fixed terms that do not depend
    on the expressive scan."""

    sample_mask: np.ndarray       # (H, W) bool: the grid vertices that are data points
    sample: np.ndarray            # (m, 3) their positions
    lattice: BSplineLattice
    system: LatticeSystem
    rest: np.ndarray              # (n_nodes,) each node's pull toward rest
    bending_values: np.ndarray    # the bending energy in the system's pattern


def prepare_registration(neutral_points, neutral_mask, options: MotionOptions = MotionOptions()) -> RegistrationGrid:
    """The part of :func:`register_surfaces` that depends on the neutral grid and the
    options alone: made once, it can be made ahead (a transfer makes it on a second
    thread while it aligns the expressive scan and tracks the texture)."""
    points = np.asarray(neutral_points, dtype=np.float64)
    mask = np.asarray(neutral_mask, dtype=bool)
    sample_mask = np.zeros(mask.shape, dtype=bool)
    sample_mask[::options.sample_step, ::options.sample_step] = True
    sample_mask &= mask
    sample = points[sample_mask]
    valid = points[mask]
    lattice = BSplineLattice(valid[:, :2].min(axis=0), valid[:, :2].max(axis=0), options.spacing_mm)
    system = LatticeSystem(lattice, sample[:, :2])
    rest = rest_pull_per_node(system.basis, grid_normals(points)[sample_mask], options.rest_weight)
    bending_values = system.aligned(sp.block_diag([lattice.bending()] * 3))
    return RegistrationGrid(sample_mask, sample, lattice, system, rest, bending_values)


def register_surfaces(neutral_points, neutral_mask, neutral_landmarks, expressive_surface: MeshSurface,
                      expressive_landmarks, options: MotionOptions = MotionOptions(), weight=None,
                      texture=None, prepared: RegistrationGrid | None = None, pairs=None,
                      landmarks_detected: bool = False) -> DenseMotion:
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
    texture : TextureMatches, optional
        Matches of the neutral grid's vertices on the expressive surface by their skin's
        pattern (:func:`tpscore.expression.texture.track_texture`); without them the
        geometry and the landmarks alone say how the skin slides.
    prepared : RegistrationGrid, optional
        :func:`prepare_registration` of these neutral points, mask and options, if
        already made.
    pairs : (from_points, to_points, weights), optional
        More soft pairs, like the landmarks' (k, 3), (k, 3) and (k,): e.g. where the
        rims of an opening went (:mod:`tpscore.expression.cut_motion`).
    landmarks_detected : bool, default False
        Whether the landmarks were found by a detector rather than labelled: the
        landmark pairs then hold the registration only where the texture (or, without
        it, a patch fit of the surface) says where a neutral landmark went
        (:func:`~tpscore.expression.landmark_pairs.landmark_term`).

    Returns
    -------
    DenseMotion
    """
    points = np.asarray(neutral_points, dtype=np.float64)
    mask = np.asarray(neutral_mask, dtype=bool)
    if prepared is None:
        prepared = prepare_registration(points, mask, options)
    sample_mask, sample, lattice, system = prepared.sample_mask, prepared.sample, prepared.lattice, prepared.system
    prior = np.ones(len(sample)) if weight is None else np.asarray(weight, dtype=np.float64)[sample_mask]
    basis, n_nodes = system.basis, lattice.n_nodes
    # the terms that do not change over the iterations, in the system's pattern
    landmarks, landmark_rhs = landmark_term(lattice, points, mask, neutral_landmarks, expressive_landmarks,
                                            expressive_surface, options.landmark_weight, texture,
                                            landmarks_detected=landmarks_detected)
    if pairs is not None:
        pair_matrix, pair_rhs = soft_pairs(lattice, *pairs)
        landmarks, landmark_rhs = landmarks + pair_matrix, landmark_rhs + pair_rhs
    fixed_values = system.aligned(landmarks + sp.block_diag([sp.diags(_RIDGE + prepared.rest, format="csr")] * 3))
    bending_values = prepared.bending_values
    if texture is not None:
        texture_targets, texture_prior = _texture_samples(texture, sample_mask, prior, options)
    surface_normals = face_normals(expressive_surface.vertices, expressive_surface.faces)
    stiffness = np.geomspace(options.stiffness_start, options.stiffness_end, options.iterations)
    floors = np.geomspace(SCALE_FLOOR_START_MM, SCALE_FLOOR_END_MM, options.iterations)
    texture_floors = np.geomspace(TEXTURE_SCALE_FLOOR_START_MM, TEXTURE_SCALE_FLOOR_END_MM, options.iterations)
    values = np.zeros((n_nodes, 3))
    along, pair_weights = np.zeros(0), np.zeros(0)
    for iteration, (alpha, floor, texture_floor) in enumerate(zip(stiffness, floors, texture_floors)):
        if texture is not None and iteration > 0 and iteration == options.texture_refine_after:
            # the stiff first iterations have found the large motions: match the texture
            # again with the expressive image warped back by them
            displacement = np.full(points.shape, np.nan)
            displacement[mask] = lattice.evaluate(points[mask][:, :2], values)
            texture = texture.refined(displacement)
            texture_targets, texture_prior = _texture_samples(texture, sample_mask, prior, options)
        moved = sample + basis @ values
        closest = expressive_surface.closest_point(moved)
        pairs = _Pairs(moved, closest.points, closest.distances, surface_normals[closest.triangles])
        blocks, rhs, along, pair_weights = _point_to_plane(sample, pairs, prior, floor)
        if texture is not None:
            texture_blocks, texture_rhs = _texture_pull(sample, pairs, texture_targets, texture_prior, texture_floor)
            blocks, rhs = blocks + texture_blocks, rhs + texture_rhs
        matrix_values = system.data_term(blocks) + alpha * bending_values + fixed_values
        values = system.solve(matrix_values, (basis.T @ rhs + landmark_rhs).T.ravel()).reshape(3, n_nodes).T.copy()
    # how well the last iteration's pairs fit, measured once
    residual_rms, inliers = _fit_measures(along, pair_weights) if len(along) else (float("nan"), 0.0)
    return DenseMotion(lattice, values, residual_rms, inliers, texture)
