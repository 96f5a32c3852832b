"""Demo faces: Bosphorus-format scans of real face shapes, with a skin of tpscore's own.

The shapes come from a compact extract of the ICT FaceKit face model that ships with
tpscore for the demo only (``tpscore/data/ict_demo_faces.npz``, MIT licence, text in
``tpscore/data/ict_facekit_LICENSE.txt``; written by ``tools/make_demo_faces.py``): the face
area a frontal scanner sees, four people, and the expression shapes of the action
units tpscore implements (AU1 browInnerUp, AU2 browOuterUp, AU4 browDown, AU12
mouthSmile, AU14 mouthDimple, AU15 mouthFrown, AU17 mouthShrugLower, AU20
mouthStretch; ``_L`` is the subject's left). The expression-transfer method never
reads this data: it is what the demo scans are made of, and the truth they are scored
against.

:func:`make_demo_scan` poses a person's mesh, wearing an expression or not, in front of
an orthographic scanner looking down -z and writes what it sees as a depth grid (a
:class:`~tpscore.face.io.BntScan`), a colour image the grid's u,v point into, and the 22
Bosphorus landmarks read off the mesh. The skin is procedural (mottling, a few spots,
brows, a lash line, lips, a blush) and glued to the skin: its colour is a function of
where a surface point sits on the generic neutral face, so an expression carries the
pattern with the skin as a photograph's texture moves. Light and exposure are fixed in
the scanner's frame.

Units are mm; the frame is tpscore's (+x the subject's left, +y up, the face looks
toward +z).
"""
from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..face.io import BntScan, write_bnt, write_lm3, write_png
from ..mesh import vertex_normals
from ..raster import rasterise
from ..spatial import KDTree, MeshSurface

__all__ = ["DemoFaceModel", "DemoScan", "load_demo_model", "make_demo_scan", "DEMO_AUS"]

#: The action units the extract holds expression shapes for.
DEMO_AUS: tuple[str, ...] = ("1", "2", "4", "5", "12", "14", "15", "17", "20", "26", "43")

_DATA_FILE = "ict_demo_faces.npz"

# A frontal structured-light scanner loses the surface it sees at a grazing angle;
# 80 degrees is where the benchmark's scans lose it too.
MAX_VIEW_ANGLE_DEG = 80.0
GRID_MARGIN_PIXELS = 2
BACKGROUND_GREY = 0.1
# The scanner's lamp: above and to the viewer's right of the camera, jittered a few
# degrees per scan, so each scan's shading differs a little as real sessions do.
LIGHT_DIRECTION = (0.25, 0.4, 1.0)
LIGHT_JITTER = 0.05
AMBIENT = 0.38
SPECULAR = 0.06
SHININESS = 30.0
SENSOR_NOISE = 1.5 / 255.0

_AU_KEY = re.compile(r"^(?:au)?\s*(\d+)\s*([lr]?)$", re.IGNORECASE)


# --------------------------------------------------------------------------- the model

