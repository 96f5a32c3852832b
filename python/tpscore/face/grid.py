"""Preprocessing: turn a raw scan into a regular face grid with snapped landmarks.

A raw scan is a point cloud with background and holes (for example a Bosphorus
``.bnt``, about 35k valid points). :func:`resample_scan` drops the invalid points,
resamples x, y onto an H x W grid spanning the valid data and interpolates z
linearly over the valid points, as a Delaunay-based ``griddata`` would, keeping a
validity mask. The result, a :class:`FaceGrid`, induces quads (two triangles each)
and a u,v map; its landmarks are snapped to the nearest valid grid vertex.

Two interpolation paths give the same kind of result:

- **Regular source grid** (a ``.bnt``, a depth image): each target point is located
  in its source cell by arithmetic and interpolated linearly on one of the cell's two
  triangles. This is hundreds of times faster than a Delaunay triangulation of the
  same points; :func:`resample_scan` detects the structure automatically.
- **Unstructured point cloud** (mesh vertices, any scattered points): a Delaunay
  triangulation of x, y (``scipy.spatial.Delaunay``), evaluated like
  ``scipy.interpolate.LinearNDInterpolator``.

Conventions: units mm; row 0 of a grid is the largest y (the top of the face),
column 0 the smallest x, as in a ``.bnt``; u,v are image coordinates in [0, 1]
(u to the right, v downward, as in a ``.bnt``).
"""
from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import Delaunay, QhullError

from .._threads import blas_on_one_thread, num_threads
from .._validation import MAX_COORDINATE, as_array, as_path, as_positive
from ..geometry import FrameTransform
from ..mesh import grid_triangles
from ..raster import interpolate_pixels, rasterise
from .detect import LandmarksDetectedWarning, detect_landmarks
from .image import as_colour_image as _as_colour_image
from .image import check_image_fits, sample_image
from .io import (BntScan, ColourWarning, MeshColours, landmark_file_beside, read_bnt, read_image,
                 read_landmarks, read_mesh_colours)
from .landmarks import LANDMARK_NAMES, N_LANDMARKS, as_landmarks, empty_landmarks
from .pose import scan_pose

__all__ = [
    "FaceGrid",
    "GridMesh",
    "LandmarkSnapWarning",
    "resample_scan",
    "load_scan",
    "load_scans",
    "DEFAULT_GRID_SHAPE",
    "DEFAULT_MAX_GAP_MM",
    "MAX_GRID_VERTICES",
    "LANDMARK_SNAP_WARNING_MM",
]

#: Default output grid (rows, columns).
DEFAULT_GRID_SHAPE = (150, 150)

#: The largest grid, in vertices (1024 x 1024). A transfer on it takes about 2 GB of
#: memory and tens of seconds; a scan has fewer points than that (a Bosphorus scan about
#: 200,000), so a finer grid would only interpolate.
MAX_GRID_VERTICES = 1024 * 1024

#: Default widest gap (mm) between valid points that resampling bridges by linear
#: interpolation beyond the scan's own sampling. 3 mm fills scanner dropouts of a
#: few pixels (at the 0.3-0.7 mm spacing of face scanners) without inventing surface
#: over the eye openings, parted lips or real holes, which are wider.
DEFAULT_MAX_GAP_MM = 3.0

#: A landmark farther than this (mm) from every valid grid vertex still snaps, with
#: a :class:`LandmarkSnapWarning`: it probably lies over a hole or outside the scan.
LANDMARK_SNAP_WARNING_MM = 10.0

# A source grid counts as regular when every valid x (y) lies within this fraction of
# the spacing of x0 + c * sx (y0 + r * sy). Scanner depth images are exact lattices up
# to rounding (float32 files round by ~1e-5 of a 0.7 mm spacing at 100 mm); treating
# them as exact moves a point by at most 1e-4 spacing, far below scanner noise.
# Anything less regular goes the Delaunay way, which makes no such assumption.
_LATTICE_TOLERANCE = 1e-4

# In the unstructured path a Delaunay triangle is always kept when its longest edge is
# at most this many times the median Delaunay edge: irregular (even random) sampling
# has edges up to about twice the median that do not span holes.
_UNSTRUCTURED_EDGE_FACTOR = 3.0


class LandmarkSnapWarning(UserWarning):
    """A landmark is far from every valid grid vertex (it may lie over a hole)."""


