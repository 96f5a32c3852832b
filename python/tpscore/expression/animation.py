"""Animation: the modelled motion carried onto the target, as one displacement field per
AU that a frame scales and adds.

The default reads, at each target vertex, the source's registered motion at the
corresponding point (the landmark TPS target -> source), weighted by the AU's region and
side; a bilateral expression's carried field is averaged with its mirror image across
the target's own plane too. The method as published warps each region through the moved
control points instead (:mod:`tpscore.expression.published`). Both are linear in the
magnitude, so a frame of an animation is a scaled add of precomputed fields.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from .._threads import side_by_side
from .._validation import as_real
from ..face.landmarks import landmark_map
from ..face.normalise import NormalisedFace
from ..face.regions import region_weight, side_weight, smoothstep
from .action_units import MAX_WEIGHT
from .mirror import MirroredMotion
from .modelling import ExpressionModel, mirrored
from .published import control_point_warp, mouth_width_ratio

__all__ = ["Animation", "animate", "magnitude_weights"]


@dataclass
class Animation:
    """Precomputed displacement fields of a transfer on the target grid.

    ``frame(m)`` is the target's neutral grid plus m times the summed AU fields (or a
    weight per AU); it costs one scaled add per AU.
    """

    target: NormalisedFace
    labels: list[str]
    fields: np.ndarray            # (n_aus, H, W, 3) displacement at magnitude 1, reference frame
    control_points: list[np.ndarray]
    moved_control_points: list[np.ndarray]

    def __post_init__(self):
        self._neutral = np.where(self.target.grid.mask[..., None], self.target.grid.points, np.nan)
        self._to_grid = self.target.transform.inverse()
        # a scan resampled from another frame or unit goes back there
        scan_frame = self.target.grid.scan_frame
        self._to_scan = self._to_grid if scan_frame is None else self._to_grid.then(scan_frame)

    def _weights(self, magnitude) -> np.ndarray:
        w = magnitude_weights(magnitude, self.labels)
        if ((w < 0) | (w > 1)).any():
            warnings.warn(f"magnitude {w.tolist()} is outside [0, 1]: extrapolating the expression",
                          stacklevel=3)
        return w

    def displacement(self, magnitude=1.0) -> np.ndarray:
        """(H, W, 3) displacement in the reference frame for a magnitude (or per-AU weights)."""
        w = self._weights(magnitude)
        out = w[0] * self.fields[0]
        for k in range(1, len(w)):
            out += w[k] * self.fields[k]
        return out

    def frame(self, magnitude=1.0) -> np.ndarray:
        """(H, W, 3) animated target in the reference frame (NaN where the grid is invalid)."""
        return self._neutral + self.displacement(magnitude)

    def frame_in_grid(self, magnitude=1.0) -> np.ndarray:
        """(H, W, 3) animated target in the frame of the target grid (the scan's frame,
        or the canonical frame the scan was resampled in, see :class:`FaceGrid`)."""
        return self._to_grid.apply(self.frame(magnitude))

    def frame_in_scan(self, magnitude=1.0) -> np.ndarray:
        """(H, W, 3) animated target in the target scan's own frame."""
        return self._to_scan.apply(self.frame(magnitude))

    def sweep(self, magnitudes: Sequence[float]) -> list[np.ndarray]:
        return [self.frame(m) for m in magnitudes]

    @classmethod
    def combine(cls, animations: Sequence["Animation"]) -> "Animation":
        """One animation from several on the same target (e.g. each AU modelled from its
        own expressive scan); their fields add, each keeping its own weight."""
        animations = list(animations)
        if not animations:
            raise ValueError("combine needs at least one animation")
        first = animations[0]
        for other in animations[1:]:
            if other.target.grid.points.shape != first.target.grid.points.shape or not np.array_equal(
                    other.target.grid.points, first.target.grid.points, equal_nan=True):
                raise ValueError("animations can only be combined on the same target grid")
        labels = [label for a in animations for label in a.labels]
        if len(set(labels)) != len(labels):
            raise ValueError(f"the animations repeat AU labels: {labels}")
        return cls(first.target, labels, np.concatenate([a.fields for a in animations]),
                   [c for a in animations for c in a.control_points],
                   [c for a in animations for c in a.moved_control_points])


def magnitude_weights(magnitude, labels: Sequence[str] | None = None) -> np.ndarray:
    """The weight of each AU field for a magnitude: a number, a sequence with one per
    label, or a mapping {label: weight} (unnamed labels 0).

    Each must be finite and within [-MAX_WEIGHT, MAX_WEIGHT]. Without ``labels`` only
    the values are checked (and returned in their order).
    """
    bound = {"low": -MAX_WEIGHT, "high": MAX_WEIGHT}
    if isinstance(magnitude, Mapping):
        if labels is not None:
            unknown = set(magnitude) - set(labels)
            if unknown:
                raise ValueError(f"magnitude: unknown AU label(s) {sorted(map(str, unknown))}; "
                                 f"this animation has {list(labels)}")
        checked = {key: as_real(value, f"magnitude[{key!r}]", **bound) for key, value in magnitude.items()}
        return np.array([checked.get(label, 0.0) for label in labels] if labels is not None
                        else list(checked.values()), dtype=np.float64)
    if np.ndim(magnitude) == 0:
        value = as_real(magnitude, "magnitude", **bound)
        return np.full(len(labels) if labels is not None else 1, value)
    values = [as_real(v, f"magnitude[{k}]", **bound) for k, v in enumerate(np.asarray(magnitude).reshape(-1))]
    if labels is not None and len(values) == 1:
        values = values * len(labels)
    if labels is not None and len(values) != len(labels):
        raise ValueError(f"magnitude has {len(values)} weights for the {len(labels)} fields {list(labels)}")
    return np.array(values, dtype=np.float64)


