"""Modelling: how an expression moves the source person's face.

The default registers the source's neutral surface onto its expressive scan densely
(:mod:`tpscore.expression.registration`), after aligning the expressive scan rigidly onto
the neutral one (:mod:`tpscore.expression.alignment`): normalising it on its own landmarks
would remove real motion (AU17 moves the chin, a landmark of the normalisation). Where
the expressive scan shows an opening (the mouth, an eye) open by another amount than
the neutral one, the motion is cut there (:mod:`tpscore.expression.cut_motion`). Each
AU's control points, placed once on the reference face
(:mod:`tpscore.expression.action_units`), are carried onto the neutral source by the
landmark TPS, and their motion read from the field. The method as published models
their motion from the landmark TPS alone (:mod:`tpscore.expression.published`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from .._threads import helper_thread
from ..face.grid import FaceGrid
from ..face.normalise import NormalisedFace, landmark_transform
from ..face.openings import find_openings
from ..face.regions import HALVES, region_weight
from .action_units import ActionUnit, ActionUnitLibrary, Activation, WHOLE_FACE
from .alignment import ANCHOR_PARTS, Realigned, align_rigid, fit_mirror_symmetry, residual_rigid_motion, stable_weight
from .cut_motion import CutMotion, eye_windows, moved_openings, register_cut
from .mirror import Coverage, MirroredMotion
from .registration import DenseMotion, MotionOptions, RegistrationGrid, prepare_registration, register_surfaces
from .texture import TextureOptions, TextureWarning, track_texture

__all__ = ["ControlPointMotion", "ExpressionModel", "PersonMismatchWarning", "PersonMismatchError", "place_control_points", "Extended",
           "align_expressive", "still_weight", "dense_motion", "mirror_plane", "mirrored", "coverage",
           "registration_grid", "openings", "activation_weight", "needs_realignment", "half_of", "realigned",
           "SAME_PERSON_MEDIAN_MM"]


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
    """One AU's control points on the neutral source and their modelled motion (empty
    for a whole expression, which has none)."""

    activation: Activation
    names: tuple[str, ...]
    neutral: np.ndarray        # (k, 3) on the neutral source, reference frame
    motion: np.ndarray         # (k, 3) v_i, already weighted by side and AU weight


@dataclass
class ExpressionModel:
    """The modelled motion of one or more AUs (or a whole expression) on a source person.

    ``dense`` is the registered displacement field of the source (cut at its moved
    openings, averaged with its mirror image for a bilateral expression; None for the
    method as published); ``motions`` hold each AU's control points and their motion;
    ``reference`` is the reference face the AUs' regions are placed on.
    """

    source: NormalisedFace
    motions: list[ControlPointMotion]
    reference: NormalisedFace
    library: ActionUnitLibrary
    dense: object = None

    @property
    def labels(self) -> list[str]:
        return [m.activation.label for m in self.motions]

    @property
    def texture(self):
        """The texture matches the dense motion used
        (:class:`tpscore.expression.texture.TextureMatches`), or None when it came from
        the geometry alone."""
        dense = self.dense
        while dense is not None and not isinstance(dense, (DenseMotion, CutMotion)):  # unwrap
            dense = getattr(dense, "motion", None)
        return getattr(dense, "texture", None)


class PersonMismatchWarning(UserWarning):
    """The source's expressive scan does not fit its neutral scan rigidly: it may be a
    scan of another person, and the modelled motion would then be their difference."""


class PersonMismatchError(ValueError):
    """The source's expressive scan fits its neutral scan so badly that it is another
    person's. A caller sure of the scans passes ``allow_other_person=True``
    (``TransferOptions(allow_other_person=True)``)."""


#: Median distance (mm) of the expressive scan's still part from the neutral surface
#: after the rigid alignment, above which :func:`align_expressive` warns. Measured on
#: the generated development scans (0.15 mm depth noise): one person's still part (the
#: upper face of a smile, the lower face of a brow raise) lies 0.07 to 0.09 mm off,
#: another person's 0.44 mm and more; with no still part (an emotion that moves the
#: whole face), one person's face lies 0.5 to 0.85 mm off, another's 1.7 mm and more.
SAME_PERSON_MEDIAN_MM = {"still": 0.35, "whole": 1.3}
#: Above these the scans are refused as two people's (:class:`PersonMismatchError`):
#: two and a half times the farthest one person's scans lay on the development scans
#: (still parts 0.07-0.28 mm, against another person's 0.40-3.7 mm; whole faces 0.85);
#: between the two limits they are warned about.
OTHER_PERSON_MEDIAN_MM = {"still": 0.7, "whole": 2.2}


def activation_weight(activation: Activation, points, landmarks, library: ActionUnitLibrary,
                      reference_landmarks, transition_mm: float, to_reference=None) -> np.ndarray:
    """Weight in [0, 1] of an activation's region at points (..., 3) of a face with these
    landmarks: a half of the face (by its eye line, with a seam ``transition_mm`` wide),
    the whole face (1), or a named region, placed on the reference face's landmarks
    after ``to_reference`` (a map of points into the reference frame; default: the
    similarity over the landmarks)."""
    region = activation.action_unit.region
    p = np.asarray(points, dtype=np.float64)
    if region in HALVES:
        return region_weight(region, p, landmarks, transition_mm)
    if region == WHOLE_FACE:
        return np.where(np.isfinite(p).all(axis=-1), 1.0, 0.0)
    if to_reference is None:
        to_reference = landmark_transform(landmarks, reference_landmarks).apply
    mapped = to_reference(p.reshape(-1, 3)).reshape(p.shape)
    return library.region(region).weight(mapped, reference_landmarks)


#: Width (mm) of the seam between the upper and the lower face where an AU of one half
#: has the other half aligned as still.
STILL_SEAM_MM = 10.0


def half_of(action_unit: ActionUnit, library: ActionUnitLibrary, reference_landmarks) -> str | None:
    """The half of the face an AU acts in: its region if that is a half, the half that
    holds its named region on the reference face (the chin's region lies in the lower
    face, :meth:`tpscore.face.regions.Region.half`), else None (a region across the eye
    line, or the whole face)."""
    region = action_unit.region
    if region in HALVES:
        return region
    if region == WHOLE_FACE:
        return None
    return library.region(region).half(reference_landmarks, STILL_SEAM_MM)


def still_weight(grid: FaceGrid, activations: Sequence[Activation], library: ActionUnitLibrary,
                 reference_landmarks):
    """Where an expression should leave the expressive scan still, as a weight per grid
    vertex (None: no part can be said to be still, align the whole face robustly):

    - AUs of one half of the face (its named regions included): the other half (a
      10 mm seam);
    - otherwise (AUs of regions across the eye line, whose skin pulls on much of the
      face around them, or a whole expression): the parts no expression moves much
      (:func:`stable_weight`); the motion is then realigned (:func:`realigned`).
    """
    halves = {half_of(act.action_unit, library, reference_landmarks) for act in activations}
    if None not in halves:
        if len(halves) != 1:
            return None
        other = "lower" if halves == {"upper"} else "upper"
        return region_weight(other, grid.points, grid.landmarks, STILL_SEAM_MM)
    return stable_weight(grid.points, grid.landmarks)


def needs_realignment(activations: Sequence[Activation], library: ActionUnitLibrary, reference_landmarks) -> bool:
    """Whether the alignment relied on the stable parts alone (see :func:`still_weight`),
    so that the registered motion still holds a rigid part to take out."""
    return any(half_of(act.action_unit, library, reference_landmarks) is None for act in activations)


def align_expressive(neutral: NormalisedFace, neutral_grid: FaceGrid, expressive_grid: FaceGrid,
                     still=None, *, allow_other_person: bool = False) -> NormalisedFace:
    """The source's expressive scan in the reference frame, by rigid alignment onto the
    same person's neutral scan followed by the neutral scan's normalisation.

    ``still`` (a weight per vertex of the expressive grid, :func:`still_weight`) says
    which part the alignment relies on; None: the whole face, robustly. Scans that fit
    as two people's do are refused (:class:`PersonMismatchError`) unless
    ``allow_other_person``, and warned about where they may be.
    """
    # the neutral scan's tree, kept with the face: its surface in the reference frame is
    # then this tree moved, not a second build
    alignment = align_rigid(expressive_grid, neutral_grid, fixed_surface=neutral.scan_frame_surface(neutral_grid),
                            still_weight=still)
    kind = "whole" if still is None else "still"
    limit, refused = SAME_PERSON_MEDIAN_MM[kind], OTHER_PERSON_MEDIAN_MM[kind]
    distance = alignment.median_distance_mm
    if distance > limit:
        part = "the face" if still is None else "its still part"
        found = (f"the expressive scan does not fit the neutral scan rigidly: {part} lies a median "
                 f"{distance:.2f} mm off it after the alignment (two scans of one person: under {limit:g} mm)")
        # the other cause of a still part that does not fit: a scan that moves more than
        # the request (brows asked of a surprise, whose jaw drops)
        more = ("" if still is None else
                " Or does the expressive scan move more than the requested AUs, its still part too (a whole "
                "expression)? Then carry all of it: 'all' or the emotion's name.")
        if distance > refused and not allow_other_person:
            raise PersonMismatchError(
                f"{found}, beyond the {refused:g} mm of two people's scans: they are not one person's. If they "
                f"are, pass allow_other_person=True (TransferOptions(allow_other_person=True)).{more}")
        warnings.warn(f"{found}. Are they scans of the same person?{more}", PersonMismatchWarning, stacklevel=3)
    transform = alignment.transform.then(neutral.transform)
    moved = replace(expressive_grid, points=transform.apply(expressive_grid.points),
                    landmarks=transform.apply(expressive_grid.landmarks))
    return NormalisedFace(moved, transform)


def openings(face: NormalisedFace):
    """The face's openings (:func:`tpscore.face.openings.find_openings`), found once per face."""
    return face.derived("openings", find_openings)


