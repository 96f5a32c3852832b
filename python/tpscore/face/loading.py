"""Loading scans: a scan file (a Bosphorus ``.bnt`` with its colour image, or any mesh or
point cloud trimesh reads, with its colours), its landmarks (the file beside it, or
detected) and the face grid :func:`~tpscore.face.resampling.resample_scan` makes of them
(:func:`load_scan`, :func:`load_scans`)."""
from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import Delaunay, QhullError

from .._threads import blas_on_one_thread, num_threads
from .._validation import as_path
from ..raster import interpolate_pixels, rasterise
from .detect import LandmarksDetectedWarning, detect_landmarks
from .grid import DEFAULT_GRID_SHAPE, FaceGrid, LandmarkSnapWarning, _as_shape
from .image import as_colour_image as _as_colour_image
from .image import check_image_fits, sample_image
from .io import (BntScan, ColourWarning, MeshColours, landmark_file_beside, read_bnt, read_image,
                 read_landmarks, read_mesh_colours)
from .landmarks import as_landmarks, empty_landmarks
from .pose import scan_pose
from .resampling import DEFAULT_MAX_GAP_MM, resample_scan

__all__ = [
    "load_scan",
    "load_scans",
]

def load_scan(path, landmarks_path=None, shape=DEFAULT_GRID_SHAPE, *,
              max_gap_mm: float = DEFAULT_MAX_GAP_MM, image_path=None, detect: bool = True) -> FaceGrid:
    """Read a scan and its landmarks and resample them with :func:`~tpscore.face.resampling.resample_scan`.

    Parameters
    ----------
    path : str or PathLike
        A Bosphorus ``.bnt``, or any mesh or point cloud trimesh reads (its vertices
        are the points). A mesh's colours come with it (:func:`~tpscore.face.io.read_mesh_colours`): an
        OBJ's texture through its ``.mtl`` (a texture whose u,v map the face's x, y with
        square pixels, as :func:`~tpscore.face.io.write_textured_obj` writes, is used as it is), vertex
        colours of a PLY, GLB or OBJ, or another texture, rendered along the viewing axis
        into an image of 0.3 mm pixels; ``FaceGrid.image`` and ``uv`` then feed the
        texture tracker as a ``.bnt``'s image does. A colour source that cannot be used
        gives a :class:`~tpscore.face.io.ColourWarning` and a scan without colour.
    landmarks_path : str or PathLike, optional
        ``.lm3``, ``.csv`` or ``.json``, or ``"auto"`` to detect them from the scan
        (:func:`~tpscore.face.detect.detect_landmarks`). By default the file beside
        `path` with the same stem and one of these suffixes (``.lm3`` first); if there
        is none, the landmarks are detected and a
        :class:`~tpscore.face.detect.LandmarksDetectedWarning` says so. Detected
        landmarks set ``FaceGrid.landmarks_detected``, which a transfer follows more
        loosely than labelled ones.
    shape, max_gap_mm
        As in :func:`~tpscore.face.resampling.resample_scan`.
    image_path : str or PathLike, optional
        The colour image of a ``.bnt`` scan. By default the image the ``.bnt`` names,
        beside it; when that file does not exist the scan is geometry only
        (``FaceGrid.image`` is None) and every step works without colour.
    detect : bool, default True
        Whether a scan without a landmark file has its landmarks detected; False keeps
        them all missing (a :class:`~tpscore.face.grid.LandmarkSnapWarning` says so).

    Raises
    ------
    ValueError
        Naming the file: an unreadable scan, landmark file or image, or an image whose
        size does not fit the scan's u,v.
    """
    path = Path(as_path(path))
    # the size is checked before the scan is read, which may be large
    shape = _as_shape(shape)
    # the scan first: a missing scan is the error to report, not its missing landmarks
    image = None
    if path.suffix.lower() == ".bnt":
        source = read_bnt(path)
        if image_path is None and source.image_name:
            beside = path.parent / source.image_name
            image_path = beside if beside.exists() else None
        if image_path is not None:
            image = read_image(image_path)
            check_image_fits(image, source.points, source.uv, source.valid, repr(str(image_path)))
    else:
        if image_path is not None:
            raise ValueError(f"image_path: only a .bnt scan carries the u,v an image needs, not {str(path)!r}")
        coloured = read_mesh_colours(path)
        source = coloured.vertices
    if not isinstance(detect, (bool, np.bool_)):
        raise ValueError(f"detect: must be True or False, got {detect!r}")
    auto = isinstance(landmarks_path, str) and landmarks_path == "auto"
    detected = auto
    if auto:
        landmarks = _detect(source, path, image)
    elif landmarks_path is None:
        found = landmark_file_beside(path)
        if found is not None:
            landmarks = read_landmarks(found)
        elif detect:
            landmarks, detected = _detect(source, path, image), True
            warnings.warn(f"no landmark file beside {str(path)!r} (looked for .lm3, .csv, .json): "
                          "landmarks detected from the scan", LandmarksDetectedWarning, stacklevel=2)
        else:
            warnings.warn(
                f"no landmark file beside {str(path)!r} (looked for .lm3, .csv, .json); "
                "all landmarks are missing", LandmarkSnapWarning, stacklevel=2)
            landmarks = None
    else:
        landmarks = read_landmarks(landmarks_path)
    uv = None
    try:
        if not isinstance(source, BntScan):
            image, uv = _mesh_colour_image(coloured, landmarks, repr(str(path)))
        grid = resample_scan(source, landmarks, shape, max_gap_mm=max_gap_mm, uv=uv)
    except ValueError as exc:
        raise ValueError(f"{str(path)!r}: {exc}") from None
    if image is not None:
        grid.image = _as_colour_image(image)
    grid.landmarks_detected = detected
    return grid


