"""Expression transfer: model an AU on a source person, animate it on a target person.

The method (see DESIGN.md, method 1):

1. Every face is resampled onto a grid (:mod:`tpscore.face.grid`) and brought into the
   reference face's frame (:mod:`tpscore.face.normalise`).
2. The AU's control points, defined once on the reference face
   (:mod:`tpscore.action_units`), are mapped onto the neutral source with the landmark
   TPS (reference landmarks -> source landmarks) and snapped onto its surface.
3. *Modelling*: the landmark TPS from the source's neutral to its expressive landmarks
   carries them onto the expressive scan, where they are snapped again; their motion is
   v_i = P'_i - P_i.
4. *Animation*: the points are mapped from the neutral source to the neutral target
   (landmark TPS + snap) and moved by v_i * m * (s_t / s_s) in the lower face (s: mouth
   width) or v_i * m in the upper face; each region of the target is warped with the
   TPS from the points to their moved positions.

Because the TPS is linear in its targets, the warp for magnitude m is x + m d(x): each
AU's displacement field d is computed once, and a frame of an animation is a scaled
add of precomputed fields (:class:`Animation`).

:class:`TransferOptions` switches between the method as published
(:meth:`TransferOptions.thesis`) and the defaults, which measured better on the
fidelity benchmark (README): the source's expressive scan aligned rigidly onto its
neutral scan (:mod:`tpscore.alignment`) instead of normalised on its own landmarks, a
dense registration of the neutral onto the expressive surface (:mod:`tpscore.motion`)
instead of landmark-driven control points, and that displacement field carried to the
target through the landmark correspondence within the AU's region, with a smooth
region boundary. The control-point animation (TPS with anchors, or a Wendland warp)
remains available (``animation="control-points"``).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from .action_units import ActionUnit, ActionUnitLibrary, Activation, default_library
from .alignment import align_rigid, fit_mirror_symmetry
from .csrbf import CSRBF
from .face.landmarks import landmark_index, landmark_map
from .motion import (AdaptedMotion, DenseMotion, MirroredMotion, MotionOptions, adapt_motion,
                     curvature_image, register_surfaces)
from .face.normalise import FrameTransform, NormalisedFace, landmark_transform, normalise_face
from .face.grid import FaceGrid
from .rbf import TPS
from .face.regions import region_weight, side_weight, smoothstep
from .spatial import KDTree, MeshSurface
from .texture import track_texture

__all__ = [
    "TransferOptions",
    "place_control_points",
    "ControlPointMotion",
    "ExpressionModel",
    "align_expressive",
    "dense_motion",
    "model_expression",
    "Animation",
    "animate",
    "TransferResult",
    "transfer",
    "mouth_width",
]



@dataclass(frozen=True)
class TransferOptions:
    """Choices of the transfer pipeline. Defaults are the best measured variant.

    Attributes
    ----------
    normalisation : {"similarity", "affine"}
        Pose/size normalisation to the reference (see :mod:`tpscore.face.normalise`).
    alignment : {"rigid", "normalise"}
        How the source's expressive scan joins its neutral scan: ``"rigid"`` aligns it
        rigidly onto the neutral scan (landmarks, then ICP on the still region of the
        face; :mod:`tpscore.alignment`) and gives it the neutral scan's normalisation;
        ``"normalise"`` normalises it on its own landmarks (the method as published,
        which removes real motion of the landmarks it uses).
    motion : {"dense", "adapt", "landmarks"}
        How the source's motion is modelled: ``"dense"`` registers the neutral surface
        onto the expressive one (:mod:`tpscore.motion`: B-spline non-rigid ICP);
        ``"adapt"`` does it with the multilevel RBF/CSRBF template adaptation
        (:func:`tpscore.adapt`); ``"landmarks"`` maps the
        control points with the landmark TPS and snaps them onto the expressive scan
        (the method as published).
    animation : {"field", "control-points"}
        ``"field"`` carries the dense displacement field over to the target (each
        target vertex reads the source's motion at its corresponding point, through
        the landmark TPS target -> source) within the AU's region; ``"control-points"``
        moves the AU's control points and warps the region with an interpolant
        through them (the method as published). ``"field"`` needs a dense motion.
    warp : {"tps", "wendland"}
        Interpolant of the control-point warp: the thin-plate spline, or Wendland's
        compactly supported RBF with support ``wendland_support_mm`` (no motion beyond
        the support around the control points).
    snap : {"surface", "vertex"}
        Snap mapped control points to the closest point of the surface, or to the
        nearest grid vertex (the method as published).
    anchors : bool
        Add zero-motion anchor points to each AU's control-point warp: the region's
        landmarks and a lattice of surface points farther than ``anchor_distance_mm``
        from every control point of the AU. Without anchors the TPS's affine part may
        move the whole region.
    anchor_distance_mm, anchor_spacing_mm : float
        Clearance around the control points, and the lattice spacing of the anchors.
    wendland_support_mm : float
        Support radius of the Wendland warp.
    transition_mm : float
        Width of the smooth blend across the upper/lower boundary (0 = hard seam).
    side_transition_mm : float
        Width of the smooth blend across the midline for one-sided AUs (``12L``) in
        the field animation.
    upper_spill : float
        In the field animation, the carried motion of upper-face AUs is kept below the
        upper/lower boundary where it continues the motion above it: at least this
        fraction of the upper face's peak motion (95th percentile; a smooth ramp up
        to twice the fraction), not more than the peak (ramping out by 1.5 times it),
        and in one connected patch with the motion above the boundary; 0 = the
        boundary cuts it. The brow muscles also move the skin of the nasal root and
        bridge, which lies below the eye corners. Lower-face motion is not let over the
        boundary: the brows would then take the registration's stray motion of every
        smile.
    mirror_average : bool
        For expressions that move both sides of the face (every AU without ``L`` or
        ``R``, and emotions), average the dense field with its mirror image across the
        source's plane of symmetry (:class:`tpscore.motion.MirroredMotion`), and the
        carried field with its mirror image across the target's: a bilateral AU moves
        both sides alike, so the two sides' independent errors (landmark labels, holes,
        scanner noise) average out. One-sided AUs (``12L``) and landmark models are left
        as they are.
    still_motion_mm : float
        Source motion below about this size is treated as registration noise and
        faded out (a smooth ramp from half of it to one and a half times it); 0 keeps
        every motion.
    scale_lower_face : bool
        Scale lower-face motion by the ratio of the mouth widths, target / source (the
        method as published). Off by default: the faces are already brought to one size
        by the normalisation, and the ratio of two noisy landmark distances scales the
        whole motion by its error.
    landmark_smoothing : float
        Smoothing lambda of the landmark TPS maps (0 = interpolate the landmarks).
    merge_landmarks_mm : float
        Landmarks of one face closer than this are merged (their mean) before a
        landmark TPS: the inner-lip landmarks of a closed mouth nearly coincide and
        otherwise make the map fold.
    motion_options : MotionOptions
        Settings of the dense registration.
    """

    normalisation: str = "similarity"
    alignment: str = "rigid"
    motion: str = "dense"
    animation: str = "field"
    warp: str = "tps"
    snap: str = "surface"
    anchors: bool = True
    anchor_distance_mm: float = 18.0
    anchor_spacing_mm: float = 12.0
    wendland_support_mm: float = 40.0
    transition_mm: float = 10.0
    side_transition_mm: float = 10.0
    upper_spill: float = 0.1
    mirror_average: bool = True
    still_motion_mm: float = 0.0
    scale_lower_face: bool = False
    landmark_smoothing: float = 0.0
    merge_landmarks_mm: float = 3.0
    motion_options: MotionOptions = MotionOptions()

    def __post_init__(self):
        choices = {"normalisation": ("similarity", "affine"), "alignment": ("rigid", "normalise"),
                   "motion": ("dense", "adapt", "landmarks"), "animation": ("field", "control-points"),
                   "warp": ("tps", "wendland"), "snap": ("surface", "vertex")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        for name in ("anchor_distance_mm", "anchor_spacing_mm", "transition_mm",
                     "side_transition_mm", "still_motion_mm", "landmark_smoothing",
                     "merge_landmarks_mm", "upper_spill"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if not np.isfinite(self.wendland_support_mm) or self.wendland_support_mm <= 0:
            raise ValueError(f"wendland_support_mm must be finite and > 0, got {self.wendland_support_mm!r}")
        if self.anchors and self.anchor_spacing_mm <= 0:
            raise ValueError("anchor_spacing_mm must be > 0 when anchors are on")
        if self.animation == "field" and self.motion == "landmarks":
            raise ValueError("animation='field' needs a dense motion (a landmark model has no field)")
        if not isinstance(self.motion_options, MotionOptions):
            raise ValueError("motion_options must be a MotionOptions")

    @classmethod
    def thesis(cls) -> "TransferOptions":
        """The method exactly as published: each scan normalised on its own landmarks by
        the affine map, control points moved by the landmark TPS and nearest-vertex
        snapping, a TPS warp through the control points only, hard region seam, raw
        landmarks."""
        return cls(normalisation="affine", alignment="normalise", motion="landmarks",
                   animation="control-points", warp="tps", snap="vertex", anchors=False,
                   transition_mm=0.0, mirror_average=False, scale_lower_face=True,
                   landmark_smoothing=0.0, merge_landmarks_mm=0.0)

    @classmethod
    def landmark_model(cls) -> "TransferOptions":
        """The best variant without dense motion: rigid alignment, landmark-modelled
        control points, anchored TPS warp, smooth seam (lower-face motion scaled by
        the mouth widths, as the method does)."""
        return cls(motion="landmarks", animation="control-points", scale_lower_face=True)


# --------------------------------------------------------------------------- faces

def mouth_width(landmarks) -> float:
    """Distance between the mouth corners (mm), NaN when one is missing."""
    lm = np.asarray(landmarks, dtype=np.float64)
    a = lm[landmark_index("Left mouth corner")]
    b = lm[landmark_index("Right mouth corner")]
    return float(np.linalg.norm(a - b))


# --------------------------------------------------------------------------- landmark TPS

# --------------------------------------------------------------------------- control points

def place_control_points(action_unit: ActionUnit, reference: NormalisedFace) -> np.ndarray:
    """(k, 3) positions of an AU's control points on the reference surface.

    x, y come from the AU's definition; z is where a ray along -z meets the reference
    surface (the nearest vertex in x, y where the ray misses, e.g. over a hole).
    """
    xy = action_unit.positions_xy(reference.landmarks)
    top = np.nanmax(reference.grid.points[..., 2]) + 100.0
    origins = np.column_stack([xy, np.full(len(xy), top)])
    hits = reference.surface().intersect_rays(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    points = np.where(hits.hit[:, None], hits.points, np.nan)
    if not hits.hit.all():
        flat = reference.grid.points.reshape(-1, 3)[reference.grid.mask.ravel()]
        for i in np.flatnonzero(~hits.hit):
            points[i] = flat[np.argmin(((flat[:, :2] - xy[i]) ** 2).sum(axis=1))]
    return points


@dataclass(frozen=True)
class ControlPointMotion:
    """One AU's control points on the neutral source and their modelled motion."""

    activation: Activation
    names: tuple[str, ...]
    neutral: np.ndarray        # (k, 3) on the neutral source, reference frame
    motion: np.ndarray         # (k, 3) v_i, already weighted by side and AU weight