@dataclass(frozen=True, eq=False)
class DemoFaceModel:
    """The shipped extract: a generic neutral face, people and expression shapes.

    Attributes
    ----------
    neutral : (n, 3) float64
        The generic neutral face (mm); also the skin's rest coordinates.
    faces : (m, 3) int64
        Triangles, counter-clockwise seen from outside (normals toward +z in front).
    people : (k, n, 3) float64
        Each person's neutral face as a delta from ``neutral``.
    shapes : dict str -> (n, 3) float64
        ICT expression shapes (deltas at weight 1), by name.
    au_shapes : dict str -> tuple of str
        AU number -> its shapes (``_L`` then ``_R`` where the AU has two).
    bosphorus_index : (22,) int64
        Vertex of each Bosphorus landmark.
    landmarks68 : (68,) int64
        Vertex of each iBUG-68 landmark, -1 where it lies outside the scanned area.
    source : str
        Where the data came from, and its licence.
    """

    neutral: np.ndarray
    faces: np.ndarray
    people: np.ndarray
    shapes: dict
    au_shapes: dict
    bosphorus_index: np.ndarray
    landmarks68: np.ndarray
    source: str

    @property
    def n_people(self) -> int:
        return len(self.people)

    def person(self, person: int) -> np.ndarray:
        """(n, 3) the person's neutral face (mm)."""
        if isinstance(person, bool) or not isinstance(person, (int, np.integer)) \
                or not 0 <= person < self.n_people:
            raise ValueError(f"person must be an integer in [0, {self.n_people}), got {person!r}")
        return self.neutral + self.people[person]

    def expression_delta(self, expression) -> np.ndarray:
        """(n, 3) displacement of an expression: a dict of AU weights such as
        ``{"12": 1.0, "4L": 0.5}``, or one AU key (``"12"``); None or {} is neutral."""
        delta = np.zeros_like(self.neutral)
        for shape, weight in self._shape_weights(expression).items():
            delta += weight * self.shapes[shape]
        return delta

    def _shape_weights(self, expression) -> dict:
        if expression is None:
            return {}
        if isinstance(expression, str):
            expression = {expression: 1.0}
        if not isinstance(expression, dict):
            raise ValueError(f"expression must be None, an AU key or a dict of AU weights, got {expression!r}")
        weights: dict[str, float] = {}
        for key, value in expression.items():
            match = _AU_KEY.match(str(key).strip())
            if not match or match.group(1) not in self.au_shapes:
                raise ValueError(f"expression: unknown AU {key!r}; the demo faces have AUs "
                                 f"{', '.join(self.au_shapes)} (optionally L or R)")
            try:
                weight = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"expression: the weight of {key!r} must be a number, got {value!r}") from None
            if not np.isfinite(weight):
                raise ValueError(f"expression: the weight of {key!r} must be finite, got {value!r}")
            au, side = match.group(1), match.group(2).upper()
            shapes = self.au_shapes[au]
            if side:
                if len(shapes) == 1:
                    raise ValueError(f"expression: AU{au} has one shape for both sides; {key!r} cannot be one-sided")
                shapes = tuple(s for s in shapes if s.endswith("_" + side))
            for shape in shapes:
                weights[shape] = weights.get(shape, 0.0) + weight
        return weights


@lru_cache(maxsize=1)
def load_demo_model() -> DemoFaceModel:
    """The demo-face extract shipped in ``tpscore/data`` (read once, then cached)."""
    with resources.files("tpscore").joinpath("data", _DATA_FILE).open("rb") as handle:
        with np.load(handle) as data:
            quantum = float(data["quantum_mm"])
            neutral = data["neutral"].astype(np.float64) * quantum
            expressions = data["expressions"].astype(np.float64) * quantum
            names = [str(n) for n in data["expression_names"]]
            au_shapes = {str(au): tuple(str(s).split("+"))
                         for au, s in zip(data["au_names"], data["au_shapes"])}
            model = DemoFaceModel(
                neutral=neutral,
                faces=data["faces"].astype(np.int64),
                people=data["people"].astype(np.float64) * quantum,
                shapes=dict(zip(names, expressions)),
                au_shapes=au_shapes,
                bosphorus_index=data["bosphorus_index"].astype(np.int64),
                landmarks68=data["landmarks68"].astype(np.int64),
                source=str(data["source"]),
            )
    for array in (model.neutral, model.people, *model.shapes.values()):
        array.flags.writeable = False
    return model


# --------------------------------------------------------------------------- the skin

