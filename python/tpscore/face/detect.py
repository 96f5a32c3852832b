"""Automatic landmarks: the 22 Bosphorus landmarks of a raw scan, in its own frame.

The scan's geometry and, where it has one, its colour image find them; no annotated
face model is used beyond tpscore's own
average face (:func:`~tpscore.face.average_face.load_average_face`, built from the
procedural faces):

1. a coarse nose tip, the most prominent point of the smoothed depth near the middle
   of the face (scans look toward +z), where it stands out furthest from the depth
   smoothed over a nose's size (or a point nearly as prominent above it on the
   midline: lips pushed forward stand out further than the nose);
2. the average face fitted to the scan by a trimmed similarity ICP from that nose tip,
   then once more per region (brows, eyes, nose, mouth, chin) by a rigid ICP of the
   average face's patch around the region's landmarks, which carries its landmarks
   (all once more from the most protruding point a nose's distance below the eyes when
   the nose tip lands further below them than on any face);
3. local cues: the nose tip moves to the most protruding point near it; the upper and
   lower lips to the bulges of the midline profile below the nose, the inner lips to
   the hollow between them (or the edges of the opening when the mouth is open), the
   chin to where the midline turns under the face; the mouth corners follow the lips'
   contact line; the inner eye corners move to the deepest point near them and the
   outer ones follow; the brows to the brow ridge;
4. with a colour image, the colour cues: the brows' dark bands, the ends of the eye
   openings, the lips' red region (corners, outer middles, the line between them), and
   the chin again below the lower lip;
5. the nose peaks and saddles in proportion to the landmarks found by then: the peaks
   part of the way from the nose tip to the upper lip, the saddles part of the way from
   the inner eye corners to the nose tip, each part of the corners' spacing apart;
6. every landmark onto the surface along the face's view axis; one with no scan
   surface under it (a hole, a cut) is NaN.

:mod:`tpscore.face.detect_cues` holds the local cues, :mod:`tpscore.face.detect_colour`
the colour cues; docs/landmarks.md the method and its accuracy.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._validation import as_array
from ..geometry import similarity_transform
from ..spatial import KDTree
from .landmarks import N_LANDMARKS, landmark_index
from . import detect_colour as _colour
from . import detect_cues as _cues
from .image import as_colour_image, check_image_fits

__all__ = ["detect_landmarks", "LandmarksDetectedWarning", "DETECT_REGIONS"]


class LandmarksDetectedWarning(UserWarning):
    """A scan had no landmark file: its landmarks were detected from the scan."""


#: The regions fitted one by one after the global fit: a name and its landmarks.
DETECT_REGIONS: dict[str, tuple[int, ...]] = {
    "left brow": (0, 1, 2),
    "right brow": (3, 4, 5),
    "left eye": (6, 7, 10),
    "right eye": (8, 9, 11),
    "nose": (10, 11, 12, 13, 14),
    "mouth": (15, 16, 17, 18, 19, 20),
    "chin": (20, 21),
}
#: The radius (mm) of the average face's patch around a region's landmarks.
_PATCH_RADIUS_MM = 18.0
#: A landmark with no scan point within this distance (mm, across the face) is missing.
_MISSING_MM = 2.5
#: Points the global ICP uses at most (evenly spread over the scan's grid).
_MAX_ICP_POINTS = 6000
#: The average face within this distance (mm, across the face) of its nose tip is fitted.
_GLOBAL_RADIUS_MM = 70.0
_GLOBAL_SCALE = False
#: The nose tip lies between these multiples of the inner eye corners' spacing from the
#: point between them (1.03-1.52 on the development scans' true landmarks).
_TIP_DROP_MIN, _TIP_DROP_MAX = 0.8, 1.65
_NOSE_TIP = landmark_index("Nose tip")
_INNER_EYES = (landmark_index("Inner left eye corner"), landmark_index("Inner right eye corner"))


def _scan_points(scan) -> tuple[np.ndarray, np.ndarray | None]:
    """(n, 3) finite points and, for a grid, the (H, W, 3) grid with NaN holes."""
    points = getattr(scan, "points", scan)
    if points is None:
        raise ValueError("scan: must carry points, got None")
    array = as_array(points, "scan")
    if array.dtype == object or not np.issubdtype(array.dtype, np.number):
        raise ValueError(f"scan: must be numeric points, got dtype {array.dtype}")
    array = np.asarray(array, dtype=np.float64)
    grid = None
    if array.ndim == 3 and array.shape[2] == 3:
        grid = array.copy()
        valid = getattr(scan, "valid", getattr(scan, "mask", None))
        finite = np.isfinite(grid).all(axis=2)
        if valid is not None:
            valid = np.asarray(valid, dtype=bool)
            if valid.shape != finite.shape:
                raise ValueError(f"scan: its mask has shape {valid.shape}, its points {array.shape[:2]}")
            finite &= valid
        grid[~finite] = np.nan
        flat = grid[finite]
    elif array.ndim == 2 and array.shape[1] == 3:
        if not np.isfinite(array).all():
            raise ValueError("scan: a point cloud must be finite (NaN or inf among its points)")
        flat = array
    else:
        raise ValueError(f"scan: must be (n, 3) points or an (H, W, 3) grid, got shape {array.shape}")
    if len(flat) < 200:
        raise ValueError(f"scan: needs at least 200 valid points to find a face, got {len(flat)}")
    if np.abs(flat).max() > 1e5:
        raise ValueError("scan: coordinates beyond 1e5 mm; a face is measured in millimetres")
    return flat, grid


def _similarity(source: np.ndarray, target: np.ndarray, scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t minimising |s R source + t - target|^2 (:func:`tpscore.geometry.similarity_transform`)."""
    matrix = similarity_transform(source, target, scale=scale).matrix
    s = float(np.cbrt(np.linalg.det(matrix[:3, :3]))) if scale else 1.0
    return s, matrix[:3, :3] / s, matrix[:3, 3]


