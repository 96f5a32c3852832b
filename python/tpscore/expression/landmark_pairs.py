"""The landmark pairs of the dense registration: where each labelled neutral landmark
went in the expressive scan, and how firmly the registration should hold to it.

A labelled landmark is about a millimetre off in each scan, as much as the motion of the
subtle AUs. With the scans' colour images, the skin's pattern at the neutral landmark's
vertex shows where it went (:func:`texture_landmarks`). Without them, each pair is
refined by fitting the neutral surface patch around the landmark onto the expressive
surface (:func:`refine_landmark_motion`) and trusted per direction, as far as the
patch's shape pins the shift down (:func:`refined_pair_trust`). :func:`landmark_term`
turns the pairs into the registration's soft constraints.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..geometry import off_surface
from ..lattice import BSplineLattice
from ..mesh import face_normals
from ..spatial import MeshSurface

__all__ = ["refine_landmark_motion", "refined_pair_trust", "texture_landmarks", "landmark_term",
           "LANDMARK_PATCH_MM", "REFINED_LANDMARK_WEIGHT", "REFINE_MAX_RMS_MM"]

#: Radius of the neutral surface patch around a landmark that is fitted onto the
#: expressive surface (7 and 14 mm scored 0.354 / 0.361 against 0.360 for 10 mm on the
#: registration alone; benchmarks/FIDELITY.md).
LANDMARK_PATCH_MM = 10.0
#: Weight of a refined pair along the directions it is trusted in, relative to one data
#: point (a labelled pair has the registration's ``landmark_weight``).
REFINED_LANDMARK_WEIGHT = 10.0
#: A refined pair is trusted fully along a direction while its uncertainty there (the
#: patch's fit rms over the square root of its normal-matrix eigenvalue in that
#: direction) is below this, and not at all beyond twice it (0.5 mm scored 0.382
#: against 0.373; benchmarks/FIDELITY.md).
REFINE_MAX_RMS_MM = 0.35
# Ridge of the patch fit per patch point (a unit normal gives 1 per point along it):
# directions in which the patch has less shape than this keep the labelled motion.
REFINE_RIDGE = 0.03


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
    normals_of = face_normals(expressive_surface.vertices, expressive_surface.faces)
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
        return closest, normals, along, (~off_surface(along, closest.distances)).astype(np.float64)

    for _ in range(iterations):
        # all patches in one closest-point query; one 3 x 3 solve per patch
        _, normals, along, w = contact(shift)
        outer = np.einsum("i,ij,ik->ijk", w, normals, normals)
        matrix = np.zeros((len(index), 3, 3))
        np.add.at(matrix, owner, outer)
        rhs = np.zeros((len(index), 3))
        np.add.at(rhs, owner, (w * along)[:, None] * normals)
        # a small ridge (per point) keeps directions the patch does not pin down
        matrix += REFINE_RIDGE * counts[:, None, None] * np.eye(3)
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
    shape[index[fitted]] = (matrix[fitted] - REFINE_RIDGE * counts[fitted, None, None] * np.eye(3)) \
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


def texture_landmarks(points, mask, lm_from, lm_to, texture, *, matched_only: bool = False) -> np.ndarray:
    """The expressive landmarks, each replaced by the texture match of its neutral
    landmark's grid vertex where there is one: the skin's pattern shows where a labelled
    point went more precisely than a second label (about a millimetre off in each scan)
    or a patch fit of the surface, which cannot follow skin that slides. With
    ``matched_only``, a landmark without a match is NaN instead of its expressive label
    (for labels a detector made, a few millimetres off)."""
    out = np.full_like(lm_to, np.nan) if matched_only else lm_to.copy()
    present = np.flatnonzero(np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1))
    if len(present) == 0:
        return out
    valid = np.flatnonzero(mask.reshape(-1))
    flat = points.reshape(-1, 3)[valid]
    # a neutral landmark sits on a grid vertex (it was snapped there): find that vertex
    # (|a - b|^2 up to the landmark's own |a|^2, as one matrix product)
    squared = (flat * flat).sum(axis=1)[None, :] - 2.0 * lm_from[present] @ flat.T
    nearest = valid[np.argmin(squared, axis=1)]
    matched = texture.confidence.reshape(-1)[nearest] > 0
    out[present[matched]] = texture.targets.reshape(-1, 3)[nearest[matched]]
    return out


def landmark_term(lattice: BSplineLattice, points, mask, neutral_landmarks, expressive_landmarks,
                  expressive_surface: MeshSurface, landmark_weight: float, texture=None, *,
                  landmarks_detected: bool = False):
    """The landmark pairs as soft constraints of the registration's normal equations.

    Each pair pulls the field at its neutral landmark toward a target with a 3 x 3
    weight W: (u - t)^T W (u - t). A labelled pair has W = landmark_weight I. With
    texture matches, the pair's expressive end is the texture match of the neutral
    landmark's vertex where there is one (:func:`texture_landmarks`); without them the
    pair is refined by a patch fit and trusted per direction
    (:func:`refine_landmark_motion`, :func:`refined_pair_trust`).

    ``landmarks_detected``: the landmarks were found by a detector, not labelled. Two
    scans' detections differ by a few millimetres where a labelled pair differs by one
    or two, more than the motion of most AUs, and held to them the registration carries
    the detector's error as motion. With texture matches, only the pairs whose
    expressive end is a match are kept (a match at a detected neutral landmark is still
    where that skin went); without them, the labelled part of each pair goes and only
    the patch fit's trusted directions stay. Development subjects, every landmark
    detected: AUs 1, 2, 4, 17 without texture 0.296 held to the pairs, 0.248 not; nine
    AUs with texture 0.234 without pairs, 0.219 with the texture's (benchmarks/LANDMARKS.md).

    Returns
    -------
    matrix : (3 n_nodes, 3 n_nodes) scipy.sparse.csr_matrix
        The pairs' term of the normal matrix, in component blocks [x; y; z].
    rhs : (n_nodes, 3) ndarray
        Their term of the right-hand side.
    """
    lm_from = np.asarray(neutral_landmarks, dtype=np.float64)
    lm_to = np.asarray(expressive_landmarks, dtype=np.float64)
    if landmarks_detected and texture is None:
        landmark_weight = 0.0
    if texture is not None:
        lm_to = texture_landmarks(points, mask, lm_from, lm_to, texture, matched_only=landmarks_detected)
    both = np.isfinite(lm_from).all(axis=1) & np.isfinite(lm_to).all(axis=1)
    eye = np.eye(3)[None]
    if texture is not None:
        weight = np.repeat(landmark_weight * eye, int(both.sum()), axis=0)
        pull = landmark_weight * (lm_to - lm_from)[both]
    else:
        refined, fit_rms, shape = refine_landmark_motion(points, mask, lm_from, expressive_surface, lm_to,
                                                         LANDMARK_PATCH_MM, return_shape=True)
        trust = refined_pair_trust(fit_rms, shape, REFINE_MAX_RMS_MM)[both]
        weight = landmark_weight * (eye - trust) + REFINED_LANDMARK_WEIGHT * trust
        pull = np.einsum("kij,kj->ki", landmark_weight * (eye - trust), (lm_to - lm_from)[both]) \
            + np.einsum("kij,kj->ki", REFINED_LANDMARK_WEIGHT * trust, (np.nan_to_num(refined) - lm_from)[both])
    basis = lattice.basis(lm_from[both, :2])
    matrix = sp.bmat([[basis.T @ basis.multiply(weight[:, a, b][:, None]) for b in range(3)]
                      for a in range(3)]).tocsr()
    return matrix, basis.T @ pull