class _ValueNoise:
    """Smooth random values in 3D: random numbers at the nodes of a lattice of one
    wavelength's spacing, blended across each cell with a smoothstep; about unit
    amplitude. ``stretch`` shortens the wavelength along an axis (hair runs along a
    brow, so its streaks are short across it)."""

    _TABLE = 4096

    def __init__(self, rng, wavelength_mm: float, stretch=(1.0, 1.0, 1.0)):
        self.scale = np.asarray(stretch, dtype=np.float64) / wavelength_mm
        self.offset = rng.uniform(0.0, 1000.0, 3)
        self.table = rng.uniform(-1.0, 1.0, self._TABLE)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = points * self.scale + self.offset
        cell = np.floor(p).astype(np.int64)
        t = p - cell
        t = t * t * (3.0 - 2.0 * t)
        # large primes mix the three node indices into one table slot
        steps = (73856093, 19349663, 83492791)
        hashed = [cell[:, axis] * prime for axis, prime in enumerate(steps)]
        total = np.zeros(len(p))
        for dx in (0, 1):
            wx = t[:, 0] if dx else 1.0 - t[:, 0]
            hx = hashed[0] + dx * steps[0]
            for dy in (0, 1):
                wxy = wx * (t[:, 1] if dy else 1.0 - t[:, 1])
                hxy = hx ^ (hashed[1] + dy * steps[1])
                for dz in (0, 1):
                    slot = (hxy ^ (hashed[2] + dz * steps[2])) & (self._TABLE - 1)
                    total += wxy * (t[:, 2] if dz else 1.0 - t[:, 2]) * self.table[slot]
        return total


def _distance_to_polyline(xy: np.ndarray, polyline: np.ndarray, reach: float = np.inf):
    """Distance from (n, 2) points to a 2D polyline, and where along it (0 at the first
    node, 1 at the last) the nearest point lies; points farther than `reach` from the
    polyline's bounding box get inf (and are not worked on: most of a face is far from
    a brow or the lips)."""
    best = np.full(len(xy), np.inf)
    along = np.zeros(len(xy))
    low, high = polyline.min(axis=0) - reach, polyline.max(axis=0) + reach
    near = np.flatnonzero(((xy >= low) & (xy <= high)).all(axis=1))
    points = xy[near]
    lengths = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    start = np.concatenate([[0.0], np.cumsum(lengths)]) / lengths.sum()
    near_best = np.full(len(near), np.inf)
    near_along = np.zeros(len(near))
    for k in range(len(polyline) - 1):
        a, b = polyline[k], polyline[k + 1]
        t = np.clip(((points - a) @ (b - a)) / max((b - a) @ (b - a), 1e-12), 0.0, 1.0)
        d = np.hypot(*(points - (a + t[:, None] * (b - a))).T)
        closer = d < near_best
        near_best[closer] = d[closer]
        near_along[closer] = start[k] + t[closer] * (start[k + 1] - start[k])
    best[near], along[near] = near_best, near_along
    return best, along


