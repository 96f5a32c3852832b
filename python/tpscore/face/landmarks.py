"""The 22 Bosphorus landmarks: names, order and left/right pairing.

Left and right are the subject's. A landmark that is missing is NaN in a (22, 3)
array, never a guess.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .._validation import MAX_COORDINATE, as_array
from ..rbf import TPS

__all__ = [
    "LANDMARK_NAMES",
    "N_LANDMARKS",
    "landmark_index",
    "as_landmarks",
    "MIRROR_LANDMARK",
    "MIRROR_PAIRS",
    "mirror_estimate",
    "empty_landmarks",
    "landmark_map",
    "MIN_LANDMARKS",
    "validate_anchor",
    "anchor_point",
]

#: A 3D TPS with an affine part needs five landmark pairs that are not coplanar.
MIN_LANDMARKS = 5

#: The 22 Bosphorus landmark names, in Bosphorus order.
LANDMARK_NAMES: tuple[str, ...] = (
    "Outer left eyebrow",
    "Middle left eyebrow",
    "Inner left eyebrow",
    "Inner right eyebrow",
    "Middle right eyebrow",
    "Outer right eyebrow",
    "Outer left eye corner",
    "Inner left eye corner",
    "Inner right eye corner",
    "Outer right eye corner",
    "Nose saddle left",
    "Nose saddle right",
    "Left nose peak",
    "Nose tip",
    "Right nose peak",
    "Left mouth corner",
    "Upper lip outer middle",
    "Right mouth corner",
    "Upper lip inner middle",
    "Lower lip inner middle",
    "Lower lip outer middle",
    "Chin middle",
)
N_LANDMARKS = len(LANDMARK_NAMES)
_INDEX = {name.lower(): i for i, name in enumerate(LANDMARK_NAMES)}


def landmark_index(name: str) -> int:
    """Index of a landmark by its Bosphorus name (case-insensitive).

    Raises ValueError for an unknown name, listing the known ones.
    """
    try:
        return _INDEX[str(name).strip().lower()]
    except KeyError:
        raise ValueError(
            f"unknown landmark name {str(name)[:80]!r}; known names: {', '.join(LANDMARK_NAMES)}"
        ) from None


def as_landmarks(landmarks, name: str = "landmarks") -> np.ndarray:
    """A (22, 3) float64 copy; rows are either all finite or all NaN (missing)."""
    array = np.array(as_array(landmarks, name), dtype=np.float64)
    if array.shape != (N_LANDMARKS, 3):
        raise ValueError(f"{name} must have shape ({N_LANDMARKS}, 3), got {array.shape}")
    finite = np.isfinite(array)
    partial = finite.any(axis=1) & ~finite.all(axis=1)
    if np.isinf(array).any() or partial.any():
        bad = np.flatnonzero(partial | np.isinf(array).any(axis=1))[0]
        raise ValueError(
            f"{name} row {bad} ({LANDMARK_NAMES[bad]}) has non-finite coordinates "
            f"{array[bad].tolist()}; a missing landmark is a row of three NaN"
        )
    if (np.abs(array[finite]) > MAX_COORDINATE).any():
        bad = np.flatnonzero((np.abs(np.where(finite, array, 0.0)) > MAX_COORDINATE).any(axis=1))[0]
        raise ValueError(f"{name} row {bad} ({LANDMARK_NAMES[bad]}) has coordinates beyond "
                         f"+-{MAX_COORDINATE:.0e} mm: {array[bad].tolist()}")
    return array


def _mirror(name: str) -> str:
    swapped = name.replace("left", "\0").replace("right", "left").replace("\0", "right")
    swapped = swapped.replace("Left", "\0").replace("Right", "Left").replace("\0", "Right")
    return swapped


#: For each landmark index, the index of its mirror image (itself on the midline).
MIRROR_LANDMARK: tuple[int, ...] = tuple(landmark_index(_mirror(n)) for n in LANDMARK_NAMES)
#: Each left landmark with its right partner, (left, right) by index.
MIRROR_PAIRS: tuple[tuple[int, int], ...] = tuple(
    (i, j) for i, j in enumerate(MIRROR_LANDMARK) if i != j and "left" in LANDMARK_NAMES[i].lower())


def mirror_estimate(landmarks: np.ndarray, index: int) -> np.ndarray | None:
    """Where a missing landmark lies, from its partner on the other side of the face
    reflected across the face's plane of symmetry; None without its partner or without
    two other pairs to place the plane.

    The plane is fitted to the landmarks themselves: its normal is the mean direction
    from each right landmark to its left partner, and it passes through the pairs'
    midpoints and the midline landmarks on average. A face is not exactly symmetric, so
    the estimate is off by its asymmetry there (a millimetre or two on a typical face):
    good enough to find an opening between two corners, not to replace a label.
    """
    landmarks = np.asarray(landmarks, dtype=np.float64)
    partner = MIRROR_LANDMARK[index]
    present = np.isfinite(landmarks).all(axis=1)
    if partner == index or not present[partner]:
        return None
    pairs = [(left, right) for left, right in MIRROR_PAIRS
             if present[left] and present[right] and index not in (left, right)]
    if len(pairs) < 2:
        return None
    normal = np.array([landmarks[left] - landmarks[right] for left, right in pairs]).sum(axis=0)
    normal /= np.linalg.norm(normal)
    on_plane = [0.5 * (landmarks[i] + landmarks[j]) for i, j in pairs]
    on_plane += [landmarks[i] for i, j in enumerate(MIRROR_LANDMARK) if i == j and present[i]]
    offset = float(np.mean(np.asarray(on_plane) @ normal))
    point = landmarks[partner]
    return point - 2.0 * (point @ normal - offset) * normal


def validate_anchor(owner: str, at, offset_mm) -> tuple[dict[str, float], tuple[float, float]]:
    """Check a place defined relative to the landmarks: weights over landmark names and
    an (x, y) offset in mm. Returns them as a dict of floats and a 2-tuple; raises
    ValueError naming `owner` for an unknown name, a weight <= 0 or a bad offset."""
    if not at:
        raise ValueError(f"{owner}: 'at' names no landmark")
    weights = {}
    for name, weight in dict(at).items():
        landmark_index(name)  # raises for an unknown name
        weight = float(weight)
        if not np.isfinite(weight) or weight <= 0:
            raise ValueError(f"{owner}: the weight of {name!r} must be > 0")
        weights[name] = weight
    offset = tuple(float(v) for v in offset_mm)
    if len(offset) != 2 or not np.isfinite(offset).all():
        raise ValueError(f"{owner}: offset_mm must be two finite numbers")
    return weights, offset


#: The sides an anchored point can be on (the subject's left and right).
SIDES = ("left", "right", "centre")


@dataclass(frozen=True)
class AnchoredPoint:
    """A named place on a face, defined relative to its landmarks: the weighted mean of
    the landmarks named in ``at`` (weights > 0) plus an (x, y) offset in mm. Control
    points of every method are anchored points.

    Attributes
    ----------
    name : str
    side : {"left", "right", "centre"}
        The side of the face it is on (the subject's).
    at : mapping of landmark name -> weight
    offset_mm : (float, float)
    note : str
        Free text (what the point follows, why it is where it is).
    """

    name: str
    side: str
    at: Mapping[str, float]
    offset_mm: tuple[float, float] = (0.0, 0.0)
    note: str = ""

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"control point {self.name!r}: side must be one of {SIDES}, got {self.side!r}")
        at, offset = validate_anchor(f"control point {self.name!r}", self.at, self.offset_mm)
        object.__setattr__(self, "at", at)
        object.__setattr__(self, "offset_mm", offset)

    def anchor(self, landmarks) -> np.ndarray:
        """The weighted mean (3,) of the named landmarks of a face."""
        return anchor_point(landmarks, self.at, f"control point {self.name!r}")

    def position_xy(self, landmarks) -> np.ndarray:
        """(x, y) of the point on a face with the given (22, 3) landmarks."""
        return self.anchor(landmarks)[:2] + self.offset_mm


def anchor_point(landmarks, at, owner: str = "anchor") -> np.ndarray:
    """The weighted mean (3,) of the landmarks named in `at`; ValueError if one is missing."""
    lm = np.asarray(landmarks, dtype=np.float64)
    total = 0.0
    point = np.zeros(3)
    for name, weight in at.items():
        p = lm[landmark_index(name)]
        if not np.isfinite(p).all():
            raise ValueError(f"landmarks: {name!r} is missing (NaN) but is needed for {owner}")
        point += weight * p
        total += weight
    return point / total


def empty_landmarks() -> np.ndarray:
    """A (22, 3) array of NaN: every landmark missing."""
    return np.full((N_LANDMARKS, 3), np.nan)


# Landmarks closer than this are the same point whatever merge distance is asked for:
# two TPS centres at one place would have to map to two places at once.
_COINCIDENT_MM = 1e-6


def _merge_close(lm: np.ndarray, other: np.ndarray, merge_mm: float):
    """Pairs present in both sets; pairs closer than merge_mm in either set are merged
    into their mean (transitively), so no two TPS centres nearly coincide."""
    use = np.flatnonzero(np.isfinite(lm).all(axis=1) & np.isfinite(other).all(axis=1))
    a, b = lm[use], other[use]
    if len(a) < 2:
        return a, b
    limit = max(merge_mm, _COINCIDENT_MM)
    close = ((np.linalg.norm(a[:, None] - a[None], axis=2) < limit)
             | (np.linalg.norm(b[:, None] - b[None], axis=2) < limit))
    group = np.arange(len(a))
    for i, j in zip(*np.nonzero(np.triu(close, 1))):
        group[group == group[j]] = group[i]
    labels = np.unique(group)
    merged_a = np.array([a[group == g].mean(axis=0) for g in labels])
    merged_b = np.array([b[group == g].mean(axis=0) for g in labels])
    return merged_a, merged_b


def landmark_map(from_landmarks, to_landmarks, *, smoothing: float = 0.0,
                 merge_mm: float = 0.0, what: str = "landmark map", extra=None) -> TPS:
    """The TPS taking one face's landmarks onto another's, over the landmarks both have
    (and ``extra``, further corresponding points (k, 3) and (k, 3), when given).

    Raises a ValueError that says how many landmarks remain when fewer than five are
    present in both faces (a 3D TPS needs five non-coplanar pairs).
    """

    a = np.asarray(from_landmarks, dtype=np.float64)
    b = np.asarray(to_landmarks, dtype=np.float64)
    if a.shape != (N_LANDMARKS, 3) or b.shape != (N_LANDMARKS, 3):
        raise ValueError(f"{what}: landmarks must have shape ({N_LANDMARKS}, 3)")
    src, dst = _merge_close(a, b, merge_mm)
    if len(src) < MIN_LANDMARKS:
        raise ValueError(
            f"{what}: only {len(src)} landmark(s) are present in both faces; "
            f"at least {MIN_LANDMARKS} are needed"
        )
    if extra is not None and len(extra[0]):
        src, dst = _with_extra(src, dst, np.asarray(extra[0], dtype=np.float64), np.asarray(extra[1], dtype=np.float64))
    return TPS(src, dst, smoothing=smoothing)


#: An extra pair of :func:`landmark_map` is kept only this far (mm) from every centre
#: already kept, in both faces: nearly coinciding centres would fold the map.
EXTRA_SPACING_MM = 1.5


def _with_extra(src, dst, more_src, more_dst):
    """The centres with the extra pairs that keep their distance (greedy, in order)."""
    keep_src, keep_dst = list(src), list(dst)
    for a, b in zip(more_src, more_dst):
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            continue
        if (np.linalg.norm(np.asarray(keep_src) - a, axis=1).min() > EXTRA_SPACING_MM
                and np.linalg.norm(np.asarray(keep_dst) - b, axis=1).min() > EXTRA_SPACING_MM):
            keep_src.append(a)
            keep_dst.append(b)
    return np.array(keep_src), np.array(keep_dst)
