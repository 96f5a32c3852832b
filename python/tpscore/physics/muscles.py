"""Muscles of the physical skin: where they attach, what they pull, and how hard.

A **linear muscle** runs from an attachment on the skull (or the mandible) to an
insertion in the skin. Both are stored as a triangle of the head mesh and
barycentric coordinates on it (:class:`SurfacePoint`): the skull shares the skin's
triangles, so a muscle defined on the template survives any fit of the template
unchanged. It pulls the hypodermal particles within its zone of influence toward
the attachment, each with a weight from vector-muscle fall-offs (after Waters 1987):
an angular cosine over the cone of half-angle ``angular_zone_deg`` about the line from
the attachment to the insertion, times a radial cosine that is 1 at the insertion's
distance from the attachment and fades to 0 over ``falloff_mm`` nearer and farther.
Waters' radial fall-off spreads the pull over the whole length of the muscle; a
mimic muscle inserts into the skin around its insertion, and pulling the tissue next
to the attachment as hard folds it over there.

A **sphincter muscle** is an ellipse: an epicentre and two semi-axis vectors. It pulls
particles toward the epicentre within the ellipse's plane, with a weight that rises
from the centre to the ring (sin(pi/2 rho), rho the elliptic radius) and fades over
``falloff`` ellipse radii outside it.

Both act only on the particles of their ``regions``. Each muscle's weights are
normalised to sum to 1, so ``max_force_n`` is the total force it exerts at contraction
1, whatever the mesh resolution.

:func:`place_muscles` builds muscles from landmark-relative definitions (the shipped
set in ``tpscore/data/skin_muscles.json``): a place is a weighted mean of named
landmarks plus an (x, y) offset in the face frame, projected onto the skin or the
skull along the frame's -z.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Mapping

import numpy as np

from .._validation import as_positive
from ..face.landmarks import anchor_point, landmark_index, validate_anchor
from ..face.normalise import face_frame
from ..spatial import MeshSurface

__all__ = [
    "SurfacePoint",
    "SkinLinearMuscle",
    "SkinSphincterMuscle",
    "place_muscles",
    "read_muscle_file",
    "muscle_weights",
    "BONES",
]

#: Bones a muscle's fixed end can sit on.
BONES = ("skull", "mandible")


@dataclass(frozen=True)
class SurfacePoint:
    """A point on a mesh: a triangle index and barycentric weights on its corners."""

    face: int
    barycentric: tuple

    def __post_init__(self):
        face = int(self.face)
        weights = np.asarray(self.barycentric, dtype=np.float64).reshape(-1)
        if face < 0:
            raise ValueError(f"face must be a triangle index >= 0, got {self.face!r}")
        if weights.shape != (3,) or not np.isfinite(weights).all() or np.any(weights < -1e-9) \
                or abs(weights.sum() - 1.0) > 1e-6:
            raise ValueError(f"barycentric must be three weights >= 0 summing to 1, got {self.barycentric!r}")
        object.__setattr__(self, "face", face)
        object.__setattr__(self, "barycentric", tuple(float(w) for w in weights))

    def position(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The point (3,) on the mesh (vertices, faces)."""
        if self.face >= len(faces):
            raise ValueError(f"surface point on face {self.face}, but the mesh has {len(faces)} faces")
        return np.asarray(self.barycentric) @ vertices[faces[self.face]]


def _regions(value, name):
    regions = tuple(str(r) for r in value)
    if not regions:
        raise ValueError(f"muscle {name!r}: regions is empty; a muscle must act on at least one region")
    return regions