@dataclass
class ExpressionModel:
    """The modelled motion of one or more AUs on a source person.

    ``dense`` is the registered displacement field of the source (None for the
    landmark model; averaged with its mirror image for a bilateral expression);
    ``motions`` hold each AU's control points and their motion.
    """

    source: NormalisedFace
    motions: list[ControlPointMotion]
    options: TransferOptions
    dense: DenseMotion | AdaptedMotion | MirroredMotion | None = None

    @property
    def labels(self) -> list[str]:
        return [m.activation.label for m in self.motions]

    @property
    def texture(self):
        """The texture matches the dense motion used (:class:`tpscore.texture.TextureMatches`),
        or None when it came from the geometry alone."""
        dense = self.dense.motion if isinstance(self.dense, MirroredMotion) else self.dense
        return getattr(dense, "texture", None)


def align_expressive(neutral: NormalisedFace, neutral_grid: FaceGrid, expressive_grid: FaceGrid,
                     regions: Sequence[str] = ()) -> NormalisedFace:
    """The source's expressive scan in the reference frame, by rigid alignment onto the
    same person's neutral scan (:func:`tpscore.alignment.align_rigid`) followed by the
    neutral scan's normalisation.

    When every AU moves one region, the ICP relies on the other region (a smile does not
    move the forehead, a brow raise not the chin); otherwise on the whole face, robustly.
    """
    still = None
    if len(set(regions)) == 1:
        moving_region = next(iter(regions))
        still = region_weight("lower" if moving_region == "upper" else "upper",
                              expressive_grid.points, expressive_grid.landmarks, 10.0)
    alignment = align_rigid(expressive_grid, neutral_grid, fixed_surface=None, still_weight=still)
    transform = alignment.transform.then(neutral.transform)
    moved = replace(expressive_grid, points=transform.apply(expressive_grid.points),
                    landmarks=transform.apply(expressive_grid.landmarks))
    return NormalisedFace(moved, transform)