class GridMesh(NamedTuple):
    """The valid part of a :class:`FaceGrid` as an indexed triangle mesh.

    Attributes
    ----------
    vertices : (n, 3) float64, the valid grid vertices (mm), in row-major grid order.
    faces : (m, 3) int64, indices into ``vertices``, counter-clockwise seen from +z.
    uv : (n, 2) float64, the u,v map at those vertices.
    grid_index : (n,) int64, flat grid index (``r * W + c``) of each vertex.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    grid_index: np.ndarray


# eq=False: element-wise array comparison has no single truth value.
@dataclass(eq=False)
class FaceGrid:
    """A face as a regular H x W grid of vertices with a validity mask and landmarks.

    Attributes
    ----------
    points : (H, W, 3) float64
        Vertex positions in mm; NaN where ``mask`` is False.
    mask : (H, W) bool
        Where the grid has surface.
    uv : (H, W, 2) float64
        Texture coordinates (u right, v down, in [0, 1]), finite everywhere.
    landmarks : (22, 3) float64
        The 22 Bosphorus landmarks, each equal to the grid vertex it was snapped to;
        NaN rows for missing landmarks.
    landmark_vertices : (22,) int64
        Flat grid index (``r * W + c``) of each landmark's vertex; -1 when missing.
    image : (h, w, 3) uint8 or None
        The scan's colour image at full resolution, which ``uv`` points into (None for
        a scan without one). It is shared, not copied, between grids made from one
        scan, and read-only.
    scan_frame : FrameTransform or None
        The map from the grid's frame back to the frame of the scan it was made from,
        when :func:`resample_scan` brought the scan into the canonical frame (see
        :mod:`tpscore.face.pose`); None when the two are the same.
    """

    points: np.ndarray
    mask: np.ndarray
    uv: np.ndarray
    landmarks: np.ndarray
    landmark_vertices: np.ndarray
    image: np.ndarray | None = None
    scan_frame: FrameTransform | None = None

    def __post_init__(self):
        mask = np.array(self.mask, dtype=bool)
        if mask.ndim != 2 or min(mask.shape) < 2:
            raise ValueError(f"mask must have shape (H, W) with H, W >= 2, got {mask.shape}")
        height, width = mask.shape
        points = np.array(as_array(self.points, "points"), dtype=np.float64)
        if points.shape != (height, width, 3):
            raise ValueError(f"points must have shape ({height}, {width}, 3), got {points.shape}")
        if not np.isfinite(points[mask]).all():
            raise ValueError("points has NaN or infinite values at vertices the mask marks valid")
        points[~mask] = np.nan
        uv = np.array(as_array(self.uv, "uv"), dtype=np.float64)
        if uv.shape != (height, width, 2) or not np.isfinite(uv).all():
            raise ValueError(f"uv must be a finite ({height}, {width}, 2) array, got shape {uv.shape}")
        landmarks = as_landmarks(self.landmarks)
        index = np.array(self.landmark_vertices)
        if index.shape != (N_LANDMARKS,) or not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"landmark_vertices must be ({N_LANDMARKS},) integers, got {index.shape} {index.dtype}")
        index = index.astype(np.int64)
        present = np.isfinite(landmarks).all(axis=1)
        if not np.array_equal(index >= 0, present) or index.max() >= height * width:
            raise ValueError(
                "landmark_vertices must be -1 exactly for the missing (NaN) landmarks and "
                f"a flat grid index in [0, {height * width}) for the others"
            )
        if not mask.reshape(-1)[index[present]].all():
            bad = np.flatnonzero(present & ~mask.reshape(-1)[np.maximum(index, 0)])[0]
            raise ValueError(f"landmark {LANDMARK_NAMES[bad]!r} refers to a vertex outside the mask")
        self.points, self.mask, self.uv = points, mask, uv
        self.landmarks, self.landmark_vertices = landmarks, index
        if self.image is not None:
            self.image = _as_colour_image(self.image)
        if self.scan_frame is not None and not isinstance(self.scan_frame, FrameTransform):
            raise ValueError(f"scan_frame must be a FrameTransform or None, got {type(self.scan_frame).__name__}")

    def __repr__(self) -> str:
        height, width = self.shape
        present = int(np.count_nonzero(self.landmark_vertices >= 0))
        image = "no image" if self.image is None else f"image {self.image.shape[1]}x{self.image.shape[0]}"
        return (f"FaceGrid({height}x{width}, {self.n_valid} valid vertices, "
                f"{present}/{N_LANDMARKS} landmarks, {image})")

    @property
    def shape(self) -> tuple[int, int]:
        """Grid size (H, W)."""
        return self.mask.shape

    @property
    def vertices(self) -> np.ndarray:
        """All H * W vertices as a flat (H*W, 3) view, NaN where masked out."""
        return self.points.reshape(-1, 3)

    @property
    def n_valid(self) -> int:
        """Number of valid vertices."""
        return int(np.count_nonzero(self.mask))

    @property
    def colours(self) -> np.ndarray | None:
        """(H, W, 3) float32 RGB in [0, 1] of each vertex, read from ``image`` at its u,v
        (NaN where the mask is False); None without an image."""
        if self.image is None:
            return None
        colours = sample_image(self.image, self.uv) / 255.0
        colours[~self.mask] = np.nan
        return colours

    def triangles(self) -> np.ndarray:
        """Triangles over the valid grid vertices, as flat grid indices.

        Each quad (r, c), (r, c+1), (r+1, c), (r+1, c+1) whose four vertices are valid
        gives two triangles split along the (r, c)-(r+1, c+1) diagonal; a quad with
        exactly three valid vertices gives the one triangle they form (so the surface
        reaches the outline and hole edges, as the resampling does). Triangles run
        counter-clockwise seen from +z, in row-major quad order.

        Returns
        -------
        (m, 3) int64 indices into ``self.vertices``.
        """
        height, width = self.shape
        return grid_triangles(self.mask)

    def mesh(self) -> GridMesh:
        """The valid vertices and the triangles over them, reindexed (see :class:`GridMesh`)."""
        grid_index = np.flatnonzero(self.mask.reshape(-1))
        remap = np.full(self.mask.size, -1, dtype=np.int64)
        remap[grid_index] = np.arange(len(grid_index))
        return GridMesh(
            vertices=np.ascontiguousarray(self.vertices[grid_index]),
            faces=remap[self.triangles()],
            uv=np.ascontiguousarray(self.uv.reshape(-1, 2)[grid_index]),
            grid_index=grid_index,
        )

    @classmethod
    def from_points(cls, points, mask=None, landmarks=None) -> "FaceGrid":
        """A grid from (H, W, 3) points (NaN or `mask` False where invalid), with the
        default u,v map and `landmarks` (22, 3; NaN rows missing) snapped to it."""
        points = np.array(as_array(points, "points"), dtype=np.float64)
        if points.ndim != 3 or points.shape[2] != 3:
            raise ValueError(f"points must have shape (H, W, 3), got {points.shape}")
        valid = np.isfinite(points).all(axis=2)
        if mask is not None:
            valid &= np.asarray(mask, dtype=bool)
        landmarks = empty_landmarks() if landmarks is None else landmarks
        snapped, index = _snap_landmarks(points.reshape(-1, 3), valid.reshape(-1), landmarks)
        return cls(points, valid, _default_uv(*valid.shape), snapped, index)

    def copy(self) -> "FaceGrid":
        """A deep copy."""
        return FaceGrid(self.points.copy(), self.mask.copy(), self.uv.copy(),
                        self.landmarks.copy(), self.landmark_vertices.copy(), self.image, self.scan_frame)

    def with_points(self, new_points) -> "FaceGrid":
        """The same grid (mask, u,v map, landmark vertices) with moved vertices.

        Parameters
        ----------
        new_points : (H, W, 3) or (H*W, 3) array-like, mm
            Finite at every valid vertex; values at masked-out vertices are ignored.

        Returns
        -------
        FaceGrid whose landmarks are the new positions of the landmark vertices.
        """
        height, width = self.shape
        points = np.array(as_array(new_points, "new_points"), dtype=np.float64)
        if points.shape == (height * width, 3):
            points = points.reshape(height, width, 3)
        if points.shape != (height, width, 3):
            raise ValueError(
                f"new_points must have shape ({height}, {width}, 3) or ({height * width}, 3), got {points.shape}"
            )
        if not np.isfinite(points[self.mask]).all():
            raise ValueError("new_points has NaN or infinite values at valid vertices")
        points[~self.mask] = np.nan
        landmarks = empty_landmarks()
        present = self.landmark_vertices >= 0
        landmarks[present] = points.reshape(-1, 3)[self.landmark_vertices[present]]
        return FaceGrid(points, self.mask.copy(), self.uv.copy(), landmarks, self.landmark_vertices.copy(),
                        self.image, self.scan_frame)

    def with_landmarks(self, landmarks) -> "FaceGrid":
        """The same grid with `landmarks` (22, 3; NaN rows missing) snapped to it.

        Each finite landmark moves to the nearest valid vertex (3D distance); see
        :func:`resample_scan` for the warning given when that vertex is far.
        """
        snapped, index = _snap_landmarks(self.vertices, self.mask.reshape(-1), landmarks)
        return FaceGrid(self.points.copy(), self.mask.copy(), self.uv.copy(), snapped, index, self.image,
                        self.scan_frame)


# --------------------------------------------------------------------------- resampling

def resample_scan(scan_or_points, landmarks=None, shape=DEFAULT_GRID_SHAPE, *,
                  max_gap_mm: float = DEFAULT_MAX_GAP_MM, uv=None) -> FaceGrid:
    """Resample a raw scan onto a regular H x W face grid and snap its landmarks.

    The grid spans the bounding box of the valid points in x, y: column 0 at the
    smallest x, row 0 at the largest y (as in a ``.bnt``), W and H points evenly
    spaced. z is linear over a triangulation of the valid points, as a Delaunay-based
    ``griddata(..., method="linear")`` computes it:

    - regular source grids (a :class:`~tpscore.face.io.BntScan`, an (R, C, 3) depth image,
      or an (n, 3) cloud whose x, y lie on a lattice) are interpolated cell by cell:
      a cell with four valid corners is split along its (r, c)-(r+1, c+1) diagonal;
      a cell with three valid corners uses the triangle they form; a point on a cell
      edge or corner needs only the corners it depends on.
    - other point clouds are triangulated with ``scipy.spatial.Delaunay``.

    Validity mask: a grid vertex is valid only where the interpolating triangle's
    corners are all valid points. So no surface is invented outside the data or
    across a hole, except that gaps up to `max_gap_mm` are bridged first: on a regular
    source grid each missing source point whose nearest valid neighbours along its
    row (or column) are at most `max_gap_mm` apart gets z interpolated linearly between
    them (both directions averaged, weighted by 1 / span); in the unstructured path
    Delaunay triangles whose longest edge exceeds ``max(max_gap_mm, 3 * median
    Delaunay edge)`` are dropped. Gaps wider than `max_gap_mm`, and everything outside the
    data, stay invalid. ``max_gap_mm=0`` bridges nothing beyond the sampling itself.

    Pose and unit: a scan whose landmarks show another frame (its axes swapped, as in a
    profile view or a y-forward, z-up scanner frame) or unit (centimetres, metres) is
    first brought to the canonical frame, looking toward +z with +y up, in millimetres
    (:func:`tpscore.face.pose.scan_pose`); the grid's ``scan_frame`` maps back. A scan
    within 45 degrees of frontal and in millimetres is resampled as it is.

    Landmarks: each finite landmark is snapped to the nearest valid grid vertex
    (3D distance); missing (NaN) landmarks stay missing. A landmark farther than
    :data:`LANDMARK_SNAP_WARNING_MM` from every valid vertex still snaps but raises a
    :class:`LandmarkSnapWarning` (it probably lies over a hole or outside the scan).

    Parameters
    ----------
    scan_or_points : BntScan, (R, C, 3) array or (n, 3) array, mm
        The scan. In arrays, NaN marks invalid points.
    landmarks : (22, 3) array-like or None
        Landmarks in the scan's frame, NaN rows for missing ones; None: all missing.
    shape : (int, int)
        Output grid (H, W), each >= 2, at most MAX_GRID_VERTICES (1024 x 1024) in all.
    max_gap_mm : float >= 0
        Widest gap bridged by interpolation (see above).
    uv : (R, C, 2) or (n, 2) array-like, optional
        Texture coordinates of the source points (a BntScan brings its own). They are
        interpolated onto the grid; without them the grid's u,v are its normalised
        pixel centres ``((c + 0.5) / W, (r + 0.5) / H)``.

    Returns
    -------
    FaceGrid

    Raises
    ------
    ValueError
        Fewer than 3 valid points, valid points without extent in x or y (or
        collinear), a point beyond +-1e15 mm, a bad `shape` (more than
        :data:`MAX_GRID_VERTICES`) or `max_gap_mm`, landmarks not of shape (22, 3), or
        no grid vertex inside the data.
    """
    height, width = _as_shape(shape)
    max_gap_mm = as_positive(max_gap_mm, "max_gap_mm", allow_zero=True)
    grid, valid, source_uv, cloud, cloud_uv = _split_input(scan_or_points, uv)
    landmarks = empty_landmarks() if landmarks is None else as_landmarks(landmarks)

    # Every step from here on reads depth along z and works in millimetres. A scan in
    # another frame (axes swapped, a profile view) or unit is brought into the canonical
    # one, without rounding its coordinates; the grid keeps the way back.
    pose = scan_pose(landmarks)
    scan_frame = None
    if pose is not None and not pose.canonical:
        landmarks = pose.to_canonical(landmarks)
        if grid is not None:
            grid = pose.to_canonical(grid)
        else:
            cloud = pose.to_canonical(cloud)
        scan_frame = pose.transform.inverse()

    # one outlier far out would stretch the grid over it, leaving no vertex on the face,
    # and overflow the lattice indices below: judged on the valid points first
    _check_extent(grid[valid] if grid is not None else cloud)
    lattice = None
    if grid is not None:
        lattice = _fit_lattice(grid, valid)
        if lattice is None:
            cloud = grid[valid]
            cloud_uv = None if source_uv is None else source_uv[valid]
            # a lattice whose rows and columns do not run along y and x (a depth image
            # turned into the canonical frame) is still one
            detected = _cloud_to_lattice(cloud, cloud_uv)
            if detected is not None:
                grid, valid, source_uv, lattice = detected
            else:
                grid = None
    else:
        detected = _cloud_to_lattice(cloud, cloud_uv)
        if detected is not None:
            grid, valid, source_uv, lattice = detected

    if lattice is not None:
        n_valid = int(np.count_nonzero(valid))
        lattice, (x_min, x_max, y_min, y_max) = lattice
    else:
        n_valid = len(cloud)
    if n_valid < 3:
        raise ValueError(f"scan_or_points has {n_valid} valid point(s); at least 3 are needed")
    if lattice is None:
        x_min, y_min = cloud[:, 0].min(), cloud[:, 1].min()
        x_max, y_max = cloud[:, 0].max(), cloud[:, 1].max()
    if not (x_max > x_min and y_max > y_min):
        raise ValueError(
            "scan_or_points: the valid points have no extent in x or y "
            f"(x in [{x_min}, {x_max}], y in [{y_min}, {y_max}])"
        )
    xs = np.linspace(x_min, x_max, width)
    ys = np.linspace(y_max, y_min, height)

    if lattice is not None:
        z, mask, grid_uv = _resample_lattice(grid, valid, source_uv, lattice, xs, ys, max_gap_mm)
    else:
        z, mask, grid_uv = _resample_delaunay(cloud, cloud_uv, xs, ys, max_gap_mm)
    if not mask.any():
        raise ValueError("scan_or_points: no grid vertex lies inside the valid data")
    if grid_uv is None:
        grid_uv = _default_uv(height, width)

    points = np.empty((height, width, 3))
    points[..., 0] = xs[None, :]
    points[..., 1] = ys[:, None]
    points[..., 2] = z
    points[~mask] = np.nan
    snapped, index = _snap_landmarks(points.reshape(-1, 3), mask.reshape(-1), landmarks)
    return FaceGrid(points, mask, grid_uv, snapped, index, scan_frame=scan_frame)


def load_scan(path, landmarks_path=None, shape=DEFAULT_GRID_SHAPE, *,
              max_gap_mm: float = DEFAULT_MAX_GAP_MM, image_path=None, detect: bool = True) -> FaceGrid:
    """Read a scan and its landmarks and resample them with :func:`resample_scan`.

    Parameters
    ----------
    path : str or PathLike
        A Bosphorus ``.bnt``, or any mesh or point cloud trimesh reads (its vertices
        are the points). A mesh's colours come with it (:func:`read_mesh_colours`): an
        OBJ's texture through its ``.mtl`` (a texture whose u,v map the face's x, y with
        square pixels, as :func:`write_textured_obj` writes, is used as it is), vertex
        colours of a PLY, GLB or OBJ, or another texture, rendered along the viewing axis
        into an image of 0.3 mm pixels; ``FaceGrid.image`` and ``uv`` then feed the
        texture tracker as a ``.bnt``'s image does. A colour source that cannot be used
        gives a :class:`~tpscore.face.io.ColourWarning` and a scan without colour.
    landmarks_path : str or PathLike, optional
        ``.lm3``, ``.csv`` or ``.json``, or ``"auto"`` to detect them from the scan
        (:func:`~tpscore.face.detect.detect_landmarks`). By default the file beside
        `path` with the same stem and one of these suffixes (``.lm3`` first); if there
        is none, the landmarks are detected and a
        :class:`~tpscore.face.detect.LandmarksDetectedWarning` says so.
    shape, max_gap_mm
        As in :func:`resample_scan`.
    image_path : str or PathLike, optional
        The colour image of a ``.bnt`` scan. By default the image the ``.bnt`` names,
        beside it; when that file does not exist the scan is geometry only
        (``FaceGrid.image`` is None) and every step works without colour.
    detect : bool, default True
        Whether a scan without a landmark file has its landmarks detected; False keeps
        them all missing (a :class:`LandmarkSnapWarning` says so).

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
    if auto:
        landmarks = _detect(source, path)
    elif landmarks_path is None:
        found = landmark_file_beside(path)
        if found is not None:
            landmarks = read_landmarks(found)
        elif detect:
            landmarks = _detect(source, path)
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
    return grid


