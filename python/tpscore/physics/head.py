"""A head for the physical skin: the skin mesh and the structure under it.

:class:`Head` holds a skin mesh with 22 landmark vertices, a skull with the same
triangles (skull vertex i lies under skin vertex i), a region per vertex, which
vertices the mandible carries, the jaw's pivot and axis, and the muscles.

The template head that ships with tpscore (:func:`load_template`,
``tpscore/data/skin_template.npz``) is made by :func:`build_template` from tpscore's own
procedural average face (:func:`tpscore.showcase.datasets.make_face` with the default
identity): the face sampled on a regular grid, triangulated, with the mouth cut open
between the mouth corners (the lips get separate vertices along the mouth line, so
the jaw can open it). Its skull is an inner surface at soft-tissue depths per region:
each skin vertex moves along the ray toward the head's geometric centre (the centre of
the sphere that best fits the face) by a depth interpolated from
:data:`TISSUE_DEPTHS_MM`, a table of soft-tissue thicknesses at craniometric points,
rounded from the means that forensic facial-reconstruction studies report for adults
(for example Rhine and Campbell 1980; De Greef et al. 2006, Forensic Science
International 159S). Over the nose, the depth is that to the bony aperture.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Mapping

import numpy as np

from .._validation import as_faces, as_points
from ..face.io import write_npz
from ..face.landmarks import LANDMARK_NAMES, MIRROR_LANDMARK, N_LANDMARKS, landmark_index
from .muscles import SkinLinearMuscle, SkinSphincterMuscle, place_muscles, read_muscle_file

__all__ = [
    "Head",
    "REGIONS",
    "TISSUE_DEPTHS_MM",
    "DEFAULT_SPACING_MM",
    "build_template",
    "load_template",
    "tissue_depth",
    "sphere_centre",
]

#: The regions every vertex of a head belongs to (one each).
REGIONS = ("upper_face", "nose", "cheek_left", "cheek_right", "modiolus_left", "modiolus_right",
           "upper_lip", "lower_lip", "chin")

#: Grid spacing of the shipped template (mm): about 2,600 vertices.
DEFAULT_SPACING_MM = 2.5

#: Soft-tissue depth (mm) at places given relative to the landmarks: (landmark weights,
#: (x, y) offset in the face frame in mm, depth). Bilateral places are listed for the
#: subject's left and mirrored.
TISSUE_DEPTHS_MM = (
    # midline
    ({"Inner left eyebrow": 1, "Inner right eyebrow": 1}, (0.0, 28.0), 4.5),   # metopion
    ({"Inner left eyebrow": 1, "Inner right eyebrow": 1}, (0.0, 8.0), 5.0),    # supraglabella
    ({"Inner left eyebrow": 1, "Inner right eyebrow": 1}, (0.0, 0.0), 5.5),    # glabella
    ({"Nose saddle left": 1, "Nose saddle right": 1}, (0.0, 4.0), 6.5),        # nasion
    ({"Nose saddle left": 1, "Nose saddle right": 1}, (0.0, -16.0), 3.0),      # rhinion
    ({"Nose tip": 1}, (0.0, 0.0), 18.0),                                       # tip to the aperture
    ({"Upper lip outer middle": 1}, (0.0, 8.0), 13.0),                         # subnasale
    ({"Upper lip outer middle": 1}, (0.0, 4.0), 11.5),                         # mid-philtrum
    ({"Upper lip outer middle": 1}, (0.0, 0.0), 12.5),                         # labrale superius
    ({"Lower lip outer middle": 1}, (0.0, 0.0), 13.5),                         # labrale inferius
    ({"Lower lip outer middle": 1}, (0.0, -6.0), 11.5),                        # chin-lip fold
    ({"Chin middle": 1}, (0.0, 3.0), 11.0),                                    # mental eminence
    ({"Chin middle": 1}, (0.0, -9.0), 7.5),                                    # menton
    # bilateral (left)
    ({"Middle left eyebrow": 1}, (-4.0, 22.0), 4.5),                           # frontal eminence
    ({"Middle left eyebrow": 1}, (0.0, 0.0), 6.5),                             # supraorbital
    ({"Outer left eyebrow": 1}, (10.0, 10.0), 6.0),                            # temple front
    ({"Outer left eye corner": 1}, (4.0, 0.0), 7.5),                           # lateral orbit
    ({"Outer left eye corner": 1, "Inner left eye corner": 1}, (0.0, 0.0), 4.0),   # closed lid over the eyeball
    ({"Outer left eye corner": 1, "Inner left eye corner": 1}, (0.0, -10.0), 6.0),  # suborbital
    ({"Outer left eye corner": 1}, (6.0, -20.0), 7.0),                         # zygomatic
    ({"Outer left eye corner": 1, "Inner left eye corner": 1}, (2.0, -28.0), 13.0),  # inferior malar
    ({"Left nose peak": 1}, (0.0, 0.0), 11.0),                                 # alar base
    ({"Left mouth corner": 1}, (18.0, 8.0), 19.0),                             # buccal
    ({"Left mouth corner": 1}, (8.0, 0.0), 17.0),                              # occlusal line
    ({"Left mouth corner": 1}, (0.0, 0.0), 13.0),                              # mouth corner
    ({"Left mouth corner": 1}, (5.0, -26.0), 10.0),                            # mandible body
    ({"Left mouth corner": 1}, (22.0, -20.0), 13.0),                           # toward gonion
)

# Spread (mm) of the Gaussian weights that interpolate the depth table across the face.
_DEPTH_SPREAD_MM = 12.0
# The jaw's pivot (the condyles' axis) relative to the nose tip in the face frame:
# about 15 mm above it, near the level of the ear canal, and 100 mm behind it, just in
# front of the ear canal (an adult's tragion lies some 110-120 mm behind the nose tip).
# The chin then moves down more than back as the jaw opens.
_JAW_PIVOT_MM = (0.0, 15.0, -100.0)


def _mirror_name(name: str) -> str:
    """The landmark on the other side of the face (itself on the midline)."""
    return LANDMARK_NAMES[MIRROR_LANDMARK[landmark_index(name)]]


def tissue_depth(points_frame: np.ndarray, landmarks_frame: np.ndarray) -> np.ndarray:
    """Soft-tissue depth (mm) at face-frame points (n, 3), interpolated from
    :data:`TISSUE_DEPTHS_MM` placed on the landmarks (face-frame (22, 3)) by normalised
    Gaussian weights over x, y."""
    places, depths = [], []
    for at, offset, depth in TISSUE_DEPTHS_MM:
        mirrored = {_mirror_name(k): v for k, v in at.items()}
        sides = [(at, offset)]
        if mirrored != at or offset[0] != 0.0:
            sides.append((mirrored, (-offset[0], offset[1])))
        for names, (dx, dy) in sides:
            weights = np.array(list(names.values()), dtype=np.float64)
            rows = [landmark_index(k) for k in names]
            centre = weights @ landmarks_frame[rows] / weights.sum()
            places.append(centre[:2] + np.array([dx, dy]))
            depths.append(depth)
    places = np.array(places)
    depths = np.array(depths)
    d2 = np.sum((points_frame[:, None, :2] - places[None]) ** 2, axis=2)
    weights = np.exp(-0.5 * d2 / _DEPTH_SPREAD_MM**2)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)
    return weights @ depths


def sphere_centre(points: np.ndarray) -> np.ndarray:
    """Centre (3,) of the least-squares sphere through the points: for a face, the
    head's geometric centre, about 10 cm behind the nose tip."""
    design = np.c_[2.0 * points, np.ones(len(points))]
    solution = np.linalg.lstsq(design, np.sum(points**2, axis=1), rcond=None)[0]
    return solution[:3]