def dense_motion(source_neutral: NormalisedFace, source_expressive: NormalisedFace,
                 options: TransferOptions = TransferOptions()) -> DenseMotion | AdaptedMotion:
    """Register the neutral source onto its expressive scan (both in the reference frame)."""
    if options.motion == "adapt":
        return adapt_motion(source_neutral.grid, source_expressive.grid)
    motion_options = options.motion_options
    expressive_curvature = None
    if motion_options.shape_weight > 0:
        grid = source_expressive.grid
        # the surface's vertices are the grid's valid vertices in row-major order
        expressive_curvature = curvature_image(grid.points, grid.mask, motion_options.shape_sigma_mm
                                               ).reshape(-1)[np.flatnonzero(grid.mask.ravel())]
    texture = None
    if source_neutral.grid.image is not None or source_expressive.grid.image is not None:
        # with one image missing this warns that the geometry alone is used
        texture = track_texture(source_neutral.grid, source_expressive.grid)
    return register_surfaces(source_neutral.grid.points, source_neutral.grid.mask,
                             source_neutral.landmarks, source_expressive.surface(),
                             source_expressive.landmarks, motion_options,
                             expressive_curvature=expressive_curvature, texture=texture)


def _mirrored(field, face: NormalisedFace):
    """A displacement field on ``face`` averaged with its mirror image across the face's
    plane of symmetry, or unchanged (with a warning) when the plane cannot be fitted."""
    try:
        mirror = fit_mirror_symmetry(face.grid, fixed_surface=face.surface())
    except ValueError as error:
        warnings.warn(f"the field is not averaged with its mirror image: {error}", stacklevel=3)
        return field
    return MirroredMotion(field, mirror, face.grid.points[face.grid.mask])


