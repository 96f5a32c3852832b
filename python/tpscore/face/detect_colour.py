"""The colour cues of :mod:`tpscore.face.detect`: brows, eye openings and lips read off
the scan's colour image.

The cues work on the scan's grid, each point with the colour its u,v see, in the fitted
face's axes (x to the face's left, y up). They read colour relative to the skin around
them, not absolute colours: the brows are a band darker than the skin beside it, the eye
openings are holes in the scan or much darker than the skin, the lips are redder than the
skin of the lower face. A cue that finds nothing convincing (no band of the right
length, no opening, no red of the lips' size) leaves the geometric estimate as it is.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .image import grey_levels, sample_image
from .landmarks import landmark_index

__all__ = ["ColourScan", "colour_scan", "refine_with_colour"]

_TIP = landmark_index("Nose tip")
#: Each brow's landmarks: (outer, middle, inner) and the sign of the face's x on its side.
_BROWS = (((landmark_index("Outer left eyebrow"), landmark_index("Middle left eyebrow"),
            landmark_index("Inner left eyebrow")), 1.0),
          ((landmark_index("Outer right eyebrow"), landmark_index("Middle right eyebrow"),
            landmark_index("Inner right eyebrow")), -1.0))
#: Each eye's (outer, inner) corners and the sign of the face's x on its side.
_EYES = (((landmark_index("Outer left eye corner"), landmark_index("Inner left eye corner")), 1.0),
         ((landmark_index("Outer right eye corner"), landmark_index("Inner right eye corner")), -1.0))
_LEFT_CORNER = landmark_index("Left mouth corner")
_RIGHT_CORNER = landmark_index("Right mouth corner")
_UPPER_OUTER = landmark_index("Upper lip outer middle")
_LOWER_OUTER = landmark_index("Lower lip outer middle")
_UPPER_INNER = landmark_index("Upper lip inner middle")
_LOWER_INNER = landmark_index("Lower lip inner middle")

#: The skin level a point's darkness is judged against: the lightest grey level of the
#: scan within about this radius (mm), smoothed.
_SKIN_RADIUS_MM = 7.0
#: A brow band is at least this long (mm) across the face, an eye opening this wide.
_MIN_BROW_MM, _MIN_EYE_MM, _MAX_EYE_MM = 18.0, 14.0, 45.0
#: The lips' red stretches at least this far across the face (mm), at most the second.
_MIN_MOUTH_MM, _MAX_MOUTH_MM = 25.0, 85.0
#: An eye opening that is not a hole is darker than the skin by at least this fraction.
_EYE_DARKNESS = 0.45
#: The inner eye corner: the deepest scan points within this distance (mm, across the
#: face) of the opening's medial end.
_HOLLOW_MM = 8.0
#: A brow's band: darker than the skin by at least the first fraction somewhere, and
#: by the second all along it.
_BROW_STRONG, _BROW_WEAK = 0.08, 0.05
#: A landmark at an end of a region: the mean of its points within this distance (mm)
#: of the extreme one along the face.
_END_MM = 1.5
#: The inner brow: the band's cells this far (mm, across the face) inside its medial
#: tip, where the brow is dense enough to be marked; the middle brow: the band's cells
#: this fraction of the way from there to the band's lateral end (across the face). Both
#: from the development scans (subjects 0-9, 14 expressions): the inner brows' median
#: error 2.4 / 2.4 mm at the tip, 1.3 / 1.2 here; the middle brows' 2.8 / 3.5 mm between
#: the top of the band's arch and its middle, 1.4 / 1.7 here (5.9 / 5.8 at 0.47, 3.4 at 0.6).
_INNER_BROW_INSET_MM, _MIDDLE_BROW_FRACTION = 2.0, 0.55
#: The anatomical corners lie beyond the colour's ends: the inner eye corner this far
#: (mm, across the face) medial of the hollow beside the opening's end, the mouth
#: corner this far lateral of the red's end, where the lips' colour has faded (the
#: development scans' median offsets, subjects 0-9, 14 expressions: 1.6-1.7 and
#: 1.9-2.0 mm).
_INNER_EYE_CORNER_INSET_MM, _MOUTH_CORNER_OUTSET_MM = 1.7, 2.0
#: A piece of a brow's band joins it across a gap of at most this (mm, across the face)
#: and a step in height of at most the second (mm) plus the third times the gap: a
#: brow's tail falls steeply toward the temple. From the development scans (subjects
#: 0-9, 14 expressions, every landmark's mean error): 2.85 mm with a gap of 12 and a
#: step of 4, 2.82 with steps of 4 + 0.5 per mm, 2.81 with 4 + 0.7 (as with 4 + 1.0),
#: 2.80 with gaps up to 16 (as up to 20).
_JOIN_GAP_MM, _JOIN_RISE_MM, _JOIN_RISE_PER_MM = 16.0, 4.0, 0.7


@dataclass
class ColourScan:
    """A scan grid with the colour each point sees: ``rgb`` (H, W, 3) in [0, 1],
    ``valid`` (H, W), ``xyz`` (H, W, 3) with holes filled (x, y from the grid's lattice,
    z from the nearest valid point), ``grey`` and ``darkness`` (H, W; the fraction a
    point is darker than the skin around it) and ``spacing`` (mm between grid points)."""

    rgb: np.ndarray
    valid: np.ndarray
    xyz: np.ndarray
    grey: np.ndarray
    darkness: np.ndarray
    spacing: float

    def cells(self, mm: float) -> float:
        return mm / self.spacing


def _lattice_xy(grid: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """x, y of every grid point (holes too) from the affine map (row, column) -> x, y
    the valid points follow; None when they do not lie on a lattice."""
    rows, cols = np.nonzero(valid)
    design = np.column_stack([rows, cols, np.ones(len(rows))]).astype(np.float64)
    xy = grid[rows, cols, :2]
    affine, *_ = np.linalg.lstsq(design, xy, rcond=None)
    if np.abs(design @ affine - xy).max() > 0.05 * max(np.abs(affine[:2]).max(), 1e-9):
        return None
    r, c = np.mgrid[0:grid.shape[0], 0:grid.shape[1]]
    return np.stack([r, c, np.ones_like(r)], axis=-1).astype(np.float64) @ affine


def colour_scan(grid: np.ndarray, image: np.ndarray, uv: np.ndarray) -> ColourScan | None:
    """The colour cues' view of a grid scan (NaN at holes) with its image and per-point
    u,v; None when the grid is not a regular lattice."""
    valid = np.isfinite(grid).all(axis=2)
    xy = _lattice_xy(grid, valid)
    if xy is None:
        return None
    spacing = float(np.sqrt(abs(np.linalg.det(np.stack([xy[1, 0] - xy[0, 0], xy[0, 1] - xy[0, 0]])))))
    if not spacing > 0:
        return None
    nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    xyz = np.concatenate([xy, grid[nearest[0], nearest[1], 2][..., None]], axis=-1)
    coords = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=0.0)
    # the image is finer than the grid: averaged over a grid step before it is sampled
    step = spacing / max(np.linalg.norm(xy[0, 1] - xy[0, 0]), 1e-9) * image.shape[1] / grid.shape[1]
    picture = np.asarray(image, dtype=np.float32)
    if step > 1.5:
        picture = ndimage.gaussian_filter(picture, sigma=(step / 3, step / 3, 0))
    rgb = np.clip(sample_image(picture, coords) / 255.0, 0.0, 1.0)
    grey = grey_levels(rgb).astype(np.float64)
    # the skin level around each point: the grey level's closing over a disk wider than a
    # brow or an eye, so that narrow dark features do not lower it but broad shading does
    nearest_grey = grey[nearest[0], nearest[1]]
    skin = ndimage.grey_closing(nearest_grey, footprint=_disk(_SKIN_RADIUS_MM / spacing))
    skin = ndimage.gaussian_filter(skin, 2.0 / spacing)
    darkness = np.where(valid, 1.0 - grey / np.maximum(skin, 1e-3), np.nan)
    return ColourScan(rgb, valid, xyz, grey, darkness, spacing)


def _disk(radius_cells: float) -> np.ndarray:
    r = max(1, int(round(radius_cells)))
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= radius_cells * radius_cells + 0.25


def _end(cells_u: np.ndarray, which: float) -> np.ndarray:
    """The cells within :data:`_END_MM` of the extreme along u (which = +1: the largest)."""
    extreme = cells_u.max() if which > 0 else cells_u.min()
    return np.abs(cells_u - extreme) <= _END_MM


def _components(mask: np.ndarray, min_cells: float) -> list[np.ndarray]:
    labels, count = ndimage.label(mask)
    if count == 0:
        return []
    sizes = np.bincount(labels.ravel())
    return [labels == k for k in range(1, count + 1) if sizes[k] >= min_cells]


def _brow(result, cs: ColourScan, frame, marks, indices, side) -> bool:
    """One brow: the highest long dark band across the face near the fitted brow. The
    inner brow lies a little inside its medial tip, the outer brow at its lateral end,
    and the middle brow part of the way between them."""
    outer, middle, inner = indices
    here = marks[list(indices)]
    if not np.isfinite(here).all():
        return False
    u, v = frame[..., 0], frame[..., 1]
    window = ((side * u > 3.0) & (side * u < side * here[0, 0] + 20.0)
              & (v > here[:, 1].min() - 12.0) & (v < here[:, 1].max() + 14.0))
    inside = ndimage.binary_erosion(cs.valid, _disk(cs.cells(1.5))) & window
    if inside.sum() < cs.cells(10.0) ** 2:
        return False
    darkness = ndimage.gaussian_filter(np.nan_to_num(cs.darkness, nan=0.0), cs.cells(0.8))
    top = np.percentile(darkness[inside], 98)
    strong = ndimage.binary_opening((darkness > max(_BROW_STRONG, 0.5 * top)) & inside, _disk(cs.cells(1.0)))
    weak = ndimage.binary_opening((darkness > max(_BROW_WEAK, 0.35 * top)) & inside, _disk(cs.cells(0.7)))
    # the weak mask's parts, labelled once: the larger are candidate bands, any may
    # continue the chosen one
    pieces = _components(weak, cs.cells(2.0) ** 2)
    best, height = None, -np.inf
    for component in (p for p in pieces if p.sum() >= cs.cells(4.0) ** 2):
        # a band is judged whole: a broken brow's pieces are each too short, or their
        # arched tail too steep, and the shadow below would win (development scans'
        # every landmark: 2.87 mm judging each piece alone, 2.85 joined first)
        component = _join_pieces(component, pieces, u, v)
        if not (component & strong).sum() >= cs.cells(3.0) ** 2:
            continue
        extent = np.ptp(u[component])
        if not (extent > _MIN_BROW_MM and np.ptp(v[component]) < 0.6 * extent):
            continue
        # the highest band: the shadow under the brow ridge and the lid's crease, often
        # darker and longer than a light brow, lie below it, the bare forehead above
        # (development scans' brows: 4.3 mm mean error with the longest band, 4.1 with the highest)
        centre = float(np.median(v[component]))
        if centre > height:
            best, height = component, centre
    if best is None:
        return False
    across = side * u[best]
    points = cs.xyz[best]
    result[outer] = points[_end(across, 1)].mean(axis=0)
    result[inner] = points[_end(across, -1)].mean(axis=0)
    start = across.min() + _INNER_BROW_INSET_MM
    for index, at in ((inner, start), (middle, start + _MIDDLE_BROW_FRACTION * (across.max() - start))):
        column = np.abs(across - at) <= _END_MM
        if column.any():
            result[index] = points[column].mean(axis=0)
    return True


def _join_pieces(band: np.ndarray, pieces: list[np.ndarray], u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The band with the pieces that continue it joined: a light brow breaks into
    pieces along its line. A piece joins when it starts within :data:`_JOIN_GAP_MM`
    across the face of an end of the band, its own end within :data:`_JOIN_RISE_MM`
    (and :data:`_JOIN_RISE_PER_MM` per mm of the gap) of the band's end in height
    (development scans, 14 expressions: the brows' mean error 2.47 mm without joining,
    2.30 with gaps up to 8 mm, 2.25 up to 12; 1.99 once the rise may grow with the gap,
    the gap reaches 16 mm and candidate bands are judged joined)."""
    joined = True
    while joined:
        joined = False
        bu, bv = u[band], v[band]
        for piece in pieces:
            if (piece & band).any():
                continue
            pu, pv = u[piece], v[piece]
            # the piece beyond the band's larger-u end, or beyond its smaller-u end
            for gap, band_end, piece_end in (
                    (pu.min() - bu.max(), bv[bu >= bu.max() - 3.0], pv[pu <= pu.min() + 3.0]),
                    (bu.min() - pu.max(), bv[bu <= bu.min() + 3.0], pv[pu >= pu.max() - 3.0])):
                rise = abs(piece_end.mean() - band_end.mean())
                if -1.0 < gap < _JOIN_GAP_MM and rise < _JOIN_RISE_MM + _JOIN_RISE_PER_MM * max(gap, 0.0):
                    band = band | piece
                    joined = True
                    break
    return band