def dense_motion(source_neutral: NormalisedFace, source_expressive: NormalisedFace, motion: MotionOptions,
                 texture_options: TextureOptions):
    """Register the neutral source onto its expressive scan (both in the reference
    frame), with their texture when either has a colour image (warning and falling back
    to the geometry when the other has none or the images cannot be used): a
    :class:`DenseMotion`, or a :class:`CutMotion` where the expressive scan shows an
    opening open by another amount."""
    texture = None
    detected = source_neutral.grid.landmarks_detected or source_expressive.grid.landmarks_detected
    with helper_thread("tpscore-surface") as second_thread:
        # the expressive surface is built while the texture is tracked
        surface = second_thread.submit(source_expressive.surface)
        if source_neutral.grid.image is not None or source_expressive.grid.image is not None:
            # the neutral scan's view, kept with the face by an earlier transfer, if any
            seen = ("texture view", texture_options)
            # the eyes' windows are asked for once the whole face is flowed: the
            # openings are found meanwhile (on the transfer's second thread); a
            # registration that refines its matches has the eyes matched then instead,
            # with the expressive image warped back by the motion found so far
            refines = 0 < motion.texture_refine_after < motion.iterations
            texture = track_texture(source_neutral.grid, source_expressive.grid, texture_options,
                                    lambda: eye_windows(openings(source_neutral).values(), source_neutral.grid),
                                    neutral_view=source_neutral.derived_so_far(seen), fine_regions_later=refines)
            if texture is not None:
                source_neutral.derived(seen, lambda face: texture.neutral_view)
        else:
            warnings.warn("neither source scan has a colour image: the motion comes from the geometry "
                          "alone, which follows the skin less closely (give each scan its image, a "
                          "textured mesh or vertex colours)", TextureWarning, stacklevel=2)
        grid = source_neutral.grid
        prepared = registration_grid(source_neutral, motion)

        def register(weight=None, landmarks=None, pairs=None):
            field = register_surfaces(grid.points, grid.mask,
                                      source_neutral.landmarks if landmarks is None else landmarks,
                                      surface.result(), source_expressive.landmarks, motion, weight=weight,
                                      texture=texture, prepared=prepared, pairs=pairs,
                                      landmarks_detected=detected)
            return Extended(field, source_neutral)

        moved = moved_openings(openings(source_neutral), source_expressive.grid)
        if not moved:
            return register()
        return register_cut(source_neutral, source_expressive, moved, register, texture, motion.texture_weight)