def _fade_small(displacement: np.ndarray, still_mm: float) -> np.ndarray:
    """Fade displacements shorter than about still_mm out (smooth ramp from 0.5 to 1.5
    times it): registration noise where the skin does not move would otherwise leak."""
    if still_mm <= 0:
        return displacement
    length = np.linalg.norm(displacement, axis=-1, keepdims=True)
    return displacement * smoothstep(0.5 * still_mm, 1.5 * still_mm, length)


def model_expression(source_neutral: NormalisedFace, source_expressive: NormalisedFace,
                     activations: Sequence[Activation], reference: NormalisedFace,
                     options: TransferOptions = TransferOptions()) -> ExpressionModel:
    """Modelling: each AU's control points on the neutral source and their motion v_i,
    from the dense registration (``options.motion == "dense"``) or from the landmark TPS
    and a snap onto the expressive scan (the method as published)."""
    to_source = landmark_map(reference.landmarks, source_neutral.landmarks,
                             smoothing=options.landmark_smoothing,
                             merge_mm=options.merge_landmarks_mm, what="reference -> source")
    dense = None
    if options.motion != "landmarks":
        dense = dense_motion(source_neutral, source_expressive, options)
        if options.mirror_average and all(act.side is None for act in activations):
            dense = _mirrored(dense, source_neutral)
    else:
        to_expressive = landmark_map(source_neutral.landmarks, source_expressive.landmarks,
                                     smoothing=options.landmark_smoothing,
                                     merge_mm=options.merge_landmarks_mm,
                                     what="source neutral -> expressive")
    motions = []
    for act in activations:
        on_reference = place_control_points(act.action_unit, reference)
        neutral = source_neutral.snap(to_source(on_reference), options.snap)
        if dense is not None:
            motion = _fade_small(dense(neutral), options.still_motion_mm)
        else:
            motion = source_expressive.snap(to_expressive(neutral), options.snap) - neutral
        weights = act.action_unit.side_weights(act.side) * act.weight
        motions.append(ControlPointMotion(act, tuple(act.action_unit.names), neutral,
                                          motion * weights[:, None]))
    return ExpressionModel(source_neutral, motions, options, dense)


