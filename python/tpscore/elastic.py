"""Elastic surface parameterisation of expressions.

A face mesh is deformed by minimising a stretching and bending energy discretised with
the cotangent Laplacian L and the lumped mass matrix M,

    (-k_s L + k_b L M^-1 L) d = 0      on the free vertices,

with the displacement d prescribed at a few handle vertices (the facial control points)
and zero on a fixed region (the far part of the head, which an expression leaves still).
With the handles and the fixed region given, d is linear in the handle displacements, so
the sparse system is factorised once and one basis function is precomputed per handle:
an expression is then ``basis @ params`` with ``params`` the (k, 3) handle
displacements, one small matrix product per frame.

On top of the deformer, :class:`ElasticFace` learns the parameters of example
expressions by least squares (QR), blends them by weights, and clones them onto another
face of any mesh structure (control points carried over by the landmark TPS and snapped
to the target; displacements rotated between the two faces' frames and scaled by the
facial unit, the distance between the inner eye corners). :mod:`tpscore.muscles` drives
the control points with linear and sphincter muscles.

The default control points (``tpscore/data/elastic_control_points.json``) are defined
relative to the 22 landmarks: a weighted mean of named landmarks plus an (x, y) offset
in the face frame, projected onto the surface along the frame's -z and snapped to a
vertex. All lengths are in mm.
"""
from __future__ import annotations

import copy
import json
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ._validation import as_faces, as_points, as_positive, check_finite
from .face.landmarks import N_LANDMARKS, anchor_point, landmark_index, validate_anchor
from .mesh import cotan_laplacian, voronoi_areas
from .sparse import SparseCholesky
from .spatial import MeshSurface

__all__ = [
    "ElasticFace",
    "ExpressionSet",
    "ElasticControlPoint",
    "FaceFrame",
    "face_frame",
    "default_control_points",
    "load_control_points",
    "place_control_points",
    "transfer_control_points",
    "default_fixed_region",
    "DEFAULT_FIXED_FACTOR",
]

#: Default fixed-region radius, in multiples of the nose-tip-to-forehead distance. On
#: the ICT face the eyebrows lie within 1.55 of it and the chin within 1.4, while the
#: region beyond 1.8 (temples, ears, the neck below the jaw) carries under 15 % of the
#: motion energy of any brow or mouth shape.
DEFAULT_FIXED_FACTOR = 1.8

_REGIONS = ("eyebrows", "eyelids", "nose", "cheeks", "lips", "jaw")
_SIDES = ("left", "right", "centre")