def _detect(source, path):
    try:
        return detect_landmarks(source)
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
    nearly square pixels (as a ``.bnt``'s image, or :func:`write_textured_obj`'s output)
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


# --------------------------------------------------------------------------- helpers

def _as_shape(shape, name: str = "shape") -> tuple[int, int]:
    try:
        if len(shape) != 2 or any(isinstance(v, (str, bytes, bool, np.bool_)) for v in shape):
            raise TypeError
        height, width = (int(v) for v in shape)
        exact = all(float(v) == int(v) for v in shape)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name} must be two integers (H, W), got {shape!r}") from None
    if not exact or height < 2 or width < 2:
        raise ValueError(f"{name} must be two integers (H, W), each >= 2, got {shape!r}")
    if height * width > MAX_GRID_VERTICES:
        raise ValueError(f"{name} {height} x {width} has {height * width:,} vertices; the largest grid has "
                         f"{MAX_GRID_VERTICES:,} (1024 x 1024)")
    return height, width


def _default_uv(height: int, width: int) -> np.ndarray:
    uv = np.empty((height, width, 2))
    uv[..., 0] = ((np.arange(width) + 0.5) / width)[None, :]
    uv[..., 1] = ((np.arange(height) + 0.5) / height)[:, None]
    return uv


def _split_input(scan_or_points, uv):
    """(grid, valid, grid_uv, cloud, cloud_uv): one of grid or cloud is None."""
    if isinstance(scan_or_points, BntScan):
        if uv is not None:
            raise ValueError("uv: a BntScan brings its own u,v; do not pass uv with it")
        return scan_or_points.points, scan_or_points.valid, scan_or_points.uv, None, None
    array = as_array(scan_or_points, "scan_or_points")
    if array.ndim == 3 and array.shape[2] == 3:
        valid = np.isfinite(array).all(axis=2)
        source_uv = None
        if uv is not None:
            source_uv = as_array(uv, "uv")
            if source_uv.shape != array.shape[:2] + (2,):
                raise ValueError(f"uv must have shape {array.shape[:2] + (2,)}, got {source_uv.shape}")
            if not np.isfinite(source_uv[valid]).all():
                raise ValueError("uv has NaN or infinite values at valid points")
        return array, valid, source_uv, None, None
    if array.ndim == 2 and array.shape[1] == 3:
        keep = np.isfinite(array).all(axis=1)
        cloud_uv = None
        if uv is not None:
            cloud_uv = as_array(uv, "uv")
            if cloud_uv.shape != (len(array), 2):
                raise ValueError(f"uv must have shape ({len(array)}, 2), got {cloud_uv.shape}")
            cloud_uv = cloud_uv[keep]
            if not np.isfinite(cloud_uv).all():
                raise ValueError("uv has NaN or infinite values at valid points")
        return None, None, None, np.ascontiguousarray(array[keep]), cloud_uv
    raise ValueError(
        f"scan_or_points must be a BntScan, an (R, C, 3) grid or an (n, 3) point array, got shape {array.shape}"
    )