def _detect(source, path, image=None):
    """The scan's landmarks found by :func:`detect_landmarks`, with the colour image of a
    ``.bnt`` (its colour cues: brows, lips, eye openings) when it has one."""
    try:
        return detect_landmarks(source, image=image)
    except ValueError as exc:
        raise ValueError(f"{str(path)!r}: landmarks cannot be detected: {exc}") from None


#: The size of a pixel of the image a mesh's colours are rendered into (mm): finer than
#: a face scanner's camera sees the skin, so that the texture tracker loses no detail.
MESH_COLOUR_PIXEL_MM = 0.3
#: The most pixels across that image: a mesh far wider than a face is rendered coarser.
MAX_MESH_COLOUR_PIXELS = 2048


def _mesh_colour_image(coloured: MeshColours, landmarks, where: str):
    """The colour image and per-vertex u,v a mesh's colours give a face grid, or
    (None, None) for a mesh without colour.

    A texture whose u,v are one per vertex and map the face's x, y onto the image with
    nearly square pixels (as a ``.bnt``'s image, or :func:`~tpscore.face.io.write_textured_obj`'s output)
    is used as it is. Other colours (vertex colours, a texture atlas with seams) are
    rendered orthographically along the viewing axis into an image over the face's
    x, y at :data:`MESH_COLOUR_PIXEL_MM`, and each vertex's u,v is its place in it: the
    texture tracker then sees the mesh as it sees a scanner's image.
    """
    vertices, faces = coloured.vertices, coloured.faces
    if coloured.image is None and coloured.vertex_colors is None:
        return None, None
    if coloured.image is not None:
        vertex_uv = np.full((len(vertices), 2), np.nan)
        vertex_uv[faces.reshape(-1)] = coloured.corner_uv.reshape(-1, 2)
        used = np.isfinite(vertex_uv[:, 0])
        if np.count_nonzero(used) >= 3 and np.abs(coloured.corner_uv - vertex_uv[faces]).max() < 1e-9:
            # vertices no triangle uses (a scan's isolated points) take the u,v of the
            # affine map from x, y the others follow
            if not used.all():
                design = np.column_stack([vertices[used, :2], np.ones(np.count_nonzero(used))])
                affine = np.linalg.lstsq(design, vertex_uv[used], rcond=None)[0]
                vertex_uv[~used] = np.column_stack([vertices[~used, :2], np.ones(np.count_nonzero(~used))]) @ affine
            try:
                check_image_fits(coloured.image, vertices, vertex_uv, np.ones(len(vertices), bool), where)
                return coloured.image, vertex_uv
            except ValueError:
                pass  # an atlas: rendered below
    # the viewing axis is the canonical frame's z: a scan in another pose is turned first
    pose = scan_pose(empty_landmarks() if landmarks is None else as_landmarks(landmarks))
    seen = vertices if pose is None or pose.canonical else pose.to_canonical(vertices)
    extent = np.ptp(seen[:, :2], axis=0)
    if not (extent > 0).all():
        return None, None
    pixel_mm = max(MESH_COLOUR_PIXEL_MM, extent.max() / MAX_MESH_COLOUR_PIXELS)
    width, height = (int(np.ceil(e / pixel_mm)) + 1 for e in extent)
    origin = np.array([seen[:, 0].min(), seen[:, 1].max()])
    pixels = np.column_stack([seen[:, 0] - origin[0], origin[1] - seen[:, 1]]) / pixel_mm + 0.5
    if len(faces):
        triangles = faces
    else:
        try:  # a coloured point cloud: triangulated over x, y
            triangles = Delaunay(pixels).simplices.astype(np.int64)
        except QhullError:
            return None, None
    if coloured.image is not None:
        # each corner its own vertex, so that seams keep both sides' u,v
        corners = triangles.reshape(-1)
        triangle, barycentric = rasterise(pixels[corners], seen[corners, 2], np.arange(len(corners)).reshape(-1, 3),
                                          width, height)
        uv = interpolate_pixels(coloured.corner_uv.reshape(-1, 2), np.arange(len(corners)).reshape(-1, 3),
                                triangle, barycentric)
        colours = sample_image(coloured.image, np.nan_to_num(uv))
    else:
        triangle, barycentric = rasterise(pixels, seen[:, 2], triangles, width, height)
        colours = interpolate_pixels(coloured.vertex_colors.astype(np.float64), triangles, triangle, barycentric)
    covered = triangle >= 0
    if not covered.any():
        warnings.warn(f"{where}: its colours cover no pixel of the face's image: read without colour",
                      ColourWarning, stacklevel=3)
        return None, None
    # pixels beside the surface take the nearest covered colour, so that sampling at
    # the rim does not blend in black
    nearest = distance_transform_edt(~covered, return_distances=False, return_indices=True)
    colours = colours[nearest[0], nearest[1]]
    image = np.clip(np.round(colours), 0, 255).astype(np.uint8)
    vertex_uv = pixels / np.array([width, height], dtype=np.float64)
    return image, vertex_uv


