"""The face grid: a face as a regular H x W grid of vertices with a validity mask, a u,v
map and the 22 landmarks snapped to its vertices (:class:`FaceGrid`), and the triangle
mesh over its valid vertices (:class:`GridMesh`). :mod:`tpscore.face.resampling` makes a
grid from a raw scan, :mod:`tpscore.face.loading` from a scan file.

Conventions: units mm; row 0 of a grid is the largest y (the top of the face),
column 0 the smallest x, as in a ``.bnt``; u,v are image coordinates in [0, 1]
(u to the right, v downward, as in a ``.bnt``).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._validation import as_array, as_flag
from ..geometry import FrameTransform
from ..mesh import grid_triangles
from .image import as_colour_image as _as_colour_image
from .image import sample_image
from .landmarks import LANDMARK_NAMES, N_LANDMARKS, as_landmarks, empty_landmarks

__all__ = [
    "FaceGrid",
    "GridMesh",
    "LandmarkSnapWarning",
    "DEFAULT_GRID_SHAPE",
    "MAX_GRID_VERTICES",
    "LANDMARK_SNAP_WARNING_MM",
]

#: Default output grid (rows, columns).
DEFAULT_GRID_SHAPE = (150, 150)

#: The largest grid, in vertices (1024 x 1024). A transfer on it takes about 2 GB of
#: memory and tens of seconds; a scan has fewer points than that (a Bosphorus scan about
#: 200,000), so a finer grid would only interpolate.
MAX_GRID_VERTICES = 1024 * 1024

#: A landmark farther than this (mm) from every valid grid vertex still snaps, with
#: a :class:`LandmarkSnapWarning`: it probably lies over a hole or outside the scan.
LANDMARK_SNAP_WARNING_MM = 10.0


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
        when :func:`~tpscore.face.resampling.resample_scan` brought the scan into the canonical frame (see
        :mod:`tpscore.face.pose`); None when the two are the same.
    landmarks_detected : bool
        Whether the landmarks were found by :func:`~tpscore.detect_landmarks` rather
        than read from a file (:func:`~tpscore.load_scan` sets it): the transfer then
        holds its registration only to the landmark pairs the texture confirms, since
        two scans' detections differ by a few millimetres where a labelled pair differs
        by one or two.
    """

    points: np.ndarray
    mask: np.ndarray
    uv: np.ndarray
    landmarks: np.ndarray
    landmark_vertices: np.ndarray
    image: np.ndarray | None = None
    scan_frame: FrameTransform | None = None
    landmarks_detected: bool = False

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
        self.landmarks_detected = as_flag(self.landmarks_detected, "landmarks_detected")
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
                        self.landmarks.copy(), self.landmark_vertices.copy(), self.image, self.scan_frame,
                        self.landmarks_detected)

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
                        self.image, self.scan_frame, self.landmarks_detected)

    def with_landmarks(self, landmarks) -> "FaceGrid":
        """The same grid with `landmarks` (22, 3; NaN rows missing) snapped to it.

        Each finite landmark moves to the nearest valid vertex (3D distance); see
        :func:`~tpscore.face.resampling.resample_scan` for the warning given when that vertex is far.
        """
        snapped, index = _snap_landmarks(self.vertices, self.mask.reshape(-1), landmarks)
        return FaceGrid(self.points.copy(), self.mask.copy(), self.uv.copy(), snapped, index, self.image,
                        self.scan_frame)


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
