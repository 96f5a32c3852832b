"""Regions of the face, defined from landmarks: the upper and lower face, and named
parts finer than those (:class:`Region`).

The boundary is the straight line through the eye corners, fitted by least squares
to the four eye corners present (in the x-y plane of the normalised frame, where the
face looks toward +z): everything above it is the upper face (brows, forehead,
upper eyelids), everything below it the lower face (cheeks, nose, mouth, chin).
Upper-face AUs move only the upper face and lower-face AUs only the lower face, so
a brow raise cannot move the mouth and a smile cannot move the brows.

With ``transition_mm = 0`` the split is a hard seam (the method as published); a
positive value blends the two sides over a band of that width centred on the line,
with a smooth (C1) ramp, so a region's warp fades out instead of stopping at a seam.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .landmarks import AnchoredPoint, landmark_index

__all__ = ["region_boundary", "height_above_boundary", "upper_face_weight", "region_weight", "midline_x", "side_weight",
           "smoothstep", "Region", "HALVES"]

#: The two halves of the face the eye line separates.
HALVES = ("upper", "lower")

_EYE_CORNERS = ("Outer left eye corner", "Inner left eye corner",
                "Inner right eye corner", "Outer right eye corner")
_FALLBACK = ("Nose saddle left", "Nose saddle right")
_MIDLINE = ("Nose tip", "Upper lip outer middle", "Upper lip inner middle",
            "Lower lip inner middle", "Lower lip outer middle", "Chin middle")
_PAIRS = (("Inner left eye corner", "Inner right eye corner"),
          ("Outer left eye corner", "Outer right eye corner"),
          ("Left mouth corner", "Right mouth corner"))


def smoothstep(edge0, edge1, value) -> np.ndarray:
    """0 before edge0, 1 after edge1, C1 cubic in between (edges may be decreasing)."""
    t = np.clip((np.asarray(value, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def region_boundary(landmarks) -> tuple[float, float]:
    """(slope, intercept) of the boundary line y = slope * x + intercept.

    Uses the eye corners present; with only one, a horizontal line through it; with
    none, the nose saddles. Raises ValueError when none of these is present.
    """
    lm = np.asarray(landmarks, dtype=np.float64)
    pts = lm[[landmark_index(n) for n in _EYE_CORNERS]]
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        pts = lm[[landmark_index(n) for n in _FALLBACK]]
        pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("cannot place the upper/lower face boundary: no eye corner and no nose saddle landmark")
    if len(pts) == 1 or np.ptp(pts[:, 0]) < 1.0:
        return 0.0, float(pts[:, 1].mean())
    slope, intercept = np.polyfit(pts[:, 0], pts[:, 1], 1)
    return float(slope), float(intercept)


def height_above_boundary(points, landmarks) -> np.ndarray:
    """Each point's (..., >=2) signed distance (mm) above the upper/lower boundary
    (:func:`region_boundary`), measured perpendicular to it in the x-y plane; negative
    below it, NaN at NaN points."""
    p = np.asarray(points, dtype=np.float64)
    slope, intercept = region_boundary(landmarks)
    return (p[..., 1] - (slope * p[..., 0] + intercept)) / np.hypot(1.0, slope)


def upper_face_weight(points, landmarks, transition_mm: float = 0.0) -> np.ndarray:
    """Weight in [0, 1] of the upper face at each point (..., 3); NaN points get 0."""
    above = height_above_boundary(points, landmarks)
    above = np.where(np.isfinite(above), above, -np.inf)
    if transition_mm <= 0:
        return (above > 0).astype(np.float64)
    return smoothstep(-0.5 * transition_mm, 0.5 * transition_mm, above)


def region_weight(region: str, points, landmarks, transition_mm: float = 0.0) -> np.ndarray:
    """Weight of `region` ('upper' or 'lower') at each point; the two weights sum to 1."""
    upper = upper_face_weight(points, landmarks, transition_mm)
    if region == "upper":
        return upper
    if region == "lower":
        return 1.0 - upper
    raise ValueError(f"region must be 'upper' or 'lower', got {region!r}")


def midline_x(landmarks) -> float:
    """x of the face's midline in a normalised frame (face looking toward +z): the median
    x of the midline landmarks and of the midpoints of left/right pairs present; 0 when
    none is present."""
    lm = np.asarray(landmarks, dtype=np.float64)
    xs = [lm[landmark_index(n), 0] for n in _MIDLINE]
    xs += [0.5 * (lm[landmark_index(a), 0] + lm[landmark_index(b), 0]) for a, b in _PAIRS]
    xs = np.array(xs)
    xs = xs[np.isfinite(xs)]
    return float(np.median(xs)) if len(xs) else 0.0


def side_weight(side: str | None, points, landmarks, transition_mm: float = 0.0) -> np.ndarray:
    """Weight in [0, 1] of one side of the face ('L': the subject's left, +x; 'R': the
    right; None: both, all ones) at points (..., 3), with a smooth ramp of width
    ``transition_mm`` across the midline; NaN points get 0."""
    p = np.asarray(points, dtype=np.float64)
    if side is None:
        return np.where(np.isfinite(p[..., 0]), 1.0, 0.0)
    if side not in ("L", "R"):
        raise ValueError(f"side must be 'L', 'R' or None, got {side!r}")
    across = p[..., 0] - midline_x(landmarks)
    if side == "R":
        across = -across
    across = np.where(np.isfinite(across), across, -np.inf)
    if transition_mm <= 0:
        return (across > 0).astype(np.float64)
    return smoothstep(-0.5 * transition_mm, 0.5 * transition_mm, across)


@dataclass(frozen=True)
class Region:
    """A named part of the face where an action unit acts, finer than the upper and
    lower face: a union of polygons whose corners are anchored points (weighted means
    of landmarks plus an x, y offset, as control points are), with a soft edge.

    Its weight at a point is 1 inside a polygon and falls smoothly (C1) to 0 at
    ``margin_mm`` outside it, measured in the x-y plane of the frame the landmarks are
    in (a normalised face looks toward +z).

    Attributes
    ----------
    name : str
    polygons : tuple of tuple of AnchoredPoint
        Each polygon's corners in order (at least three).
    margin_mm : float
    description : str
    """

    name: str
    polygons: tuple
    margin_mm: float = 5.0
    description: str = ""

    def __post_init__(self):
        if not self.polygons:
            raise ValueError(f"region {self.name!r}: needs at least one polygon")
        for polygon in self.polygons:
            if len(polygon) < 3:
                raise ValueError(f"region {self.name!r}: a polygon needs at least three corners")
        if not np.isfinite(self.margin_mm) or self.margin_mm < 0:
            raise ValueError(f"region {self.name!r}: margin_mm must be finite and >= 0, got {self.margin_mm!r}")
        object.__setattr__(self, "polygons", tuple(tuple(p) for p in self.polygons))

    def corners(self, landmarks) -> list[np.ndarray]:
        """Each polygon's (k, 2) corners on a face with these landmarks."""
        return [np.array([corner.position_xy(landmarks) for corner in polygon]) for polygon in self.polygons]

    def weight(self, points, landmarks) -> np.ndarray:
        """Weight in [0, 1] at points (..., >=2); NaN points get 0."""
        p = np.asarray(points, dtype=np.float64)
        flat = p.reshape(-1, p.shape[-1])[:, :2]
        finite = np.isfinite(flat).all(axis=1)
        best = np.zeros(len(flat))
        for corners in self.corners(landmarks):
            inside = _inside(flat[finite], corners)
            distance = np.where(inside, 0.0, _distance_to_outline(flat[finite], corners))
            if self.margin_mm > 0:
                w = smoothstep(self.margin_mm, 0.0, distance)
            else:
                w = inside.astype(np.float64)
            best[finite] = np.maximum(best[finite], w)
        return best.reshape(p.shape[:-1])

    def half(self, landmarks, seam_mm: float = 0.0) -> str | None:
        """The half of the face (``"upper"`` or ``"lower"``, split by the eye line,
        :func:`region_boundary`) that holds the whole region with its soft edge, and
        half of a seam ``seam_mm`` wide between the halves, on a face with these
        landmarks; None if it reaches across (the eyes' region does)."""
        if not np.isfinite(seam_mm) or seam_mm < 0:
            raise ValueError(f"seam_mm must be finite and >= 0, got {seam_mm!r}")
        corners = np.concatenate(self.corners(landmarks))
        if not np.isfinite(corners).all():
            return None
        above = height_above_boundary(corners, landmarks)
        reach = self.margin_mm + 0.5 * seam_mm
        if (above >= reach).all():
            return "upper"
        if (above <= -reach).all():
            return "lower"
        return None

    def to_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "margin_mm": self.margin_mm,
                "polygons": [[{"at": dict(c.at), "offset_mm": list(c.offset_mm)} for c in polygon]
                             for polygon in self.polygons]}

    @classmethod
    def from_dict(cls, data) -> "Region":
        try:
            name = str(data["name"])
            polygons = tuple(
                tuple(AnchoredPoint(name=f"{name} corner {k}", side="centre", at=c["at"],
                                    offset_mm=tuple(c.get("offset_mm", (0.0, 0.0)))) for k, c in enumerate(polygon))
                for polygon in data["polygons"])
            return cls(name, polygons, float(data.get("margin_mm", 5.0)), str(data.get("description", "")))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"region entry {str(data)[:60]!r} is malformed: {exc}") from None


def _inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd rule for (m, 2) points in a (k, 2) polygon."""
    inside = np.zeros(len(points), dtype=bool)
    x, y = points[:, 0], points[:, 1]
    for (x1, y1), (x2, y2) in zip(polygon, np.roll(polygon, -1, axis=0)):
        crosses = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            at = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (x < at)
    return inside


def _distance_to_outline(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Distance of (m, 2) points to the outline of a (k, 2) polygon."""
    best = np.full(len(points), np.inf)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        edge = b - a
        t = np.clip(((points - a) @ edge) / max(float(edge @ edge), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * edge), axis=1))
    return best
