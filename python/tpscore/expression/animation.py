"""Animation: the modelled motion carried onto the target, as one displacement field per
AU (or whole expression) that a frame scales and adds.

The default reads, at each target vertex, the source's registered motion at the
corresponding point (the landmark TPS target -> source, or the adapted map:
:mod:`tpscore.expression.correspondence`), weighted by the AU's region and
side; a bilateral expression's carried field is averaged with its mirror image across
the target's own plane too. Where the source's motion is cut at an opening, a target
vertex takes the side of the target's own opening it lies on, and the target's mesh
opens there. The method as published warps each region through the moved control
points instead (:mod:`tpscore.expression.published`). Both are linear in the
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
from ..face.openings import opening_cut, opening_sides
from ..face.regions import height_above_boundary, region_weight, side_weight, smoothstep
from .action_units import MAX_WEIGHT, WHOLE_FACE
from .correspondence import adapted_correspondence, landmark_correspondence
from .cut_motion import CutMotion, opening_pairs
from .mirror import MirroredMotion
from .modelling import ExpressionModel, activation_weight, coverage, mirrored, openings

__all__ = ["Animation", "carry", "magnitude_weights", "field_labels"]

@dataclass
class Animation:
    """Precomputed displacement fields of a transfer on the target grid.

    ``frame(m)`` is the target's neutral grid plus m times the summed AU fields (or a
    weight per AU); it costs one scaled add per AU. ``cut`` is, where the motion is cut
    at an opening, the side of the cut each target vertex lies on (+1 above, -1 below, 0
    away from it; :func:`tpscore.face.openings.opening_cut`), None without a cut:
    :meth:`triangles` leaves out the triangles that straddle it.
    """

    target: NormalisedFace
    labels: list[str]
    fields: np.ndarray            # (n_aus, H, W, 3) displacement at magnitude 1, reference frame
    control_points: list[np.ndarray]
    moved_control_points: list[np.ndarray]
    cut: np.ndarray | None = None

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

    def triangles(self) -> np.ndarray:
        """(m, 3) the target grid's triangles (flat grid indices, see
        :meth:`tpscore.FaceGrid.triangles`) without those that straddle a cut opening:
        an opened mouth is an opening in the mesh."""
        triangles = self.target.grid.triangles()
        if self.cut is None:
            return triangles
        side = self.cut.reshape(-1)[triangles]
        torn = (side.min(axis=1) < 0) & (side.max(axis=1) > 0)
        return triangles[~torn]

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
        cuts = [a.cut for a in animations if a.cut is not None]
        return cls(first.target, labels, np.concatenate([a.fields for a in animations]),
                   [c for a in animations for c in a.control_points],
                   [c for a in animations for c in a.moved_control_points],
                   cuts[0] if cuts else None)


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


def by_region(activations) -> dict[str, list]:
    """Activations (or anything with ``.activation``) grouped by their region, in order:
    AUs of one region modelled from one scan share one field."""
    groups: dict[str, list] = {}
    for item in activations:
        activation = getattr(item, "activation", item)
        groups.setdefault(activation.action_unit.region, []).append(item)
    return groups


def field_labels(activations) -> list[str]:
    """The labels of a transfer's fields (``AU1+AU4``, ``AU12``, ``happiness``), known
    before the transfer runs (a magnitude given per field names them)."""
    return ["+".join(getattr(a, "activation", a).label for a in group) for group in by_region(activations).values()]


def _carried(model: ExpressionModel, target: NormalisedFace, to_source):
    """The source's dense motion read at the target's valid vertices through the map
    ``to_source`` (:func:`_target_to_source`; averaged with its mirror image for a
    bilateral expression); with the share of the upper side each takes where the motion
    is cut (None otherwise)."""
    dense = model.dense
    sides = (dense.upper, dense.lower) if isinstance(dense, CutMotion) else (dense,)

    def carried_side(field):
        def carry(points):
            return field(to_source(points))

        if isinstance(field, MirroredMotion):
            # a bilateral expression is symmetric on the target too: the mirror image of
            # the carried field evens out the correspondence's landmark noise
            carry = mirrored(carry, target)
        return carry

    grid = target.grid
    points = grid.points.reshape(-1, 3)[grid.mask.ravel()]
    # point by point, so two halves on two threads give the same field (the second
    # core is free once the source is registered)
    half = len(points) // 2
    values = []
    for field in sides:
        carry = carried_side(field)
        values.append(np.concatenate(side_by_side(lambda: carry(points[:half]), lambda: carry(points[half:]))))
    if len(values) == 1:
        return values[0], None
    names = {opening.name for opening in dense.openings}
    own = [opening for name, opening in openings(target).items() if name in names]
    share = opening_sides(own, points)
    cut = np.zeros(grid.mask.shape, dtype=np.int8)
    cut[grid.mask] = opening_cut(own, points)
    upper = values[0]
    for opening in own:
        if opening.name in dense.closure:
            upper = _closing(opening, dense.closure[opening.name], points, upper)
    return share[:, None] * upper + (1.0 - share[:, None]) * values[1], cut


#: The factor an eye's carried upper-lid motion is scaled by stays within these bounds.
CLOSING_SCALE = (0.5, 2.0)


def _closing(opening, closure: np.ndarray, points: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """The upper side's motion at an eye of the target, scaled so that the target's own
    upper lid travels the share of its own opening that the source's did (``closure``
    per knot): eyes differ in height, and a lid carried in millimetres would stop short
    of the lower lid or cross it. The factor is measured at the rim (the vertices that
    border the eye's hole) per knot, and fades with the eye's window."""
    top, bottom = opening.top, opening.bottom
    known = np.isfinite(top) & np.isfinite(bottom) & np.isfinite(closure)
    if known.sum() < 3:
        return motion
    a, b = opening.coordinates(points)
    moved_b = opening.coordinates(points + motion)[1]
    knot = np.rint(np.clip(a, 0.0, 1.0) * (len(top) - 1)).astype(np.int64)
    near_rim = (b > top[knot]) & (b < top[knot] + 1.5) & known[knot] & (a > 0.05) & (a < 0.95)
    factor = np.full(len(top), np.nan)
    for k in np.flatnonzero(known):
        here = near_rim & (knot == k)
        travel = -np.median(moved_b[here] - b[here]) if here.any() else np.nan
        wanted = closure[k] * (top[k] - bottom[k])
        if np.isfinite(travel) and abs(travel) > 0.5 and wanted * travel > 0:
            factor[k] = np.clip(wanted / travel, *CLOSING_SCALE)
    found = np.isfinite(factor)
    if found.sum() < 3:
        return motion
    scale = np.interp(a, opening.knots[found], factor[found])
    side, split = opening.sides(points)
    weight = np.where(side > 0, split, 0.0)
    return motion * (1.0 + (scale - 1.0) * weight)[:, None]


#: Smoothing of the target -> source landmark TPS when either face's landmarks were
#: detected (``FaceGrid.landmarks_detected``): the map then follows the detections'
#: overall shape rather than each one's few millimetres of error (development subjects,
#: AUs 1, 2, 4, 17: mean ratio 0.248 through them, 0.241 at 5000, 0.244 at 20000).
DETECTED_MAP_SMOOTHING = 5000.0


def _target_to_source(model: ExpressionModel, target: NormalisedFace, merge_mm: float, correspondence: str):
    """The map of target points onto the source (:mod:`tpscore.expression.correspondence`).
    The landmark TPS goes through the openings' edges too where the motion is cut at
    them (:func:`tpscore.expression.cut_motion.opening_pairs`), and near its pairs
    rather than through them for detected landmarks (:data:`DETECTED_MAP_SMOOTHING`).
    The adapted map needs no edge pairs: it follows the two surfaces' lips and lids."""
    if correspondence == "adapted":
        return adapted_correspondence(target, model.source)
    extra = None
    if isinstance(model.dense, CutMotion):
        names = [opening.name for opening in model.dense.openings]
        extra = opening_pairs(openings(target), target, openings(model.source), model.source, names)
    detected = target.grid.landmarks_detected or model.source.grid.landmarks_detected
    smoothing = DETECTED_MAP_SMOOTHING if detected else 0.0
    return landmark_correspondence(target, model.source, extra, merge_mm, smoothing)


#: How far below the upper/lower boundary (mm) the upper face's motion may continue
#: (the brows' muscles move the nasal root and bridge, not the mouth: a scan of a whole
#: expression moves the jaw too, and its motion reaches the brows' through the cheeks).
SPILL_REACH_MM = 30.0


def _spill(upper_weight: np.ndarray, carried: np.ndarray, fraction: float,
           valid: np.ndarray, below_mm: np.ndarray | None = None) -> np.ndarray:
    """Raise the upper region's weight to 1 where the carried motion continues the upper
    region's own motion below the boundary, at most :data:`SPILL_REACH_MM` below it
    (``below_mm``: each vertex's distance below the boundary).

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
    if below_mm is not None:
        t = t * (below_mm < SPILL_REACH_MM)
    part = np.zeros(valid.shape, dtype=bool)
    part[valid] = t > 0
    labels = ndimage.label(part)[0][valid]
    # only patches that reach the upper region continue its motion
    joined = np.unique(labels[inside & (t > 0)])
    keep = np.isin(labels, joined[joined > 0])
    return np.maximum(upper_weight, np.where(keep, t, 0.0))


def _below_boundary(points, landmarks) -> np.ndarray:
    """Each point's distance (mm) below the upper/lower boundary (negative above it)."""
    return -height_above_boundary(points, landmarks)


def _covered(model: ExpressionModel, target: NormalisedFace, to_source) -> np.ndarray:
    """How well the source's scan covers where each valid target vertex reads its motion
    through the map ``to_source`` (or that point's mirror image, for a mirrored field): a
    whole expression fades where the source's scan has no data."""
    grid = target.grid
    at = to_source(grid.points.reshape(-1, 3)[grid.mask.ravel()])
    covers = coverage(model.source)
    weight = covers(at)
    dense = model.dense.upper if isinstance(model.dense, CutMotion) else model.dense
    if isinstance(dense, MirroredMotion):
        weight = np.maximum(weight, covers(dense.mirror.apply(at)))
    return weight


def carry(model: ExpressionModel, target: NormalisedFace, *, transition_mm: float, side_transition_mm: float,
          upper_spill: float, merge_landmarks_mm: float, correspondence: str = "landmarks") -> Animation:
    """Carry the source's dense motion onto the target and precompute the fields.

    AUs of one region modelled from the same expressive scan share one field (labelled
    e.g. ``AU1+AU4``): that scan shows their combined motion, so a point two AUs share
    moves once. Regions that overlap share a point's motion (their weights there are
    scaled to add up to at most 1). AUs modelled from different scans are combined
    with :meth:`Animation.combine`, where their fields add.
    """
    grid = target.grid
    flat, valid = grid.points.reshape(-1, 3), grid.mask.ravel()
    groups = by_region(model.motions)
    # one map for the motion and its coverage: the landmark map's TPS fit and the
    # openings' edge pairs are made once
    to_source = _target_to_source(model, target, merge_landmarks_mm, correspondence)
    carried, cut = _carried(model, target, to_source)
    upper = region_weight("upper", grid.points, target.landmarks, transition_mm).ravel()[valid]
    if "upper" in groups and upper_spill > 0:
        # one scan's motion is shared by its regions: the lower region gives up what
        # the upper one keeps, so each point still takes the motion once
        upper = _spill(upper, carried, upper_spill, grid.mask, _below_boundary(flat[valid], target.landmarks))
    to_reference = None
    region_weights = {}
    for region, motions in groups.items():
        if region == "upper":
            region_weights[region] = upper
        elif region == "lower":
            region_weights[region] = 1.0 - upper
        elif region == WHOLE_FACE:
            region_weights[region] = _covered(model, target, to_source)
        else:
            if to_reference is None:
                to_reference = landmark_map(target.landmarks, model.reference.landmarks, merge_mm=merge_landmarks_mm,
                                            what="target -> reference")
            region_weights[region] = activation_weight(motions[0].activation, flat[valid], target.landmarks,
                                                       model.library, model.reference.landmarks, transition_mm,
                                                       to_reference)
    total = np.sum(list(region_weights.values()), axis=0)
    # (the two halves add up to 1 but for rounding: they are left as they are)
    overlap = np.where(total > 1.0 + 1e-9, 1.0 / np.maximum(total, 1e-12), 1.0)
    labels, fields = [], []
    for region, motions in groups.items():
        # each point takes the scan's motion once, at the largest weight of the AUs that
        # cover its side
        sides = np.max([m.activation.weight * side_weight(m.activation.side, grid.points, target.landmarks,
                                                          side_transition_mm) for m in motions], axis=0)
        weight = region_weights[region] * overlap * np.broadcast_to(sides, grid.mask.shape).ravel()[valid]
        field_flat = np.zeros_like(flat)
        field_flat[valid] = carried * weight[:, None]
        labels.append("+".join(m.activation.label for m in motions))
        fields.append(field_flat.reshape(grid.points.shape))
    controls = [target.snap(_to_target(model, target, merge_landmarks_mm)(np.vstack([m.neutral for m in motions])),
                            "surface") if any(len(m.neutral) for m in motions) else np.zeros((0, 3))
                for motions in groups.values()]
    moved = [c + np.vstack([m.motion for m in motions]) if len(c) else c
             for c, motions in zip(controls, groups.values())]
    return Animation(target, labels, np.stack(fields), controls, moved, cut)


def _to_target(model: ExpressionModel, target: NormalisedFace, merge_mm: float):
    return landmark_map(model.source.landmarks, target.landmarks, merge_mm=merge_mm, what="source -> target")
