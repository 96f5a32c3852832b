"""A face's pose and unit from its landmarks, and the canonical frame the steps assume.

Every step of a transfer assumes a face in millimetres that looks toward +z with +y up
(the frame of a frontal depth scan): resampling reads depth along z, the upper/lower
split and the same-person alignment work in the scan's x, y and in millimetres.
Scanners write other frames (y forward and z up, say) and other units (metres). A
face's landmarks say which: fitted to the reference face's landmarks by a least-squares
similarity, they give the rotation and the scale from the scan's frame to the
reference's.

:func:`scan_pose` keeps the exact part of that fit: the nearest of the 24 rotations
that permute and flip the axes, and the nearest power of ten as the unit. A face within
45 degrees of frontal and in millimetres is left exactly as it is (every step copes
with such a pose, and results on such scans stay what they were), while a frame with
swapped axes, or a scan in centimetres or metres, is brought into the canonical frame;
a signed permutation of the axes moves numbers without rounding them.

The same fit finds landmarks that cannot be right. Landmarks whose left and right are
swapped are the mirror image of a face, which a reflection fits and no rotation does:
:func:`check_landmarks` refuses them (:class:`MirroredLandmarksError`), since a transfer
would put the expression on the wrong side. A shuffled or mislabelled set fits the
reference face poorly: that is warned (:class:`ImplausibleLandmarksWarning`), naming the
landmarks farthest off, because an unusual face can fit poorly too.
"""
from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from ..geometry import FrameTransform
from .io import read_npz
from .landmarks import LANDMARK_NAMES, MIRROR_PAIRS, as_landmarks

__all__ = [
    "ScanPose",
    "scan_pose",
    "check_landmarks",
    "reference_landmarks",
    "MirroredLandmarksError",
    "ImplausibleLandmarksWarning",
    "ImplausibleLandmarksError",
    "UNITS_MM",
    "IMPLAUSIBLE_RESIDUAL",
]

#: Millimetres per unit of the units a scan is recognised in, by their names.
UNITS_MM = {1.0: "millimetres", 10.0: "centimetres", 1000.0: "metres"}

# A face in millimetres is between half and twice the size of the reference face (the
# landmarks' spread; adults vary by about +-15 %). Powers of ten are 10x apart, so at
# most one unit fits; a face in inches (25.4 mm) fits none and is left alone.
_SIZE_RANGE = (0.5, 2.0)

#: RMS distance of the landmarks from the reference face's after the similarity fit,
#: as a fraction of the reference landmarks' RMS spread, above which the landmarks are
#: warned as implausible. Faces fit to 0.02 to 0.06 (the procedural faces the reference
#: was built from) and 0.15 to 0.19 (the ICT faces of the generated development scans,
#: whose proportions differ), a shuffled set to 0.85 and more.
IMPLAUSIBLE_RESIDUAL = 0.3
#: Above this residual the landmarks are refused (:class:`ImplausibleLandmarksError`)
#: rather than warned about: the development scans' landmarks fit to 0.21 at most (an
#: open mouth included), a shuffled set to 0.87 and more, four of them exchanged in a
#: cycle to 0.34-0.8; between the two limits they are warned about.
IMPLAUSIBLE_REFUSED_RESIDUAL = 0.6

# Landmarks are mirrored when their mirror image fits the reference face better than
# they do. Measured: correct labels fit at least 2.1 times better than their mirror
# image, left-right swapped labels at least 2.1 times worse.
_MIRROR_RATIO = 1.0


# The fit needs four landmarks: three fix a rotation, the fourth tells a mirror image.
_MIN_POSE_LANDMARKS = 4


class MirroredLandmarksError(ValueError):
    """The landmarks are a mirror image of a face: their left and right are swapped, or
    the scan's frame is left-handed."""


class ImplausibleLandmarksError(ValueError):
    """The landmarks fit no face: shuffled or mislabelled beyond doubt. A caller sure of
    them passes ``check_landmarks=False`` (``TransferOptions(check_landmarks=False)``)."""


class ImplausibleLandmarksWarning(UserWarning):
    """The landmarks fit the reference face poorly (shuffled or mislabelled?)."""


@lru_cache(maxsize=1)
def reference_landmarks() -> np.ndarray:
    """The landmarks of the shipped average face, the canonical frame's reference (mm,
    nose tip at the origin, looking toward +z, +y up); read-only."""
    path = resources.files("tpscore").joinpath("data/average_face.npz")
    with resources.as_file(path) as real:
        landmarks = as_landmarks(read_npz(real, ("landmarks",), what="the average face model")["landmarks"])
    landmarks.setflags(write=False)
    return landmarks