# --------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class FaceFrame:
    """A face's own frame, from its landmarks.

    ``origin`` is the nose tip; the rows of ``axes`` are the unit x (toward the subject's
    left, through the eye corners), y (up, from the chin toward the brows, made
    orthogonal to x) and z = x cross y (out of the face). ``facial_unit`` is the
    distance between the inner eye corners (mm), ``forehead`` the midpoint of the inner
    eyebrows.
    """

    origin: np.ndarray
    axes: np.ndarray
    facial_unit: float
    forehead: np.ndarray

    def to_frame(self, points) -> np.ndarray:
        """World points (m, 3) -> frame coordinates (m, 3)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def to_world(self, coordinates) -> np.ndarray:
        """Frame coordinates (m, 3) -> world points (m, 3)."""
        return np.asarray(coordinates, dtype=np.float64) @ self.axes + self.origin


def _as_landmarks(landmarks, name: str = "landmarks") -> np.ndarray:
    array = as_points(landmarks, name, finite=False)
    if len(array) != N_LANDMARKS:
        raise ValueError(f"{name} must have shape ({N_LANDMARKS}, 3) (the Bosphorus landmarks), got {array.shape}")
    if np.isinf(array).any():
        raise ValueError(f"{name} contains infinite values (mark a missing landmark with NaN)")
    partial = np.isnan(array).any(axis=1) & ~np.isnan(array).all(axis=1)
    if partial.any():
        raise ValueError(f"{name} row {np.flatnonzero(partial)[0]} is partly NaN; a missing landmark is NaN in all three coordinates")
    return array


def _landmark(landmarks: np.ndarray, name: str, purpose: str) -> np.ndarray:
    point = landmarks[landmark_index(name)]
    if np.isnan(point).any():
        raise ValueError(f"landmarks: {name!r} is missing (NaN) but is needed for {purpose}")
    return point


def face_frame(landmarks) -> FaceFrame:
    """The face frame of a face with the given (22, 3) landmarks (see :class:`FaceFrame`).

    Needs the nose tip, the four eye corners, the inner eyebrows and the chin middle.
    """
    lm = _as_landmarks(landmarks)
    need = "the face frame"
    tip = _landmark(lm, "Nose tip", need)
    left_eye = (_landmark(lm, "Outer left eye corner", need) + _landmark(lm, "Inner left eye corner", need)) / 2
    right_eye = (_landmark(lm, "Outer right eye corner", need) + _landmark(lm, "Inner right eye corner", need)) / 2
    forehead = (_landmark(lm, "Inner left eyebrow", need) + _landmark(lm, "Inner right eyebrow", need)) / 2
    chin = _landmark(lm, "Chin middle", need)
    x = left_eye - right_eye
    up = forehead - chin
    if np.linalg.norm(x) == 0 or np.linalg.norm(np.cross(x, up)) <= 1e-9 * np.linalg.norm(x) * np.linalg.norm(up):
        raise ValueError("landmarks: the eyes and the chin-to-brow line are degenerate; no face frame")
    x = x / np.linalg.norm(x)
    y = up - (up @ x) * x
    y = y / np.linalg.norm(y)
    z = np.cross(x, y)
    unit = float(np.linalg.norm(_landmark(lm, "Inner left eye corner", need) - _landmark(lm, "Inner right eye corner", need)))
    if unit <= 0:
        raise ValueError("landmarks: the inner eye corners coincide; the facial unit is 0")
    return FaceFrame(origin=tip.copy(), axes=np.stack([x, y, z]), facial_unit=unit, forehead=forehead)


# ------------------------------------------------------------------ control points
@dataclass(frozen=True)
class ElasticControlPoint:
    """A named facial control point, defined relative to the landmarks.

    Its (x, y) in the face frame is the weighted mean of the landmarks named in ``at``
    plus ``offset_mm`` (scaled by facial unit / reference facial unit); its depth comes
    from the surface.
    """

    name: str
    region: str
    side: str
    at: Mapping[str, float]
    offset_mm: tuple[float, float] = (0.0, 0.0)
    note: str = ""

    def __post_init__(self):
        if self.region not in _REGIONS:
            raise ValueError(f"control point {self.name!r}: region must be one of {_REGIONS}, got {self.region!r}")
        if self.side not in _SIDES:
            raise ValueError(f"control point {self.name!r}: side must be one of {_SIDES}, got {self.side!r}")
        at, offset = validate_anchor(f"control point {self.name!r}", self.at, self.offset_mm)
        object.__setattr__(self, "at", at)
        object.__setattr__(self, "offset_mm", offset)

    def anchor(self, landmarks: np.ndarray) -> np.ndarray:
        """The weighted mean of the named landmarks (3,), world coordinates."""
        return anchor_point(landmarks, self.at, f"control point {self.name!r}")


def load_control_points(path=None) -> tuple[ElasticControlPoint, ...]:
    """Control point definitions from a JSON file (default: the shipped set of 47).

    Returns the points and, as attribute-free data, uses the file's
    ``reference_facial_unit_mm`` through :func:`place_control_points`.
    """
    return _load_control_points(path)[0]


def _load_control_points(path=None):
    try:
        if path is None:
            text = resources.files("tpscore").joinpath("data/elastic_control_points.json").read_text(encoding="utf-8")
            source = "the default control points"
        else:
            text = Path(path).read_text(encoding="utf-8")
            source = str(path)
        data = json.loads(text)
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read control points: {exc}") from None
    if not isinstance(data, Mapping) or "control_points" not in data:
        raise ValueError(f"{source}: expected an object with a 'control_points' list")
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
    reference_unit = as_positive(data.get("reference_facial_unit_mm", 36.88), "reference_facial_unit_mm")
    return points, reference_unit


def default_control_points() -> tuple[ElasticControlPoint, ...]:
    """The shipped 47 facial control points (eyebrows, eyelids, nose, cheeks, lips, jaw)."""
    return load_control_points()


def _snap_to_corner(faces: np.ndarray, triangles: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
    """The corner of each hit triangle with the largest barycentric weight.

    Snapping to the hit triangle's own corner (not the nearest vertex in space) keeps a
    point on the sheet it landed on where two sheets lie close (the lips).
    """
    return faces[triangles, np.argmax(barycentric, axis=1)].astype(np.int64)


def place_control_points(vertices, faces, landmarks, control_points=None, *,
                         reference_facial_unit_mm: float | None = None) -> np.ndarray:
    """Vertex indices of control points on a face mesh.

    Each point's (x, y) in the face frame (:func:`face_frame`) is the weighted mean of
    its landmarks plus its offset scaled by the facial unit; a ray from in front of the
    face along the frame's -z finds the front-most surface there, and the point snaps to
    the nearest corner of the hit triangle. Where the ray passes through a hole (eye or
    mouth opening), the closest surface point to the anchor (landmark mean plus offset,
    at the anchor's depth) is used instead.

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
        The facial unit the offsets were written for (default: the value in the JSON
        file, 36.88 mm, that of the ICT generic face).

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
    lm = _as_landmarks(landmarks)
    if control_points is None:
        control_points, default_unit = _load_control_points()
    else:
        control_points = tuple(control_points)
        default_unit = 36.88
    unit_ref = default_unit if reference_facial_unit_mm is None else as_positive(reference_facial_unit_mm, "reference_facial_unit_mm")
    frame = face_frame(lm)
    scale = frame.facial_unit / unit_ref
    anchors = np.array([frame.to_frame(p.anchor(lm)[None])[0] for p in control_points])
    anchors[:, :2] += np.array([p.offset_mm for p in control_points]) * scale
    surface = MeshSurface(vertices, faces)
    height = frame.to_frame(vertices)[:, 2].max() + 10.0 * frame.facial_unit
    origins = frame.to_world(np.column_stack([anchors[:, :2], np.full(len(anchors), height)]))
    directions = np.repeat(-frame.axes[2][None], len(anchors), axis=0)
    hits = surface.intersect_rays(origins, directions)
    indices = np.empty(len(anchors), dtype=np.int64)
    if hits.hit.any():
        indices[hits.hit] = _snap_to_corner(faces, hits.triangles[hits.hit], hits.barycentric[hits.hit])
    missed = ~hits.hit
    if missed.any():
        closest = surface.closest_point(frame.to_world(anchors[missed]))
        indices[missed] = _snap_to_corner(faces, closest.triangles, closest.barycentric)
    _check_distinct(indices, [p.name for p in control_points])
    return indices


def _check_distinct(indices: np.ndarray, names: Sequence[str]) -> None:
    unique, first, counts = np.unique(indices, return_index=True, return_counts=True)
    if (counts > 1).any():
        vertex = unique[counts > 1][0]
        clash = [names[i] for i in np.flatnonzero(indices == vertex)]
        raise ValueError(
            f"control points {', '.join(map(repr, clash))} land on the same vertex {vertex}; "
            "the mesh is too coarse for them or their definitions coincide")


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
    from .rbf import TPS

    points = as_points(source_points, "source_points", allow_empty=False)
    source_lm = _as_landmarks(source_landmarks, "source_landmarks")
    target_lm = _as_landmarks(target_landmarks, "target_landmarks")
    vertices = as_points(target_vertices, "target_vertices", allow_empty=False)
    faces = as_faces(target_faces, len(vertices), "target_faces")
    common = ~(np.isnan(source_lm).any(axis=1) | np.isnan(target_lm).any(axis=1))
    if common.sum() < 5:
        raise ValueError(f"only {int(common.sum())} landmarks are present on both faces; the TPS needs at least 5")
    warp = TPS(source_lm[common], target_lm[common])
    mapped = warp(points)
    closest = MeshSurface(vertices, faces).closest_point(mapped)
    indices = _snap_to_corner(faces, closest.triangles, closest.barycentric)
    _check_distinct(indices, list(names) if names is not None else [f"#{i}" for i in range(len(points))])
    return indices


def default_fixed_region(vertices, landmarks, factor: float = DEFAULT_FIXED_FACTOR) -> np.ndarray:
    """Mask of the vertices farther from the nose tip than ``factor`` times the distance
    from the nose tip to the forehead (the midpoint of the inner eyebrows).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    vertices = as_points(vertices, "vertices")
    factor = as_positive(factor, "fixed_factor")
    frame = face_frame(landmarks)
    radius = factor * float(np.linalg.norm(frame.forehead - frame.origin))
    return np.linalg.norm(vertices - frame.origin, axis=1) > radius


# ------------------------------------------------------------------- expressions
@dataclass(frozen=True)
class ExpressionSet:
    """Learned (or cloned) expression parameters: handle displacements per expression.

    Attributes
    ----------
    names : tuple of str
        One per expression.
    parameters : ndarray, shape (e, k, 3)
        Handle displacements (mm), in the order of the face's control points.
    rms_mm : ndarray, shape (e,) or None
        Root-mean-square per-vertex error of the reconstruction ``basis @ parameters``
        against the example expression (mm), when fitted.
    max_mm : ndarray, shape (e,) or None
        Largest per-vertex error (mm), when fitted.
    motion_rms_mm : ndarray, shape (e,) or None
        RMS per-vertex motion of the example itself (mm): rms_mm / motion_rms_mm is the
        fraction of the motion the model misses.
    """

    names: tuple[str, ...]
    parameters: np.ndarray
    rms_mm: np.ndarray | None = None
    max_mm: np.ndarray | None = None
    motion_rms_mm: np.ndarray | None = None

    def __post_init__(self):
        parameters = np.asarray(self.parameters, dtype=np.float64)
        if parameters.ndim != 3 or parameters.shape[2] != 3:
            raise ValueError(f"parameters must have shape (e, k, 3), got {parameters.shape}")
        check_finite(parameters.reshape(len(parameters), -1), "parameters")
        names = tuple(str(n) for n in self.names)
        if len(names) != len(parameters):
            raise ValueError(f"names has {len(names)} entries for {len(parameters)} expressions")
        parameters = parameters.copy()
        parameters.setflags(write=False)
        object.__setattr__(self, "parameters", parameters)
        object.__setattr__(self, "names", names)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"unknown expression {name!r}; known: {', '.join(self.names)}") from None


def _mask_from(value, n: int, name: str) -> np.ndarray:
    """A (n,) bool mask from a mask or an index list."""
    array = np.asarray(value)
    if array.dtype == bool:
        if array.shape != (n,):
            raise ValueError(f"{name} as a mask must have shape ({n},), got {array.shape}")
        return array.copy()
    if array.size == 0:
        return np.zeros(n, dtype=bool)
    if array.ndim != 1 or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"{name} must be a boolean mask of shape ({n},) or a 1-D array of vertex indices")
    if array.min() < 0 or array.max() >= n:
        raise ValueError(f"{name} refers to vertex indices outside [0, {n})")
    mask = np.zeros(n, dtype=bool)
    mask[array] = True
    return mask


class ElasticFace:
    """A face mesh with facial control points and a precomputed elastic deformation basis.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Neutral face vertices (mm).
    faces : array_like of int, shape (m, 3)
        Triangles.
    control_points : array_like of int (k,), or sequence of ElasticControlPoint, optional
        Handle vertices given directly as vertex indices, or definitions placed on this
        mesh with ``landmarks`` (:func:`place_control_points`). Default: the shipped 47
        points, placed with ``landmarks``.
    landmarks : array_like, shape (22, 3), optional
        The face's Bosphorus landmarks (mm), NaN where missing. Needed for the default
        control points, the default fixed region and cloning (frame and facial unit).
    fixed : array_like, optional
        Vertices held still: a (n,) bool mask or vertex indices. Default: every vertex
        farther from the nose tip than ``fixed_factor`` times the nose-tip-to-forehead
        distance (:func:`default_fixed_region`); pass an empty list for none. Vertices
        used by no triangle are always held still (they have no energy).
    fixed_factor : float, default 1.8
        The radius multiple of the default fixed region.
    stretching, bending : float, default 0 and 1
        k_s and k_b of the energy (-k_s L + k_b L M^-1 L); pure bending by default.
        L is dimensionless and L M^-1 L is in 1/mm^2, so k_s / k_b is an inverse squared
        length: stretching dominates above features wider than sqrt(k_b / k_s) mm.
    names : sequence of str, optional
        Names of the control points when they are given as indices.
    unanchored : {"error", "fix"}, default "error"
        What to do with a connected part of the mesh that has neither a control point
        nor a fixed vertex (its position would be undetermined): raise, or hold it
        still (scans often carry small islands of this kind, e.g. inside a nostril).

    Raises
    ------
    ValueError
        For bad arrays, a handle inside the fixed region, duplicate handles, or a part of
        the mesh with neither a handle nor a fixed vertex (its position would be free).

    Notes
    -----
    The factorisation and the basis are computed in the constructor; ``timings`` holds
    how long each took (seconds). The basis is read-only, so an ElasticFace can be used
    from several threads; :meth:`fit` and cloning set :attr:`expressions`.
    """

    def __init__(self, vertices, faces, control_points=None, *, landmarks=None, fixed=None,
                 fixed_factor: float = DEFAULT_FIXED_FACTOR, stretching: float = 0.0,
                 bending: float = 1.0, names: Sequence[str] | None = None,
                 unanchored: str = "error"):
        vertices = as_points(vertices, "vertices", allow_empty=False).copy()
        faces = as_faces(faces, len(vertices)).copy()
        if len(faces) == 0:
            raise ValueError("faces is empty; the deformation needs a triangle mesh")
        n = len(vertices)
        self._landmarks = None if landmarks is None else _as_landmarks(landmarks).copy()
        self._frame = None if self._landmarks is None else face_frame(self._landmarks)

        # Handles.
        if control_points is None or (not isinstance(control_points, np.ndarray)
                                      and len(control_points)
                                      and isinstance(next(iter(control_points)), ElasticControlPoint)):
            if self._landmarks is None:
                raise ValueError("landmarks are needed to place the control points on the face "
                                 "(or pass control_points as vertex indices)")
            definitions = None if control_points is None else tuple(control_points)
            if definitions is None:
                definitions, unit = _load_control_points()
            else:
                unit = None
            handles = place_control_points(vertices, faces, self._landmarks, definitions,
                                           reference_facial_unit_mm=unit)
            point_names = tuple(p.name for p in definitions)
            self._definitions = definitions
        else:
            handles = np.asarray(control_points)
            if handles.ndim != 1 or handles.size == 0 or not np.issubdtype(handles.dtype, np.integer):
                raise ValueError("control_points must be a non-empty 1-D array of vertex indices "
                                 f"(or control point definitions), got shape {handles.shape} dtype {handles.dtype}")
            handles = handles.astype(np.int64)
            if handles.min() < 0 or handles.max() >= n:
                raise ValueError(f"control_points refers to vertex indices outside [0, {n})")
            point_names = tuple(names) if names is not None else tuple(f"cp{i}" for i in range(len(handles)))
            if len(point_names) != len(handles):
                raise ValueError(f"names has {len(point_names)} entries for {len(handles)} control points")
            _check_distinct(handles, point_names)
            self._definitions = None

        # Fixed region.
        if fixed is None:
            if self._landmarks is None:
                raise ValueError("landmarks are needed for the default fixed region (or pass fixed=...)")
            fixed_mask = default_fixed_region(vertices, self._landmarks, fixed_factor)
        else:
            fixed_mask = _mask_from(fixed, n, "fixed")
        inside = np.flatnonzero(fixed_mask[handles])
        if len(inside):
            listed = ", ".join(f"{point_names[i]!r} (vertex {handles[i]})" for i in inside[:5])
            raise ValueError(
                f"{len(inside)} control point(s) lie inside the fixed region: {listed}; "
                "shrink the fixed region (a larger fixed_factor) or move the control points")
        referenced = np.zeros(n, dtype=bool)
        referenced[faces.ravel()] = True
        fixed_mask |= ~referenced
        if fixed_mask[handles].any():
            raise ValueError("a control point is a vertex used by no triangle")

        stretching = as_positive(stretching, "stretching", allow_zero=True)
        bending = as_positive(bending, "bending", allow_zero=True)
        if stretching == 0 and bending == 0:
            raise ValueError("stretching and bending are both 0: there is no energy to minimise")

        self._vertices = vertices
        self._faces = faces
        self._handles = handles
        self._names = point_names
        self._fixed = fixed_mask
        self._stretching = stretching
        self._bending = bending
        if unanchored not in ("error", "fix"):
            raise ValueError(f"unanchored must be 'error' or 'fix', got {unanchored!r}")
        self._check_anchored(fix=unanchored == "fix")
        self._timings: dict[str, float] = {}
        self._basis = self._compute_basis()
        self._qr = None
        self.expressions: ExpressionSet | None = None
        for array in (self._vertices, self._faces, self._handles, self._fixed, self._basis):
            array.setflags(write=False)

    # ---------------------------------------------------------------- the deformer
    def _check_anchored(self, fix: bool) -> None:
        """Every connected part of the mesh needs a handle or a fixed vertex (or, with
        ``fix``, is held still whole)."""
        n = len(self._vertices)
        edges = np.concatenate([self._faces[:, [0, 1]], self._faces[:, [1, 2]], self._faces[:, [2, 0]]])
        graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
        count, labels = connected_components(graph, directed=False)
        anchored = np.zeros(count, dtype=bool)
        anchored[labels[self._handles]] = True
        anchored[labels[self._fixed]] = True
        if fix:
            self._fixed |= ~anchored[labels]
        elif not anchored.all():
            part = np.flatnonzero(~anchored)[0]
            size = int((labels == part).sum())
            raise ValueError(
                f"a connected part of the mesh ({size} vertices, e.g. vertex "
                f"{np.flatnonzero(labels == part)[0]}) has no control point and no fixed vertex, "
                "so its position is undetermined")

    def energy_matrix(self) -> sp.csr_matrix:
        """The (n, n) energy operator -k_s L + k_b L M^-1 L (symmetric positive semi-definite)."""
        laplacian = cotan_laplacian(self._vertices, self._faces)
        areas = voronoi_areas(self._vertices, self._faces)
        # A vertex of zero area (degenerate triangles only) would make M^-1 infinite;
        # a floor of 1e-3 of the median area keeps the operator finite and barely
        # changes it (that vertex's bending term is still 1000 times stiffer).
        floor = 1e-3 * float(np.median(areas[areas > 0])) if (areas > 0).any() else 1.0
        areas = np.maximum(areas, floor)
        operator = sp.csr_matrix(laplacian.shape)
        if self._bending:
            operator = operator + self._bending * (laplacian @ sp.diags(1.0 / areas) @ laplacian)
        if self._stretching:
            operator = operator - self._stretching * laplacian
        operator = sp.csr_matrix(operator)
        # Remove the rounding asymmetry of the triple product before the symmetry check.
        return sp.csr_matrix((operator + operator.T) * 0.5)

    def _compute_basis(self) -> np.ndarray:
        n = len(self._vertices)
        constrained = self._fixed.copy()
        constrained[self._handles] = True
        free = np.flatnonzero(~constrained)
        operator = self.energy_matrix()
        basis = np.zeros((n, len(self._handles)))
        basis[self._handles, np.arange(len(self._handles))] = 1.0
        start = time.perf_counter()
        if len(free):
            free_block = operator[free][:, free]
            self._factor = SparseCholesky(free_block)
        else:
            self._factor = None
        self._timings["factorisation_s"] = time.perf_counter() - start
        self._free = free
        start = time.perf_counter()
        if len(free):
            coupling = operator[free][:, self._handles].toarray()
            basis[free] = self._factor.solve(-coupling)
        self._timings["basis_s"] = time.perf_counter() - start
        self._coupling = operator[free][:, self._handles].tocsr() if len(free) else None
        return basis

    # ------------------------------------------------------------------ properties
    @property
    def vertices(self) -> np.ndarray:
        """Neutral vertices (n, 3), mm, read-only."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """Triangles (m, 3) int64, read-only."""
        return self._faces

    @property
    def handles(self) -> np.ndarray:
        """Vertex index of each control point (k,), read-only."""
        return self._handles

    @property
    def control_point_names(self) -> tuple[str, ...]:
        return self._names

    @property
    def control_point_positions(self) -> np.ndarray:
        """Neutral positions of the control points (k, 3), mm."""
        return self._vertices[self._handles]

    @property
    def fixed(self) -> np.ndarray:
        """Mask (n,) of the vertices held still, read-only."""
        return self._fixed

    @property
    def basis(self) -> np.ndarray:
        """The deformation basis (n, k): column j is the displacement field (per unit) of
        handle j moved alone; rows of handles are the identity, fixed rows are 0."""
        return self._basis

    @property
    def landmarks(self) -> np.ndarray | None:
        return self._landmarks

    @property
    def frame(self) -> FaceFrame | None:
        """The face frame (needs landmarks)."""
        return self._frame

    @property
    def timings(self) -> dict[str, float]:
        """Seconds spent factorising the free block and precomputing the basis."""
        return dict(self._timings)

    def __repr__(self) -> str:
        return (f"ElasticFace(vertices={len(self._vertices)}, control_points={len(self._handles)}, "
                f"fixed={int(self._fixed.sum())}, stretching={self._stretching:g}, bending={self._bending:g})")

    # ------------------------------------------------------------------ deformation
    def _as_parameters(self, params, name: str = "params") -> tuple[np.ndarray, bool]:
        try:
            array = np.asarray(params, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be numeric: {exc}") from None
        k = len(self._handles)
        single = array.ndim == 2
        if single:
            array = array[None]
        if array.ndim != 3 or array.shape[1:] != (k, 3):
            raise ValueError(f"{name} must have shape ({k}, 3) or (e, {k}, 3) (one displacement per control point), got {np.shape(params)}")
        check_finite(array.reshape(len(array), -1), name)
        return array, single

    def displacement(self, params) -> np.ndarray:
        """Per-vertex displacement ``basis @ params``: (n, 3) for params (k, 3), or
        (e, n, 3) for (e, k, 3); mm."""
        array, single = self._as_parameters(params)
        result = np.einsum("nk,ekd->end", self._basis, array, optimize=True)
        return result[0] if single else result

    def deform(self, params) -> np.ndarray:
        """Deformed vertices ``vertices + basis @ params``: (n, 3) or (e, n, 3), mm.

        Parameters
        ----------
        params : array_like, shape (k, 3) or (e, k, 3)
            Displacement of each control point (mm).
        """
        return self._vertices + self.displacement(params)

    def solve_direct(self, params) -> np.ndarray:
        """Deformed vertices (n, 3) from a fresh solve with the factor (no basis).

        The same result as :meth:`deform` up to rounding; useful to check the basis and
        when only one deformation of a face is ever needed.
        """
        array, single = self._as_parameters(params)
        if not single:
            raise ValueError("solve_direct takes one expression's params of shape (k, 3)")
        displacement = np.zeros_like(self._vertices)
        displacement[self._handles] = array[0]
        if len(self._free):
            displacement[self._free] = self._factor.solve(-(self._coupling @ array[0]))
        return self._vertices + displacement

    # --------------------------------------------------------------------- learning
    def _least_squares(self):
        if self._qr is None:
            # Reduced QR of the (n, k) basis; its rows of handles are the identity, so it
            # has full column rank and R is invertible.
            self._qr = np.linalg.qr(self._basis)
        return self._qr

    def fit(self, expressive_vertices, names: Sequence[str] | None = None, *, faces=None) -> ExpressionSet:
        """Learn the control-point displacements of example expressions by least squares.

        For each expression, params = argmin || basis @ params - (expressive - neutral) ||
        over all vertices, solved with the QR factorisation of the basis.

        Parameters
        ----------
        expressive_vertices : array_like, shape (e, n, 3) or (n, 3)
            Expressive meshes with this face's connectivity (vertex i of each is vertex i
            of the neutral), mm.
        names : sequence of str, optional
            Expression names (default "expr0", ...).
        faces : array_like, optional
            The expressive meshes' triangles; when given they must equal this face's
            triangles, which guards against meshes of another connectivity.

        Returns
        -------
        ExpressionSet
            Parameters (e, k, 3) with per-expression reconstruction errors; also stored
            as :attr:`expressions`.
        """
        try:
            examples = np.asarray(expressive_vertices, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"expressive_vertices must be numeric: {exc}") from None
        if examples.ndim == 2:
            examples = examples[None]
        n = len(self._vertices)
        if examples.ndim != 3 or examples.shape[2] != 3:
            raise ValueError(f"expressive_vertices must have shape (e, {n}, 3) or ({n}, 3), got {np.shape(expressive_vertices)}")
        if examples.shape[1] != n:
            raise ValueError(
                f"expressive_vertices has {examples.shape[1]} vertices per mesh but the neutral face has {n}: "
                "the expressions must share the neutral mesh's connectivity")
        if faces is not None:
            other = np.asarray(faces)
            if other.shape != self._faces.shape or not np.array_equal(other, self._faces):
                raise ValueError("faces of the expressive meshes differ from the neutral face's: "
                                 "the expressions must share the neutral mesh's connectivity")
        check_finite(examples.reshape(len(examples), -1), "expressive_vertices")
        if len(examples) == 0:
            raise ValueError("expressive_vertices holds no expression")
        expression_names = tuple(names) if names is not None else tuple(f"expr{i}" for i in range(len(examples)))
        if len(expression_names) != len(examples):
            raise ValueError(f"names has {len(expression_names)} entries for {len(examples)} expressions")
        motion = examples - self._vertices
        q, r = self._least_squares()
        e, k = len(examples), len(self._handles)
        stacked = motion.transpose(1, 0, 2).reshape(n, 3 * e)
        solution = scipy.linalg.solve_triangular(r, q.T @ stacked)
        params = solution.reshape(k, e, 3).transpose(1, 0, 2)
        residual = np.einsum("nk,ekd->end", self._basis, params, optimize=True) - motion
        error = np.linalg.norm(residual, axis=2)
        result = ExpressionSet(
            names=expression_names, parameters=params,
            rms_mm=np.sqrt((error ** 2).mean(axis=1)), max_mm=error.max(axis=1),
            motion_rms_mm=np.sqrt((motion ** 2).sum(axis=2).mean(axis=1)))
        self.expressions = result
        return result

    def _expressions(self, expressions) -> ExpressionSet:
        if expressions is None:
            expressions = self.expressions
        if expressions is None:
            raise ValueError("this face has no learned expressions: call fit() first (or pass expressions=)")
        if expressions.parameters.shape[1] != len(self._handles):
            raise ValueError(f"expressions have {expressions.parameters.shape[1]} control points; this face has {len(self._handles)}")
        return expressions

    def blend_parameters(self, weights, expressions: ExpressionSet | None = None) -> np.ndarray:
        """Control-point displacements (k, 3) of a blend: sum_e weights[e] * params[e]."""
        expressions = self._expressions(expressions)
        if isinstance(weights, Mapping):
            vector = np.zeros(len(expressions))
            for name, w in weights.items():
                vector[expressions.index(name)] = float(w)
        else:
            try:
                vector = np.asarray(weights, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"weights must be numeric: {exc}") from None
        if vector.shape != (len(expressions),):
            raise ValueError(f"weights must have shape ({len(expressions)},) (one per expression) or be a name -> weight mapping, got {np.shape(weights)}")
        check_finite(vector, "weights")
        return np.tensordot(vector, expressions.parameters, axes=1)

    def blend(self, weights, expressions: ExpressionSet | None = None) -> np.ndarray:
        """A new expression from weights over learned ones, blended at the control points.

        Parameters
        ----------
        weights : array_like (e,) or mapping name -> weight
            One weight per learned expression (any real numbers; 0..1 is typical).
        expressions : ExpressionSet, optional
            Default: :attr:`expressions`.

        Returns
        -------
        ndarray, shape (n, 3)
            The deformed vertices (mm).
        """
        return self.deform(self.blend_parameters(weights, expressions))

    def expression(self, name: str, magnitude: float = 1.0) -> np.ndarray:
        """Vertices (n, 3) of one learned expression at a magnitude."""
        expressions = self._expressions(None)
        return self.deform(expressions.parameters[expressions.index(name)] * float(magnitude))

    # ---------------------------------------------------------------------- cloning
    def clone_to(self, target, expressions: ExpressionSet | None = None, *, target_landmarks=None,
                 **face_options) -> "ElasticFace":
        """Clone the learned expressions onto another face, of any mesh structure.

        The target's control points are this face's control points carried over by the
        landmark TPS and snapped to the target (unless ``target`` is an ElasticFace, whose
        own control points, in the same order, are used). Each displacement is expressed
        in this face's frame, divided by its facial unit, multiplied by the target's, and
        expressed back in the target's frame; the target's own basis spreads it.

        Parameters
        ----------
        target : ElasticFace or (vertices, faces)
            The target face. A (vertices, faces) pair needs ``target_landmarks``.
        expressions : ExpressionSet, optional
            Default: :attr:`expressions`.
        target_landmarks : array_like, shape (22, 3), optional
            The target's landmarks (mm) when ``target`` is a mesh.
        **face_options
            Passed to the target's :class:`ElasticFace` (fixed, fixed_factor, stretching,
            bending, unanchored).

        Returns
        -------
        ElasticFace
            The target face with :attr:`expressions` holding the cloned parameters (a
            shallow copy when ``target`` was an ElasticFace; the original is unchanged).
        """
        expressions = self._expressions(expressions)
        if self._frame is None:
            raise ValueError("cloning needs this face's landmarks (ElasticFace(..., landmarks=...))")
        if isinstance(target, ElasticFace):
            if face_options or target_landmarks is not None:
                raise ValueError("target is already an ElasticFace; target_landmarks and face options do not apply")
            if target._frame is None:
                raise ValueError("the target ElasticFace has no landmarks; cloning needs its frame and facial unit")
            if len(target._handles) != len(self._handles) or (
                    target._definitions is not None and self._definitions is not None
                    and target._names != self._names):
                raise ValueError(
                    f"the target has {len(target._handles)} control points {target._names[:3]}...; the source has "
                    f"{len(self._handles)} {self._names[:3]}...: they must correspond one to one")
            target_face = copy.copy(target)
        else:
            try:
                target_vertices, target_faces = target
            except (TypeError, ValueError):
                raise ValueError("target must be an ElasticFace or a (vertices, faces) pair") from None
            if target_landmarks is None:
                raise ValueError("target_landmarks are needed to clone onto a (vertices, faces) target")
            handles = transfer_control_points(self.control_point_positions, self._landmarks,
                                              target_vertices, target_faces, target_landmarks,
                                              names=self._names)
            target_face = ElasticFace(target_vertices, target_faces, handles, landmarks=target_landmarks,
                                      names=self._names, **face_options)
        mapped = self.map_displacements(expressions.parameters, target_face._frame)
        target_face.expressions = ExpressionSet(names=expressions.names, parameters=mapped)
        return target_face

    def map_displacements(self, displacements, target_frame: FaceFrame) -> np.ndarray:
        """Displacements (..., 3) of this face, rotated into ``target_frame`` and scaled by
        the ratio of facial units (target / this)."""
        source = self._frame
        array = np.asarray(displacements, dtype=np.float64)
        return (array @ source.axes.T) * (target_frame.facial_unit / source.facial_unit) @ target_frame.axes

    # ---------------------------------------------------------------------- storage
    def storage(self, expressions: ExpressionSet | None = None) -> dict[str, float]:
        """Numbers stored for an expression set, in float64 values.

        Returns
        -------
        dict
            ``parameters`` (e * k * 3), ``basis`` (n * k), ``per_vertex`` (e * n * 3, the
            displacements of every vertex), ``ratio`` ((parameters + basis) / per_vertex,
            the method's storage ratio) and ``ratio_parameters_only`` (parameters /
            per_vertex, when the basis is recomputed from the neutral mesh instead of
            stored).
        """
        expressions = self._expressions(expressions)
        e, k, n = len(expressions), len(self._handles), len(self._vertices)
        parameters, basis, per_vertex = e * k * 3, n * k, e * n * 3
        return {"expressions": e, "control_points": k, "vertices": n,
                "parameters": parameters, "basis": basis, "per_vertex": per_vertex,
                "ratio": (parameters + basis) / per_vertex,
                "ratio_parameters_only": parameters / per_vertex}