# --------------------------------------------------------------------------- animation

def _anchor_points(target: NormalisedFace, region_w: np.ndarray, control: np.ndarray,
                   options: TransferOptions) -> np.ndarray:
    """Zero-motion points of an AU's warp: the region's landmarks and a lattice of its
    valid vertices, all farther than anchor_distance_mm from every control point."""
    grid = target.grid
    flat = grid.points.reshape(-1, 3)
    inside = grid.mask.ravel() & (region_w.ravel() > 0.5)
    candidates = [target.landmarks[np.isfinite(target.landmarks).all(axis=1)]]
    # a lattice in x, y: the valid vertex nearest to each lattice node
    pts = flat[inside]
    if len(pts):
        step = options.anchor_spacing_mm
        cells = np.floor(pts[:, :2] / step).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        candidates.append(pts[first])
    cand = np.vstack(candidates)
    cand = cand[region_w.ravel()[target.nearest_vertex(cand)] > 0.5]
    if len(cand) == 0:
        return cand
    d = np.linalg.norm(cand[:, None, :] - control[None, :, :], axis=2).min(axis=1)
    return cand[d > options.anchor_distance_mm]


def _dedupe(points: np.ndarray, values: np.ndarray, tol_mm: float = 0.5):
    """Merge points closer than tol_mm (mean value): coincident TPS centres are singular."""
    keep_p, keep_v = [], []
    taken = np.zeros(len(points), bool)
    for i in range(len(points)):
        if taken[i]:
            continue
        close = np.linalg.norm(points - points[i], axis=1) < tol_mm
        close &= ~taken
        taken |= close
        keep_p.append(points[close].mean(axis=0))
        keep_v.append(values[close].mean(axis=0))
    return np.array(keep_p), np.array(keep_v)


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
        self._inverse = self.target.transform.inverse()

    def _weights(self, magnitude) -> np.ndarray:
        if isinstance(magnitude, Mapping):
            unknown = set(magnitude) - set(self.labels)
            if unknown:
                raise ValueError(f"unknown AU label(s) {sorted(unknown)}; this animation has {self.labels}")
            w = np.array([float(magnitude.get(label, 0.0)) for label in self.labels])
        else:
            w = np.broadcast_to(np.asarray(magnitude, dtype=np.float64), (len(self.labels),)).copy()
        if not np.isfinite(w).all():
            raise ValueError("magnitude must be finite")
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

    def frame_in_scan(self, magnitude=1.0) -> np.ndarray:
        """(H, W, 3) animated target in the target scan's own frame."""
        return self._inverse.apply(self.frame(magnitude))

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


def _lower_face_scale(model: ExpressionModel, target: NormalisedFace) -> float:
    """s_t / s_s, the ratio of the mouth widths (1 with a warning when one is missing)."""
    scale_s, scale_t = mouth_width(model.source.landmarks), mouth_width(target.landmarks)
    if np.isfinite(scale_s * scale_t) and scale_s > 0:
        return scale_t / scale_s
    warnings.warn("a mouth corner is missing: lower-face motion is not scaled by mouth width",
                  stacklevel=3)
    return 1.0