def _inside(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd test of (n, 2) points against a closed polygon."""
    inside = np.zeros(len(xy), dtype=bool)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        if a[1] == b[1]:
            continue
        crosses = (a[1] > xy[:, 1]) != (b[1] > xy[:, 1])
        x_cross = a[0] + (xy[:, 1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside ^= crosses & (xy[:, 0] < x_cross)
    return inside


def _smoothstep(edge0, edge1, x):
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


# Skin tones (linear-ish RGB albedo) from light to dark, and matching hair: one per
# person, so the demo's people do not all look alike.
_SKIN_TONES = np.array([[0.80, 0.62, 0.53], [0.62, 0.45, 0.34], [0.86, 0.70, 0.60], [0.45, 0.31, 0.23]])
_HAIR = np.array([[0.23, 0.15, 0.10], [0.10, 0.07, 0.05], [0.42, 0.30, 0.20], [0.06, 0.05, 0.04]])


class _Skin:
    """One person's skin albedo as a function of rest position (the generic face's mm)."""

    def __init__(self, model: DemoFaceModel, person: int):
        rng = np.random.default_rng([0x5C1, person])
        self.tone = _SKIN_TONES[person % len(_SKIN_TONES)] * rng.uniform(0.96, 1.04, 3)
        self.hair = _HAIR[person % len(_HAIR)]
        fine = rng.uniform(0.4, 1.0)   # how clearly the fine pattern shows, per person
        self.mottling = [(_ValueNoise(rng, 16.0), 0.07), (_ValueNoise(rng, 5.0), 0.05 * fine),
                         (_ValueNoise(rng, 1.6), 0.05 * fine), (_ValueNoise(rng, 0.7), 0.04 * fine)]
        self.redness = _ValueNoise(rng, 12.0)
        self.streaks = _ValueNoise(rng, 1.2, stretch=(0.25, 3.0, 1.0))
        rest = model.neutral
        index = model.landmarks68

        def points(indices):
            chosen = index[list(indices)]
            return rest[chosen[chosen >= 0], :2]

        # iBUG-68: 17-21 and 22-26 the brows (outer to inner, inner to outer), 36-47 the
        # eyes, 48-59 the outer lip line
        self.brows = [points(range(21, 16, -1)), points(range(22, 27))]   # inner to outer
        self.eyes = [points(range(36, 42)), points(range(42, 48))]
        self.lips = points(range(48, 60))
        eye_centres = [e.mean(axis=0) for e in self.eyes]
        self.cheeks = [c + np.array([np.sign(c[0]) * 6.0, -30.0]) for c in eye_centres]
        n_spots = rng.poisson(rng.uniform(5.0, 40.0))
        valid = np.unique(model.faces)
        centre = rest[model.bosphorus_index[13], :2]
        near = valid[np.linalg.norm(rest[valid, :2] - centre, axis=1) < 85.0]
        self.spots = rest[rng.choice(near, n_spots), :2] if n_spots else np.zeros((0, 2))
        self.spot_radius = rng.uniform(0.3, 1.0, n_spots)
        self.spot_darkness = rng.uniform(0.1, 0.35, n_spots)

    def albedo(self, rest: np.ndarray) -> np.ndarray:
        """(n, 3) RGB in [0, 1] at (n, 3) rest positions."""
        xy = rest[:, :2]
        shade = 1.0 + sum(amplitude * noise(rest) for noise, amplitude in self.mottling)
        if len(self.spots):
            planar = np.column_stack([xy, np.zeros(len(xy))])
            distance, nearest = KDTree(np.column_stack([self.spots, np.zeros(len(self.spots))])).query(
                planar, k=min(3, len(self.spots)), distance_upper_bound=4.0)
            distance, nearest = distance.reshape(len(xy), -1), nearest.reshape(len(xy), -1)
            found = np.isfinite(distance)
            index = np.where(found, nearest, 0)
            shade -= np.where(found, self.spot_darkness[index]
                              * np.exp(-0.5 * (np.where(found, distance, 0.0) / self.spot_radius[index]) ** 2),
                              0.0).sum(axis=1)
        rgb = self.tone * shade[:, None]
        # blood shows through: redder in patches and over the cheeks
        blush = sum(np.exp(-0.5 * ((xy - c) ** 2).sum(axis=1) / 15.0 ** 2) for c in self.cheeks)
        red = 0.035 * self.redness(rest) + 0.06 * blush
        rgb *= np.column_stack([1.0 + red, 1.0 - 0.5 * red, 1.0 - 0.5 * red])
        # lips: a muted rose, with a border about a millimetre wide
        lip_edge, _ = _distance_to_polyline(xy, np.vstack([self.lips, self.lips[:1]]), reach=2.0)
        inside = _inside(xy, self.lips)
        lip = np.where(inside, 0.5 + 0.5 * _smoothstep(0.0, 1.2, lip_edge),
                       0.5 * (1.0 - _smoothstep(0.0, 0.8, lip_edge)))
        lip_colour = self.tone * np.array([0.92, 0.62, 0.62]) * shade[:, None]
        rgb = rgb * (1.0 - 0.8 * lip[:, None]) + lip_colour * (0.8 * lip[:, None])
        # lashes along the rim of each eye opening
        for eye in self.eyes:
            d, _ = _distance_to_polyline(xy, np.vstack([eye, eye[:1]]), reach=4.0)
            rgb *= (1.0 - 0.5 * np.exp(-0.5 * (d / 0.8) ** 2))[:, None]
        # brows: hairs, dense at the inner end and thinning toward the tail
        for brow in self.brows:
            d, along = _distance_to_polyline(xy, brow, reach=8.0)
            near = np.isfinite(d)
            half_height = 4.0 - 2.2 * along[near]
            density = (1.0 - _smoothstep(0.5, 1.15, d[near] / half_height)) * (0.9 - 0.3 * along[near])
            hairs = np.clip(0.7 + 0.5 * self.streaks(rest[near]), 0.0, 1.0)
            cover = (density * hairs)[:, None]
            rgb[near] = rgb[near] * (1.0 - cover) + self.hair[None] * cover
        return np.clip(rgb, 0.0, 1.0)


# --------------------------------------------------------------------------- scans

@dataclass(frozen=True, eq=False)
class DemoScan:
    """A demo scan and its ground truth.

    Attributes
    ----------
    scan : BntScan
        The depth grid (0.7 mm spacing by default), NaN at background and holes, with
        u,v into ``image``.
    image : (h, w, 3) uint8
        The colour image (``texture_scale`` pixels per grid spacing).
    landmarks : (22, 3) float64
        The Bosphorus landmarks: their mesh vertices, plus annotation noise.
    vertices : (n, 3) float64
        The clean posed mesh that was scanned (mm, scan frame).
    neutral_vertices : (n, 3) float64
        The same person's neutral mesh in the same pose.
    faces : (m, 3) int64
    pose : (4, 4) float64
        Model frame -> scan frame.
    person : int
    expression : dict
        AU weights ({} for neutral).
    """

    scan: BntScan
    image: np.ndarray
    landmarks: np.ndarray
    vertices: np.ndarray
    neutral_vertices: np.ndarray
    faces: np.ndarray
    pose: np.ndarray
    person: int
    expression: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        label = "+".join(f"AU{k}" + (f"x{v:g}" if v != 1 else "") for k, v in self.expression.items()) \
            or "neutral"
        return (f"DemoScan(person {self.person}, {label}, {self.scan.nrows}x{self.scan.ncols} grid, "
                f"{self.scan.n_valid} valid points, image {self.image.shape[1]}x{self.image.shape[0]})")

    def write(self, folder, stem: str) -> Path:
        """Write ``stem.bnt``, ``stem.png`` (the image it names) and ``stem.lm3`` into
        `folder` (which must exist); returns the ``.bnt`` path."""
        folder = Path(folder)
        # the .bnt stores the image's name in ASCII: check it before anything is written
        if not stem or not all(32 < ord(c) < 127 for c in stem) or "/" in stem or "\\" in stem:
            raise ValueError(f"stem must be a file name of printable ASCII without spaces, got {stem!r}")
        scan = BntScan(self.scan.nrows, self.scan.ncols, self.scan.zmin, f"{stem}.png",
                       self.scan.points, self.scan.uv, self.scan.valid)
        write_png(folder / f"{stem}.png", self.image)
        write_lm3(folder / f"{stem}.lm3", self.landmarks)
        write_bnt(folder / f"{stem}.bnt", scan)
        return folder / f"{stem}.bnt"

    def true_positions(self, points, expression) -> np.ndarray:
        """Where skin points of this person's NEUTRAL face move with an expression.

        Parameters
        ----------
        points : (k, 3) array_like
            Points on (or within a scanner's noise of) the neutral surface, scan frame.
        expression : dict or str
            AU weights, as :func:`make_demo_scan` takes them.

        Returns
        -------
        (k, 3) float64, scan frame: each point's place on the neutral mesh (closest
        point), carried by the expression's displacement at that place.
        """
        model = load_demo_model()
        closest = MeshSurface(self.neutral_vertices, self.faces).closest_point(
            np.asarray(points, dtype=np.float64).reshape(-1, 3))
        delta = model.expression_delta(expression) @ self.pose[:3, :3].T
        corners = self.faces[closest.triangles]
        return closest.points + np.einsum("kj,kjd->kd", closest.barycentric, delta[corners])


def _random_pose(rng, pose_deg: float, pivot: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    if pose_deg > 0:
        yaw, pitch = rng.uniform(-pose_deg, pose_deg, 2)
        roll = rng.uniform(-pose_deg / 2, pose_deg / 2)
        rotation = Rotation.from_euler("YXZ", [yaw, pitch, roll], degrees=True).as_matrix()
        pose[:3, :3] = rotation
        pose[:3, 3] = pivot - rotation @ pivot + rng.uniform(-5.0, 5.0, 3)
    return pose


def _check_number(value, name, low, high):
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (np.isfinite(number) and low <= number <= high):
        raise ValueError(f"{name} must be in [{low:g}, {high:g}], got {value!r}")
    return number


def make_demo_scan(person: int, expression=None, *, spacing_mm: float = 0.7, texture_scale: int = 2,
                   noise_mm: float = 0.1, holes: int = 0, pose_deg: float = 4.0,
                   landmark_noise_mm: float = 0.5, seed: int = 0) -> DemoScan:
    """Scan one of the demo people, neutral or wearing an expression.

    Parameters
    ----------
    person : int
        0 to ``load_demo_model().n_people - 1``.
    expression : None, str or dict
        AU weights (``{"12": 1.0}``, ``{"1": 1, "4": 0.5, "15": 1}``, ``"12L"``); the
        AUs of :data:`DEMO_AUS`, optionally one-sided (not AU17 or AU26).
    spacing_mm : float
        Depth-grid spacing (0.3 to 3 mm).
    texture_scale : int
        Image pixels per grid spacing (1 to 4).
    noise_mm : float
        Standard deviation of the depth noise.
    holes : int
        Elliptical dropouts (semi-axes 2 to 6 mm) cut at random places of the face.
    pose_deg : float
        Largest yaw and pitch (roll half of it) of a random head pose, with a shift of
        up to 5 mm per axis.
    landmark_noise_mm : float
        Standard deviation (per axis) of the annotation noise on the landmarks.
    seed : int
        Seed of the pose, noise, holes, landmarks and lighting.

    Returns
    -------
    DemoScan
    """
    model = load_demo_model()
    neutral = model.person(person)
    spacing = _check_number(spacing_mm, "spacing_mm", 0.3, 3.0)
    noise = _check_number(noise_mm, "noise_mm", 0.0, 5.0)
    pose_limit = _check_number(pose_deg, "pose_deg", 0.0, 30.0)
    landmark_noise = _check_number(landmark_noise_mm, "landmark_noise_mm", 0.0, 10.0)
    for name, value, low, high in (("texture_scale", texture_scale, 1, 4), ("holes", holes, 0, 20)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
            raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    expression_dict = {} if expression is None else ({expression: 1.0} if isinstance(expression, str)
                                                    else dict(expression))
    delta = model.expression_delta(expression_dict)
    # one stream per purpose, so that changing one option leaves the other draws alone
    label = repr(sorted(expression_dict.items())).encode()
    pose_rng, noise_rng, hole_rng, landmark_rng, light_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), person, zlib.crc32(label)]).spawn(5))

    pose = _random_pose(pose_rng, pose_limit, neutral[model.bosphorus_index].mean(axis=0))
    rotation, shift = pose[:3, :3], pose[:3, 3]
    vertices = (neutral + delta) @ rotation.T + shift
    neutral_vertices = neutral @ rotation.T + shift
    faces = model.faces

    # the depth grid: pixel (r, c) looks down -z at x0 + c s, y_top - r s
    used = vertices[np.unique(faces)]
    margin = GRID_MARGIN_PIXELS * spacing
    x0 = np.floor((used[:, 0].min() - margin) / spacing) * spacing
    y_top = np.ceil((used[:, 1].max() + margin) / spacing) * spacing
    ncols = int(np.ceil((used[:, 0].max() + margin - x0) / spacing)) + 1
    nrows = int(np.ceil((y_top - used[:, 1].min() + margin) / spacing)) + 1
    pixels = np.column_stack([(vertices[:, 0] - x0) / spacing + 0.5, (y_top - vertices[:, 1]) / spacing + 0.5])
    triangle, weights = rasterise(pixels, vertices[:, 2], faces, ncols, nrows)
    seen = triangle >= 0
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing = normals[:, 2] / np.maximum(np.linalg.norm(normals, axis=1), 1e-300)
    # surfaces seen edge-on or from behind (the inner lips, the nostrils) are lost
    seen &= facing[np.maximum(triangle, 0)] >= np.cos(np.radians(MAX_VIEW_ANGLE_DEG))
    z = np.einsum("rcj,rcj->rc", weights, vertices[:, 2][faces[np.maximum(triangle, 0)]])
    columns, rows = np.meshgrid(np.arange(ncols), np.arange(nrows))
    x, y = x0 + spacing * columns, y_top - spacing * rows
    for _ in range(holes):
        candidates = np.argwhere(seen)
        if len(candidates) == 0:
            break
        r, c = candidates[hole_rng.integers(len(candidates))]
        a, b = hole_rng.uniform(2.0, 6.0, 2)
        angle = hole_rng.uniform(0.0, np.pi)
        du = (x - x[r, c]) * np.cos(angle) + (y - y[r, c]) * np.sin(angle)
        dv = -(x - x[r, c]) * np.sin(angle) + (y - y[r, c]) * np.cos(angle)
        seen &= (du / a) ** 2 + (dv / b) ** 2 > 1.0
    if noise > 0:
        z = z + noise_rng.normal(0.0, noise, z.shape)
    points = np.where(seen[..., None], np.stack([x, y, z], axis=-1), np.nan)
    scan = BntScan.from_points(points, image_name="")

    image = _colour_image(model, person, vertices, faces, x0, y_top, spacing, nrows, ncols,
                          int(texture_scale), light_rng)
    landmarks = vertices[model.bosphorus_index] + landmark_rng.normal(0.0, landmark_noise, (22, 3))
    canonical = {str(k): float(v) for k, v in expression_dict.items()}
    return DemoScan(scan, image, landmarks, vertices, neutral_vertices, faces, pose, int(person), canonical)


def _colour_image(model, person, vertices, faces, x0, y_top, spacing, nrows, ncols, scale, rng) -> np.ndarray:
    """The scan's colour image, aligned so that a grid point's u,v (its pixel centre over
    the grid size) falls where the image sees the same spot of skin."""
    step = spacing / scale
    height, width = nrows * scale, ncols * scale
    # image pixel (R, C) has its centre at x0 - spacing/2 + (C + 0.5) step
    pixels = np.column_stack([(vertices[:, 0] - x0 + spacing / 2) / step,
                              (y_top + spacing / 2 - vertices[:, 1]) / step])
    triangle, weights = rasterise(pixels, vertices[:, 2], faces, width, height)
    rows, cols = np.nonzero(triangle >= 0)
    hit = triangle[rows, cols]
    bary = weights[rows, cols]
    corners = faces[hit]
    rest = np.einsum("kj,kjd->kd", bary, model.neutral[corners])
    albedo = _Skin(model, person).albedo(rest)
    normals = vertex_normals(vertices, faces)
    normal = np.einsum("kj,kjd->kd", bary, normals[corners])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    light = np.asarray(LIGHT_DIRECTION) + rng.normal(0.0, LIGHT_JITTER, 3)
    light /= np.linalg.norm(light)
    halfway = light + [0.0, 0.0, 1.0]
    halfway /= np.linalg.norm(halfway)
    diffuse = np.clip(normal @ light, 0.0, 1.0)
    specular = SPECULAR * np.clip(normal @ halfway, 0.0, 1.0) ** SHININESS
    exposure = rng.uniform(0.95, 1.05) * rng.uniform(0.98, 1.02, 3)
    picture = np.full((height, width, 3), BACKGROUND_GREY)
    picture[rows, cols] = albedo * (AMBIENT + (1.0 - AMBIENT) * diffuse)[:, None] + specular[:, None]
    picture = picture * exposure + rng.normal(0.0, SENSOR_NOISE, picture.shape)
    return np.clip(np.round(picture * 255.0), 0, 255).astype(np.uint8)
