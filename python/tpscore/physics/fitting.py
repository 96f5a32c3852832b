"""Carrying the physical structure through a template fit.

The head-adaptation method fits the template's skin to a scan (:func:`tpscore.adapt`)
and brings everything under the skin along, so that the fitted head can be animated
at once:

- linear muscles are stored by triangle and barycentric coordinates, on the skin
  (insertions) and on the skull (attachments), so they survive the fit unchanged;
- the skull is moved by the same fitted map as the skin (:meth:`AdaptResult.deform`,
  the multilevel RBF/CSRBF field the fit built);
- a sphincter's epicentre is moved by that map, its axes turn with the map's local
  linear part, and each semi-axis is scaled by how the distance between the
  landmarks around it changed (the mouth corners for the horizontal axis of the
  orbicularis oris, the lip middles for the vertical one);
- the jaw's pivot is moved by the map, and its axis is the fitted face's own x axis
  (from the eye corners); regions and the mandible mask are per vertex and stay.

:func:`carry_head` does that for any map from the template's frame to the fitted
head's; :func:`fit_head` runs the fit first; :func:`deform_from_vertices` makes a
map from a template already fitted by other means (vertex for vertex).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from .._validation import as_points
from ..adaptation import AdaptOptions, AdaptResult, adapt
from ..face.landmarks import landmark_index
from ..face.normalise import face_frame
from ..geometry import spread_vertices
from ..rbf import RBF
from .head import Head, load_template
from .muscles import SkinSphincterMuscle

__all__ = ["carry_head", "fit_head", "deform_from_vertices"]

# Step (mm) of the central differences that give the fitted map's local linear part.
_JACOBIAN_STEP_MM = 2.0
# Vertices spread over the template that define the map of deform_from_vertices.
_MAP_CENTRES = 400


def deform_from_vertices(template: Head, vertices) -> Callable[[np.ndarray], np.ndarray]:
    """A smooth map from the template's frame to a head fitted to it vertex for vertex.

    A biharmonic RBF (phi(r) = r, affine part) through a spread subset of the vertex
    pairs (about 400, plus the landmark vertices), lightly smoothed, so points off the
    surface (the skull, the jaw's pivot) move with their surroundings.
    """
    vertices = as_points(vertices, "vertices")
    if vertices.shape != template.vertices.shape:
        raise ValueError(f"vertices must have the template's shape {template.vertices.shape}, got {vertices.shape}")
    width = float(np.ptp(template.vertices, axis=0).max())
    spacing = width / np.sqrt(_MAP_CENTRES)
    chosen = spread_vertices(template.vertices, spacing)
    chosen = np.union1d(chosen, template.landmark_vertices[template.landmark_vertices >= 0])
    field = RBF(template.vertices[chosen], vertices[chosen], "biharmonic", smoothing=1e-3)
    return field


def carry_head(template: Head, deform, vertices=None) -> Head:
    """The template's physical structure on a fitted head.

    Parameters
    ----------
    template : Head
    deform : AdaptResult or callable
        The fit: an :class:`tpscore.AdaptResult` of ``tpscore.adapt`` with the template's
        mesh, or a callable taking (m, 3) template-frame points to the fitted frame.
    vertices : (n, 3) array_like, optional
        The fitted skin, vertex for vertex (default: ``deform.vertices`` of an
        AdaptResult, or ``deform(template.vertices)``).

    Returns
    -------
    Head
        The fitted head, in the fitted frame, with the template's triangles, regions,
        mandible and muscles.
    """
    if isinstance(deform, AdaptResult):
        if vertices is None:
            vertices = deform.vertices
        mapping = deform.deform
    elif callable(deform):
        mapping = deform
    else:
        raise ValueError(f"deform must be an AdaptResult or a callable, got {type(deform).__name__}")
    if vertices is None:
        vertices = mapping(template.vertices)
    vertices = as_points(vertices, "vertices")
    if vertices.shape != template.vertices.shape:
        raise ValueError(f"vertices must have the template's shape {template.vertices.shape}, got {vertices.shape}")

    skull = np.asarray(mapping(template.skull_vertices), dtype=np.float64)
    if len(skull) == len(vertices):
        # Each skull vertex lies under the skin vertex of its column. The fit's final
        # snap moves the skin beyond the smooth map by up to a few millimetres; where it
        # moves the skin toward the skull, the skull follows along the column by as
        # much, so the tissue keeps the depth the smooth map gave it (a snap that
        # crushed the chin's tissue to 2 mm made the skin chatter); where it moves the
        # skin out, the tissue thickens. Only the column's part of the snap is followed:
        # its sideways part differs from one vertex to the next, and following it
        # folded skull triangles over, behind which tissue was caught.
        smooth = np.asarray(mapping(template.vertices), dtype=np.float64)
        column = smooth - skull
        length = np.linalg.norm(column, axis=1)
        outward = np.divide(column, length[:, None], out=np.zeros_like(column), where=length[:, None] > 0)
        inward = np.maximum(-np.einsum("ij,ij->i", vertices - smooth, outward), 0.0)
        skull = skull - inward[:, None] * outward
    pivot = np.asarray(mapping(template.jaw_pivot[None]), dtype=np.float64)[0]
    fitted_landmarks = np.full((len(template.landmark_vertices), 3), np.nan)
    present = template.landmark_vertices >= 0
    fitted_landmarks[present] = vertices[template.landmark_vertices[present]]
    try:
        axis = face_frame(fitted_landmarks).axes[0]
    except ValueError:
        # without the landmarks a face frame needs, the template's axis, mapped
        ends = mapping(np.stack([template.jaw_pivot - 10 * template.jaw_axis, template.jaw_pivot + 10 * template.jaw_axis]))
        axis = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    template_landmarks = template.landmarks

    muscles = []
    for muscle in template.muscles:
        if isinstance(muscle, SkinSphincterMuscle):
            muscles.append(_carry_sphincter(muscle, mapping, template_landmarks, fitted_landmarks))
        else:
            muscles.append(muscle)
    if not np.isfinite(skull).all() or not np.isfinite(pivot).all():
        raise ValueError("the fitted map gives non-finite points under the skin")
    return replace(template, vertices=vertices, skull_vertices=skull, jaw_pivot=pivot, jaw_axis=axis,
                   muscles=tuple(muscles))


def _carry_sphincter(muscle: SkinSphincterMuscle, mapping, template_landmarks, fitted_landmarks) -> SkinSphincterMuscle:
    centre = muscle.epicentre
    points = np.stack([centre] + [centre + s * _JACOBIAN_STEP_MM * a / np.linalg.norm(a)
                                  for a in muscle.axes for s in (-1.0, 1.0)])
    moved = np.asarray(mapping(points), dtype=np.float64)
    new_axes = []
    for k, axis in enumerate(muscle.axes):
        direction = moved[2 + 2 * k] - moved[1 + 2 * k]
        direction /= np.linalg.norm(direction)
        length = np.linalg.norm(axis)
        if muscle.axis_landmarks:
            a, b = (landmark_index(name) for name in muscle.axis_landmarks[k])
            before = np.linalg.norm(template_landmarks[a] - template_landmarks[b])
            after = np.linalg.norm(fitted_landmarks[a] - fitted_landmarks[b])
            if np.isfinite(after) and before > 0:
                length *= after / before
        new_axes.append(length * direction)
    return replace(muscle, epicentre=moved[0], axes=np.stack(new_axes))


def fit_head(scan, scan_landmarks, template: Head | None = None, *,
             adapt_options: AdaptOptions | None = None) -> tuple:
    """Fit the template head to a scan and carry its physical structure along.

    Parameters
    ----------
    scan : mesh, FaceGrid, GridMesh or BntScan
        What :func:`tpscore.adapt` accepts.
    scan_landmarks : (22, 3) array_like
        The scan's landmarks (NaN where missing).
    template : Head, optional
        Default: the shipped template (:func:`load_template`).
    adapt_options : AdaptOptions, optional
        Settings of :func:`tpscore.adapt` (default: its own).

    Returns
    -------
    head : Head
        The fitted head, in the scan's frame.
    adaptation : AdaptResult
        The fit.
    """
    template = load_template() if template is None else template
    if not isinstance(template, Head):
        raise ValueError(f"template must be a tpscore.physics.Head, got {type(template).__name__}")
    if adapt_options is not None and not isinstance(adapt_options, AdaptOptions):
        raise ValueError(f"adapt_options must be a tpscore.AdaptOptions, got {type(adapt_options).__name__}")
    result = _adapt_skin(template, scan, scan_landmarks, adapt_options or AdaptOptions())
    return carry_head(template, result), result


def _adapt_skin(template: Head, scan, scan_landmarks, adapt_options: AdaptOptions) -> AdaptResult:
    # The one place the physical skin calls the template adaptation (docs/design.md,
    # method 2, of which the skin is the last stage).
    return adapt((template.vertices, template.faces), scan, template.landmark_vertices, scan_landmarks,
                 options=adapt_options)