def animate(model: ExpressionModel, target: NormalisedFace) -> Animation:
    """Animation: carry the modelled motion onto the target and precompute the fields.

    With ``options.animation == "field"`` each target vertex reads the source's dense
    displacement at its corresponding point (landmark TPS target -> source), weighted by
    the region (and side) of the AUs; otherwise each region is warped through the AUs'
    moved control points (TPS with anchors, or Wendland).

    AUs of one region modelled from the same expressive scan share one warp (and one
    field, labelled e.g. ``AU1+AU4``): that scan shows their combined motion, so a
    control point two AUs share (the inner brow of AU1 and AU4), or the field under
    both, carries that motion once, not once per AU. AUs modelled from different scans
    are combined with :meth:`Animation.combine`, where their fields add.
    """
    options = model.options
    to_target = landmark_map(model.source.landmarks, target.landmarks,
                             smoothing=options.landmark_smoothing,
                             merge_mm=options.merge_landmarks_mm, what="source -> target")
    lower_scale = _lower_face_scale(model, target) if options.scale_lower_face else 1.0
    grid = target.grid
    flat = grid.points.reshape(-1, 3)
    valid = grid.mask.ravel()
    carried = None
    if options.animation == "field":
        to_source = landmark_map(target.landmarks, model.source.landmarks,
                                 smoothing=options.landmark_smoothing,
                                 merge_mm=options.merge_landmarks_mm, what="target -> source")

        def carry(points):
            return model.dense(to_source(points))

        if isinstance(model.dense, MirroredMotion):
            # a bilateral expression is symmetric on the target too: the mirror image
            # of the carried field evens out the correspondence's landmark noise
            carry = _mirrored(carry, target)
        carried = _fade_small(carry(flat[valid]), options.still_motion_mm)
    by_region: dict[str, list[ControlPointMotion]] = {}
    for motion in model.motions:
        by_region.setdefault(motion.activation.action_unit.region, []).append(motion)
    if carried is not None:
        upper_flat = region_weight("upper", grid.points, target.landmarks,
                                   options.transition_mm).ravel()[valid]
        if "upper" in by_region and options.upper_spill > 0:
            # one scan's motion is shared by its regions: the lower region gives up
            # what the upper one keeps, so each point still takes the motion once
            upper_flat = _spill(upper_flat, carried, options.upper_spill, grid.mask)
    labels, fields, controls, moved = [], [], [], []
    for region, motions in by_region.items():
        neutral = np.vstack([m.neutral for m in motions])
        control = target.snap(to_target(neutral), options.snap)
        scale = lower_scale if region == "lower" else 1.0
        displacement = np.vstack([m.motion for m in motions]) * scale
        field_flat = np.zeros_like(flat)
        if carried is not None:
            # the scan shows the AUs' combined motion: each point takes it once, at the
            # largest weight of the AUs that cover its side
            share = np.max([m.activation.weight * side_weight(m.activation.side, grid.points,
                                                              target.landmarks,
                                                              options.side_transition_mm)
                            for m in motions], axis=0)
            region_flat = upper_flat if region == "upper" else 1.0 - upper_flat
            weight = region_flat * np.broadcast_to(share, grid.mask.shape).ravel()[valid]
            field_flat[valid] = carried * (scale * weight[:, None])
        else:
            region_w = region_weight(region, grid.points, target.landmarks, options.transition_mm)
            warp = _control_point_warp(target, control, displacement, region_w, options)
            field_flat[valid] = warp(flat[valid]) * region_w.ravel()[valid, None]
        labels.append("+".join(m.activation.label for m in motions))
        fields.append(field_flat.reshape(grid.points.shape))
        controls.append(control)
        moved.append(control + displacement)
    return Animation(target, labels, np.stack(fields), controls, moved)


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


def _control_point_warp(target: NormalisedFace, control: np.ndarray, displacement: np.ndarray,
                        region_w: np.ndarray, options: TransferOptions):
    """The displacement field (a callable on (m, 3) points) of a region warp through the
    control points: TPS or Wendland, with zero-motion anchors when asked."""
    centres, values = _dedupe(control, displacement)
    if options.anchors:
        anchors = _anchor_points(target, region_w, centres, options)
        centres = np.vstack([centres, anchors])
        values = np.vstack([values, np.zeros_like(anchors)])
        centres, values = _dedupe(centres, values)
    if options.warp == "wendland":
        return CSRBF(centres, values, options.wendland_support_mm)
    return TPS(centres, centres + values).displacement


