"""The 22 Bosphorus landmarks: names, order and left/right pairing.

Left and right are the subject's. A landmark that is missing is NaN in a (22, 3)
array, never a guess.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "LANDMARK_NAMES",
    "N_LANDMARKS",
    "landmark_index",
    "MIRROR_LANDMARK",
    "empty_landmarks",
]

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
            f"unknown landmark name {name!r}; known names: {', '.join(LANDMARK_NAMES)}"
        ) from None


def _mirror(name: str) -> str:
    swapped = name.replace("left", "\0").replace("right", "left").replace("\0", "right")
    swapped = swapped.replace("Left", "\0").replace("Right", "Left").replace("\0", "Right")
    return swapped


#: For each landmark index, the index of its mirror image (itself on the midline).
MIRROR_LANDMARK: tuple[int, ...] = tuple(landmark_index(_mirror(n)) for n in LANDMARK_NAMES)


def empty_landmarks() -> np.ndarray:
    """A (22, 3) array of NaN: every landmark missing."""
    return np.full((N_LANDMARKS, 3), np.nan)