@dataclass(frozen=True)
class SkinLinearMuscle:
    """A linear muscle from a bony attachment to a skin insertion.

    Parameters
    ----------
    name : str
    attachment : SurfacePoint
        On the skull mesh (the head's triangles, skull vertices).
    insertion : SurfacePoint
        On the skin.
    regions : tuple of str
        Region names whose particles it may pull.
    max_force_n : float
        Total force at contraction 1 (newtons), > 0.
    bone : {"skull", "mandible"}
        What the attachment moves with.
    angular_zone_deg : float
        Half-angle of the cone of influence about the muscle's line, (0, 90].
    falloff_mm : float
        Over what distance from the insertion (nearer to or farther from the
        attachment) the pull fades to zero, > 0.
    """

    name: str
    attachment: SurfacePoint
    insertion: SurfacePoint
    regions: tuple
    max_force_n: float
    bone: str = "skull"
    angular_zone_deg: float = 30.0
    falloff_mm: float = 12.0

    def __post_init__(self):
        if not isinstance(self.attachment, SurfacePoint) or not isinstance(self.insertion, SurfacePoint):
            raise ValueError(f"muscle {self.name!r}: attachment and insertion must be SurfacePoint")
        if self.bone not in BONES:
            raise ValueError(f"muscle {self.name!r}: bone must be one of {BONES}, got {self.bone!r}")
        object.__setattr__(self, "regions", _regions(self.regions, self.name))
        object.__setattr__(self, "max_force_n", as_positive(self.max_force_n, f"muscle {self.name!r} max_force_n"))
        zone = as_positive(self.angular_zone_deg, f"muscle {self.name!r} angular_zone_deg")
        if zone > 90:
            raise ValueError(f"muscle {self.name!r}: angular_zone_deg must be at most 90, got {zone}")
        object.__setattr__(self, "angular_zone_deg", zone)
        object.__setattr__(self, "falloff_mm", as_positive(self.falloff_mm, f"muscle {self.name!r} falloff_mm"))

    kind = "linear"


@dataclass(frozen=True)
class SkinSphincterMuscle:
    """An elliptical sphincter muscle.

    Parameters
    ----------
    name : str
    epicentre : (3,) array_like
        The ellipse's centre (mm).
    axes : (2, 3) array_like
        The two semi-axis vectors (mm), not parallel; the second is made orthogonal to
        the first.
    regions : tuple of str
    max_force_n : float
        Total force at contraction 1 (newtons), > 0.
    falloff : float
        Outside the ellipse the pull fades to zero over this many ellipse radii, > 0.
    axis_landmarks : tuple of two (name, name) pairs, optional
        Landmarks whose distances the semi-axes scale with when the head is fitted to
        another face (e.g. the mouth corners for the horizontal axis).
    bone : {"skull", "mandible"}
    """

    name: str
    epicentre: np.ndarray
    axes: np.ndarray
    regions: tuple
    max_force_n: float
    falloff: float = 0.5
    axis_landmarks: tuple = ()
    bone: str = "skull"

    def __post_init__(self):
        centre = np.asarray(self.epicentre, dtype=np.float64).reshape(-1)
        if centre.shape != (3,) or not np.isfinite(centre).all():
            raise ValueError(f"sphincter {self.name!r}: epicentre must be a finite point (3,)")
        axes = np.asarray(self.axes, dtype=np.float64)
        if axes.shape != (2, 3) or not np.isfinite(axes).all():
            raise ValueError(f"sphincter {self.name!r}: axes must be two finite vectors, shape (2, 3)")
        lengths = np.linalg.norm(axes, axis=1)
        if np.any(lengths <= 0):
            raise ValueError(f"sphincter {self.name!r}: a semi-axis has zero length")
        a = axes[0] / lengths[0]
        b = axes[1] - (axes[1] @ a) * a
        if np.linalg.norm(b) < 1e-6 * lengths[1]:
            raise ValueError(f"sphincter {self.name!r}: the two axes are parallel")
        axes = np.stack([axes[0], b / np.linalg.norm(b) * lengths[1]])
        if self.bone not in BONES:
            raise ValueError(f"sphincter {self.name!r}: bone must be one of {BONES}, got {self.bone!r}")
        pairs = tuple(tuple(str(n) for n in pair) for pair in self.axis_landmarks)
        if pairs and (len(pairs) != 2 or any(len(p) != 2 for p in pairs)):
            raise ValueError(f"sphincter {self.name!r}: axis_landmarks must be two pairs of landmark names")
        for pair in pairs:
            for landmark in pair:
                landmark_index(landmark)
        centre.setflags(write=False)
        axes.setflags(write=False)
        object.__setattr__(self, "epicentre", centre)
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "axis_landmarks", pairs)
        object.__setattr__(self, "regions", _regions(self.regions, self.name))
        object.__setattr__(self, "max_force_n", as_positive(self.max_force_n, f"sphincter {self.name!r} max_force_n"))
        object.__setattr__(self, "falloff", as_positive(self.falloff, f"sphincter {self.name!r} falloff"))

    kind = "sphincter"