@dataclass(frozen=True, eq=False)
class Head:
    """A skin mesh with its skull, regions, jaw and muscles (mm).

    Attributes
    ----------
    vertices : (n, 3) ndarray
        The skin (epidermis).
    faces : (m, 3) int64 ndarray
        Triangles, shared by skin and skull.
    skull_vertices : (n, 3) ndarray
        The skull under each skin vertex.
    landmark_vertices : (22,) int64 ndarray
        Vertex of each Bosphorus landmark (-1 where the head has none).
    regions : (n,) int64 ndarray
        Index into ``region_names`` per vertex.
    region_names : tuple of str
    mandible : (n,) bool ndarray
        Vertices whose skull and anchors the mandible carries.
    jaw_pivot : (3,) ndarray
        A point on the jaw's axis of rotation.
    jaw_axis : (3,) ndarray
        Unit axis (the head's x, toward the subject's left); a positive jaw angle opens.
    muscles : tuple of SkinLinearMuscle / SkinSphincterMuscle
    action_units : dict
        FACS AU code -> {muscle name: relative contraction}.
    """

    vertices: np.ndarray
    faces: np.ndarray
    skull_vertices: np.ndarray
    landmark_vertices: np.ndarray
    regions: np.ndarray
    region_names: tuple
    mandible: np.ndarray
    jaw_pivot: np.ndarray
    jaw_axis: np.ndarray
    muscles: tuple = ()
    action_units: dict = field(default_factory=dict)

    def __post_init__(self):
        vertices = as_points(self.vertices, "vertices", allow_empty=False)
        n = len(vertices)
        faces = as_faces(self.faces, n, "faces")
        skull = as_points(self.skull_vertices, "skull_vertices")
        if skull.shape != vertices.shape:
            raise ValueError(f"skull_vertices must have the shape of vertices {vertices.shape}, got {skull.shape}")
        lm = np.asarray(self.landmark_vertices)
        if lm.shape != (N_LANDMARKS,) or not np.issubdtype(lm.dtype, np.integer) or lm.min() < -1 or lm.max() >= n:
            raise ValueError(f"landmark_vertices must be ({N_LANDMARKS},) vertex indices in [-1, {n})")
        regions = np.asarray(self.regions)
        names = tuple(str(r) for r in self.region_names)
        if regions.shape != (n,) or not np.issubdtype(regions.dtype, np.integer) or regions.min() < 0 \
                or regions.max() >= len(names):
            raise ValueError(f"regions must be ({n},) indices into region_names ({len(names)} names)")
        mandible = np.asarray(self.mandible, dtype=bool)
        if mandible.shape != (n,):
            raise ValueError(f"mandible must be a ({n},) bool mask")
        pivot = as_points(np.reshape(self.jaw_pivot, (1, 3)), "jaw_pivot")[0]
        axis = as_points(np.reshape(self.jaw_axis, (1, 3)), "jaw_axis")[0]
        if np.linalg.norm(axis) == 0:
            raise ValueError("jaw_axis must be non-zero")
        for muscle in self.muscles:
            if not isinstance(muscle, (SkinLinearMuscle, SkinSphincterMuscle)):
                raise ValueError(f"muscles must be SkinLinearMuscle or SkinSphincterMuscle, got {type(muscle).__name__}")
            for region in muscle.regions:
                if region not in names:
                    raise ValueError(f"muscle {muscle.name!r} acts on region {region!r}, which the head lacks")
            if isinstance(muscle, SkinLinearMuscle):
                for point in (muscle.attachment, muscle.insertion):
                    if point.face >= len(faces):
                        raise ValueError(f"muscle {muscle.name!r} refers to face {point.face}; the head has "
                                         f"{len(faces)}")
        muscle_names = [m.name for m in self.muscles]
        if len(set(muscle_names)) != len(muscle_names):
            raise ValueError("muscle names are not unique")
        units = {}
        for code, recipe in dict(self.action_units).items():
            units[str(code)] = {str(k): float(v) for k, v in dict(recipe).items()}
            for muscle in units[str(code)]:
                if muscle not in muscle_names:
                    raise ValueError(f"action unit {code!r} uses muscle {muscle!r}, which the head lacks")
        for name, value in (("vertices", vertices), ("faces", faces), ("skull_vertices", skull),
                            ("landmark_vertices", lm.astype(np.int64)), ("regions", regions.astype(np.int64)),
                            ("mandible", mandible), ("jaw_pivot", pivot), ("jaw_axis", axis / np.linalg.norm(axis))):
            value = np.array(value, copy=True)
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "region_names", names)
        object.__setattr__(self, "muscles", tuple(self.muscles))
        object.__setattr__(self, "action_units", units)

    # ---------------------------------------------------------------- queries
    @property
    def landmarks(self) -> np.ndarray:
        """(22, 3) landmark positions on the skin (NaN where the head has none)."""
        out = np.full((N_LANDMARKS, 3), np.nan)
        present = self.landmark_vertices >= 0
        out[present] = self.vertices[self.landmark_vertices[present]]
        return out

    @property
    def muscle_names(self) -> tuple:
        return tuple(m.name for m in self.muscles)

    def muscle(self, name: str):
        for m in self.muscles:
            if m.name == name:
                return m
        raise ValueError(f"unknown muscle {name!r}; known: {', '.join(self.muscle_names)}")

    def region_mask(self, names) -> np.ndarray:
        """(n,) bool: the vertices in any of the named regions."""
        wanted = [self.region_names.index(r) for r in names]
        return np.isin(self.regions, wanted)

    def tissue_depth(self) -> np.ndarray:
        """(n,) distance (mm) from each skin vertex to its skull vertex."""
        return np.linalg.norm(self.vertices - self.skull_vertices, axis=1)

    def contractions_for(self, action_units) -> dict:
        """Muscle contractions {muscle: value} for AU intensities, e.g. ``{"12": 0.8}``;
        ``"12L"``/``"12R"`` use only that side's muscles. Contractions of AUs that share a
        muscle add."""
        if isinstance(action_units, str):
            action_units = {action_units: 1.0}
        out: dict[str, float] = {}
        for code, value in dict(action_units).items():
            code = str(code).upper().removeprefix("AU")
            side = code[-1] if code[-1] in "LR" else ""
            base = code[:-1] if side else code
            if base not in self.action_units:
                raise ValueError(f"action_units: unknown AU {code!r}; known: {', '.join(self.action_units)}")
            for muscle, weight in self.action_units[base].items():
                if side == "L" and muscle.endswith("_right") or side == "R" and muscle.endswith("_left"):
                    continue
                out[muscle] = out.get(muscle, 0.0) + float(value) * weight
        return out

    def with_changes(self, **changes) -> "Head":
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)

    # ---------------------------------------------------------------- files
    def save(self, path) -> None:
        """Write the geometry (not the muscles, which are placed from their definitions)."""
        write_npz(path, vertices=self.vertices, faces=self.faces, skull_vertices=self.skull_vertices,
                  landmark_vertices=self.landmark_vertices, regions=self.regions,
                  region_names=np.array(self.region_names), mandible=self.mandible,
                  jaw_pivot=self.jaw_pivot, jaw_axis=self.jaw_axis)


