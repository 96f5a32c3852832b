"""Cloning expressions between faces: handle displacements are carried from one face's
frame into another's and scaled by the ratio of their facial units (the distance
between the inner eye corners), so that a smile moves a small face as far, relative to
its size, as it moved the large one."""
from __future__ import annotations

import copy

import numpy as np

from ..face.normalise import FaceFrame
from .control_points import transfer_control_points
from .energy import ElasticOptions
from .fitting import ExpressionSet

__all__ = ["map_displacements", "clone_expressions"]


def map_displacements(displacements, source_frame: FaceFrame, target_frame: FaceFrame) -> np.ndarray:
    """Displacements (..., 3) of the source face, rotated from its frame into
    ``target_frame`` and scaled by the ratio of facial units (target / source)."""
    array = np.asarray(displacements, dtype=np.float64)
    ratio = target_frame.facial_unit / source_frame.facial_unit
    return (array @ source_frame.axes.T) * ratio @ target_frame.axes


def clone_expressions(source, target, expressions: ExpressionSet, *, target_landmarks=None,
                      options: ElasticOptions | None = None):
    """The target face with ``expressions`` of ``source`` cloned onto it.

    ``source`` is an ElasticFace with landmarks; ``target`` a face of the same class
    (used as it is, in a shallow copy) or a (vertices, faces) pair with
    ``target_landmarks`` (built with ``options`` and the source's control points
    carried over by the landmark TPS). See :meth:`tpscore.elastic.ElasticFace.clone_to`.
    """
    if source.frame is None:
        raise ValueError("cloning needs this face's landmarks (ElasticFace(..., landmarks=...))")
    # Faces are built as the source's own class, so that this module needs no import of
    # the class that calls it.
    face_class = type(source)
    if isinstance(target, face_class):
        if options is not None or target_landmarks is not None:
            raise ValueError("target is already an ElasticFace; target_landmarks and options do not apply")
        if target.frame is None:
            raise ValueError("the target ElasticFace has no landmarks; cloning needs its frame and facial unit")
        _check_corresponding(source, target)
        target_face = copy.copy(target)
    else:
        try:
            target_vertices, target_faces = target
        except (TypeError, ValueError):
            raise ValueError("target must be an ElasticFace or a (vertices, faces) pair") from None
        if target_landmarks is None:
            raise ValueError("target_landmarks are needed to clone onto a (vertices, faces) target")
        names = source.control_point_names
        handles = transfer_control_points(source.control_point_positions, source.landmarks, target_vertices,
                                          target_faces, target_landmarks, names=names)
        target_face = face_class(target_vertices, target_faces, handles, landmarks=target_landmarks, names=names,
                                 options=options or ElasticOptions())
    mapped = map_displacements(expressions.parameters, source.frame, target_face.frame)
    target_face.expressions = ExpressionSet(names=expressions.names, parameters=mapped)
    return target_face


def _check_corresponding(source, target) -> None:
    """Raise ValueError unless two faces' control points correspond one to one: as many
    on each, and the same names in the same order where both were placed from
    definitions."""
    source_names, target_names = source.control_point_names, target.control_point_names
    named = source.control_points is not None and target.control_points is not None
    if len(target_names) != len(source_names) or (named and target_names != source_names):
        raise ValueError(
            f"the target has {len(target_names)} control points {target_names[:3]}...; the source has "
            f"{len(source_names)} {source_names[:3]}...: they must correspond one to one")
