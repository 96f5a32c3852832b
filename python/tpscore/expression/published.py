"""The parts of the method as published that the default replaced (docs/design.md, method 1):
lower-face motion scaled by the ratio of the mouth widths, and each region of the target
warped by a thin-plate spline through the AU's moved control points alone.

They stay because the published method is the baseline every measurement is held
against (``TransferOptions.published()``; 2.70 mean residual ratio on the benchmark
against 0.37 for the default without texture).
"""
from __future__ import annotations

import warnings

import numpy as np

from ..face.landmarks import landmark_index, landmark_map
from ..rbf import TPS

__all__ = ["mouth_width", "mouth_width_ratio", "control_point_warp", "model_control_points", "warp_regions"]


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


def _flat(points: np.ndarray, ratio: float = 0.1) -> bool:
    """Whether the points' thinnest extent is under ``ratio`` of their widest."""
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(spread[-1] < ratio * spread[0])


def control_point_warp(control: np.ndarray, displacement: np.ndarray):
    """The displacement field (a callable on (m, 3) points) of the TPS that moves the
    control points by their displacements; with fewer than five distinct points (a 3D
    TPS needs five: AU25's inner-lip points coincide on a closed mouth) their mean
    displacement everywhere, and the same for points that lie almost in one plane or on
    one line (the lips' contact line: the TPS's affine part would extrapolate across
    the face without bound)."""
    centres, values = _merge_coincident(control, displacement)
    if len(centres) < 5 or _flat(centres):
        mean = values.mean(axis=0)
        return lambda points: np.broadcast_to(mean, np.shape(points)).copy()
    return TPS(centres, centres + values).displacement


def model_control_points(source_neutral, source_expressive, activations, reference, place, merge_mm: float):
    """Each AU's control points on the neutral source and their motion as published:
    mapped onto the expressive scan by the landmark TPS (neutral -> expressive) and
    snapped to its nearest vertex. ``place(action_unit)`` gives the points on the
    reference face. Returns (activation, names, neutral points, motion) per AU."""
    to_source = landmark_map(reference.landmarks, source_neutral.landmarks, merge_mm=merge_mm,
                             what="reference -> source")
    to_expressive = landmark_map(source_neutral.landmarks, source_expressive.landmarks, merge_mm=merge_mm,
                                 what="source neutral -> expressive")
    out = []
    for act in activations:
        neutral = source_neutral.snap(to_source(place(act.action_unit)), "vertex")
        motion = source_expressive.snap(to_expressive(neutral), "vertex") - neutral
        weights = act.action_unit.side_weights(act.side) * act.weight
        out.append((act, tuple(act.action_unit.names), neutral, motion * weights[:, None]))
    return out


def warp_regions(groups, source_landmarks, target, region_weight, merge_mm: float):
    """The published animation: each region's control points carried onto the target by
    the landmark TPS (source -> target, nearest-vertex snap), their motion scaled by the
    ratio of the mouth widths in the lower face, and each region of the target warped by
    the TPS through them. ``groups`` maps a region to its list of ControlPointMotion;
    ``region_weight(region)`` is the region's (H, W) weight on the target grid.
    Returns labels, fields (n, H, W, 3), control points and moved control points."""
    to_target = landmark_map(source_landmarks, target.landmarks, merge_mm=merge_mm, what="source -> target")
    lower_scale = mouth_width_ratio(source_landmarks, target.landmarks)
    grid = target.grid
    flat, valid = grid.points.reshape(-1, 3), grid.mask.ravel()
    labels, fields, controls, moved = [], [], [], []
    for region, motions in groups.items():
        control = target.snap(to_target(np.vstack([m.neutral for m in motions])), "vertex")
        displacement = np.vstack([m.motion for m in motions]) * (lower_scale if region == "lower" else 1.0)
        weight = region_weight(region)
        field = np.zeros_like(flat)
        field[valid] = control_point_warp(control, displacement)(flat[valid]) * weight.ravel()[valid, None]
        labels.append("+".join(m.activation.label for m in motions))
        fields.append(field.reshape(grid.points.shape))
        controls.append(control)
        moved.append(control + displacement)
    return labels, np.stack(fields), controls, moved