# ------------------------------------------------------------------ the template
def _grid_mesh_with_mouth(points: np.ndarray, valid: np.ndarray, y_mouth: float, x_corner: float, spacing: float):
    """Triangulate a grid (rows top to bottom) and cut the mouth line open.

    Returns vertices, faces, the original grid index of each vertex, and a mask of the
    lower-lip copies of the vertices along the cut.
    """
    rows, cols = valid.shape
    index = -np.ones(valid.shape, dtype=np.int64)
    index[valid] = np.arange(valid.sum())
    vertices = points[valid]
    grid_index = np.flatnonzero(valid.reshape(-1))
    faces = []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a, b, d, e = index[r, c], index[r, c + 1], index[r + 1, c], index[r + 1, c + 1]
            # Each cell is cut along a diagonal, the two halves of the face mirror images
            # of each other: a mesh whose diagonals all lean one way is stiffer to one
            # side, and a symmetric pull then buckles one side of the face first.
            # Triangles counter-clockwise seen from +z (rows run toward -y).
            corners = (a, b, d, e)
            if min(corners) >= 0:
                if points[r, c, 0] + points[r, c + 1, 0] < 0:
                    faces += [(a, d, b), (b, d, e)]
                else:
                    faces += [(a, d, e), (a, e, b)]
            elif sum(v >= 0 for v in corners) == 3:
                # at the outline: the one triangle of the three corners there are
                for triangle in ((a, d, b), (b, d, e), (a, d, e), (a, e, b)):
                    if min(triangle) >= 0:
                        faces.append(triangle)
                        break
    faces = np.array(faces, dtype=np.int64)
    # the cut: grid vertices on the mouth line strictly between the corners
    on_line = np.isclose(vertices[:, 1], y_mouth, atol=1e-6) & (np.abs(vertices[:, 0]) < x_corner - 0.5 * spacing)
    cut = np.flatnonzero(on_line)
    copies = np.arange(len(vertices), len(vertices) + len(cut))
    lower_of = dict(zip(cut.tolist(), copies.tolist()))
    centroid_y = vertices[faces].mean(axis=1)[:, 1]
    below = centroid_y < y_mouth
    for f in np.flatnonzero(below & np.isin(faces, cut).any(axis=1)):
        faces[f] = [lower_of.get(int(v), int(v)) for v in faces[f]]
    vertices = np.vstack([vertices, vertices[cut]])
    grid_index = np.concatenate([grid_index, grid_index[cut]])
    lower_copy = np.zeros(len(vertices), dtype=bool)
    lower_copy[copies] = True
    return vertices, faces, grid_index, lower_copy