def _fit_line(index: np.ndarray, values: np.ndarray):
    """(origin, step) of values = origin + step * index when that holds to the lattice
    tolerance, else None."""
    if index.min() == index.max():
        return None
    mean_index, mean_value = index.mean(), values.mean()
    centred = index - mean_index
    # einsum rather than np.dot: a BLAS call may wake a thread pool, which on a busy
    # machine costs tens of milliseconds for this microsecond sum.
    step = float(np.einsum("i,i->", centred, values - mean_value) / np.einsum("i,i->", centred, centred))
    origin = float(mean_value - step * mean_index)
    if step == 0.0:
        return None
    residual = np.abs(values - (origin + step * index)).max()
    return (origin, step) if residual <= _LATTICE_TOLERANCE * abs(step) else None


def _fit_lattice(grid: np.ndarray, valid: np.ndarray):
    """((x0, sx, y0, sy), (x_min, x_max, y_min, y_max)) when x = x0 + sx * c and
    y = y0 + sy * r at every valid point, else None. The extents are those of the
    valid points."""
    if min(valid.shape) < 2 or valid.sum() < 3:
        return None
    rows, cols = np.nonzero(valid)
    x, y = grid[rows, cols, 0], grid[rows, cols, 1]
    fit_x = _fit_line(cols.astype(np.float64), x)
    if fit_x is None:
        return None
    fit_y = _fit_line(rows.astype(np.float64), y)
    if fit_y is None:
        return None
    return fit_x + fit_y, (x.min(), x.max(), y.min(), y.max())