@blas_on_one_thread
def load_scans(paths, landmarks_paths=None, shape=DEFAULT_GRID_SHAPE, *,
               max_gap_mm: float = DEFAULT_MAX_GAP_MM) -> list[FaceGrid]:
    """:func:`load_scan` for several scans at once, on as many threads as the kernels
    use (see :func:`tpscore.num_threads`).

    Reading, decoding the image and resampling spend most of their time outside the
    GIL, so the three scans of a transfer load in about 0.6 times the time of one after
    the other on two cores.

    Parameters
    ----------
    paths : sequence of str or PathLike
    landmarks_paths : sequence, optional
        One landmark file (or None: the one beside the scan) per path.
    shape, max_gap_mm
        As in :func:`load_scan`.

    Returns
    -------
    list of FaceGrid, in the order of ``paths``.

    Raises
    ------
    ValueError
        As :func:`load_scan`, for the first path in order that fails.
    """
    if isinstance(paths, (str, bytes, os.PathLike)):
        raise ValueError(f"paths must be a sequence of scan paths, got the one path {paths!r:.80} "
                         "(use load_scan for one scan)")
    paths = list(paths)
    landmarks_paths = [None] * len(paths) if landmarks_paths is None else list(landmarks_paths)
    if len(landmarks_paths) != len(paths):
        raise ValueError(f"landmarks_paths has {len(landmarks_paths)} entries for {len(paths)} paths")
    shape = _as_shape(shape)
    workers = max(1, min(len(paths), num_threads()))
    if workers == 1:
        return [load_scan(p, lm, shape, max_gap_mm=max_gap_mm) for p, lm in zip(paths, landmarks_paths)]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="tpscore-load") as pool:
        return list(pool.map(lambda p, lm: load_scan(p, lm, shape, max_gap_mm=max_gap_mm), paths, landmarks_paths))