@lru_cache(maxsize=1)
def _axis_rotations() -> np.ndarray:
    """The 24 rotations that permute and flip the axes, identity first, (24, 3, 3)."""
    rotations = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), order] = signs
            if np.linalg.det(matrix) > 0:
                rotations.append(matrix)
    return np.array(rotations)


@dataclass(frozen=True)
class ScanPose:
    """How a face's frame relates to the canonical one, from its landmarks.

    Attributes
    ----------
    rotation : (3, 3) array
        The axis permutation (with signs, determinant +1) nearest to the fitted rotation,
        from the face's axes to the canonical ones.
    mm_per_unit : float
        1 (millimetres), 10 (centimetres) or 1000 (metres); NaN when the size fits none.
    fitted_rotation : (3, 3) array
        The least-squares rotation onto the reference face's landmarks.
    scale : float
        The least-squares scale onto them (reference mm per face unit).
    residual : float
        RMS landmark distance after the fit, relative to the reference's spread.
    mirrored_residual : float
        The same for the face's mirror image.
    residuals_mm : (22,) array
        Each landmark's distance after the fit (reference mm; NaN where missing).
    """

    rotation: np.ndarray
    mm_per_unit: float
    fitted_rotation: np.ndarray
    scale: float
    residual: float
    mirrored_residual: float
    residuals_mm: np.ndarray
    swapped: tuple = ()

    @property
    def mirrored(self) -> bool:
        """Whether the landmarks are a mirror image of a face (left and right swapped)."""
        return (self.mirrored_residual < _MIRROR_RATIO * self.residual
                and self.mirrored_residual <= IMPLAUSIBLE_RESIDUAL)

    @property
    def plausible(self) -> bool:
        """Whether the landmarks fit the reference face as a face's do (the fit, not the
        left-right order of each pair: see :attr:`swapped_pairs`)."""
        return not self.mirrored and self.residual <= IMPLAUSIBLE_RESIDUAL

    @property
    def swapped_pairs(self) -> list[tuple[str, str]]:
        """Left/right landmark pairs that lie on each other's side once the face is in
        the reference frame (the subject's left at +x): mislabelled, one pair at a time.
        Empty for mirrored landmarks, where every pair is swapped."""
        if self.mirrored:
            return []
        return list(self.swapped)

    @property
    def canonical(self) -> bool:
        """Whether the face is within 45 degrees of frontal and in millimetres (or its
        landmarks are not plausible enough to tell otherwise)."""
        if not self.plausible or not np.isfinite(self.mm_per_unit):
            return True
        return self.mm_per_unit == 1.0 and np.array_equal(self.rotation, np.eye(3))

    @property
    def transform(self) -> FrameTransform:
        """The map from the face's frame to the canonical one: the axis rotation and the
        unit, no translation (identity when :attr:`canonical`)."""
        matrix = np.eye(4)
        if not self.canonical:
            matrix[:3, :3] = self.rotation * (self.mm_per_unit if np.isfinite(self.mm_per_unit) else 1.0)
        return FrameTransform(matrix, "pose")

    def to_canonical(self, points) -> np.ndarray:
        """Points (..., 3) in the canonical frame. The axis rotation only moves and flips
        coordinates, so a face in millimetres comes out unrounded."""
        points = np.asarray(points, dtype=np.float64)
        if self.canonical:
            return points.copy()
        order = np.argmax(np.abs(self.rotation), axis=1)
        signs = self.rotation[np.arange(3), order] * self.mm_per_unit
        return points[..., order] * signs

    def describe(self) -> str:
        """What the fit found, in words: how the face is turned, and its unit."""
        parts = []
        if not np.array_equal(self.rotation, np.eye(3)):
            looks = _direction(self.rotation.T @ np.array([0.0, 0.0, 1.0]))
            up = _direction(self.rotation.T @ np.array([0.0, 1.0, 0.0]))
            view = "a profile view" if abs(self.rotation[2, 2]) < 0.5 and abs(self.rotation[1, 1]) > 0.5 else \
                "turned in its own plane" if self.rotation[2, 2] > 0.5 else "a view from an unusual side"
            parts.append(f"looks toward {looks} with {up} up ({view})")
        if self.mm_per_unit != 1.0:
            unit = UNITS_MM.get(self.mm_per_unit)
            parts.append(f"is in {unit}" if unit else
                         f"is {self.scale:.3g} times smaller than a face in millimetres (unknown unit)")
        return " and ".join(parts) if parts else "is frontal, in millimetres"


def _direction(vector: np.ndarray) -> str:
    axis = int(np.argmax(np.abs(vector)))
    return ("-" if vector[axis] < 0 else "+") + "xyz"[axis]