def _check_extent(points: np.ndarray) -> None:
    extent = np.abs(points).max() if points.size else 0.0
    if extent > MAX_COORDINATE:
        raise ValueError(f"scan_or_points has a point {extent:.3g} mm from the origin, beyond the "
                         f"+-{MAX_COORDINATE:.0e} mm tpscore accepts (an outlier, or not millimetres?)")


def _lattice_steps(values: np.ndarray):
    """Integer lattice index of each value and the step, or None."""
    unique = np.unique(values)
    if len(unique) < 2:
        return None
    step = float(np.diff(unique).min())
    position = (values - unique[0]) / step
    index = np.rint(position)
    if np.abs(position - index).max() > _LATTICE_TOLERANCE:
        return None
    if index.max() > 2**31:
        return None  # a step tiny against the range: no lattice (and no int64 index)
    return index.astype(np.int64), step


def _cloud_to_lattice(cloud: np.ndarray, cloud_uv):
    """Scatter an (n, 3) cloud whose x, y lie on a lattice into a grid, or None.

    Returns (grid, valid, grid_uv, lattice) in the .bnt orientation (row 0 = largest y).
    """
    n = len(cloud)
    # A lattice of n points has far fewer distinct x than points; this rejects
    # scattered clouds after one np.unique.
    if n < 16 or len(np.unique(cloud[:, 0])) > n // 2:
        return None
    columns = _lattice_steps(cloud[:, 0])
    rows = _lattice_steps(-cloud[:, 1])
    if columns is None or rows is None:
        return None
    (col, _), (row, _) = columns, rows
    n_rows, n_cols = int(row.max()) + 1, int(col.max()) + 1
    # A sparse lattice (mostly empty cells) gains nothing over Delaunay.
    if n_rows * n_cols > 20 * n or n_rows < 2 or n_cols < 2:
        return None
    flat = row * n_cols + col
    if len(np.unique(flat)) != n:
        return None  # two points share an x, y position
    grid = np.full((n_rows, n_cols, 3), np.nan)
    grid.reshape(-1, 3)[flat] = cloud
    valid = np.zeros((n_rows, n_cols), dtype=bool)
    valid.reshape(-1)[flat] = True
    grid_uv = None
    if cloud_uv is not None:
        grid_uv = np.full((n_rows, n_cols, 2), np.nan)
        grid_uv.reshape(-1, 2)[flat] = cloud_uv
    lattice = _fit_lattice(grid, valid)
    if lattice is None:
        return None
    return grid, valid, grid_uv, lattice


