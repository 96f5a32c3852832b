"""Pose and size normalisation of a face against a reference face.

Two ways to bring a face into the reference frame:

* ``"affine"`` -- the method's transform: translate the nose tip to the origin, then
  apply T = A B^-1, where the columns of B are the face's outer eye corners, chin
  middle and nose tip in homogeneous coordinates and A holds the same landmarks of
  the reference. It maps those four landmarks exactly and needs all four.
* ``"similarity"`` -- a least-squares rotation, uniform scale and translation over all
  landmarks present in both faces (Umeyama's closed form). It uses every landmark,
  so one noisy or missing landmark matters less; it is the default.

Every result keeps its 4 x 4 matrix so that outputs can be mapped back into the
scan's own frame.

A face's own frame (:func:`face_frame`: origin at the nose tip, axes from the eyes and
the chin-to-brow line, the facial unit) needs no reference face; it is the one frame
from landmarks that every method places things in.
"""
from __future__ import annotations

import itertools
import threading
import warnings
import weakref
from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry import FrameTransform, paired_points, similarity_transform
from ..spatial import KDTree, MeshSurface
from .grid import FaceGrid
from .landmarks import N_LANDMARKS, anchor_point, as_landmarks, landmark_index

__all__ = [
    "FaceFrame",
    "face_frame",
    "FrameTransform",
    "similarity_transform",
    "thesis_affine_transform",
    "landmark_transform",
    "AFFINE_LANDMARKS",
    "NORMALISATION_METHODS",
    "NormalisedFace",
    "normalise_face",
    "kept_normalisation",
]

#: The four landmarks of the method's affine normalisation (B's columns).
AFFINE_LANDMARKS = ("Outer left eye corner", "Outer right eye corner", "Chin middle", "Nose tip")
NORMALISATION_METHODS = ("similarity", "affine", "none")


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


def face_frame(landmarks) -> FaceFrame:
    """The frame of a face with the given (22, 3) landmarks (see :class:`FaceFrame`).

    Needs the nose tip, the four eye corners, the inner eyebrows and the chin middle;
    raises ValueError naming the first one that is missing.
    """
    lm = as_landmarks(landmarks)

    def mean_of(*names: str) -> np.ndarray:
        return anchor_point(lm, dict.fromkeys(names, 1.0), "the face frame")

    tip = mean_of("Nose tip")
    left_eye = mean_of("Outer left eye corner", "Inner left eye corner")
    right_eye = mean_of("Outer right eye corner", "Inner right eye corner")
    forehead = mean_of("Inner left eyebrow", "Inner right eyebrow")
    chin = mean_of("Chin middle")
    x = left_eye - right_eye
    up = forehead - chin
    if np.linalg.norm(x) == 0 or np.linalg.norm(np.cross(x, up)) <= 1e-9 * np.linalg.norm(x) * np.linalg.norm(up):
        raise ValueError("landmarks: the eyes and the chin-to-brow line are degenerate; no face frame")
    x = x / np.linalg.norm(x)
    y = up - (up @ x) * x
    y = y / np.linalg.norm(y)
    z = np.cross(x, y)
    unit = float(np.linalg.norm(mean_of("Inner left eye corner") - mean_of("Inner right eye corner")))
    if unit <= 0:
        raise ValueError("landmarks: the inner eye corners coincide; the facial unit is 0")
    return FaceFrame(origin=tip, axes=np.stack([x, y, z]), facial_unit=unit, forehead=forehead)


def thesis_affine_transform(landmarks, reference) -> FrameTransform:
    """The method's affine normalisation T = A B^-1 after moving the nose tip to the origin.

    Parameters
    ----------
    landmarks, reference : (22, 3) array_like
        The face's and the reference's landmarks (mm), Bosphorus order.

    Raises
    ------
    ValueError
        One of the four landmarks is missing, or they are coplanar (B singular).
    """
    lm, ref, both = paired_points(landmarks, reference, "landmarks", "reference landmarks")
    if len(lm) != N_LANDMARKS:
        raise ValueError(f"landmarks must have shape ({N_LANDMARKS}, 3), got {lm.shape}")
    idx = [landmark_index(n) for n in AFFINE_LANDMARKS]
    missing = [AFFINE_LANDMARKS[k] for k, i in enumerate(idx) if not both[i]]
    if missing:
        raise ValueError(
            "the affine normalisation needs the outer eye corners, chin middle and nose tip; "
            f"missing: {', '.join(missing)}"
        )
    tip = landmark_index("Nose tip")
    shift = np.eye(4)
    shift[:3, 3] = -lm[tip]
    b = np.vstack([(lm[idx] - lm[tip]).T, np.ones(4)])
    a = np.vstack([ref[idx].T, np.ones(4)])
    if abs(np.linalg.det(b[:3, :3] - b[:3, 3:4])) < 1e-6 * np.abs(b[:3]).max() ** 3:
        raise ValueError("the outer eye corners, chin middle and nose tip are coplanar")
    t = a @ np.linalg.inv(b)
    t[3] = [0.0, 0.0, 0.0, 1.0]  # exact: both bottom rows are ones
    return FrameTransform(t @ shift, "affine")