def scan_pose(landmarks) -> ScanPose | None:
    """The pose and unit of a face from its (22, 3) landmarks (NaN rows missing), or
    None with fewer than four landmarks (or too degenerate a set) to tell."""
    lm = as_landmarks(landmarks)
    reference = reference_landmarks()
    both = np.isfinite(lm).all(axis=1)
    if both.sum() < _MIN_POSE_LANDMARKS:
        return None
    # Umeyama's least-squares similarity, once for the face and once for its mirror
    # image: mirroring the face flips one singular vector, so one SVD gives both fits'
    # residuals (resample_scan runs this for every scan; two full fits cost more than
    # a tenth of the resampling).
    source, target = lm[both], reference[both]
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    source_centred, target_centred = source - source_mean, target - target_mean
    source_variance = float((source_centred ** 2).sum())
    target_variance = float((target_centred ** 2).sum())
    u, singular, vt = np.linalg.svd(target_centred.T @ source_centred)
    if source_variance == 0.0 or singular[1] <= 1e-9 * singular[0]:
        return None  # all on one line: no rotation to speak of
    sign = 1.0 if np.linalg.det(u) * np.linalg.det(vt) > 0 else -1.0
    proper = singular[0] + singular[1] + sign * singular[2]
    mirrored = singular[0] + singular[1] - sign * singular[2]
    spread = np.sqrt(target_variance / len(target))
    residual = float(np.sqrt(max(target_variance - proper ** 2 / source_variance, 0.0) / len(target)) / spread)
    mirrored_residual = float(np.sqrt(max(target_variance - mirrored ** 2 / source_variance, 0.0)
                                      / len(target)) / spread)
    rotation = u @ np.diag([1.0, 1.0, sign]) @ vt
    scale = proper / source_variance
    fitted = scale * (lm - source_mean) @ rotation.T + target_mean
    residuals = np.linalg.norm(fitted - reference, axis=1)
    candidates = _axis_rotations()
    nearest = candidates[int(np.argmax(np.einsum("kij,ij->k", candidates, rotation)))]
    # the unit: the power of ten that brings the face's size within range of the reference's
    mm_per_unit = np.nan
    for unit in UNITS_MM:
        if _SIZE_RANGE[0] <= scale / unit <= _SIZE_RANGE[1]:
            mm_per_unit = unit
    swapped = tuple((LANDMARK_NAMES[i], LANDMARK_NAMES[j]) for i, j in MIRROR_PAIRS
                    if both[i] and both[j] and fitted[i, 0] < fitted[j, 0])
    return ScanPose(nearest, mm_per_unit, rotation, float(scale), residual, mirrored_residual, residuals, swapped)


def check_landmarks(landmarks, name: str = "landmarks", *, refuse: bool = True) -> ScanPose | None:
    """Check that landmarks can be a face's, and return their pose.

    Raises
    ------
    MirroredLandmarksError
        The landmarks are a mirror image of a face (left and right swapped).
    ImplausibleLandmarksError
        With ``refuse``, when they fit the reference face beyond doubt badly
        (:data:`IMPLAUSIBLE_REFUSED_RESIDUAL`); without it, that is warned.

    Warns
    -----
    ImplausibleLandmarksWarning
        They fit the reference face poorly; the message names the worst landmarks.
    """
    pose = scan_pose(landmarks)
    if pose is None:
        return None
    if pose.mirrored:
        raise MirroredLandmarksError(
            f"{name} are a mirror image of a face: left and right appear swapped (or the scan's frame "
            f"is left-handed); the mirror image fits the reference face with {pose.mirrored_residual:.2f} "
            f"of its size, the landmarks as given with {pose.residual:.2f}")
    problems = []
    if pose.residual > IMPLAUSIBLE_RESIDUAL:
        order = np.argsort(-np.nan_to_num(pose.residuals_mm, nan=-1.0))[:3]
        worst = ", ".join(f"{LANDMARK_NAMES[i]} ({pose.residuals_mm[i]:.0f} mm)" for i in order)
        problems.append(f"they fit the reference face poorly ({pose.residual:.2f} of its size off, more than "
                        f"{IMPLAUSIBLE_RESIDUAL}; farthest off: {worst})")
    if pose.swapped_pairs:
        problems.append("left and right exchanged: " + "; ".join(
            f"{left!r} lies right of {right!r}" for left, right in pose.swapped_pairs))
    if problems:
        if refuse and pose.residual > IMPLAUSIBLE_REFUSED_RESIDUAL:
            raise ImplausibleLandmarksError(
                f"{name} fit no face: {'; '.join(problems)}. Shuffled or mislabelled? If they are "
                "right, pass check_landmarks=False (TransferOptions(check_landmarks=False))")
        warnings.warn(f"{name} look shuffled or mislabelled: {'; '.join(problems)}",
                      ImplausibleLandmarksWarning, stacklevel=3)
    return pose