def realigned(field, face: NormalisedFace):
    """The field with the rigid motion left in it taken out
    (:func:`tpscore.expression.alignment.residual_rigid_motion` over the face's valid
    vertices, weighted by :func:`stable_weight`, the bridge's and the temples' points
    counting twice in the choice of the still part): the alignment of a whole expression
    has no part it knows to be still."""
    points = face.grid.points[face.grid.mask]
    rigid = residual_rigid_motion(points, field(points), stable_weight(points, face.landmarks),
                                  anchor=stable_weight(points, face.landmarks, ANCHOR_PARTS, elsewhere=0.0))
    if isinstance(field, CutMotion):
        return field.split(lambda side: Realigned(side, rigid))
    return Realigned(field, rigid)


class Extended:
    """A field registered on a face, extended beyond the face's data by its value at the
    nearest vertex: past the scan's edge (a target's chin reaching lower than the
    source's scan) a lattice field only extrapolates, and a dropped jaw would lift the
    chin's lowest part instead of dropping it. Within the face's coverage
    (:class:`Coverage`) it is the field itself, beyond twice its reach the nearest
    vertex's value, blended in between."""

    def __init__(self, motion, face: NormalisedFace):
        self.motion = motion
        self.face = face
        self._coverage = coverage(face)

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = self.motion(p)
        finite = np.isfinite(p).all(axis=1)
        covered = np.ones(len(p))
        covered[finite] = self._coverage(p[finite])
        beyond = finite & (covered < 1.0)
        if beyond.any():
            nearest = self.face.grid.points.reshape(-1, 3)[self.face.nearest_vertex(p[beyond])]
            w = covered[beyond, None]
            out[beyond] = w * out[beyond] + (1.0 - w) * self.motion(nearest)
        return out


