"""The elastic model's facial control points: their definitions relative to the
landmarks, their placement on a mesh, and their transfer from one face onto another.

A control point is an :class:`~tpscore.face.landmarks.AnchoredPoint`: its (x, y) in the
face frame (:func:`~tpscore.face.normalise.face_frame`) is a weighted mean of named
landmarks plus an offset scaled by the facial unit, and its depth comes from the
surface. The shipped set (``tpscore/data/elastic_control_points.json``) has 47 points.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .._validation import as_faces, as_points, as_positive
from ..face.landmarks import AnchoredPoint, anchor_point, as_landmarks, landmark_map
from ..face.normalise import FaceFrame, face_frame
from ..spatial import MeshSurface, RayHits

__all__ = [
    "REGIONS",
    "REFERENCE_FACIAL_UNIT_MM",
    "ElasticControlPoint",
    "load_control_points",
    "default_control_points",
    "place_control_points",
    "transfer_control_points",
]

#: The parts of the face a control point can belong to.
REGIONS = ("eyebrows", "eyelids", "nose", "cheeks", "lips", "jaw")

#: The facial unit (inner eye corner distance, mm) of the ICT generic face, for which
#: the shipped offsets were written; offsets scale by a face's unit over this one.
REFERENCE_FACIAL_UNIT_MM = 36.88


@dataclass(frozen=True, kw_only=True)
class ElasticControlPoint(AnchoredPoint):
    """A named facial control point of the elastic model, in one region of the face.

    Its (x, y) in the face frame is the weighted mean of the landmarks named in ``at``
    plus ``offset_mm`` (scaled by facial unit / reference facial unit); its depth comes
    from the surface.

    Attributes
    ----------
    region : {"eyebrows", "eyelids", "nose", "cheeks", "lips", "jaw"}
        The part of the face it belongs to (keyword-only); the other fields are those
        of :class:`~tpscore.face.landmarks.AnchoredPoint`.
    """

    region: str

    def __post_init__(self):
        super().__post_init__()
        if self.region not in REGIONS:
            raise ValueError(f"control point {self.name!r}: region must be one of {REGIONS}, got {self.region!r}")


def read_data_file(path, default: str, what: str, key: str) -> dict:
    """A JSON object with a list under ``key``, from ``path`` or the shipped ``default``
    (a path inside the package); raises ValueError naming the file and ``what`` it
    should hold."""
    source = str(path) if path is not None else f"the default {what}"
    try:
        if path is None:
            text = resources.files("tpscore").joinpath(default).read_text(encoding="utf-8")
        else:
            text = Path(path).read_text(encoding="utf-8")
        data = json.loads(text)
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read {what}: {exc}") from None
    if not isinstance(data, Mapping) or key not in data:
        raise ValueError(f"{source}: expected an object with a {key!r} list")
    return data


def read_control_point_file(path=None) -> tuple[tuple[ElasticControlPoint, ...], float]:
    """The control points of a file and the facial unit their offsets were written for."""
    data = read_data_file(path, "data/elastic_control_points.json", "control points", "control_points")
    source = str(path) if path is not None else "the default control points"
    try:
        points = tuple(
            ElasticControlPoint(name=p["name"], region=p["region"], side=p["side"], at=p["at"],
                                offset_mm=tuple(p.get("offset_mm", (0.0, 0.0))), note=p.get("note", ""))
            for p in data["control_points"])
    except KeyError as exc:
        raise ValueError(f"{source}: a control point lacks the field {exc.args[0]!r}") from None
    names = [p.name for p in points]
    if len(set(names)) != len(names):
        raise ValueError(f"{source}: control point names are not unique")
    reference_unit = as_positive(data.get("reference_facial_unit_mm", REFERENCE_FACIAL_UNIT_MM),
                                 "reference_facial_unit_mm")
    return points, reference_unit


def load_control_points(path=None) -> tuple[ElasticControlPoint, ...]:
    """Control point definitions from a JSON file (default: the shipped set of 47).

    The file's ``reference_facial_unit_mm`` is the facial unit its offsets were written
    for; pass it to :func:`place_control_points` with the points.
    """
    return read_control_point_file(path)[0]


def default_control_points() -> tuple[ElasticControlPoint, ...]:
    """The shipped 47 facial control points (eyebrows, eyelids, nose, cheeks, lips, jaw)."""
    return load_control_points()


def anchored_in_frame(frame: FaceFrame, landmarks: np.ndarray, at: Mapping[str, float], offset_mm,
                      scale: float, owner: str) -> np.ndarray:
    """Frame coordinates (3,) of a place anchored to the landmarks: the weighted mean of
    the landmarks in ``at``, moved in the frame's (x, y) by ``offset_mm`` times ``scale``."""
    local = frame.to_frame(anchor_point(landmarks, at, owner)[None])[0]
    local[:2] += np.asarray(offset_mm, dtype=np.float64) * scale
    return local