def _fill_gaps(z: np.ndarray, valid: np.ndarray, step_x: float, step_y: float, max_gap_mm: float):
    """Bridge gaps of at most max_gap_mm along rows and columns of a depth grid.

    A missing point gets z interpolated linearly between its nearest valid neighbours
    to the left and right (span = their distance), and between those above and below;
    spans wider than max_gap_mm are ignored; the estimates are averaged with weights
    1 / span. A point without valid neighbours on both sides is outside the data and
    stays missing. Linear, so a plane is filled exactly.
    """
    total = np.zeros(z.shape)
    weight = np.zeros(z.shape)
    for axis, step in ((1, step_x), (0, step_y)):
        moved_z, moved_valid = (z, valid) if axis == 1 else (z.T, valid.T)
        n = moved_valid.shape[1]
        position = np.arange(n)
        before = np.maximum.accumulate(np.where(moved_valid, position, -1), axis=1)
        after = np.minimum.accumulate(np.where(moved_valid, position, n)[:, ::-1], axis=1)[:, ::-1]
        span = (after - before) * step
        candidate = ~moved_valid & (before >= 0) & (after < n) & (span <= max_gap_mm)
        lines, cells = np.nonzero(candidate)
        if len(lines) == 0:
            continue
        first, last = before[lines, cells], after[lines, cells]
        t = (cells - first) / (last - first)
        estimate = moved_z[lines, first] + t * (moved_z[lines, last] - moved_z[lines, first])
        w = 1.0 / span[lines, cells]
        if axis == 0:
            lines, cells = cells, lines
        total[lines, cells] += w * estimate
        weight[lines, cells] += w
    filled = weight > 0
    if not filled.any():
        return z, valid
    z = z.copy()
    z[filled] = total[filled] / weight[filled]
    return z, valid | filled


