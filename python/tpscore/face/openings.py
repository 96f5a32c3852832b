"""The face's openings: the two eyes and the mouth, where an expression opens or closes
the face and where the skin's motion tears apart.

A neutral face's lips touch and its eyes are open. When the jaw drops, the upper and
lower lips move apart; when the eyes close, the upper lids slide down across the eye
openings while the lower lids stay. The skin on the two sides of such an opening moves
independently, so a smooth displacement field must not run across it.

Each opening lies between two corner landmarks (the eye corners, the mouth corners).
Its chord coordinates are ``a`` (0 at the corner of smaller x, 1 at the other) and
``b`` (mm above the chord, perpendicular to it in the x-y plane of the normalised
frame, where the face looks toward +z). Along the chord the opening has a **line**
that separates its two sides: the middle of the hole where the scan shows one (an
eye, an open mouth), else the lips' contact line (the crease where closed lips meet,
found on the surface near the line through the inner-lip landmarks). Near the line,
inside a window that reaches a set share of the opening's width above, below and
beyond its corners, every point belongs to one side; outside the window a point
belongs to both.

Where the scan shows the opening as a hole, its **edges** per knot of ``a`` are the
highest and lowest b of the hole; they say how far an opening is open, and where its
rims went in an expressive scan. docs/transfer.md describes how the registration and
the carried field use them.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .image import grey_levels, pixel_coordinates, sample_image
from .landmarks import landmark_index, mirror_estimate
from .regions import smoothstep

__all__ = ["Opening", "OPENING_WINDOWS", "find_openings", "opening_sides", "opening_cut", "grid_xy", "SIDE_REACH",
           "DROPOUT_COLOUR_SHARE"]

#: Knots along each opening's chord at which its line and edges are kept.
N_KNOTS = 25
#: The window of each opening, as shares of its corner distance: how far above and
#: below its line and beyond its corners a point is taken to one side. An eye's window
#: holds its upper lid up to the fold and its lower lid (about 10 and 8 mm at an eye 23
#: mm wide); the mouth's the lips and the chin's upper part (about 14 and 22 mm at a
#: mouth 48 mm wide).
OPENING_WINDOWS = {"eye": (0.45, 0.35, 0.18), "mouth": (0.3, 0.45, 0.2)}
# A hole belongs to an opening when it reaches its chord's middle part within this
# distance of the line (mm), and spans at least this share of the middle half's knots
# (a scanner's dropout near the lips, a round patch, does not).
_HOLE_REACH_MM = 3.0
_HOLE_SPAN = 0.6
# The contact line of closed lips is searched this far (mm) either side of the line
# through the inner-lip landmarks, in steps of _CREASE_STEP_MM.
_CREASE_SEARCH_MM = 3.0
_CREASE_STEP_MM = 0.25


@dataclass(frozen=True)
class Opening:
    """One opening of a face, in the frame of the face it was found on.

    Attributes
    ----------
    name : str
        ``"right eye"``, ``"left eye"`` or ``"mouth"``.
    corners : (2, 2) ndarray
        x, y of the corner of smaller x, then of the other.
    line : (N_KNOTS,) ndarray
        b of the line between the two sides at each knot of ``a`` (0 at the corners).
    top, bottom : (N_KNOTS,) ndarray
        b of the hole's upper and lower edge at each knot; NaN where the face shows no
        hole there (a closed mouth, a closed eye, or beyond the hole's ends).
    window : (3,) tuple
        Shares of the corner distance above, below and beyond the corners
        (:data:`OPENING_WINDOWS`).
    """

    name: str
    corners: np.ndarray
    line: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    window: tuple

    @property
    def knots(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, N_KNOTS)

    @property
    def width(self) -> float:
        """Distance between the corners (mm)."""
        return float(np.linalg.norm(self.corners[1] - self.corners[0]))

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The chord's unit directions in the x-y plane: along it (a), and across it,
        pointing up (+y: b)."""
        along = (self.corners[1] - self.corners[0]) / self.width
        return along, np.array([-along[1], along[0]])

    def coordinates(self, points) -> tuple[np.ndarray, np.ndarray]:
        """The chord coordinates (a, b) of points (..., >=2)."""
        along, up = self.axes()
        offset = np.asarray(points, dtype=np.float64)[..., :2] - self.corners[0]
        return offset @ along / self.width, offset @ up

    def points_at(self, a, b) -> np.ndarray:
        """x, y (..., 2) of chord coordinates a, b."""
        along, up = self.axes()
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        return self.corners[0] + (a * self.width)[..., None] * along + b[..., None] * up

    def line_at(self, a) -> np.ndarray:
        return np.interp(a, self.knots, self.line)

    def height(self) -> np.ndarray:
        """(N_KNOTS,) how far the opening is open at each knot (mm; 0 where closed)."""
        return np.nan_to_num(self.top - self.bottom)

    def open_mm(self) -> float:
        """How far the opening is open over the middle half of its chord (the median of
        :meth:`height`; 0 closed): a stray dropout that merges with an eye's hole or
        a corner that shows no hole changes it little."""
        middle = (self.knots >= 0.25) & (self.knots <= 0.75)
        return float(np.median(self.height()[middle]))

    def area(self) -> float:
        """The open area (mm^2) between the edges."""
        height = self.height()
        return float(0.5 * np.sum(height[1:] + height[:-1]) * (self.knots[1] - self.knots[0]) * self.width)

    def sides(self, points, reach: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """For points (..., >=2): the side of the line (+1 above, -1 below) and how
        fully the point belongs to that side alone, in [0, 1]: 1 inside the window
        (scaled by ``reach``), falling smoothly to 0 over its outer 30 % and beyond the
        corners."""
        a, b = self.coordinates(points)
        offset = b - self.line_at(a)
        above = offset > 0
        up, down, beyond = (reach * share * self.width for share in self.window)
        lateral = beyond / self.width
        along = smoothstep(-lateral, 0.0, a) * smoothstep(1.0 + lateral, 1.0, a)
        across = np.where(above, smoothstep(up, 0.7 * up, offset), smoothstep(-down, -0.7 * down, offset))
        split = np.nan_to_num(along * across)
        return np.where(above, 1.0, -1.0), split

    def seen_in(self, grid, xy=None) -> "Opening":
        """This opening (same corners and line) with the edges of the hole that a grid
        of another scan of the face, in the same frame, shows at it (``xy``: the
        grid's :func:`grid_xy`, when the caller has it already). Where an eye shows no
        hole, its edges are those of the dark line where its lids meet, when the
        grid's colour image shows one (:func:`_meeting_line`)."""
        xy = grid_xy(grid.points, grid.mask) if xy is None else xy
        top, bottom = _hole_edges(self, grid, xy)[:2]
        if self.name != "mouth" and grid.image is not None:
            top, bottom = _meeting_line(self, grid, xy, top, bottom)
        return replace(self, top=top, bottom=bottom)

    def rim(self, grid, side: str, xy=None) -> np.ndarray:
        """Flat indices of the grid's valid vertices that border the hole on one side
        (``"top"``: the upper lid, the upper lip; ``"bottom"``), away from the corners
        (``xy`` as in :meth:`seen_in`)."""
        hole = _hole_edges(self, grid, xy)[2]
        if hole is None:
            return np.zeros(0, dtype=np.int64)
        border = ndimage.binary_dilation(hole, structure=np.ones((3, 3), dtype=bool)) & grid.mask
        a, b = self.coordinates(grid.points)
        offset = b - self.line_at(a)
        on_side = offset > 0 if side == "top" else offset < 0
        return np.flatnonzero((border & on_side & (a > 0.05) & (a < 0.95)).ravel())

    def rim_targets(self, rim_points, moved: "Opening", side: str) -> np.ndarray:
        """Where the rim points (k, 3) of one side of this opening went, as x, y (k, 2),
        given the opening as another scan shows it (:meth:`seen_in`): each keeps its
        distance from the hole's edge; where the other scan shows the opening closed,
        both rims meet at this opening's lower edge (the lower lid and the lower lip
        move little as an eye closes)."""
        a, b = self.coordinates(rim_points)
        own_top, own_bottom = _at(self, self.top, a), _at(self, self.bottom, a)
        new_top, new_bottom = _at(self, moved.top, a), _at(self, moved.bottom, a)
        closed = ~np.isfinite(new_top) | ~np.isfinite(new_bottom)
        if side == "top":
            target = np.where(closed, own_bottom, new_top) + (b - own_top)
        else:
            target = np.where(closed, own_bottom, new_bottom) + (b - own_bottom)
        return self.points_at(a, target)


def _at(opening: Opening, values: np.ndarray, a) -> np.ndarray:
    """values (per knot) at a, linear between the knots that have one; NaN elsewhere."""
    known = np.isfinite(values)
    out = np.full(np.shape(a), np.nan)
    if known.sum() >= 2:
        knots = opening.knots[known]
        inside = (a >= knots[0]) & (a <= knots[-1])
        out[inside] = np.interp(np.asarray(a)[inside], knots, values[known])
    return out


def grid_xy(points, mask) -> np.ndarray:
    """x, y (H, W, 2) of every grid vertex, valid or not: the grid's rows and columns
    are regular in its scan's frame, so an affine map of (row, column) fitted on the
    valid vertices gives the invalid ones (a hole's vertices have no position of their
    own). One least-squares fit over the grid: a caller that asks about several
    openings of one grid fits it once and passes it on."""
    height, width = mask.shape
    rows, columns = np.mgrid[0:height, 0:width]
    design = np.column_stack([rows[mask], columns[mask], np.ones(int(mask.sum()))])
    coefficients, *_ = np.linalg.lstsq(design, points[mask][:, :2], rcond=None)
    return np.stack([rows, columns, np.ones_like(rows)], axis=-1) @ coefficients


#: A hole whose mean colour lies within this share of the skin's around it (the length
#: of the colours' difference over that of the skin's colour) is a dropout: the scanner
#: lost the depth there, but the camera saw skin. On the development scans an eye's or a
#: mouth's hole is at 0.5 and more (dark, or an eye's white), a dropout at 0.1 or less.
DROPOUT_COLOUR_SHARE = 0.25
# The skin around a hole: the valid vertices within this many grid steps of it.
_RING_STEPS = 2


def _hole_edges(opening: Opening, grid, xy=None):
    """The hole a grid shows at the opening: its top and bottom edge per knot (NaN
    where there is none) and the hole's grid mask (None without one). ``xy``: the
    grid's :func:`grid_xy`, when the caller has it already. A hole whose colour is the
    skin's is a dropout, not the opening (:func:`_shows_skin`)."""
    nothing = np.full(N_KNOTS, np.nan)
    mask = grid.mask
    if not mask.any():
        return nothing, nothing.copy(), None
    a, b = opening.coordinates(grid_xy(grid.points, mask) if xy is None else xy)
    offset = b - opening.line_at(a)
    up, down = (share * opening.width for share in opening.window[:2])
    candidates = ~mask & (a > -0.05) & (a < 1.05) & (offset < up) & (offset > -down)
    labels, _ = ndimage.label(candidates)
    core = candidates & (a > 0.25) & (a < 0.75) & (np.abs(offset) < _HOLE_REACH_MM)
    ids = [i for i in np.unique(labels[core]) if i > 0 and not _shows_skin(grid, labels == i)]
    if len(ids) == 0:
        return nothing, nothing.copy(), None
    hole = np.isin(labels, ids)
    knot = np.rint(a[hole] * (N_KNOTS - 1)).astype(np.int64)
    inside = (knot >= 0) & (knot < N_KNOTS)
    top, bottom = nothing.copy(), nothing.copy()
    np.fmax.at(top, knot[inside], b[hole][inside])
    np.fmin.at(bottom, knot[inside], b[hole][inside])
    middle = (opening.knots >= 0.25) & (opening.knots <= 0.75)
    if np.isfinite(top[middle]).mean() < _HOLE_SPAN:
        return nothing, nothing.copy(), None
    return top, bottom, hole


def _shows_skin(grid, hole: np.ndarray) -> bool:
    """Whether the grid's colour image shows skin like the skin around it in the hole
    (H, W bool; :data:`DROPOUT_COLOUR_SHARE`): the scanner lost the depth of skin it saw
    at a grazing angle or through a highlight, and a hole over a closed eye is then no
    open eye. False without an image."""
    if grid.image is None:
        return False
    ring = ndimage.binary_dilation(hole, iterations=_RING_STEPS) & grid.mask
    if not ring.any():
        return False
    # the nearest pixel of each vertex: a mean over a hole needs no interpolation
    def colours(where):
        columns, rows = (np.rint(c).astype(np.int64) for c in pixel_coordinates(grid.image, grid.uv[where]))
        return grid.image[rows, columns].reshape(len(rows), -1).astype(np.float64)

    skin = colours(ring).mean(axis=0)
    return bool(np.linalg.norm(colours(hole).mean(axis=0) - skin) < DROPOUT_COLOUR_SHARE * np.linalg.norm(skin))


#: Where a scan shows an eye without a hole, its lids meet at a dark line in the colour
#: image (the lashes, or a slit narrower than the scan resolves): the run of the eye's
#: vertical profile darker than this share of the skin's grey level there (its 75th
#: percentile), near the open eye's lower edge (from :data:`_MEETING_BELOW_MM` below it
#: to :data:`_MEETING_ABOVE_SHARE` of the eye's height above it).
DARK_LINE_SHARE = 0.8
_MEETING_BELOW_MM = 2.0
_MEETING_ABOVE_SHARE = 0.35
_MEETING_STEP_MM = 0.25
# A knot's line more than this (mm) off the median of its own and its two neighbours'
# is a freckle or a shadow, not the lids' line.
_MEETING_OUTLIER_MM = 1.5


def _meeting_line(opening: Opening, grid, xy, top, bottom):
    """``top`` and ``bottom`` (per knot, NaN where the grid shows no hole) completed
    where the grid shows no hole and ``opening`` (the open eye) has one, by the dark
    line where the closed lids meet (:data:`DARK_LINE_SHARE`): the upper lid's rim went
    to the line's top, the lower lid's stayed."""
    knots = np.flatnonzero(~np.isfinite(top) & np.isfinite(opening.top) & np.isfinite(opening.bottom))
    if len(knots) == 0:
        return top, bottom
    line = np.full(N_KNOTS, np.nan)
    profiles = [np.arange(opening.bottom[k] - _MEETING_BELOW_MM,
                          opening.bottom[k] + _MEETING_ABOVE_SHARE * (opening.top[k] - opening.bottom[k]),
                          _MEETING_STEP_MM) for k in knots]
    # every knot's profile sampled at once (the image is read once)
    samples = np.concatenate([opening.points_at(np.full(len(b), opening.knots[k]), b) for k, b in zip(knots, profiles)])
    greys = np.split(_grey_at(grid, xy, samples), np.cumsum([len(b) for b in profiles])[:-1])
    for k, b, grey in zip(knots, profiles, greys):
        if len(b) < 3 or not np.isfinite(grey).all():
            continue
        dark = grey < DARK_LINE_SHARE * np.percentile(grey, 75)
        darkest = int(np.argmin(grey))
        if dark[darkest]:
            # the top of the run of dark samples around the darkest
            line[k] = b[darkest + int(np.argmin(dark[darkest:])) - 1] if not dark[darkest:].all() else b[-1]
    known = np.isfinite(line)
    if known.sum() >= 3:
        neighbours = ndimage.median_filter(np.where(known, line, np.nan)[known], size=3, mode="nearest")
        line[np.flatnonzero(known)[np.abs(line[known] - neighbours) > _MEETING_OUTLIER_MM]] = np.nan
    found = np.isfinite(line)
    # the upper lid's rim ends at the line's top; the lower lid stays (the line's lower
    # part is the lashes hanging over it)
    return np.where(found, line, top), np.where(found, opening.bottom, bottom)


def _grey_at(grid, xy, points_xy) -> np.ndarray:
    """The grey level of the grid's colour image at x, y (k, 2): the grid's rows and
    columns are affine in x, y (``xy``: :func:`grid_xy`), its u,v bilinear between
    them; NaN beyond the grid."""
    origin = xy[0, 0]
    steps = np.column_stack([xy[1, 0] - origin, xy[0, 1] - origin])  # x, y per row and per column
    cells = np.linalg.solve(steps, (np.asarray(points_xy, dtype=np.float64) - origin).T)
    inside = ((cells >= 0) & (cells <= np.array(grid.mask.shape)[:, None] - 1)).all(axis=0)
    uv = np.stack([ndimage.map_coordinates(grid.uv[..., c], cells, order=1, mode="nearest") for c in range(2)], axis=-1)
    grey = grey_levels(sample_image(grid.image, uv)).astype(np.float64)
    return np.where(inside, grey, np.nan)


def _crease(face, opening: Opening) -> np.ndarray:
    """The contact line of closed lips: at each knot, the lowest point (smallest z) of
    the surface's vertical profile near the opening's line, where the lips meet in a
    crease; the line itself where the profile is not seen."""
    offsets = np.arange(-_CREASE_SEARCH_MM, _CREASE_SEARCH_MM + 1e-9, _CREASE_STEP_MM)
    knots = opening.knots[1:-1]
    b = opening.line[1:-1, None] + offsets[None, :]
    xy = opening.points_at(np.broadcast_to(knots[:, None], b.shape), b).reshape(-1, 2)
    surface = face.surface()
    top = float(np.nanmax(face.grid.points[..., 2])) + 100.0
    hits = surface.intersect_rays(np.column_stack([xy, np.full(len(xy), top)]),
                                  np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    z = np.where(hits.hit, hits.points[:, 2], np.inf).reshape(b.shape)
    seen = np.isfinite(z).any(axis=1)
    line = opening.line.copy()
    line[1:-1][seen] = b[seen, np.argmin(z[seen], axis=1)]
    # one noisy profile must not kink the line: a running median over three knots
    line[1:-1] = ndimage.median_filter(line, size=3, mode="nearest")[1:-1]
    return line


def find_openings(face) -> dict[str, Opening]:
    """The openings of a face (a :class:`tpscore.face.normalise.NormalisedFace`, or any
    object with ``grid`` and ``surface()`` in a frame looking toward +z) whose corner
    landmarks are present: ``"right eye"``, ``"left eye"``, ``"mouth"``.

    An eye's line is the middle of its hole (or the chord where the scan shows none).
    The mouth's is the middle of its hole when the scan shows one, else the lips'
    contact line near the curve through the corners and the inner-lip landmarks.
    """
    grid = face.grid
    landmarks = grid.landmarks
    found = {}
    xy = grid_xy(grid.points, grid.mask) if grid.mask.any() else None  # one fit for the three openings

    def corner(name):
        # a missing corner is its partner's mirror image: an eye or a mouth found
        # between approximate corners is still cut where it opens, rather than smeared
        point = landmarks[landmark_index(name)]
        if not np.isfinite(point).all():
            point = mirror_estimate(landmarks, landmark_index(name))
        return None if point is None else point[:2]

    for side in ("right", "left"):
        inner, outer = corner(f"Inner {side} eye corner"), corner(f"Outer {side} eye corner")
        if inner is not None and outer is not None and np.linalg.norm(inner - outer) > 1.0:
            corners = np.array(sorted([inner, outer], key=lambda p: p[0]))
            found[f"{side} eye"] = _with_hole(Opening(f"{side} eye", corners, np.zeros(N_KNOTS), np.full(N_KNOTS, np.nan),
                                                      np.full(N_KNOTS, np.nan), OPENING_WINDOWS["eye"]), grid, xy)
    right, left = corner("Right mouth corner"), corner("Left mouth corner")
    if right is not None and left is not None and np.linalg.norm(right - left) > 1.0:
        corners = np.array(sorted([right, left], key=lambda p: p[0]))
        mouth = Opening("mouth", corners, np.zeros(N_KNOTS), np.full(N_KNOTS, np.nan), np.full(N_KNOTS, np.nan),
                        OPENING_WINDOWS["mouth"])
        inner = [landmarks[landmark_index(n)] for n in ("Upper lip inner middle", "Lower lip inner middle")]
        inner = [p for p in inner if np.isfinite(p).all()]
        if inner:
            # a parabola through the corners and the inner lips' middle
            a, b = mouth.coordinates(np.mean(inner, axis=0))
            a = float(np.clip(a, 0.2, 0.8))
            knots = mouth.knots
            mouth = replace(mouth, line=float(b) * knots * (1.0 - knots) / (a * (1.0 - a)))
        mouth = _with_hole(mouth, grid, xy)
        if not np.isfinite(mouth.top).any():
            mouth = replace(mouth, line=_crease(face, mouth))
        found["mouth"] = mouth
    return found


def _with_hole(opening: Opening, grid, xy=None) -> Opening:
    """The opening with the hole the grid shows at it; its line then runs through the
    hole's middle (and to the corners)."""
    top, bottom, _ = _hole_edges(opening, grid, xy)
    middle = 0.5 * (top + bottom)
    known = np.isfinite(middle)
    line = opening.line
    if known.sum() >= 2:
        knots = np.r_[0.0, opening.knots[known], 1.0]
        line = np.interp(opening.knots, knots, np.r_[0.0, middle[known], 0.0])
    return replace(opening, line=line, top=top, bottom=bottom)


#: How much farther than its window an opening decides which side's motion a point
#: takes: a side's motion is fitted without the other side's window and is poor just
#: beyond it (a mouth's upper-side motion at the chin below the window).
SIDE_REACH = 2.0


def opening_sides(openings, points) -> np.ndarray:
    """The share in [0, 1] of the upper side's motion at points (..., >=2): 1 above an
    opening's line and 0 below it, within :data:`SIDE_REACH` times its window; 0.5
    farther from every opening (both sides agree there), a smooth blend between."""
    share = np.full(np.shape(points)[:-1], 0.5)
    for opening in openings:
        side, split = opening.sides(points, SIDE_REACH)
        share = np.where(split > 0, 0.5 + 0.5 * side * split, share)
    return share


def opening_cut(openings, points) -> np.ndarray:
    """The side (+1 above, -1 below, 0 elsewhere) of each point (..., >=2) of the line of
    the opening whose window it lies in, between the opening's corners only: where the
    two sides' motions tear apart (a mesh opens between +1 and -1)."""
    cut = np.zeros(np.shape(points)[:-1], dtype=np.int8)
    for opening in openings:
        a, _ = opening.coordinates(points)
        side, split = opening.sides(points)
        inside = (split > 0.5) & (a > 0.0) & (a < 1.0)
        cut = np.where(inside, side.astype(np.int8), cut)
    return cut
