"""Pose calibration of a scan against a template before template adaptation.

Two ways to bring the scan into the template's frame, q* = S R (q - q_c) + p_c:

* ``"axes"`` -- the method's calibration: on each face, an x axis from left/right
  feature pairs (the mean of left - right), a reference axis (from one group of
  feature points to another, e.g. chin to eyes) made orthogonal to it, and their
  cross product give a frame; R maps the scan's frame onto the template's and is
  reported as the angles of R = Rz Ry Rx; S is the ratio of the reference axis
  lengths; q_c and p_c are the centroids of the feature points used.
* ``"similarity"`` -- a least-squares rotation, uniform scale and translation over
  every feature pair present on both faces (Umeyama). It uses all pairs, so one
  noisy point matters less; it is the default.

Which landmarks play which role is configurable; the defaults use the 22 Bosphorus
names.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_points
from ..face.landmarks import landmark_index
from ..face.normalise import FrameTransform, similarity_transform

__all__ = [
    "AxesCalibration",
    "DEFAULT_LEFT_RIGHT_PAIRS",
    "DEFAULT_REFERENCE_AXIS",
    "CALIBRATION_METHODS",
    "axes_calibration",
    "calibrate",
    "rotation_angles",
]

CALIBRATION_METHODS = ("similarity", "axes", "none")

#: Left/right landmark pairs whose differences define the x axis (subject's left).
DEFAULT_LEFT_RIGHT_PAIRS = (
    ("Outer left eye corner", "Outer right eye corner"),
    ("Inner left eye corner", "Inner right eye corner"),
    ("Outer left eyebrow", "Outer right eyebrow"),
    ("Left mouth corner", "Right mouth corner"),
)
#: The reference axis runs from the mean of the first group to the mean of the second:
#: chin to the eye corners, roughly the face's vertical (+y), and long enough to scale.
DEFAULT_REFERENCE_AXIS = (
    ("Chin middle",),
    ("Outer left eye corner", "Inner left eye corner", "Inner right eye corner", "Outer right eye corner"),
)


@dataclass(frozen=True)
class AxesCalibration:
    """The method's calibration q* = S R (q - q_c) + p_c, with its parts.

    Attributes
    ----------
    transform : FrameTransform
        Maps scan points into the template frame.
    rotation : (3, 3) ndarray
        R, a proper rotation.
    angles_deg : (3,) ndarray
        (x, y, z) angles in degrees with R = Rz(z) Ry(y) Rx(x).
    scale : float
        S, template reference length / scan reference length.
    scan_centre, template_centre : (3,) ndarray
        q_c and p_c, mm.
    """

    transform: FrameTransform
    rotation: np.ndarray
    angles_deg: np.ndarray
    scale: float
    scan_centre: np.ndarray
    template_centre: np.ndarray


def rotation_angles(rotation) -> np.ndarray:
    """Angles (x, y, z) in degrees with ``rotation == Rz(z) @ Ry(y) @ Rx(x)``.

    Parameters
    ----------
    rotation : (3, 3) array_like
        A proper rotation matrix.

    Returns
    -------
    (3,) ndarray, degrees; y in [-90, 90].
    """
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must have shape (3, 3), got {r.shape}")
    y = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(np.cos(y)) > 1e-9:
        x = np.arctan2(r[2, 1], r[2, 2])
        z = np.arctan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: only x - z (or x + z) is determined; put it all in x
        x = np.arctan2(-r[1, 2], r[1, 1])
        z = 0.0
    return np.degrees([x, y, z])


def _group_mean(landmarks: np.ndarray, names, role: str) -> np.ndarray:
    rows = landmarks[[landmark_index(n) for n in names]]
    rows = rows[np.isfinite(rows).all(axis=1)]
    if len(rows) == 0:
        raise ValueError(f"the {role} needs at least one of {list(names)}; all are missing")
    return rows.mean(axis=0)


def _face_frame(landmarks: np.ndarray, pairs, reference, who: str):
    """Orthonormal frame (columns x, y, z), reference length and centre of one face.

    Not :func:`tpscore.face.normalise.face_frame`: the method's calibration builds its
    axes from configurable pairs and groups, each averaged over the members present,
    so that a missing landmark does not stop it.
    """
    differences = []
    for left, right in pairs:
        a, b = landmarks[landmark_index(left)], landmarks[landmark_index(right)]
        if np.isfinite(a).all() and np.isfinite(b).all():
            differences.append(a - b)
    if not differences:
        raise ValueError(f"{who}: no left/right pair is present, so the x axis is undetermined")
    x_axis = np.mean(differences, axis=0)
    start = _group_mean(landmarks, reference[0], f"{who} reference axis start")
    end = _group_mean(landmarks, reference[1], f"{who} reference axis end")
    ref = end - start
    length = float(np.linalg.norm(ref))
    if np.linalg.norm(x_axis) < 1e-9 or length < 1e-9:
        raise ValueError(f"{who}: the x axis or the reference axis has zero length")
    x_axis = x_axis / np.linalg.norm(x_axis)
    y_axis = ref - (ref @ x_axis) * x_axis
    if np.linalg.norm(y_axis) < 1e-6 * length:
        raise ValueError(f"{who}: the reference axis is parallel to the left/right axis")
    y_axis /= np.linalg.norm(y_axis)
    z_axis = np.cross(x_axis, y_axis)
    used = {landmark_index(n) for pair in pairs for n in pair}
    used |= {landmark_index(n) for group in reference for n in group}
    rows = landmarks[sorted(used)]
    centre = rows[np.isfinite(rows).all(axis=1)].mean(axis=0)
    return np.column_stack([x_axis, y_axis, z_axis]), length, centre


def axes_calibration(scan_landmarks, template_landmarks, *, pairs=DEFAULT_LEFT_RIGHT_PAIRS,
                     reference=DEFAULT_REFERENCE_AXIS, scale: bool = True) -> AxesCalibration:
    """The method's calibration from feature axes: q* = S R (q - q_c) + p_c.

    Parameters
    ----------
    scan_landmarks, template_landmarks : (22, 3) array_like
        Bosphorus landmarks (mm) of the scan and of the template; NaN rows missing.
    pairs : sequence of (left name, right name)
        Pairs whose mean difference (left - right) is the x axis.
    reference : (names, names)
        The reference axis runs from the mean of the first group to the mean of the
        second; made orthogonal to x it is the y axis; its length sets the scale.
    scale : bool
        Fit S (True) or keep S = 1.

    Raises
    ------
    ValueError
        If every pair, or a whole reference group, is missing on either face.
    """
    scan = as_points(scan_landmarks, "scan_landmarks", finite=False)
    template = as_points(template_landmarks, "template_landmarks", finite=False)
    scan_frame, scan_length, scan_centre = _face_frame(scan, pairs, reference, "scan_landmarks")
    template_frame, template_length, template_centre = _face_frame(
        template, pairs, reference, "template_landmarks")
    rotation = template_frame @ scan_frame.T
    s = template_length / scan_length if scale else 1.0
    matrix = np.eye(4)
    matrix[:3, :3] = s * rotation
    matrix[:3, 3] = template_centre - s * rotation @ scan_centre
    return AxesCalibration(FrameTransform(matrix, "axes"), rotation, rotation_angles(rotation),
                           float(s), scan_centre, template_centre)


def calibrate(scan_landmarks, template_landmarks, method="similarity", *, weights=None) -> FrameTransform:
    """The transform that takes scan points into the template frame.

    Parameters
    ----------
    scan_landmarks, template_landmarks : (n, 3) array_like
        Corresponding feature points (mm); NaN rows are ignored. ``"axes"`` needs the
        22 Bosphorus landmarks.
    method : {"similarity", "axes", "none"} or FrameTransform
        A FrameTransform is returned as it is (an initial transform given by the
        caller).
    weights : (n,) array_like, optional
        Per-pair weights for ``"similarity"`` (0 leaves a pair out).
    """
    if isinstance(method, FrameTransform):
        return method
    if method == "similarity":
        return similarity_transform(scan_landmarks, template_landmarks, weights=weights)
    if method == "axes":
        return axes_calibration(scan_landmarks, template_landmarks).transform
    if method == "none":
        return FrameTransform.identity()
    raise ValueError(
        f"calibration must be one of {CALIBRATION_METHODS} or a FrameTransform, got {method!r}")