def cast_onto_front(surface: MeshSurface, frame: FaceFrame, xy) -> RayHits:
    """Where rays along the frame's -z, from in front of the whole face at each (x, y)
    of ``xy`` (m, 2), first meet the surface: a scanner's view of the face."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    height = frame.to_frame(surface.vertices)[:, 2].max() + 10.0 * frame.facial_unit
    origins = frame.to_world(np.column_stack([xy, np.full(len(xy), height)]))
    directions = np.repeat(-frame.axes[2][None], len(xy), axis=0)
    return surface.intersect_rays(origins, directions)


def _snap_to_corner(faces: np.ndarray, triangles: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
    """The corner of each hit triangle with the largest barycentric weight.

    Snapping to the hit triangle's own corner (not the nearest vertex in space) keeps a
    point on the sheet it landed on where two sheets lie close (the lips).
    """
    return faces[triangles, np.argmax(barycentric, axis=1)].astype(np.int64)


def check_distinct(indices: np.ndarray, names: Sequence[str]) -> None:
    """Raise ValueError naming the control points that share a vertex."""
    unique, counts = np.unique(indices, return_counts=True)
    if (counts > 1).any():
        vertex = unique[counts > 1][0]
        clash = [names[i] for i in np.flatnonzero(indices == vertex)]
        raise ValueError(
            f"control points {', '.join(map(repr, clash))} land on the same vertex {vertex}; "
            "the mesh is too coarse for them or their definitions coincide")


def place_control_points(vertices, faces, landmarks, control_points=None, *,
                         reference_facial_unit_mm: float | None = None) -> np.ndarray:
    """Vertex indices of control points on a face mesh.

    Each point's (x, y) in the face frame is the weighted mean of its landmarks plus its
    offset scaled by the facial unit; a ray from in front of the face along the frame's
    -z finds the front-most surface there, and the point snaps to the nearest corner of
    the hit triangle. Where the ray passes through a hole (eye or mouth opening), the
    closest surface point to the anchor (landmark mean plus offset, at the anchor's
    depth) is used instead.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Mesh vertices (mm).
    faces : array_like of int, shape (m, 3)
        Triangles.
    landmarks : array_like, shape (22, 3)
        The 22 Bosphorus landmarks (mm); NaN for missing ones not used by any point.
    control_points : sequence of ElasticControlPoint, optional
        Definitions; default :func:`default_control_points`.
    reference_facial_unit_mm : float, optional
        The facial unit the offsets were written for (default: the value in the shipped
        file for the shipped points, else :data:`REFERENCE_FACIAL_UNIT_MM`).

    Returns
    -------
    ndarray of int64, shape (k,)
        One vertex index per control point.

    Raises
    ------
    ValueError
        If two control points land on the same vertex, or a needed landmark is missing.
    """
    vertices = as_points(vertices, "vertices", allow_empty=False)
    faces = as_faces(faces, len(vertices))
    landmarks = as_landmarks(landmarks)
    if control_points is None:
        control_points, default_unit = read_control_point_file()
    else:
        control_points, default_unit = tuple(control_points), REFERENCE_FACIAL_UNIT_MM
    unit = default_unit if reference_facial_unit_mm is None else as_positive(
        reference_facial_unit_mm, "reference_facial_unit_mm")
    frame = face_frame(landmarks)
    scale = frame.facial_unit / unit
    anchors = np.array([anchored_in_frame(frame, landmarks, p.at, p.offset_mm, scale, f"control point {p.name!r}")
                        for p in control_points])
    surface = MeshSurface(vertices, faces)
    hits = cast_onto_front(surface, frame, anchors[:, :2])
    indices = np.empty(len(anchors), dtype=np.int64)
    if hits.hit.any():
        indices[hits.hit] = _snap_to_corner(faces, hits.triangles[hits.hit], hits.barycentric[hits.hit])
    missed = ~hits.hit
    if missed.any():
        closest = surface.closest_point(frame.to_world(anchors[missed]))
        indices[missed] = _snap_to_corner(faces, closest.triangles, closest.barycentric)
    check_distinct(indices, [p.name for p in control_points])
    return indices


def transfer_control_points(source_points, source_landmarks, target_vertices, target_faces,
                            target_landmarks, *, names: Sequence[str] | None = None) -> np.ndarray:
    """Carry control points from a source face onto a target mesh.

    The landmark TPS (source landmarks -> target landmarks, over the landmarks present on
    both) maps each source control point near the target surface; it then snaps to the
    closest surface point and to that triangle's nearest corner.

    Parameters
    ----------
    source_points : array_like, shape (k, 3)
        Control point positions on the source (mm).
    source_landmarks, target_landmarks : array_like, shape (22, 3)
        Landmarks of both faces (mm), NaN where missing; at least 5 in common.
    target_vertices, target_faces : array_like
        The target mesh.
    names : sequence of str, optional
        Control point names, for error messages.

    Returns
    -------
    ndarray of int64, shape (k,)
        Target vertex index of each control point.
    """
    points = as_points(source_points, "source_points", allow_empty=False)
    source_landmarks = as_landmarks(source_landmarks, "source_landmarks")
    target_landmarks = as_landmarks(target_landmarks, "target_landmarks")
    vertices = as_points(target_vertices, "target_vertices", allow_empty=False)
    faces = as_faces(target_faces, len(vertices), "target_faces")
    warp = landmark_map(source_landmarks, target_landmarks, what="control points source -> target")
    closest = MeshSurface(vertices, faces).closest_point(warp(points))
    indices = _snap_to_corner(faces, closest.triangles, closest.barycentric)
    check_distinct(indices, list(names) if names is not None else [f"#{i}" for i in range(len(points))])
    return indices
