"""The parts of the method as published that the default replaced (DESIGN.md, method 1):
lower-face motion scaled by the ratio of the mouth widths, and each region of the target
warped by a thin-plate spline through the AU's moved control points alone.

They stay because the published method is the baseline every measurement is held
against (``TransferOptions.published()``; 2.70 mean residual ratio on the benchmark
against 0.37 for the default without texture).
"""
from __future__ import annotations

import warnings

import numpy as np

from ..face.landmarks import landmark_index
from ..rbf import TPS

__all__ = ["mouth_width", "mouth_width_ratio", "control_point_warp"]


def mouth_width(landmarks) -> float:
    """Distance between the mouth corners (mm), NaN when one is missing."""
    lm = np.asarray(landmarks, dtype=np.float64)
    return float(np.linalg.norm(lm[landmark_index("Left mouth corner")] - lm[landmark_index("Right mouth corner")]))


def mouth_width_ratio(source_landmarks, target_landmarks) -> float:
    """s_t / s_s, the ratio of the mouth widths (1 with a warning when one is missing)."""
    source, target = mouth_width(source_landmarks), mouth_width(target_landmarks)
    if np.isfinite(source * target) and source > 0:
        return target / source
    warnings.warn("a mouth corner is missing: lower-face motion is not scaled by mouth width", stacklevel=3)
    return 1.0


def _merge_coincident(points: np.ndarray, values: np.ndarray, tol_mm: float = 0.5):
    """Merge points closer than tol_mm (mean value): coincident TPS centres are singular."""
    keep_p, keep_v = [], []
    taken = np.zeros(len(points), bool)
    for i in range(len(points)):
        if taken[i]:
            continue
        close = (np.linalg.norm(points - points[i], axis=1) < tol_mm) & ~taken
        taken |= close
        keep_p.append(points[close].mean(axis=0))
        keep_v.append(values[close].mean(axis=0))
    return np.array(keep_p), np.array(keep_v)


def control_point_warp(control: np.ndarray, displacement: np.ndarray):
    """The displacement field (a callable on (m, 3) points) of the TPS that moves the
    control points by their displacements."""
    centres, values = _merge_coincident(control, displacement)
    return TPS(centres, centres + values).displacement