def _template_regions(vertices: np.ndarray, landmarks: np.ndarray, lower_copy: np.ndarray):
    """Region index per vertex and the mandible mask, from face-frame positions."""
    x, y = vertices[:, 0], vertices[:, 1]
    lm = {name: landmarks[i] for i, name in enumerate(LANDMARK_NAMES)}
    y_eye = np.mean([lm[n][1] for n in ("Outer left eye corner", "Inner left eye corner",
                                        "Inner right eye corner", "Outer right eye corner")])
    x_alar = 0.5 * (lm["Left nose peak"][0] - lm["Right nose peak"][0])
    y_alar = 0.5 * (lm["Left nose peak"][1] + lm["Right nose peak"][1])
    x_corner = 0.5 * (lm["Left mouth corner"][0] - lm["Right mouth corner"][0])
    y_mouth = 0.5 * (lm["Left mouth corner"][1] + lm["Right mouth corner"][1])
    y_lower = lm["Lower lip outer middle"][1]
    ax = np.abs(x)
    upper_side = (y > y_mouth + 1e-6) | ((np.abs(y - y_mouth) <= 1e-6) & ~lower_copy)
    # the nose: narrow at the bridge, as wide as the alae (plus 3 mm) at their base
    t = np.clip((y_eye - y) / max(y_eye - y_alar, 1e-9), 0.0, 1.0)
    nose = (y < y_eye - 2.0) & (y > y_alar - 5.0) & (ax < 6.0 + (x_alar - 3.0) * t)
    upper_face = (y >= y_eye - 2.0) & ~nose
    # the nasolabial line runs from beside the alae to 5 mm outside the mouth corners
    s = np.clip((y_alar - y) / max(y_alar - y_mouth, 1e-9), 0.0, 1.0)
    nasolabial = x_alar + 2.0 + (x_corner + 5.0 - x_alar - 2.0) * s
    modiolus = np.hypot(ax - x_corner, y - y_mouth) <= 5.0
    upper_lip = upper_side & (y < y_alar - 5.0) & (ax < nasolabial) & ~modiolus & ~nose
    lower_lip = ~upper_side & (y > y_lower - 5.0) & (ax < x_corner + 2.0) & ~modiolus
    chin = (y <= y_lower - 5.0) & (ax < x_corner + 2.0)
    region = np.where(x >= 0, REGIONS.index("cheek_left"), REGIONS.index("cheek_right"))
    for name, mask in (("upper_face", upper_face), ("nose", nose), ("upper_lip", upper_lip),
                       ("lower_lip", lower_lip), ("chin", chin)):
        region = np.where(mask, REGIONS.index(name), region)
    region = np.where(modiolus & (x > 0), REGIONS.index("modiolus_left"), region)
    region = np.where(modiolus & (x < 0), REGIONS.index("modiolus_right"), region)
    # the mandible: below the mouth line, and below a line rising gently from the corners
    line = y_mouth + 0.2 * np.maximum(ax - x_corner, 0.0)
    mandible = (~upper_side & (ax <= x_corner)) | ((ax > x_corner) & (y < line - 1e-6))
    mandible |= lower_lip | chin
    return region.astype(np.int64), mandible