def _eye(result, cs: ColourScan, frame, marks, indices, side) -> bool:
    """One eye: the opening near the fitted corners (a hole in the scan, or a region
    much darker than the skin); its lateral end is the outer corner, and the inner
    corner lies just medial of the hollow beside its medial end."""
    outer, inner = indices
    here = marks[list(indices)]
    if not np.isfinite(here).all():
        return False
    u, v = frame[..., 0], frame[..., 1]
    centre = here.mean(axis=0)
    window = (np.abs(u - centre[0]) < 22.0) & (np.abs(v - centre[1]) < 9.0) & (side * u > 2.0)
    opening = ~cs.valid | (np.nan_to_num(cs.darkness, nan=1.0) > _EYE_DARKNESS)
    opening = ndimage.binary_opening(opening, _disk(cs.cells(0.7)))
    labels, count = ndimage.label(opening)
    if count == 0:
        return False
    border = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    counts = np.bincount(labels[window], minlength=count + 1)
    counts[0] = 0
    counts[border] = 0
    k = int(np.argmax(counts))
    if counts[k] < cs.cells(3.0) ** 2:
        return False
    component = labels == k
    cu, cv = u[component], v[component]
    if not (_MIN_EYE_MM <= np.ptp(cu) <= _MAX_EYE_MM) or np.ptp(cv) > 20.0:
        return False
    # the corners on the scan: the valid points along the opening's rim at its ends
    rim = ndimage.binary_dilation(component, _disk(cs.cells(1.0))) & cs.valid & ~component
    if rim.sum() < 4:
        return False
    ru = side * u[rim]
    points = cs.xyz[rim]
    result[outer] = points[_end(ru, 1)].mean(axis=0)
    # the inner corner lies in the hollow beside the opening's medial end: the deepest
    # scan points near that end
    end = frame[rim][_end(ru, -1)].mean(axis=0)
    near = cs.valid & ((u - end[0]) ** 2 + (v - end[1]) ** 2 < _HOLLOW_MM ** 2)
    if near.sum() < 5:
        result[inner] = points[_end(ru, -1)].mean(axis=0)
        return True
    depth = frame[..., 2][near]
    deepest = depth <= np.quantile(depth, 0.05)
    hollow = frame[near][deepest].mean(axis=0)
    result[inner] = _surface_at(cs, frame, hollow[0] - side * _INNER_EYE_CORNER_INSET_MM, hollow[1],
                                fallback=cs.xyz[near][deepest].mean(axis=0))
    return True