# --------------------------------------------------------------------------- one call

@dataclass
class TransferResult:
    """The target wearing the expression, in the reference frame and in its scan frame."""

    animation: Animation
    magnitude: float | Mapping[str, float]
    model: ExpressionModel
    timings: dict = field(default_factory=dict)  # seconds per stage

    @property
    def target(self) -> NormalisedFace:
        return self.animation.target

    @property
    def vertices_normalised(self) -> np.ndarray:
        return self.animation.frame(self.magnitude)

    @property
    def neutral_normalised(self) -> np.ndarray:
        return self.animation.frame(0.0)

    @property
    def vertices(self) -> np.ndarray:
        """(H, W, 3) animated target in the target scan's own frame."""
        return self.animation.frame_in_scan(self.magnitude)

    @property
    def neutral(self) -> np.ndarray:
        """(H, W, 3) the target grid it started from, in the target scan's own frame."""
        return self.animation.frame_in_scan(0.0)

    @property
    def mask(self) -> np.ndarray:
        return self.target.grid.mask

    def to_npz_dict(self) -> dict:
        """Arrays for ``--out result.npz`` (scan-frame arrays first, as scorers expect)."""
        return dict(
            vertices=self.vertices, neutral=self.neutral, mask=self.mask,
            vertices_normalised=self.vertices_normalised,
            neutral_normalised=self.neutral_normalised,
            scan_to_normalised=self.target.transform.matrix,
            uv=self.target.grid.uv, landmarks=self.target.transform.apply_inverse(self.target.landmarks),
            action_units=np.array(self.animation.labels),
        )


def transfer(source_neutral: FaceGrid, source_expressive: FaceGrid, target: FaceGrid, action_units,
             magnitude=1.0, *, reference=None, library: ActionUnitLibrary | None = None,
             options: TransferOptions = TransferOptions()) -> TransferResult:
    """Put the source's expression on the target.

    Parameters
    ----------
    source_neutral, source_expressive, target : FaceGrid
        Resampled faces with landmarks (see :func:`tpscore.face.grid.load_scan`).
    action_units : str, mapping or sequence
        What to transfer: ``"12"``, ``"12L"``, ``"1,4,15"``, ``"sadness"``,
        ``{"12": 0.5}`` (see :meth:`ActionUnitLibrary.parse`).
    magnitude : float or mapping
        m in [0, 1] (values outside warn), or a weight per AU label.
    reference : AverageFace, optional
        The reference face (default: the one shipped with tpscore).
    library : ActionUnitLibrary, optional
        Default: the shipped library.
    options : TransferOptions
        Pipeline choices; ``TransferOptions.thesis()`` is the method as published.
    """
    from .face.average_face import load_average_face

    clock = time.perf_counter()
    timings = {}

    def lap(stage):
        nonlocal clock
        now = time.perf_counter()
        timings[stage] = now - clock
        clock = now

    library = library or default_library()
    reference = reference or load_average_face()
    activations = library.parse(action_units)
    ref_face = reference.as_normalised_face()
    lap("setup")
    neutral = normalise_face(source_neutral, ref_face.landmarks, options.normalisation)
    target_face = normalise_face(target, ref_face.landmarks, options.normalisation)
    lap("normalise")
    if options.alignment == "rigid":
        expressive = align_expressive(neutral, source_neutral, source_expressive,
                                      [a.action_unit.region for a in activations])
    else:
        expressive = normalise_face(source_expressive, ref_face.landmarks, options.normalisation)
    lap("align")
    model = model_expression(neutral, expressive, activations, ref_face, options)
    lap("model")
    if model.texture is not None:
        # the texture tracking ran inside the modelling; report it as its own stage
        timings["texture"] = model.texture.seconds
        timings["model"] -= model.texture.seconds
    animation = animate(model, target_face)
    lap("animate")
    return TransferResult(animation, magnitude, model, timings)