def build_template(scan, spacing_mm: float = DEFAULT_SPACING_MM, *, muscles=None) -> Head:
    """The template head made from a neutral face on a regular grid.

    The shipped template is built from tpscore's procedural average face,
    :func:`tpscore.showcase.datasets.skin_template` (``make_face(None, spacing_mm=2.5)``).

    Parameters
    ----------
    scan : a synthetic scan (:class:`tpscore.showcase.datasets.SyntheticScan`)
        ``points`` (H, W, 3) on a grid of ``spacing_mm``, ``valid`` (H, W) and the 22
        ``landmarks``, in the reference frame.
    spacing_mm : float
        Its grid spacing (mm); 2.5 gives the shipped template (about 2,600 vertices),
        1.25 about 10,000.
    muscles : dict, optional
        A parsed muscle file (default: the shipped ``skin_muscles.json``).
    """
    spacing = float(spacing_mm)
    if not np.isfinite(spacing) or not 0.5 <= spacing <= 10:
        raise ValueError(f"spacing_mm must be in [0.5, 10] mm, got {spacing_mm!r}")
    with np.errstate(invalid="ignore"):
        step = float(np.nanmedian(np.diff(np.asarray(scan.points, dtype=np.float64)[..., 0], axis=1)))
    if not np.isclose(step, spacing, atol=1e-9):
        raise ValueError(f"scan: its grid spacing ({step:.4g} mm) is not spacing_mm ({spacing} mm)")
    landmarks = scan.landmarks
    y_mouth = 0.5 * (landmarks[landmark_index("Left mouth corner"), 1] + landmarks[landmark_index("Right mouth corner"), 1])
    x_corner = 0.5 * (landmarks[landmark_index("Left mouth corner"), 0] - landmarks[landmark_index("Right mouth corner"), 0])
    # The grid's rows lie on multiples of the spacing; the mouth line must be one of them.
    points = scan.points.copy()
    row_y = points[:, :, 1][scan.valid]
    if not np.any(np.isclose(row_y, y_mouth, atol=1e-6)):
        raise ValueError(f"spacing_mm {spacing} puts no grid row on the mouth line (y = {y_mouth} mm); "
                         "use a spacing that divides it")
    vertices, faces, _, lower_copy = _grid_mesh_with_mouth(points, scan.valid, y_mouth, x_corner, spacing)
    # landmark vertices: the nearest, with the inner lip landmarks on their own lip
    landmark_vertices = np.empty(N_LANDMARKS, dtype=np.int64)
    for i, name in enumerate(LANDMARK_NAMES):
        candidates = np.arange(len(vertices))
        if name == "Upper lip inner middle":
            candidates = candidates[~lower_copy]
        elif name == "Lower lip inner middle":
            candidates = candidates[lower_copy]
        d = np.linalg.norm(vertices[candidates] - landmarks[i], axis=1)
        landmark_vertices[i] = candidates[np.argmin(d)]
    centre = sphere_centre(vertices)
    rays = centre - vertices
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    depth = tissue_depth(vertices, landmarks)
    skull = vertices + depth[:, None] * rays
    regions, mandible = _template_regions(vertices, landmarks, lower_copy)
    nose_tip = landmarks[landmark_index("Nose tip")]
    pivot = nose_tip + np.array(_JAW_PIVOT_MM)
    head = Head(vertices, faces, skull, landmark_vertices, regions, REGIONS, mandible, pivot,
                np.array([1.0, 0.0, 0.0]))
    return _with_muscles(head, muscles)