def landmark_transform(landmarks, reference, method: str = "similarity") -> FrameTransform:
    """Transform taking a face's frame to the reference frame, by the named method.

    ``method`` is one of ``"similarity"`` (default), ``"affine"`` or ``"none"``.
    """
    if method == "similarity":
        return similarity_transform(landmarks, reference)
    if method == "affine":
        return thesis_affine_transform(landmarks, reference)
    if method == "none":
        return FrameTransform.identity()
    raise ValueError(f"unknown normalisation method {method!r}; use one of {NORMALISATION_METHODS}")


@dataclass
class NormalisedFace:
    """A face grid in the reference frame, with the transform from its scan frame.

    What is derived from the face (its surface, its kd-tree, anything kept with
    :meth:`derived`) is computed once, by whichever thread asks first; a transfer
    computes some of it on a second thread ahead of use.
    """

    grid: FaceGrid
    transform: FrameTransform
    _derived: dict = field(default_factory=dict, repr=False, init=False, compare=False)
    # one lock per derived name, so that a thread computing one thing (the registration
    # grid) does not hold up another computing something else (the openings); _lock
    # guards the dict of locks
    _name_locks: dict = field(default_factory=dict, repr=False, init=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, init=False, compare=False)

    @property
    def landmarks(self) -> np.ndarray:
        return self.grid.landmarks

    def __getstate__(self):
        # what was derived is made again on first use after unpickling; a lock is not
        # pickled
        return {"grid": self.grid, "transform": self.transform}

    def __setstate__(self, state):
        self.grid, self.transform = state["grid"], state["transform"]
        self._derived, self._name_locks, self._lock = {}, {}, threading.Lock()

    def derived(self, name, compute):
        """``compute(self)``, computed once per ``name`` (hashable; a ValueError it raised is
        raised again on every later call); the threads that ask for it meanwhile wait, and
        only they."""
        with self._lock:
            lock = self._name_locks.setdefault(name, threading.RLock())
        with lock:
            if name not in self._derived:
                try:
                    self._derived[name] = (compute(self), None)
                except ValueError as error:
                    self._derived[name] = (None, error)
            value, error = self._derived[name]
        if error is not None:
            raise error
        return value

    def derived_so_far(self, name):
        """What :meth:`derived` holds under ``name``, or None when nothing (or an
        error) is held: for what a step finds on its way and keeps with the face only
        when it succeeds."""
        value, _ = self._derived.get(name, (None, None))
        return value

    def _valid_index(self) -> np.ndarray:
        """Flat grid indices of the valid vertices (at least 3)."""
        return self.derived("valid vertices", _valid_vertices)

    def _surface_or_none(self) -> MeshSurface | None:
        """The surface over the valid vertices, None when they make no triangle."""
        return self.derived("surface", _surface_over_valid_vertices)

    def _vertex_tree(self) -> KDTree:
        """A kd-tree of the valid vertices, built on first use (the default transfer
        snaps onto the surface and never needs it)."""
        return self.derived("vertex tree", lambda face: KDTree(face.grid.points.reshape(-1, 3)[face._valid_index()]))

    def snap(self, points, mode: str) -> np.ndarray:
        """Snap (k, 3) points onto this face: closest surface point or nearest vertex."""
        surface = self._surface_or_none()
        points = np.asarray(points, dtype=np.float64)
        if mode == "surface" and surface is not None:
            return surface.closest_point(points).points
        tree = self._vertex_tree()
        _, nearest = tree.query(points)
        return tree.points[nearest]

    def nearest_vertex(self, points) -> np.ndarray:
        """Flat grid index (into H*W) of the valid vertex nearest to each (k, 3) point."""
        _, nearest = self._vertex_tree().query(np.asarray(points, dtype=np.float64))
        return self._valid_index()[nearest]

    def surface(self) -> MeshSurface:
        surface = self._surface_or_none()
        if surface is None:
            raise ValueError("the face has no triangles (too few valid grid vertices)")
        return surface

    def scan_frame_surface(self, scan_grid: FaceGrid) -> MeshSurface | None:
        """The surface of ``scan_grid``, the grid this face was normalised from (in its
        scan frame), built once; None when it makes no triangle. :meth:`surface`, asked
        for afterwards, is then this tree moved into the reference frame
        (:meth:`MeshSurface.moved`: the same answers for about a third of a build's time)."""
        def build(face):
            if not np.array_equal(scan_grid.mask, face.grid.mask):
                raise ValueError("scan_grid is not the grid this face was normalised from (its mask differs)")
            mesh = scan_grid.mesh()
            return MeshSurface(mesh.vertices, mesh.faces) if len(mesh.faces) else None
        return self.derived("scan-frame surface", build)