def muscle_weights(muscle, points: np.ndarray, allowed: np.ndarray, *, attachment=None,
                   insertion=None) -> tuple[np.ndarray, np.ndarray]:
    """The particles a muscle pulls and their weights (summing to 1).

    Parameters
    ----------
    muscle : SkinLinearMuscle or SkinSphincterMuscle
    points : (n, 3) ndarray
        Rest positions of the candidate particles (the hypodermal layer).
    allowed : (n,) bool ndarray
        The particles in the muscle's regions.
    attachment, insertion : (3,) ndarray
        A linear muscle's attachment and its insertion at the particles' depth.

    Returns
    -------
    indices : (e,) int64 into ``points``; weights : (e,) float64.

    Raises
    ------
    ValueError
        If no allowed particle lies in the muscle's zone.
    """
    if isinstance(muscle, SkinLinearMuscle):
        axis = insertion - attachment
        length = float(np.linalg.norm(axis))
        if length <= 0:
            raise ValueError(f"muscle {muscle.name!r}: attachment and insertion coincide")
        offset = points - attachment
        r = np.linalg.norm(offset, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_angle = np.clip(offset @ axis / (r * length), -1.0, 1.0)
        angle = np.degrees(np.arccos(cos_angle))
        zone = muscle.angular_zone_deg
        angular = np.where(angle < zone, np.cos(angle / zone * np.pi / 2), 0.0)
        radial = np.cos(np.clip(np.abs(r - length) / muscle.falloff_mm, 0.0, 1.0) * np.pi / 2)
        weight = angular * radial
    else:
        a, b = muscle.axes
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
        offset = points - muscle.epicentre
        rho = np.hypot(offset @ a / la**2, offset @ b / lb**2)
        inside = np.sin(np.clip(rho, 0.0, 1.0) * np.pi / 2)
        outside = np.cos(np.clip((rho - 1.0) / muscle.falloff, 0.0, 1.0) * np.pi / 2)
        weight = np.where(rho <= 1.0, inside, outside)
    weight = np.where(allowed & np.isfinite(weight), weight, 0.0)
    indices = np.flatnonzero(weight > 1e-6)
    total = weight[indices].sum()
    if len(indices) == 0 or total <= 0:
        raise ValueError(f"muscle {muscle.name!r} reaches no particle of its regions {muscle.regions}")
    return indices.astype(np.int64), weight[indices] / total


# ------------------------------------------------------------------ placing muscles
def read_muscle_file(path=None) -> dict:
    """The JSON muscle set (default: the shipped ``tpscore/data/skin_muscles.json``)."""
    try:
        if path is None:
            text = resources.files("tpscore").joinpath("data/skin_muscles.json").read_text(encoding="utf-8")
        else:
            text = Path(path).read_text(encoding="utf-8")
        data = json.loads(text)
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path or 'the default skin muscles'}: cannot read a muscle set: {exc}") from None
    if not isinstance(data, Mapping) or not isinstance(data.get("muscles"), list):
        raise ValueError(f"{path or 'the default skin muscles'}: expected an object with a 'muscles' list")
    return data


def _place(spec, landmarks, frame, owner):
    """Frame (x, y) of a landmark-relative place: weighted landmarks plus offset_mm."""
    if not isinstance(spec, Mapping) or "at" not in spec:
        raise ValueError(f"{owner}: a place needs 'at' (landmark weights) and optionally 'offset_mm'")
    at, offset = validate_anchor(owner, spec["at"], spec.get("offset_mm", (0.0, 0.0)))
    local = frame.to_frame(anchor_point(landmarks, at, owner)[None])[0]
    local[:2] += offset
    return local