def _surface_at(cs: ColourScan, frame, u: float, v: float, fallback: np.ndarray) -> np.ndarray:
    """The scan's surface at a point of the face's plane: the mean of the valid grid
    points within a grid step of it (``fallback`` where there are none)."""
    close = cs.valid & ((frame[..., 0] - u) ** 2 + (frame[..., 1] - v) ** 2 <= cs.spacing ** 2)
    return cs.xyz[close].mean(axis=0) if close.any() else fallback


def _lips(result, cs: ColourScan, frame, marks) -> bool:
    """The lips: the region redder than the lower face's skin around the fitted mouth.
    Just beyond its ends across the face are the mouth corners; on the column midway between them,
    its top and bottom are the outer lip middles, and the gap between the upper and the
    lower red (the line where the lips meet, or the open mouth) gives the inner ones."""
    mouth = [_LEFT_CORNER, _RIGHT_CORNER, _UPPER_OUTER, _LOWER_OUTER]
    here = marks[mouth]
    if not np.isfinite(here).all():
        return False
    u, v = frame[..., 0], frame[..., 1]
    window = (np.abs(u) < 45.0) & (v < -12.0) & (v > -75.0)
    inside = cs.valid & window
    if inside.sum() < cs.cells(10.0) ** 2:
        return False
    total = cs.rgb.sum(axis=-1)
    redness = np.where(cs.valid, cs.rgb[..., 0] / np.maximum(total, 1e-3), 0.0)
    redness = ndimage.gaussian_filter(redness, cs.cells(0.7))
    skin = np.median(redness[inside])
    top = np.percentile(redness[inside], 99)
    if top - skin < 0.02:
        return False
    mask = ndimage.binary_opening((redness > skin + 0.5 * (top - skin)) & inside, _disk(cs.cells(0.7)))
    parts = _components(mask, cs.cells(3.0) ** 2)
    if not parts:
        return False
    biggest = max(int(p.sum()) for p in parts)
    lips = np.zeros_like(mask)
    for part in parts:
        if part.sum() >= 0.15 * biggest:
            lips |= part
    cu, cv = u[lips], v[lips]
    if not (_MIN_MOUTH_MM <= np.ptp(cu) <= _MAX_MOUTH_MM):
        return False
    points = cs.xyz[lips]
    for corner, which in ((_LEFT_CORNER, 1), (_RIGHT_CORNER, -1)):
        end = _end(cu, which)
        result[corner] = _surface_at(cs, frame, cu[end].mean() + which * _MOUTH_CORNER_OUTSET_MM, cv[end].mean(),
                                     fallback=points[end].mean(axis=0))
    middle = (cu.max() + cu.min()) / 2
    column = np.abs(u - middle) <= 1.0
    red = column & lips
    if red.sum() < 3:
        return True
    rv = v[red]
    result[_UPPER_OUTER] = cs.xyz[red][rv >= rv.max() - 0.7].mean(axis=0)
    result[_LOWER_OUTER] = cs.xyz[red][rv <= rv.min() + 0.7].mean(axis=0)
    # the column's profile from the top of the red to its bottom, in grid steps
    step = cs.spacing
    bins = np.arange(rv.min(), rv.max() + step, step)
    band = column & (v >= rv.min() - step) & (v <= rv.max() + step)
    which = np.clip(np.digitize(v[band], bins) - 1, 0, len(bins) - 1)
    is_red = lips[band]
    fraction = np.bincount(which, weights=is_red, minlength=len(bins)) / np.maximum(
        np.bincount(which, minlength=len(bins)), 1)
    red_bins = fraction >= 0.5
    gap = np.flatnonzero(~red_bins)
    if len(gap):
        # the longest run of bins without red: the gap between the lips
        runs = np.split(gap, np.flatnonzero(np.diff(gap) > 1) + 1)
        run = max(runs, key=len)
        below, above = run[0] - 1, run[-1] + 1
        if below >= 0 and above < len(bins):
            upper = red & (np.abs(v - bins[above]) <= step)
            lower = red & (np.abs(v - bins[below]) <= step)
            if upper.any() and lower.any():
                result[_UPPER_INNER] = cs.xyz[upper].mean(axis=0)
                result[_LOWER_INNER] = cs.xyz[lower].mean(axis=0)
                return True
    # no gap: the inner lips keep the geometric cues' contact line
    return True


def refine_with_colour(result: np.ndarray, cs: ColourScan, rotation: np.ndarray):
    """The landmarks the colour cues find, the others as they were, and which ones are
    scan points already (the corners at an opening's rim or the lips' ends, whose depth
    the projection onto the surface would pull out of the fold they sit in)."""
    result = result.copy()
    tip = result[_TIP]
    if not np.isfinite(tip).all():
        return result, np.zeros(len(result), dtype=bool), False
    frame = (cs.xyz - tip) @ rotation
    marks = (result - tip) @ rotation
    placed = np.zeros(len(result), dtype=bool)
    for indices, side in _BROWS:
        _brow(result, cs, frame, marks, indices, side)
    for indices, side in _EYES:
        placed[list(indices)] = _eye(result, cs, frame, marks, indices, side)
    lips = _lips(result, cs, frame, marks)
    if lips:
        placed[[_LEFT_CORNER, _RIGHT_CORNER]] = True
    return result, placed, lips