def registration_grid(face: NormalisedFace, options: MotionOptions) -> RegistrationGrid:
    """:func:`prepare_registration` of the face's grid with these options, made once per face."""
    return face.derived(("registration", options),
                        lambda f: prepare_registration(f.grid.points, f.grid.mask, options))


def mirror_plane(face: NormalisedFace):
    """The face's mirror map (:func:`fit_mirror_symmetry` on its own surface), fitted
    once per face; a ValueError when the plane cannot be fitted."""
    return face.derived("mirror", lambda f: fit_mirror_symmetry(f.grid, fixed_surface=f.surface()))


def mirrored(field, face: NormalisedFace):
    """A displacement field on ``face`` averaged with its mirror image across the face's
    plane of symmetry, or unchanged (with a warning) when the plane cannot be fitted. A
    cut field is averaged side by side (a point and its mirror image lie on the same
    side of the mouth and of the eyes)."""
    if isinstance(field, CutMotion):
        return field.split(lambda side: mirrored(side, face))
    try:
        mirror = mirror_plane(face)
    except ValueError as error:
        warnings.warn(f"the field is not averaged with its mirror image: {error}", stacklevel=3)
        return field
    return MirroredMotion(field, mirror, coverage(face))


def coverage(face: NormalisedFace) -> Coverage:
    """How well the face's vertices cover points of its x-y plane (the weights of a
    mirror average), made once per face."""
    return face.derived("coverage", lambda f: Coverage(f.grid.points[f.grid.mask]))