def _icp(model: np.ndarray, tree: KDTree, targets: np.ndarray, s: float, rotation: np.ndarray,
         t: np.ndarray, *, scale: bool, iterations: int, keep: float, max_scale_step: float = 0.03):
    """Trimmed ICP of model points onto the scan's tree; returns s, R, t and the
    median residual (mm)."""
    residual = np.inf
    for _ in range(iterations):
        moved = s * model @ rotation.T + t
        distance, index = tree.query(moved)
        distance = np.asarray(distance).ravel()
        index = np.asarray(index).ravel()
        cut = np.quantile(distance, keep)
        use = distance <= cut
        if use.sum() < 10:
            break
        ds, dr, dt = _similarity(moved[use], targets[index[use]], scale)
        if scale:
            ds = float(np.clip(ds, 1 - max_scale_step, 1 + max_scale_step))
        s, rotation, t = ds * s, dr @ rotation, ds * dr @ t + dt
        residual = float(np.median(distance[use]))
    return s, rotation, t, residual


def _even_sample(points: np.ndarray, count: int) -> np.ndarray:
    step = max(1, len(points) // count)
    return points[::step]


def _fit(points: np.ndarray, grid: np.ndarray | None, tree: KDTree, tip: np.ndarray | None = None):
    """The average face fitted to the scan, globally from a nose tip (by default the
    most prominent point) and then region by region: its landmarks on the scan and
    the fit's rotation."""
    from .average_face import load_average_face  # the average face needs the grid module

    afm = load_average_face()
    model_all = afm.grid.points[afm.grid.mask]
    model_landmarks = afm.landmarks
    # 1. a coarse nose tip: the most prominent point of the smoothed surface
    if tip is None:
        tip = _cues.coarse_nose_tip(points, grid)
    # 2. the global fit: the average face's nose tip on it, then a similarity ICP
    central = np.linalg.norm(model_all[:, :2] - model_landmarks[_NOSE_TIP, :2], axis=1) < _GLOBAL_RADIUS_MM
    model = _even_sample(model_all[central], _MAX_ICP_POINTS)
    s, rotation, t = 1.0, np.eye(3), tip - model_landmarks[_NOSE_TIP]
    for keep in (0.6, 0.8, 0.9):
        s, rotation, t, _ = _icp(model, tree, points, s, rotation, t, scale=_GLOBAL_SCALE, iterations=12, keep=keep)
    fitted = s * model_landmarks @ rotation.T + t
    # 3. each region once more, rigidly, from the global fit
    result = fitted.copy()
    votes = np.zeros(N_LANDMARKS)
    sums = np.zeros((N_LANDMARKS, 3))
    for indices in DETECT_REGIONS.values():
        centre = np.nanmean(model_landmarks[list(indices)], axis=0)
        reach = _PATCH_RADIUS_MM + np.linalg.norm(model_landmarks[list(indices)] - centre, axis=1).max()
        near = np.linalg.norm(model_all - centre, axis=1) < reach
        patch = model_all[near]
        if len(patch) < 50:
            continue
        ls, lr, lt, _ = _icp(patch, tree, points, s, rotation, t, scale=False, iterations=10, keep=0.8)
        for i in indices:
            sums[i] += ls * lr @ model_landmarks[i] + lt
            votes[i] += 1
    has = votes > 0
    result[has] = sums[has] / votes[has, None]
    return result, rotation


def detect_landmarks(scan, *, image=None, uv=None) -> np.ndarray:
    """The 22 Bosphorus landmarks of a raw scan, found from its geometry and, when the
    scan has one, its colour image.

    Parameters
    ----------
    scan : path, BntScan, FaceGrid, (H, W, 3) grid or (n, 3) points
        The scan in its own frame: millimetres, the face looking toward +z (within a
        few tens of degrees), +y up. A grid's NaN points (or those outside its
        ``valid``/``mask``) are holes. A path names a ``.bnt`` file; the image it
        names, beside it, is used when it exists.
    image : (h, w, 3) uint8 array, path or None
        The scan's colour image. By default a FaceGrid's ``image``, or for a path the
        ``.bnt``'s image beside it; a BntScan does not know its folder, so its image is
        passed here. Without an image (or for a point cloud, which has no grid for the
        colour cues) the landmarks come from the geometry alone.
    uv : (H, W, 2) array-like, optional
        Each grid point's normalised image coordinates (u to the right, v down). By
        default a BntScan's or FaceGrid's own, or for a plain grid the pixel centres
        ``((c + 0.5) / W, (r + 0.5) / H)``.

    Returns
    -------
    (22, 3) float64
        In Bosphorus order (:data:`~tpscore.face.landmarks.LANDMARK_NAMES`), NaN rows
        where the scan has no surface at the landmark (a hole, a cut).

    Raises
    ------
    ValueError
        Naming ``scan``: not points, non-finite cloud, wrong shape, too few points, an
        unreadable file; naming ``image`` or ``uv``: not an image, an image given with
        a point cloud, u,v of another shape than the grid or outside [0, 1].
    """
    scan, image, uv = _colour_inputs(scan, image, uv)
    points, grid = _scan_points(scan)
    colour = _colour_of(grid, image, uv)
    tree = KDTree(points)
    result, rotation, placed = _detect(points, grid, tree, colour)
    eyes = result[list(_INNER_EYES)]
    spacing = np.linalg.norm(eyes[0] - eyes[1])
    between = eyes.mean(axis=0)
    if np.isfinite(spacing) and np.linalg.norm(result[_NOSE_TIP] - between) > _TIP_DROP_MAX * spacing:
        # the nose tip is further below the eyes than on any face: the fit started on
        # the lips or the chin, which stood out further than the nose. Once more from
        # the most protruding point at a nose's distance below the eyes
        tip = _cues.nose_tip_below_eyes(points, grid, between, rotation[:, 1],
                                        _TIP_DROP_MAX * spacing, _TIP_DROP_MIN * spacing)
        if tip is not None:
            result, rotation, placed = _detect(points, grid, tree, colour, tip)
    # 6. onto the surface along the view axis; a landmark without surface under it is missing
    return _cues.project_onto_surface(result, points, rotation, _MISSING_MM, keep=placed)


def _detect(points, grid, tree, colour, tip=None):
    """Steps 2-5 from a nose tip (by default the most prominent point): the landmarks,
    the fit's rotation and which landmarks are scan points already."""
    result, rotation = _fit(points, grid, tree, tip)
    # 4. local cues in the fitted frame (R^T maps scan directions to the face's)
    result = _cues.refine(result, points, tree, rotation, grid)
    placed = None
    if colour is not None:
        result, placed, lips = _colour.refine_with_colour(result, colour, rotation)
        if lips:
            _cues.refine_chin(result, points, rotation)
    # 5. the nose peaks and saddles in proportion to what was found
    _cues.place_nose_peaks(result, rotation)
    _cues.place_nose_saddles(result, rotation)
    return result, rotation, placed


def _colour_inputs(scan, image, uv):
    """The scan, its image (an array or None) and u,v (None: the scan's own or the
    pixel centres) from what was passed: a path is read with its image beside it."""
    from .io import read_bnt, read_image  # io reads files; the detector needs it only for paths

    if isinstance(scan, (str, os.PathLike)):
        path = Path(scan)
        if path.suffix.lower() != ".bnt":
            raise ValueError(f"scan: a path must name a .bnt scan, got {str(path)!r}")
        scan = read_bnt(path)
        if image is None and scan.image_name and (path.parent / scan.image_name).is_file():
            image = path.parent / scan.image_name
    if image is None:
        image = getattr(scan, "image", None)
    elif isinstance(image, (str, os.PathLike)):
        image = read_image(image)
    if image is not None:
        image = as_colour_image(image, "image")
    if uv is None:
        uv = getattr(scan, "uv", None)
    return scan, image, uv


def _colour_of(grid: np.ndarray | None, image: np.ndarray | None, uv):
    """The colour cues' view of the scan, or None without an image."""
    if image is None:
        return None
    if grid is None:
        raise ValueError("image: the colour cues need a grid scan (a .bnt, a FaceGrid or an (H, W, 3) "
                         "array); a point cloud is detected from its geometry alone, without an image")
    height, width = grid.shape[:2]
    if uv is None:
        rows, cols = np.mgrid[0:height, 0:width]
        uv = np.stack([(cols + 0.5) / width, (rows + 0.5) / height], axis=-1)
    uv = as_array(uv, "uv")
    if uv.shape != (height, width, 2):
        raise ValueError(f"uv: must have the grid's shape ({height}, {width}, 2), got {uv.shape}")
    valid = np.isfinite(grid).all(axis=2)
    check_image_fits(image, grid, uv, valid & np.isfinite(uv).all(axis=2), "image")
    return _colour.colour_scan(grid, image, uv)