def _valid_vertices(face: NormalisedFace) -> np.ndarray:
    valid_index = np.flatnonzero(face.grid.mask.ravel())
    if len(valid_index) < 3:
        raise ValueError("the face has fewer than 3 valid vertices")
    return valid_index


def _surface_over_valid_vertices(face: NormalisedFace) -> MeshSurface | None:
    face._valid_index()  # refuses a face of fewer than 3 valid vertices first
    mesh = face.grid.mesh()
    if len(mesh.faces) == 0:
        return None
    # the scan frame's tree, when one is built already (not waited for), fits these
    # vertices too: one mask, so the same triangles, moved by the normalisation
    scan_surface, _ = face._derived.get("scan-frame surface", (None, None))
    if scan_surface is not None:
        return scan_surface.moved(mesh.vertices)
    return MeshSurface(mesh.vertices, mesh.faces)


def normalise_face(grid: FaceGrid, reference_landmarks, method: str = "similarity") -> NormalisedFace:
    """Bring a face grid into the reference frame by its landmarks.

    The affine method needs four particular landmarks; when one is missing, the face
    is normalised by the similarity over all landmarks instead, with a warning.
    """
    try:
        transform = landmark_transform(grid.landmarks, reference_landmarks, method)
    except ValueError as exc:
        if method != "affine" or "missing" not in str(exc):
            raise
        warnings.warn(f"{exc}; using the similarity normalisation for this face", stacklevel=2)
        transform = landmark_transform(grid.landmarks, reference_landmarks, "similarity")
    moved = replace(grid, points=transform.apply(grid.points),
                    landmarks=transform.apply(grid.landmarks))
    return NormalisedFace(moved, transform)


class _Kept:
    """A grid's normalisations, with the grid as it was when they were made."""

    def __init__(self, grid: FaceGrid):
        # copies of the arrays (about 1 MB for a 150 x 150 grid): an edit in place is
        # then seen; the image is read-only, so its identity tells
        self.arrays = [np.array(a, copy=True) for a in _grid_arrays(grid)]
        self.image, self.scan_frame = grid.image, grid.scan_frame
        self.detected = grid.landmarks_detected
        self.faces: dict = {}
        self.used = next(_use_clock)

    def describes(self, grid: FaceGrid) -> bool:
        return (grid.image is self.image and grid.scan_frame is self.scan_frame
                and grid.landmarks_detected == self.detected
                and all(np.array_equal(a, b, equal_nan=True) for a, b in zip(_grid_arrays(grid), self.arrays)))


def _grid_arrays(grid: FaceGrid):
    return grid.points, grid.mask, grid.uv, grid.landmarks, grid.landmark_vertices


#: How many grids' faces are kept: those used most recently. A rig's transfers use two
#: grids (the source's neutral one and the target), a loop of one source onto many
#: targets three; each kept face holds 10-50 MB (its surfaces' trees, the registration's
#: lattice system and factor, the texture tracking's view of it), so a program that
#: holds a whole database's grids does not keep them all. 0 keeps none.
MAX_KEPT_GRIDS = 4

_kept: "weakref.WeakKeyDictionary[FaceGrid, _Kept]" = weakref.WeakKeyDictionary()
_kept_lock = threading.Lock()
_use_clock = itertools.count()


def kept_normalisation(grid: FaceGrid, reference_landmarks, method: str = "similarity") -> NormalisedFace:
    """:func:`normalise_face`, made once per grid object, reference and method for as
    long as the grid lives unchanged.

    A :class:`NormalisedFace` keeps what is computed of the face alone (its surfaces,
    mirror plane, openings, registration grid, texture view), so transfers that share a face (a rig's
    expressions from one source onto one target, a batch's codes) compute them once:
    about a quarter of a transfer's CPU from grids. The grid is compared with a copy of its arrays at
    each call (a fraction of a millisecond), so one edited in place is normalised again;
    a normalisation that fell back to the similarity (with a warning) is not kept, so it
    warns every time. The kept faces go with their grid, and only the
    :data:`MAX_KEPT_GRIDS` grids used most recently keep theirs.
    """
    landmarks = np.asarray(reference_landmarks, dtype=np.float64)
    key = (landmarks.tobytes(), landmarks.shape, method)
    with _kept_lock:
        kept = _kept.get(grid)
        face = kept.faces.get(key) if kept is not None else None
    if face is not None and kept.describes(grid):
        kept.used = next(_use_clock)
        return face
    face = normalise_face(grid, landmarks, method)
    if face.transform.method != method:
        return face
    with _kept_lock:
        kept = _kept.get(grid)
        if kept is None or not kept.describes(grid):
            kept = _kept[grid] = _Kept(grid)   # the most recently used, by its making
            by_use = sorted(_kept.items(), key=lambda item: item[1].used)
            for least_used, _ in by_use[:max(len(by_use) - MAX_KEPT_GRIDS, 0)]:
                del _kept[least_used]
        else:
            kept.used = next(_use_clock)
        # a face made meanwhile by another thread is the one kept and shared
        return kept.faces.setdefault(key, face)
