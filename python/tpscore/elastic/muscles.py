"""Muscles that drive the control points of an :class:`~tpscore.elastic.ElasticFace`,
so that an animator can pose a face by contractions instead of point displacements.

A **linear muscle** runs from a bony attachment B (fixed to the skull) to a skin
attachment S. Contracting it by a fraction c of its length pulls a control point p
toward B by

    c * |S - B| * A(p) * R(p)

where the angular fall-off A(p) = cos(alpha / Omega * pi/2) for the angle alpha between
p - B and S - B (zero beyond the muscle's angular zone Omega), and the radial fall-off
R(p) = cos((1 - r / |S - B|) * pi/2) for r = |p - B| up to the skin attachment (nothing
moves at the bone) and cos((r - |S - B|) / F * pi/2) over a fall-off length F beyond it
(zero after). This is the classic vector muscle with cosine fall-offs.

A **sphincter muscle** (around the mouth or an eye) is an ellipse of radial linear
muscles: the centre is fitted to its control points (their mean, moved ``depth_mm``
behind the surface), the ellipse's semi-axes are the points' extents along the face
frame's x and y, and ``spokes`` linear muscles run from the centre to points on the
ellipse, each with an angular zone that reaches its neighbours.

Muscles are registered to the control points once (:class:`MuscleModel`): every
muscle's displacement field per unit contraction is precomputed, so the control-point
displacements of any set of contractions are a weighted sum over muscles, and the face
follows through its elastic basis. The default set (``tpscore/data/elastic_muscles.json``)
has 22 muscles and contraction presets for the six basic emotions.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from .._validation import as_positive, check_finite
from ..face.landmarks import validate_anchor
from ..spatial import MeshSurface
from .control_points import REFERENCE_FACIAL_UNIT_MM, anchored_in_frame, cast_onto_front, read_data_file
from .model import ElasticFace

__all__ = [
    "LinearMuscle",
    "SphincterMuscle",
    "MuscleModel",
    "load_muscles",
    "EMOTIONS",
]

#: The six basic emotions that have contraction presets in the default muscle set.
EMOTIONS = ("happiness", "sadness", "surprise", "fear", "anger", "disgust")


def _as_point(value, name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a point (x, y, z): {exc}") from None
    if array.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {array.shape}")
    check_finite(array[None], name)
    return array


@dataclass(frozen=True)
class LinearMuscle:
    """A linear muscle from a bony attachment to a skin attachment (mm, world frame).

    Parameters
    ----------
    name : str
    bone, skin : array_like, shape (3,)
        Bony and skin attachments (mm), distinct.
    angular_zone_deg : float, default 40
        Omega: points more than this angle off the muscle's line (seen from the bone)
        do not move.
    falloff_mm : float, optional
        Length F beyond the skin attachment over which the pull fades to zero (default
        half the muscle's length).
    """

    name: str
    bone: np.ndarray
    skin: np.ndarray
    angular_zone_deg: float = 40.0
    falloff_mm: float | None = None

    def __post_init__(self):
        bone = _as_point(self.bone, f"muscle {self.name!r} bone")
        skin = _as_point(self.skin, f"muscle {self.name!r} skin")
        length = float(np.linalg.norm(skin - bone))
        if length == 0:
            raise ValueError(f"muscle {self.name!r}: the bony and skin attachments coincide")
        zone = as_positive(self.angular_zone_deg, f"muscle {self.name!r} angular_zone_deg")
        if zone > 180:
            raise ValueError(f"muscle {self.name!r}: angular_zone_deg must be at most 180, got {zone}")
        falloff = 0.5 * length if self.falloff_mm is None else as_positive(self.falloff_mm, f"muscle {self.name!r} falloff_mm")
        object.__setattr__(self, "bone", bone)
        object.__setattr__(self, "skin", skin)
        object.__setattr__(self, "angular_zone_deg", zone)
        object.__setattr__(self, "falloff_mm", falloff)

    @property
    def length(self) -> float:
        """|skin - bone| (mm)."""
        return float(np.linalg.norm(self.skin - self.bone))

    def influence(self, points) -> np.ndarray:
        """Angular times radial fall-off A(p) R(p) at each point (m,), in [0, 1]."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        axis = (self.skin - self.bone) / self.length
        offset = points - self.bone
        r = np.linalg.norm(offset, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_angle = np.clip((offset @ axis) / r, -1.0, 1.0)
        angle = np.degrees(np.arccos(cos_angle))
        angular = np.where(angle < self.angular_zone_deg, np.cos(angle / self.angular_zone_deg * np.pi / 2), 0.0)
        length = self.length
        inner = np.cos((1.0 - r / length) * np.pi / 2)
        outer = np.cos(np.clip((r - length) / self.falloff_mm, 0.0, 1.0) * np.pi / 2)
        radial = np.where(r <= length, inner, outer)
        weight = angular * radial
        return np.where(r > 0, weight, 0.0)

    def unit_displacement(self, points) -> np.ndarray:
        """Displacement (m, 3) of each point per unit contraction: toward the bone, by
        length * A(p) R(p) (mm)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        toward = self.bone - points
        distance = np.linalg.norm(toward, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            direction = np.where(distance[:, None] > 0, toward / distance[:, None], 0.0)
        return direction * (self.length * self.influence(points))[:, None]


@dataclass(frozen=True)
class SphincterMuscle:
    """An elliptical ring of radial linear muscles (mm, world frame).

    Parameters
    ----------
    name : str
    centre : array_like, shape (3,)
        The bony attachment shared by every spoke (behind the ring).
    ring_centre : array_like, shape (3,)
        The centre of the ellipse the spokes end on (on the skin).
    axes : array_like, shape (2, 3)
        The ellipse's semi-axis vectors (mm), along the face's x and y.
    spokes : int, default 12
        Number of radial muscles.
    """

    name: str
    centre: np.ndarray
    ring_centre: np.ndarray
    axes: np.ndarray
    spokes: int = 12

    def __post_init__(self):
        centre = _as_point(self.centre, f"sphincter {self.name!r} centre")
        ring_centre = _as_point(self.ring_centre, f"sphincter {self.name!r} ring_centre")
        axes = np.asarray(self.axes, dtype=np.float64)
        if axes.shape != (2, 3) or not np.isfinite(axes).all() or (np.linalg.norm(axes, axis=1) == 0).any():
            raise ValueError(f"sphincter {self.name!r}: axes must be two finite non-zero vectors, shape (2, 3)")
        if int(self.spokes) < 3:
            raise ValueError(f"sphincter {self.name!r}: needs at least 3 spokes, got {self.spokes}")
        object.__setattr__(self, "centre", centre)
        object.__setattr__(self, "ring_centre", ring_centre)
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "spokes", int(self.spokes))

    @classmethod
    def fit(cls, name: str, points, frame_axes, *, depth_mm: float = 0.0, spokes: int = 12) -> "SphincterMuscle":
        """Fit the ring to control points: the ring is centred on their mean with
        semi-axes their largest extents along the frame's x and y; the spokes' common
        bony attachment is ``depth_mm`` behind the ring centre (along -z of the frame)."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3:
            raise ValueError(f"sphincter {name!r}: needs at least 3 control points to fit its ellipse")
        frame_axes = np.asarray(frame_axes, dtype=np.float64)
        mean = points.mean(axis=0)
        local = (points - mean) @ frame_axes.T
        a = float(np.abs(local[:, 0]).max())
        b = float(np.abs(local[:, 1]).max())
        if a == 0 or b == 0:
            raise ValueError(f"sphincter {name!r}: its control points are collinear in the face plane")
        return cls(name, mean - depth_mm * frame_axes[2], mean,
                   np.stack([a * frame_axes[0], b * frame_axes[1]]), spokes)

    def radial_muscles(self) -> list[LinearMuscle]:
        """The spokes, as linear muscles from the centre to the ellipse.

        Each spoke's angular zone is the larger angle (seen from the bone) to its two
        neighbours, so the zones overlap and no direction around the ring is left out.
        """
        angles = 2 * np.pi * np.arange(self.spokes) / self.spokes
        ends = self.ring_centre + np.cos(angles)[:, None] * self.axes[0] + np.sin(angles)[:, None] * self.axes[1]
        directions = ends - self.centre
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        gaps = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", directions, np.roll(directions, -1, axis=0)), -1, 1)))
        zones = np.maximum(gaps, np.roll(gaps, 1))
        return [LinearMuscle(f"{self.name}[{i}]", self.centre, end, angular_zone_deg=float(zone))
                for i, (end, zone) in enumerate(zip(ends, zones))]

    def unit_displacement(self, points) -> np.ndarray:
        """Summed displacement (m, 3) of the spokes per unit contraction (mm)."""
        return sum(m.unit_displacement(points) for m in self.radial_muscles())


def _bone_attachment(entry: Mapping, muscle: str, face: ElasticFace, surface: MeshSurface, scale: float) -> np.ndarray:
    """A linear muscle's bony attachment: its anchored place on the surface (or at the
    anchor's depth over a hole), moved ``depth_mm`` into the head."""
    frame = face.frame
    at, offset = validate_anchor(f"muscle {muscle!r} bone", entry["at"], entry.get("offset_mm", (0.0, 0.0)))
    local = anchored_in_frame(frame, face.landmarks, at, offset, scale, f"muscle {muscle!r} bone")
    hits = cast_onto_front(surface, frame, local[None, :2])
    on_surface = hits.points[0] if hits.hit[0] else frame.to_world(local[None])[0]
    return on_surface - float(entry.get("depth_mm", 0.0)) * scale * frame.axes[2]


def load_muscles(face: ElasticFace, path=None):
    """Build the muscles of a muscle file (default: the shipped set) on a face.

    Parameters
    ----------
    face : ElasticFace
        A face with landmarks and named control points matching the file's.
    path : path-like, optional
        A JSON muscle file in the format of ``tpscore/data/elastic_muscles.json``.

    Returns
    -------
    muscles : list of LinearMuscle and SphincterMuscle
    emotions : dict of name -> {muscle name: contraction}
    """
    if face.frame is None:
        raise ValueError("the face has no landmarks: muscles are placed relative to them")
    data = read_data_file(path, "data/elastic_muscles.json", "muscles", "muscles")
    frame = face.frame
    unit = as_positive(data.get("reference_facial_unit_mm", REFERENCE_FACIAL_UNIT_MM), "reference_facial_unit_mm")
    scale = frame.facial_unit / unit
    positions = dict(zip(face.control_point_names, face.control_point_positions))
    surface = MeshSurface(face.vertices, face.faces)

    def control_point(name: str, muscle: str) -> np.ndarray:
        if name not in positions:
            raise ValueError(f"muscle {muscle!r} attaches to control point {name!r}, which this face does not have")
        return positions[name]

    muscles = []
    for entry in data["muscles"]:
        try:
            name, kind = entry["name"], entry["type"]
            if kind == "linear":
                muscles.append(LinearMuscle(name, _bone_attachment(entry["bone"], name, face, surface, scale),
                                            control_point(entry["skin"], name),
                                            angular_zone_deg=float(entry.get("angular_zone_deg", 40.0)),
                                            falloff_mm=entry.get("falloff_mm")))
            elif kind == "sphincter":
                points = np.array([control_point(p, name) for p in entry["control_points"]])
                muscles.append(SphincterMuscle.fit(name, points, frame.axes,
                                                   depth_mm=float(entry.get("depth_mm", 0.0)) * scale,
                                                   spokes=int(entry.get("spokes", 12))))
            else:
                raise ValueError(f"muscle {name!r}: type must be 'linear' or 'sphincter', got {kind!r}")
        except KeyError as exc:
            raise ValueError(f"a muscle entry lacks the field {exc.args[0]!r}") from None
    names = [m.name for m in muscles]
    if len(set(names)) != len(names):
        raise ValueError("muscle names are not unique")
    emotions = {str(k): {str(m): float(c) for m, c in v.items()} for k, v in data.get("emotions", {}).items()}
    return muscles, emotions


class MuscleModel:
    """Muscles registered to an ElasticFace's control points.

    Parameters
    ----------
    face : ElasticFace
        The face whose control points the muscles move.
    muscles : sequence of LinearMuscle / SphincterMuscle, optional
        Default: the shipped set, placed on this face (:func:`load_muscles`).
    emotions : mapping name -> {muscle: contraction}, optional
        Contraction presets; default: the shipped six basic emotions (with the default
        muscles) or none.

    Examples
    --------
    >>> model = MuscleModel(face)                                   # doctest: +SKIP
    >>> smiling = model.deform({"zygomatic_major_left": 0.2})        # doctest: +SKIP
    >>> happy = model.emotion("happiness")                           # doctest: +SKIP
    """

    def __init__(self, face: ElasticFace, muscles: Sequence | None = None,
                 emotions: Mapping[str, Mapping[str, float]] | None = None):
        if not isinstance(face, ElasticFace):
            raise ValueError(f"face must be an ElasticFace, got {type(face).__name__}")
        if muscles is None:
            muscles, default_emotions = load_muscles(face)
            emotions = default_emotions if emotions is None else emotions
        muscles = list(muscles)
        if not muscles:
            raise ValueError("muscles is empty")
        for muscle in muscles:
            if not isinstance(muscle, (LinearMuscle, SphincterMuscle)):
                raise ValueError(f"muscles must be LinearMuscle or SphincterMuscle, got {type(muscle).__name__}")
        self._face = face
        self._muscles = tuple(muscles)
        self._names = tuple(m.name for m in muscles)
        if len(set(self._names)) != len(self._names):
            raise ValueError("muscle names are not unique")
        points = face.control_point_positions
        # (muscles, k, 3): the registration. Contraction -> displacement is linear, so
        # any mix of contractions is one tensor contraction of this.
        self._unit = np.stack([m.unit_displacement(points) for m in muscles])
        self._unit.setflags(write=False)
        self._emotions = {}
        for name, recipe in (emotions or {}).items():
            self._emotions[str(name)] = self._vector(recipe, f"emotion {name!r}")

    @property
    def face(self) -> ElasticFace:
        return self._face

    @property
    def muscle_names(self) -> tuple[str, ...]:
        return self._names

    @property
    def muscles(self) -> tuple:
        return self._muscles

    @property
    def emotions(self) -> tuple[str, ...]:
        return tuple(self._emotions)

    def _vector(self, contractions, name: str = "contractions") -> np.ndarray:
        if isinstance(contractions, Mapping):
            vector = np.zeros(len(self._names))
            for muscle, value in contractions.items():
                if muscle not in self._names:
                    raise ValueError(f"{name}: unknown muscle {muscle!r}; known: {', '.join(self._names)}")
                vector[self._names.index(muscle)] = float(value)
        else:
            try:
                vector = np.asarray(contractions, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{name} must be numeric: {exc}") from None
            if vector.shape != (len(self._names),):
                raise ValueError(f"{name} must have shape ({len(self._names)},) (one per muscle) or be a "
                                 f"muscle -> contraction mapping, got {np.shape(contractions)}")
        check_finite(vector, name)
        return vector

    def displacements(self, contractions) -> np.ndarray:
        """Control-point displacements (k, 3), mm, summed over muscles.

        Parameters
        ----------
        contractions : array_like (muscles,) or mapping muscle -> contraction
            Fraction of each muscle's length it shortens by (0 = relaxed).
        """
        return np.tensordot(self._vector(contractions), self._unit, axes=1)

    def deform(self, contractions) -> np.ndarray:
        """The face's vertices (n, 3) with the muscles contracted, mm."""
        return self._face.deform(self.displacements(contractions))

    def emotion_contractions(self, name: str) -> dict[str, float]:
        if name not in self._emotions:
            raise ValueError(f"unknown emotion {name!r}; known: {', '.join(self._emotions)}")
        return {m: float(c) for m, c in zip(self._names, self._emotions[name]) if c}

    def emotion(self, name: str, magnitude: float = 1.0) -> np.ndarray:
        """Vertices (n, 3) of an emotion preset at a magnitude (scales every contraction)."""
        if name not in self._emotions:
            raise ValueError(f"unknown emotion {name!r}; known: {', '.join(self._emotions)}")
        return self.deform(self._emotions[name] * float(magnitude))
