"""Modelling: how an expression moves the source person's face.

The default registers the source's neutral surface onto its expressive scan densely
(:mod:`tpscore.expression.registration`), after aligning the expressive scan rigidly onto
the neutral one (:mod:`tpscore.expression.alignment`): normalising it on its own landmarks
would remove real motion (AU17 moves the chin, a landmark of the normalisation). Each
AU's control points, placed once on the reference face
(:mod:`tpscore.expression.action_units`), are carried onto the neutral source by the
landmark TPS, and their motion read from the field. The method as published models
their motion from the landmark TPS alone (:mod:`tpscore.expression.published`).
"""
from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from ..face.grid import FaceGrid
from ..face.landmarks import landmark_map
from ..face.normalise import NormalisedFace
from ..face.regions import region_weight
from .action_units import ActionUnit, Activation
from .alignment import align_rigid, fit_mirror_symmetry
from .mirror import Coverage, MirroredMotion
from .options import TransferOptions
from .registration import DenseMotion, MotionOptions, RegistrationGrid, prepare_registration, register_surfaces
from .texture import track_texture

__all__ = ["ControlPointMotion", "ExpressionModel", "PersonMismatchWarning", "place_control_points",
           "align_expressive", "dense_motion", "model_expression", "mirror_plane", "mirrored", "uses_mirror",
           "registration_grid", "SAME_PERSON_MEDIAN_MM"]


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

    ``dense`` is the registered displacement field of the source (averaged with its
    mirror image for a bilateral expression; None for the method as published);
    ``motions`` hold each AU's control points and their motion.
    """

    source: NormalisedFace
    motions: list[ControlPointMotion]
    options: TransferOptions
    dense: DenseMotion | MirroredMotion | None = None

    @property
    def labels(self) -> list[str]:
        return [m.activation.label for m in self.motions]

    @property
    def texture(self):
        """The texture matches the dense motion used
        (:class:`tpscore.expression.texture.TextureMatches`), or None when it came from
        the geometry alone."""
        dense = self.dense.motion if isinstance(self.dense, MirroredMotion) else self.dense
        return getattr(dense, "texture", None)


class PersonMismatchWarning(UserWarning):
    """The source's expressive scan does not fit its neutral scan rigidly: it may be a
    scan of another person, and the modelled motion would then be their difference."""


#: Median distance (mm) of the expressive scan's still part from the neutral surface
#: after the rigid alignment, above which :func:`align_expressive` warns. Measured on
#: the generated development scans (0.15 mm depth noise): one person's still part (the
#: upper face of a smile, the lower face of a brow raise) lies 0.07 to 0.09 mm off,
#: another person's 0.44 mm and more; with no still part (an emotion that moves the
#: whole face), one person's face lies 0.5 to 0.85 mm off, another's 1.7 mm and more.
SAME_PERSON_MEDIAN_MM = {"still": 0.35, "whole": 1.3}


def align_expressive(neutral: NormalisedFace, neutral_grid: FaceGrid, expressive_grid: FaceGrid,
                     regions: Sequence[str] = ()) -> NormalisedFace:
    """The source's expressive scan in the reference frame, by rigid alignment onto the
    same person's neutral scan followed by the neutral scan's normalisation.

    When every AU moves one region, the alignment relies on the other region (a smile
    does not move the forehead, a brow raise not the chin); otherwise on the whole face,
    robustly.
    """
    still = None
    if len(set(regions)) == 1:
        moving_region = next(iter(regions))
        still = region_weight("lower" if moving_region == "upper" else "upper",
                              expressive_grid.points, expressive_grid.landmarks, 10.0)
    alignment = align_rigid(expressive_grid, neutral_grid, fixed_surface=None, still_weight=still)
    limit = SAME_PERSON_MEDIAN_MM["whole" if still is None else "still"]
    if alignment.median_distance_mm > limit:
        part = "the face" if still is None else f"the {'lower' if moving_region == 'upper' else 'upper'} face"
        warnings.warn(
            f"the expressive scan does not fit the neutral scan rigidly: {part} lies a median "
            f"{alignment.median_distance_mm:.2f} mm off it after the alignment (two scans of one person: "
            f"under {limit:g} mm). Are they scans of the same person?", PersonMismatchWarning, stacklevel=3)
    transform = alignment.transform.then(neutral.transform)
    moved = replace(expressive_grid, points=transform.apply(expressive_grid.points),
                    landmarks=transform.apply(expressive_grid.landmarks))
    return NormalisedFace(moved, transform)


def dense_motion(source_neutral: NormalisedFace, source_expressive: NormalisedFace,
                 options: TransferOptions = TransferOptions(),
                 while_registering: Callable[[], object] | None = None) -> DenseMotion:
    """Register the neutral source onto its expressive scan (both in the reference
    frame), with their texture when either has a colour image (warning and falling back
    to the geometry when the other has none or the images cannot be used).

    ``while_registering`` is called as the registration starts: a caller starts there
    the work it wants on another thread while the registration runs (it uses one core,
    where the texture tracking before it uses two)."""
    texture = None
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tpscore-surface") as second_thread:
        # the expressive surface is built while the texture is tracked
        surface = second_thread.submit(source_expressive.surface)
        if source_neutral.grid.image is not None or source_expressive.grid.image is not None:
            texture = track_texture(source_neutral.grid, source_expressive.grid, options.texture)
        if while_registering is not None:
            while_registering()
        return register_surfaces(source_neutral.grid.points, source_neutral.grid.mask,
                                 source_neutral.landmarks, surface.result(), source_expressive.landmarks,
                                 options.motion, texture=texture,
                                 prepared=registration_grid(source_neutral, options.motion))


def registration_grid(face: NormalisedFace, options: MotionOptions) -> RegistrationGrid:
    """:func:`prepare_registration` of the face's grid with these options, made once per face."""
    return face.derived(("registration", options),
                        lambda f: prepare_registration(f.grid.points, f.grid.mask, options))