def _carried(model: ExpressionModel, target: NormalisedFace) -> np.ndarray:
    """The source's dense motion read at the target's valid vertices through the landmark
    correspondence (and averaged with its mirror image for a bilateral expression)."""
    options = model.options
    to_source = landmark_map(target.landmarks, model.source.landmarks, merge_mm=options.merge_landmarks_mm,
                             what="target -> source")

    def carry(points):
        return model.dense(to_source(points))

    if isinstance(model.dense, MirroredMotion):
        # a bilateral expression is symmetric on the target too: the mirror image of the
        # carried field evens out the correspondence's landmark noise
        carry = mirrored(carry, target)
    grid = target.grid
    points = grid.points.reshape(-1, 3)[grid.mask.ravel()]
    # point by point, so two halves on two threads give the same field (the second
    # core is free once the source is registered)
    half = len(points) // 2
    return np.concatenate(side_by_side(lambda: carry(points[:half]), lambda: carry(points[half:])))


def _spill(upper_weight: np.ndarray, carried: np.ndarray, fraction: float,
           valid: np.ndarray) -> np.ndarray:
    """Raise the upper region's weight to 1 where the carried motion continues the upper
    region's own motion below the boundary.

    The peak is the 95th percentile of the motion's size inside the upper region. A
    vertex below takes part when its motion is at least ``fraction`` of the peak (a
    smooth ramp up to twice that), at most the peak (ramping out by 1.5 times it: a
    continuation does not outgrow its source), and it lies in a connected patch of such
    vertices that reaches into the upper region.
    """
    size = np.linalg.norm(carried, axis=1)
    inside = upper_weight > 0.5
    peak = float(np.percentile(size[inside], 95)) if inside.any() else 0.0
    if not peak > 0:
        return upper_weight
    t = smoothstep(fraction * peak, 2.0 * fraction * peak, size) * smoothstep(1.5 * peak, peak, size)
    part = np.zeros(valid.shape, dtype=bool)
    part[valid] = t > 0
    labels = ndimage.label(part)[0][valid]
    # only patches that reach the upper region continue its motion
    joined = np.unique(labels[inside & (t > 0)])
    keep = np.isin(labels, joined[joined > 0])
    return np.maximum(upper_weight, np.where(keep, t, 0.0))


def animate(model: ExpressionModel, target: NormalisedFace) -> Animation:
    """Carry the modelled motion onto the target and precompute the fields.

    AUs of one region modelled from the same expressive scan share one field (labelled
    e.g. ``AU1+AU4``): that scan shows their combined motion, so a point two AUs share
    moves once. AUs modelled from different scans are combined with
    :meth:`Animation.combine`, where their fields add.
    """
    options = model.options
    published = options.method == "published"
    to_target = landmark_map(model.source.landmarks, target.landmarks, merge_mm=options.merge_landmarks_mm,
                             what="source -> target")
    lower_scale = mouth_width_ratio(model.source.landmarks, target.landmarks) if published else 1.0
    grid = target.grid
    flat, valid = grid.points.reshape(-1, 3), grid.mask.ravel()
    by_region: dict[str, list] = {}
    for motion in model.motions:
        by_region.setdefault(motion.activation.action_unit.region, []).append(motion)
    if not published:
        carried = _carried(model, target)
        upper = region_weight("upper", grid.points, target.landmarks, options.transition_mm).ravel()[valid]
        if "upper" in by_region and options.upper_spill > 0:
            # one scan's motion is shared by its regions: the lower region gives up what
            # the upper one keeps, so each point still takes the motion once
            upper = _spill(upper, carried, options.upper_spill, grid.mask)
    labels, fields, controls, moved = [], [], [], []
    for region, motions in by_region.items():
        control = target.snap(to_target(np.vstack([m.neutral for m in motions])), "vertex" if published else "surface")
        scale = lower_scale if region == "lower" else 1.0
        displacement = np.vstack([m.motion for m in motions]) * scale
        field_flat = np.zeros_like(flat)
        if published:
            region_w = region_weight(region, grid.points, target.landmarks, options.transition_mm)
            field_flat[valid] = control_point_warp(control, displacement)(flat[valid]) * region_w.ravel()[valid, None]
        else:
            # each point takes the scan's motion once, at the largest weight of the AUs
            # that cover its side
            share = np.max([m.activation.weight * side_weight(m.activation.side, grid.points, target.landmarks,
                                                              options.side_transition_mm) for m in motions], axis=0)
            region_flat = upper if region == "upper" else 1.0 - upper
            weight = region_flat * np.broadcast_to(share, grid.mask.shape).ravel()[valid]
            field_flat[valid] = carried * (scale * weight[:, None])
        labels.append("+".join(m.activation.label for m in motions))
        fields.append(field_flat.reshape(grid.points.shape))
        controls.append(control)
        moved.append(control + displacement)
    return Animation(target, labels, np.stack(fields), controls, moved)