def _cell_coordinate(target: np.ndarray, origin: float, step: float, n: int):
    """Cell index (clamped to [0, n-2]), local coordinate in [0, 1] and in-range flag."""
    position = (target - origin) / step
    # Targets at the data's extremes sit on source nodes up to rounding; put them
    # exactly there so a node on the outline does not look like it is outside.
    nearest = np.rint(position)
    position = np.where(np.abs(position - nearest) <= _LATTICE_TOLERANCE, nearest, position)
    inside = (position >= 0) & (position <= n - 1)
    cell = np.clip(np.floor(position), 0, n - 2).astype(np.int64)
    return cell, position - cell, inside


def _resample_lattice(grid, valid, source_uv, lattice, xs, ys, max_gap_mm):
    """z, mask and u,v on the target axes from a regular source grid (see resample_scan)."""
    x0, step_x, y0, step_y = lattice
    n_rows, n_cols = valid.shape
    z = grid[..., 2]
    if max_gap_mm > 0:
        z, valid = _fill_gaps(z, valid, abs(step_x), abs(step_y), max_gap_mm)
    col, u, col_in = _cell_coordinate(xs, x0, step_x, n_cols)
    row, v, row_in = _cell_coordinate(ys, y0, step_y, n_rows)
    u, v = u[None, :], v[:, None]
    a = row[:, None] * n_cols + col[None, :]          # corner (r, c); b = a + 1,
    corners = (a, a + 1, a + n_cols, a + n_cols + 1)  # c = a + C, d = a + C + 1
    z_flat = np.where(valid, z, 0.0).reshape(-1)      # 0 * NaN would poison the sums
    valid_flat = valid.reshape(-1)
    corner_valid = [valid_flat[k] for k in corners]

    # Split along the a-d diagonal: triangle a,b,d when u >= v, else a,c,d.
    upper = u >= v
    weights_ad = (np.where(upper, 1 - u, 1 - v), np.where(upper, u - v, 0.0),
                  np.where(upper, 0.0, v - u), np.where(upper, v, u))
    # Split along the b-c diagonal: triangle a,b,c when u + v <= 1, else b,c,d.
    lower = u + v <= 1
    weights_bc = (np.where(lower, 1 - u - v, 0.0), np.where(lower, u, 1 - v),
                  np.where(lower, v, 1 - u), np.where(lower, 0.0, u + v - 1))

    def usable(weights):
        # A corner with (up to rounding) zero weight need not be valid: the point is on
        # the opposite edge, for example on the outline of the data.
        ok = np.ones(a.shape, dtype=bool)
        for w, ok_corner in zip(weights, corner_valid):
            ok &= (w <= _LATTICE_TOLERANCE) | ok_corner
        return ok

    use_ad = usable(weights_ad)
    use_bc = ~use_ad & usable(weights_bc)
    mask = (use_ad | use_bc) & row_in[:, None] & col_in[None, :]
    z_out = np.zeros(a.shape)
    weight_sum = np.zeros(a.shape)
    weights = []
    for w_ad, w_bc, k, ok_corner in zip(weights_ad, weights_bc, corners, corner_valid):
        # Invalid corners carry at most a rounding-sized weight: drop it and renormalise.
        w = np.where(ok_corner, np.where(use_ad, w_ad, w_bc), 0.0)
        z_out += w * z_flat[k]
        weight_sum += w
        weights.append(w)
    z_out[mask] /= weight_sum[mask]
    z_out[~mask] = np.nan

    grid_uv = None
    if source_uv is not None:
        uv_flat = source_uv.reshape(-1, 2)
        if np.isfinite(uv_flat).all():
            # u,v known at every source pixel (a .bnt has them at background too):
            # bilinear over the whole cell, exact for the affine u,v of a depth image.
            # One contiguous channel at a time keeps the gathers cheap.
            bilinear = ((1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v)
            grid_uv = np.empty(a.shape + (2,))
            for channel in range(2):
                values = np.ascontiguousarray(uv_flat[:, channel])
                grid_uv[..., channel] = sum(w * values[k] for w, k in zip(bilinear, corners))
        else:
            # u,v only at some points: the z weights over the corners that have them.
            known = np.isfinite(uv_flat).all(axis=1)
            safe_uv = np.where(known[:, None], uv_flat, 0.0)
            total, uv_sum = np.zeros(a.shape), np.zeros(a.shape + (2,))
            for w, k in zip(weights, corners):
                w = np.where(known[k], w, 0.0)
                uv_sum += w[..., None] * safe_uv[k]
                total += w
            grid_uv = _default_uv(*a.shape)
            has = total > 0
            grid_uv[has] = uv_sum[has] / total[has][:, None]
    return z_out, mask, grid_uv


def _resample_delaunay(cloud, cloud_uv, xs, ys, max_gap_mm):
    """z, mask and u,v on the target axes from scattered points (see resample_scan)."""

    xy = np.ascontiguousarray(cloud[:, :2])
    try:
        triangulation = Delaunay(xy)
    except QhullError as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(
            f"scan_or_points: the valid points cannot be triangulated in x, y "
            f"(collinear or coincident?): {first_line}"
        ) from None
    height, width = len(ys), len(xs)
    targets = np.empty((height * width, 2))
    targets[:, 0] = np.tile(xs, height)
    targets[:, 1] = np.repeat(ys, width)
    simplex = triangulation.find_simplex(targets)

    # Drop triangles that bridge gaps wider than the sampling and max_gap_mm allow.
    corners = xy[triangulation.simplices]
    edges = np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2)
    spacing = float(np.median(edges))
    allowed = edges.max(axis=1) <= max(max_gap_mm, _UNSTRUCTURED_EDGE_FACTOR * spacing)
    found = simplex >= 0
    found[found] = allowed[simplex[found]]

    hit = simplex[found]
    transform = triangulation.transform[hit]
    barycentric = np.einsum("nij,nj->ni", transform[:, :2], targets[found] - transform[:, 2])
    weights = np.column_stack([barycentric, 1.0 - barycentric.sum(axis=1)])
    vertex = triangulation.simplices[hit]
    z = np.full(height * width, np.nan)
    z[found] = np.einsum("nk,nk->n", weights, cloud[vertex, 2])
    grid_uv = None
    if cloud_uv is not None:
        grid_uv = _default_uv(height, width).reshape(-1, 2)
        grid_uv[found] = np.einsum("nk,nkj->nj", weights, cloud_uv[vertex])
        grid_uv = grid_uv.reshape(height, width, 2)
    return z.reshape(height, width), found.reshape(height, width), grid_uv