def uses_mirror(activations: Sequence[Activation], options: TransferOptions) -> bool:
    """Whether the modelled motion is averaged with its mirror image: on by default for
    an expression of both sides (no AU with a side of its own)."""
    return options.method != "published" and options.mirror_average \
        and all(act.side is None for act in activations)


def mirror_plane(face: NormalisedFace):
    """The face's mirror map (:func:`fit_mirror_symmetry` on its own surface), fitted
    once per face; a ValueError when the plane cannot be fitted."""
    return face.derived("mirror", lambda f: fit_mirror_symmetry(f.grid, fixed_surface=f.surface()))


def mirrored(field, face: NormalisedFace):
    """A displacement field on ``face`` averaged with its mirror image across the face's
    plane of symmetry, or unchanged (with a warning) when the plane cannot be fitted."""
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


def model_expression(source_neutral: NormalisedFace, source_expressive: NormalisedFace,
                     activations: Sequence[Activation], reference: NormalisedFace,
                     options: TransferOptions = TransferOptions(),
                     while_registering: Callable[[], object] | None = None) -> ExpressionModel:
    """Each AU's control points on the neutral source and their motion: from the dense
    registration (the default), or from the landmark TPS and a snap onto the expressive
    scan (the method as published). ``while_registering``: see :func:`dense_motion`."""
    published = options.method == "published"
    snap = "vertex" if published else "surface"
    to_source = landmark_map(reference.landmarks, source_neutral.landmarks, merge_mm=options.merge_landmarks_mm,
                             what="reference -> source")
    dense = None
    if published:
        to_expressive = landmark_map(source_neutral.landmarks, source_expressive.landmarks,
                                     merge_mm=options.merge_landmarks_mm, what="source neutral -> expressive")
    else:
        dense = dense_motion(source_neutral, source_expressive, options, while_registering)
        if uses_mirror(activations, options):
            dense = mirrored(dense, source_neutral)
    motions = []
    for act in activations:
        neutral = source_neutral.snap(to_source(place_control_points(act.action_unit, reference)), snap)
        if published:
            motion = source_expressive.snap(to_expressive(neutral), snap) - neutral
        else:
            motion = dense(neutral)
        weights = act.action_unit.side_weights(act.side) * act.weight
        motions.append(ControlPointMotion(act, tuple(act.action_unit.names), neutral, motion * weights[:, None]))
    return ExpressionModel(source_neutral, motions, options, dense)