def _with_muscles(head: Head, definitions=None) -> Head:
    data = read_muscle_file() if definitions is None else definitions
    muscles = place_muscles(head.vertices, head.faces, head.skull_vertices, head.landmarks, data)
    return replace(head, muscles=muscles, action_units=data.get("action_units", {}))


def _load_head_file(path, definitions=None) -> Head:
    try:
        with np.load(path, allow_pickle=False) as data:
            head = Head(data["vertices"], data["faces"], data["skull_vertices"], data["landmark_vertices"],
                        data["regions"], tuple(str(r) for r in data["region_names"]), data["mandible"],
                        data["jaw_pivot"], data["jaw_axis"])
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: not a head file: {exc}") from None
    return _with_muscles(head, definitions)


def load_template(path=None, *, muscles=None) -> Head:
    """The shipped template head (or a head file written by :meth:`Head.save`), with
    the muscle set placed on it.

    Parameters
    ----------
    path : path-like, optional
        Default: ``tpscore/data/skin_template.npz``.
    muscles : path-like or dict, optional
        A muscle file (default: the shipped ``skin_muscles.json``).
    """
    definitions = muscles if muscles is None or isinstance(muscles, Mapping) else read_muscle_file(muscles)
    if path is None:
        with resources.as_file(resources.files("tpscore").joinpath("data/skin_template.npz")) as file:
            return _load_head_file(Path(file), definitions)
    return _load_head_file(path, definitions)