# A place whose line misses the mesh by more than this (mm, in the face plane) is an
# error; nearer, it goes to the mesh's closest point (a coarse mesh's jagged outline).
_OFF_MESH_MM = 6.0


def _project(surface, frame, local, owner):
    """The front-most point of `surface` on the frame's z line through local (x, y); for
    a line that just misses the mesh's outline, the mesh point closest to it."""
    vertices = frame.to_frame(surface.vertices)
    top = float(vertices[:, 2].max()) + 10.0
    origin = frame.to_world(np.array([[local[0], local[1], top]]))
    hits = surface.intersect_rays(origin, -frame.axes[2][None])
    if hits.hit[0]:
        return SurfacePoint(int(hits.triangles[0]), tuple(hits.barycentric[0]))
    gap = np.hypot(vertices[:, 0] - local[0], vertices[:, 1] - local[1])
    nearest = int(np.argmin(gap))
    if gap[nearest] > _OFF_MESH_MM:
        raise ValueError(f"{owner}: the place ({local[0]:.1f}, {local[1]:.1f}) mm in the face frame is "
                         "off the head mesh")
    guess = frame.to_world(np.array([[local[0], local[1], vertices[nearest, 2]]]))
    closest = surface.closest_point(guess)
    return SurfacePoint(int(closest.triangles[0]), tuple(closest.barycentric[0]))


def place_muscles(vertices, faces, skull_vertices, landmarks, definitions=None) -> tuple:
    """Muscles from landmark-relative definitions, placed on a head.

    Parameters
    ----------
    vertices, faces : the skin mesh; skull_vertices : (n, 3), the skull (same triangles).
    landmarks : (22, 3) ndarray
        The head's landmarks (the face frame comes from them).
    definitions : dict, optional
        A parsed muscle file (default: the shipped set).

    Returns
    -------
    tuple of SkinLinearMuscle and SkinSphincterMuscle
    """
    data = read_muscle_file() if definitions is None else definitions
    frame = face_frame(landmarks)
    skin = MeshSurface(vertices, faces)
    skull = MeshSurface(skull_vertices, faces)
    muscles = []
    for entry in data["muscles"]:
        try:
            name, kind = str(entry["name"]), entry["type"]
            regions = entry["regions"]
            force = entry["max_force_n"]
            bone = entry.get("bone", "skull")
            if kind == "linear":
                attachment = _project(skull, frame, _place(entry["attachment"], landmarks, frame,
                                                           f"muscle {name!r} attachment"), f"muscle {name!r} attachment")
                insertion = _project(skin, frame, _place(entry["insertion"], landmarks, frame,
                                                         f"muscle {name!r} insertion"), f"muscle {name!r} insertion")
                muscles.append(SkinLinearMuscle(name, attachment, insertion, regions, force, bone,
                                            entry.get("angular_zone_deg", 30.0), entry.get("falloff_mm", 12.0)))
            elif kind == "sphincter":
                centre_point = _project(skin, frame, _place(entry["epicentre"], landmarks, frame,
                                                            f"sphincter {name!r} epicentre"), f"sphincter {name!r}")
                centre = centre_point.position(skin.vertices, skin.faces)
                pairs = entry["axis_landmarks"]
                margins = entry.get("axis_margin_mm", (0.0, 0.0))
                axes = []
                for pair, margin, direction in zip(pairs, margins, frame.axes[:2]):
                    ends = [anchor_point(landmarks, {p: 1.0}, f"sphincter {name!r} axes") for p in pair]
                    axes.append((0.5 * np.linalg.norm(ends[0] - ends[1]) + float(margin)) * direction)
                muscles.append(SkinSphincterMuscle(name, centre, np.stack(axes), regions, force,
                                               entry.get("falloff", 0.5), tuple(tuple(p) for p in pairs), bone))
            else:
                raise ValueError(f"muscle {name!r}: type must be 'linear' or 'sphincter', got {kind!r}")
        except KeyError as exc:
            raise ValueError(f"a skin muscle entry lacks the field {exc.args[0]!r}") from None
    names = [m.name for m in muscles]
    if len(set(names)) != len(names):
        raise ValueError("muscle names are not unique")
    return tuple(muscles)
