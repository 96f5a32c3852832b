"""Rigid alignment of one person's expressive scan to the same person's neutral scan.

Normalising an expressive scan on its own landmarks removes real motion: the chin
middle, one of the affine normalisation's four landmarks, moves in AU17, and every
landmark an AU moves pulls a least-squares fit with it. A person's skull does not
change between two scans, so the expressive scan is brought onto the neutral one by
a rotation and a translation only:

1. **landmarks**: the rigid least-squares fit over the landmarks both scans have,
   refitted without the landmarks that the expression moved (residuals well above the
   rest), which gives a start within a few degrees;
2. **ICP on the surfaces**: point-to-plane iterative closest points from a sample of
   the expressive grid's vertices to the neutral surface (exact closest points on its
   triangles, :class:`tpscore.MeshSurface`). Pairs are weighted by a Tukey biweight
   of their distance, with the scale taken from the median distance, so the parts of
   the face the expression moved, and the edges where the two scans do not overlap,
   drop out while the still parts (forehead, nose, temples) decide the pose.

The result maps the expressive scan's frame onto the neutral scan's frame.

Which part of the face is still depends on the expression. For action units it is
the part outside their regions (a smile does not move the forehead). A whole
expression (an emotion, ``"all"``) may move every region; then the ICP leans on the
parts the skull holds most firmly (:func:`stable_weight`: the nose's bridge, the upper
forehead and the temples), and once the motion is registered the rigid part that is
left in it is found from the dense correspondences over those parts and taken out
(:func:`residual_rigid_motion`): unlike the surfaces' distances, the correspondences
also see the skin that slid along the surface.

The same fit finds a face's plane of symmetry (:func:`fit_mirror_symmetry`): the scan
mirrored (left and right landmarks swapped) is aligned rigidly onto itself, and the
reflection followed by that alignment is the face's mirror map.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..face.landmarks import MIRROR_LANDMARK, landmark_index
from ..face.normalise import FrameTransform, similarity_transform
from ..face.grid import FaceGrid
from ..face.regions import smoothstep
from ..geometry import fit_similarity, robust_scale, tukey_weights
from ..mesh import face_normals
from ..spatial import MeshSurface

__all__ = ["rigid_landmark_fit", "align_rigid", "RigidAlignment", "fit_mirror_symmetry", "stable_weight",
           "residual_rigid_motion", "Realigned"]

# A rigid fit over landmarks needs three pairs not on one line.
_MIN_RIGID_LANDMARKS = 3


def rigid_landmark_fit(moving_landmarks, fixed_landmarks, *, reject_factor: float = 2.5,
                       min_residual_mm: float = 2.0) -> FrameTransform:
    """Rigid fit of one face's landmarks onto another's, robust to moved landmarks.

    Fits all landmarks present in both, then refits without those whose residual is
    above ``reject_factor`` times the median residual (and above ``min_residual_mm``),
    so landmarks an expression moved do not tilt the fit.

    Raises
    ------
    ValueError
        Fewer than three landmarks present in both faces.
    """
    a = np.asarray(moving_landmarks, dtype=np.float64)
    b = np.asarray(fixed_landmarks, dtype=np.float64)
    both = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if both.sum() < _MIN_RIGID_LANDMARKS:
        raise ValueError(f"rigid alignment needs at least {_MIN_RIGID_LANDMARKS} landmarks present "
                         f"in both scans, got {int(both.sum())}")
    weights = both.astype(np.float64)
    transform = similarity_transform(a, b, scale=False, weights=weights)
    for _ in range(2):
        residual = np.linalg.norm(transform.apply(a) - b, axis=1)
        limit = max(reject_factor * np.nanmedian(residual[both]), min_residual_mm)
        keep = both & (residual <= limit)
        if keep.sum() < _MIN_RIGID_LANDMARKS or np.array_equal(keep, weights > 0):
            break
        weights = keep.astype(np.float64)
        transform = similarity_transform(a, b, scale=False, weights=weights)
    return transform


class RigidAlignment:
    """The outcome of :func:`align_rigid`.

    Attributes
    ----------
    transform : FrameTransform
        Rigid map from the moving scan's frame to the fixed scan's frame.
    landmark_transform : FrameTransform
        The landmark-only start of the ICP.
    iterations : int
        ICP iterations run.
    inlier_rms_mm : float
        RMS point-to-plane distance of the pairs with full weight at the end.
    median_distance_mm : float
        Median distance of the aligned sample points from the fixed surface, over the
        still part (``still_weight`` > 0.5) when there is one: about the scanner noise
        for two scans of one person, far more for two people (NaN without samples).
    """

    def __init__(self, transform, landmark_transform, iterations, inlier_rms_mm,
                 median_distance_mm=float("nan")):
        self.transform = transform
        self.landmark_transform = landmark_transform
        self.iterations = iterations
        self.inlier_rms_mm = inlier_rms_mm
        self.median_distance_mm = median_distance_mm

    def __repr__(self) -> str:
        return (f"RigidAlignment(iterations={self.iterations}, "
                f"inlier_rms_mm={self.inlier_rms_mm:.3f}, median_distance_mm={self.median_distance_mm:.3f})")


def align_rigid(moving: FaceGrid, fixed: FaceGrid, *, fixed_surface: MeshSurface | None = None,
                still_weight=None, iterations: int = 30, sample_step: int = 3, tukey_factor: float = 4.0,
                min_scale_mm: float = 0.3, tolerance_mm: float = 1e-3) -> RigidAlignment:
    """Rigidly align a scan of a person onto another scan of the same person.

    Parameters
    ----------
    moving, fixed : FaceGrid
        The expressive scan (moving) and the neutral scan (fixed), each in its own
        scan frame, with landmarks (NaN rows missing).
    fixed_surface : MeshSurface, optional
        The fixed grid's surface, if already built.
    iterations : int
        Most ICP iterations.
    sample_step : int
        Use every ``sample_step``-th row and column of the moving grid (a 150 x 150
        grid gives about 2,000 points at 3; the pose has six unknowns).
    tukey_factor : float
        Pairs farther than this many times the robust scale get weight 0.
    min_scale_mm : float
        Lower bound of the robust scale (about twice the scanner noise), so that an
        exact fit does not reject every pair.
    tolerance_mm : float
        Stop when the update moves no sample point by more than this.

    Returns
    -------
    RigidAlignment
    """
    start = rigid_landmark_fit(moving.landmarks, fixed.landmarks)
    if fixed_surface is None:
        mesh = fixed.mesh()
        if len(mesh.faces) == 0:
            raise ValueError("the fixed scan has no triangles")
        fixed_surface = MeshSurface(mesh.vertices, mesh.faces)
    sample_mask = np.zeros(moving.shape, dtype=bool)
    sample_mask[::sample_step, ::sample_step] = True
    sample_mask &= moving.mask
    sample = moving.points[sample_mask]
    prior = (np.ones(len(sample)) if still_weight is None
             else np.asarray(still_weight, dtype=np.float64)[sample_mask])
    if prior.sum() < 10:
        prior = np.ones(len(sample))
    if len(sample) < 10:
        return RigidAlignment(start, start, 0, float("nan"))
    normals_of_faces = face_normals(fixed_surface.vertices, fixed_surface.faces)

    matrix = start.matrix.copy()
    done = 0
    inlier_rms = float("nan")
    # the median distances (the robust scale, and the fit's measure at the end) over the
    # still part when there is one; chosen once: the loop runs up to 30 times on a few
    # thousand points, where NumPy's call overhead counts
    still = prior > 0.5
    scale_from = still if still.any() else slice(None)
    ridge = 1e-9 * np.eye(6)
    for done in range(1, iterations + 1):
        moved = sample @ matrix[:3, :3].T + matrix[:3, 3]
        closest = fixed_surface.closest_point(moved)
        normals = normals_of_faces[closest.triangles]
        # point-to-plane distance; a closest point on a triangle's edge (scan outline)
        # lies off the plane and is down-weighted by its large Euclidean distance too
        signed = np.einsum("ij,ij->i", moved - closest.points, normals)
        scale = max(1.4826 * float(np.median(closest.distances[scale_from])), min_scale_mm)
        u = closest.distances / (tukey_factor * scale)
        weight = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0) * prior
        total = weight.sum()
        if total < 6:
            break
        # linearised point-to-plane step: rotation vector omega and translation t
        # (about the sample's centroid, which keeps the 6 x 6 normal equations well scaled)
        centre = weight @ moved / total
        jac = np.hstack([np.cross(moved - centre, normals), normals])
        weighted = (jac * weight[:, None]).T
        step = np.linalg.solve(weighted @ jac + ridge, -weighted @ signed)
        rotation = Rotation.from_rotvec(step[:3]).as_matrix()
        update = np.eye(4)
        update[:3, :3] = rotation
        update[:3, 3] = centre + step[3:] - rotation @ centre
        matrix = update @ matrix
        inlier_rms = float(np.sqrt(np.average(signed ** 2, weights=weight)))
        motion = np.abs((moved - centre) @ (rotation - np.eye(3)).T + step[3:]).max()
        if motion < tolerance_mm:
            break
    final = fixed_surface.closest_point(sample @ matrix[:3, :3].T + matrix[:3, 3]).distances
    median = float(np.median(final[scale_from]))
    return RigidAlignment(FrameTransform(matrix, "rigid"), start, done, inlier_rms, median)


def fit_mirror_symmetry(grid: FaceGrid, **align_options) -> FrameTransform:
    """The reflection across a face's plane of symmetry, in the grid's frame.

    The grid is reflected across the plane x = 0 of its frame (its left and right
    landmarks swapped) and aligned rigidly onto the unreflected grid with
    :func:`align_rigid` (landmarks, then ICP on the surface); the reflection followed
    by that rigid map sends each point of the face near its mirror image. The result is
    projected onto the nearest exact plane reflection, so applying it twice is the
    identity.

    Parameters
    ----------
    grid : FaceGrid
        A face with landmarks; x should run roughly from one side of the face to the
        other (true of scans and of normalised faces).
    **align_options
        Passed to :func:`align_rigid` (here by default every 5th row and column, and a
        stop at 0.01 mm of motion: within 0.1 mm of the converged plane, in half the
        time).

    Returns
    -------
    FrameTransform
        The reflection (``method == "mirror"``, determinant -1).

    Raises
    ------
    ValueError
        Fewer than three landmarks whose mirror partners are present.
    """
    flip = np.diag([-1.0, 1.0, 1.0])
    swap = list(MIRROR_LANDMARK)
    mirrored = replace(grid, points=grid.points @ flip, landmarks=(grid.landmarks @ flip)[swap],
                       landmark_vertices=grid.landmark_vertices[swap])
    align_options = {"sample_step": 5, "tolerance_mm": 0.01, **align_options}
    rigid = align_rigid(mirrored, grid, **align_options).transform.matrix
    linear = rigid[:3, :3] @ flip
    # the nearest plane reflection I - 2 n n^T: n is the eigenvector of the linear
    # part's symmetric half with the most negative eigenvalue; the plane n.x = d is the
    # set of midpoints between points and their images
    _, vectors = np.linalg.eigh(0.5 * (linear + linear.T))
    normal = vectors[:, 0]
    offset = 0.5 * float(normal @ rigid[:3, 3])
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) - 2.0 * np.outer(normal, normal)
    matrix[:3, 3] = 2.0 * offset * normal
    return FrameTransform(matrix, "mirror")


#: Weight of the rest of the face beside the stable parts in :func:`stable_weight`: it
#: keeps the rotation determined when a stable part is missing from the scan.
STABLE_ELSEWHERE = 0.1
# The stable parts, in units of the inner eye corners' distance (about 37 mm) from the
# middle of the eye line: the nose's bridge from above the saddles to half way down the
# nose; the forehead from 1.2 units above the eye line; the temples beyond 0.55 of the
# outer corners' distance, from 0.3 units below the eye line to 0.9 above it.
_BRIDGE_HALF_WIDTH = (0.35, 0.5)
_BRIDGE_SPAN = ((-0.95, -0.75), (0.45, 0.25))
_FOREHEAD_FROM = (1.2, 1.45)
_TEMPLE_FROM = (0.55, 0.62)
_TEMPLE_SPAN = ((-0.3, -0.1), (0.9, 0.7))
# The eye corners (the canthi, which the canthal tendons tie to the orbit's rim): full
# weight within 0.14 units (about 5 mm) of a corner, none beyond 0.22 (about 8 mm),
# where the lids' own motion begins to dominate.
_CANTHUS_RADIUS = (0.22, 0.14)
# The eye corners' distances assumed when a pair is missing (mm).
_INNER_EYES_MM, _OUTER_EYES_MM = 37.0, 89.0


STABLE_PARTS = ("bridge", "forehead", "temples")
#: Every part :func:`stable_weight` places: the stable parts and the eye corners.
PLACED_PARTS = (*STABLE_PARTS, "canthi")


def stable_weight(points, landmarks, parts=STABLE_PARTS, elsewhere: float = STABLE_ELSEWHERE) -> np.ndarray:
    """Weight in [0, 1] of each point (..., 3) of a face (roughly frontal, +y up) as a
    part that no expression moves much: 1 on the nose's bridge, the upper forehead and
    the temples (bone under thin skin), or at the eye corners (``"canthi"``, tied to
    the bone by tendons); ``parts`` names those wanted,
    ``elsewhere`` (:data:`STABLE_ELSEWHERE`) elsewhere, 0 at NaN points. Placed from the
    eye corners (the nose saddles if they are missing).

    Raises
    ------
    ValueError
        Naming ``parts``: a part it does not place (:data:`PLACED_PARTS`).
    """
    unknown = [part for part in parts if part not in PLACED_PARTS]
    if unknown:
        raise ValueError(f"parts must name parts of {PLACED_PARTS}, got {unknown}")
    lm = np.asarray(landmarks, dtype=np.float64)

    def corner(name):
        return lm[landmark_index(name)]

    inner = [corner("Inner left eye corner"), corner("Inner right eye corner")]
    outer = [corner("Outer left eye corner"), corner("Outer right eye corner")]
    eyes = np.array([p for p in inner + outer if np.isfinite(p).all()])
    if len(eyes) == 0:
        eyes = np.array([p for p in (corner("Nose saddle left"), corner("Nose saddle right")) if np.isfinite(p).all()])
    p = np.asarray(points, dtype=np.float64)
    if len(eyes) == 0:
        return np.where(np.isfinite(p).all(axis=-1), 1.0, 0.0)
    middle = eyes.mean(axis=0)
    inner_mm = float(np.linalg.norm(inner[0] - inner[1])) if np.isfinite(inner).all() else _INNER_EYES_MM
    outer_mm = float(np.linalg.norm(outer[0] - outer[1])) if np.isfinite(outer).all() else _OUTER_EYES_MM
    across = np.abs(p[..., 0] - middle[0])
    up = (p[..., 1] - middle[1]) / inner_mm
    bridge = (smoothstep(_BRIDGE_HALF_WIDTH[1] * inner_mm, _BRIDGE_HALF_WIDTH[0] * inner_mm, across)
              * smoothstep(*_BRIDGE_SPAN[0], up) * smoothstep(*_BRIDGE_SPAN[1], up))
    forehead = smoothstep(*_FOREHEAD_FROM, up)
    temples = (smoothstep(_TEMPLE_FROM[0] * outer_mm, _TEMPLE_FROM[1] * outer_mm, across)
               * smoothstep(*_TEMPLE_SPAN[0], up) * smoothstep(*_TEMPLE_SPAN[1], up))
    found = {"bridge": bridge, "forehead": forehead, "temples": temples}
    if "canthi" in parts:
        # the corners present (not the saddles that stand in for them above)
        corners = [c for c in inner + outer if np.isfinite(c).all()]
        if corners:
            nearest = np.min([np.linalg.norm(p - c, axis=-1) for c in corners], axis=0)
            found["canthi"] = smoothstep(_CANTHUS_RADIUS[0] * inner_mm, _CANTHUS_RADIUS[1] * inner_mm, nearest)
        else:
            found["canthi"] = np.zeros(up.shape)
    weight = np.maximum.reduce([*(found[part] for part in parts), np.full(up.shape, float(elsewhere))])
    return np.where(np.isfinite(weight), weight, 0.0)


#: The residual rigid motion's final fits keep the pairs within 3 times this of it
#: (mm): about twice the registration's noise on still skin.
MODE_SCALE_MM = 0.3
#: The final fits start from the field as it is, from the prior's fit, and from that fit
#: moved this far (mm) up and down: raised brows and a dropped jaw pull a fit along the
#: face's vertical axis.
MODE_STARTS_MM = (-2.0, 2.0)


#: The parts whose points count twice when the residual rigid motion picks the largest
#: part that moved as one: the bone under the nose's bridge, the temples and the eye
#: corners. Not the forehead, which raised brows carry up as a block. In whole
#: expressions that move every part of the face a little (anger's cheeks and nose rise
#: by about a millimetre together, a nose wrinkler lifts the chin with the lip), the
#: largest such part need not be the still one.
ANCHOR_PARTS = ("bridge", "temples", "canthi")


def residual_rigid_motion(points, motion, prior, *, anchor=None, iterations: int = 10, tukey_factor: float = 3.0,
                          min_scale_mm: float = 0.3) -> FrameTransform:
    """The rigid motion left in a registered field: the rigid map E that takes the
    points p (m, 3) to p + motion(p) over the largest part of the face that moved as one.

    A robust fit (Tukey weights of the residuals) leaning on ``prior`` (m,), where a
    point should be still, with the scale from the residuals' median over the points it
    trusts most (at least ``min_scale_mm``), gives a start. From it, from no motion, and
    from it moved up and down (:data:`MODE_STARTS_MM`), fits over every point with a
    fixed small scale (:data:`MODE_SCALE_MM`) each settle on a set of points that one
    rigid motion explains; the largest set wins (the still part: a part that moved as a
    block, the forehead under raised brows or the dropped jaw, is a smaller one). A point
    counts 1 + ``anchor`` (m,) in that choice (none given: 1)."""
    p = np.asarray(points, dtype=np.float64)
    moved = p + np.asarray(motion, dtype=np.float64)
    prior = np.asarray(prior, dtype=np.float64)
    count = 1.0 + (np.zeros(len(p)) if anchor is None else np.asarray(anchor, dtype=np.float64))
    ok = np.isfinite(p).all(axis=1) & np.isfinite(moved).all(axis=1) & (prior > 0)
    p, moved, prior, count = p[ok], moved[ok], prior[ok], count[ok]
    if len(p) < 10:
        return FrameTransform.identity()
    trusted = prior > 0.5 if np.count_nonzero(prior > 0.5) >= 10 else slice(None)

    def fit(weight):
        # the points are finite and a weight sum of 6 or more (each at most 1) leaves
        # at least 6 pairs: the checked fit's checks cost more than the fit here
        use = weight > 0
        return fit_similarity(p[use], moved[use], weight[use], scale=False)

    start = fit(prior)
    for _ in range(iterations):
        residual = np.linalg.norm(start.apply(p) - moved, axis=1)
        weight = tukey_weights(residual, tukey_factor * robust_scale(residual[trusted], min_scale_mm)) * prior
        if weight.sum() < 6:
            break
        start = fit(weight)

    def settle(transform):
        """The fit with the fixed small scale from a start, and how many points it explains."""
        for _ in range(iterations + 5):
            weight = tukey_weights(np.linalg.norm(transform.apply(p) - moved, axis=1), tukey_factor * MODE_SCALE_MM)
            if weight.sum() < 6:
                return transform, 0.0
            transform = fit(weight)
        weight = tukey_weights(np.linalg.norm(transform.apply(p) - moved, axis=1), tukey_factor * MODE_SCALE_MM)
        return transform, float(weight @ count)

    starts = [FrameTransform.identity(), start]
    for shift in MODE_STARTS_MM:
        matrix = start.matrix.copy()
        matrix[1, 3] += shift
        starts.append(FrameTransform(matrix, "rigid"))
    best, _ = max((settle(s) for s in starts), key=lambda fit: fit[1])
    return FrameTransform(best.matrix, "rigid")


class Realigned:
    """A displacement field with a rigid motion E taken out of it: the point a field
    moves p to, p + u(p), mapped back by E^-1 (the expressive scan's pose corrected)."""

    def __init__(self, motion, rigid: FrameTransform):
        self.motion = motion
        self.rigid = rigid
        self._inverse = rigid.inverse()

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self._inverse.apply(p + self.motion(p)) - p