def _snap_landmarks(vertices: np.ndarray, mask: np.ndarray, landmarks):
    """Snap each finite landmark to the nearest valid vertex: (snapped (22, 3), index (22,))."""
    landmarks = as_landmarks(landmarks)
    snapped = empty_landmarks()
    index = np.full(N_LANDMARKS, -1, dtype=np.int64)
    present = np.flatnonzero(np.isfinite(landmarks).all(axis=1))
    candidates = np.flatnonzero(mask)
    if len(present) == 0:
        return snapped, index
    if len(candidates) == 0:
        raise ValueError("cannot snap landmarks: the grid has no valid vertex")
    # Brute force over the valid vertices, one coordinate at a time on a (landmarks,
    # vertices) array: exact, and no BLAS call (whose thread pool can cost more than
    # the arithmetic on a busy machine).
    valid_vertices = vertices[candidates]
    targets = landmarks[present]
    squared = np.subtract(valid_vertices[None, :, 0], targets[:, 0:1])
    squared *= squared
    scratch = np.empty_like(squared)
    for axis in (1, 2):
        np.subtract(valid_vertices[None, :, axis], targets[:, axis:axis + 1], out=scratch)
        scratch *= scratch
        squared += scratch
    nearest = squared.argmin(axis=1)
    index[present] = candidates[nearest]
    snapped[present] = vertices[index[present]]
    distance = np.linalg.norm(snapped[present] - targets, axis=1)
    far = distance > LANDMARK_SNAP_WARNING_MM
    if far.any():
        listed = ", ".join(f"{LANDMARK_NAMES[present[k]]} ({distance[k]:.1f} mm)" for k in np.flatnonzero(far))
        warnings.warn(
            f"landmark(s) farther than {LANDMARK_SNAP_WARNING_MM:g} mm from every valid grid vertex, "
            f"snapped anyway (over a hole or outside the scan?): {listed}",
            LandmarkSnapWarning, stacklevel=3)
    return snapped, index
