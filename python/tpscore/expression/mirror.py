"""The mirror average of a bilateral expression's motion.

A bilateral AU moves both sides of the face alike, so a displacement field and its
mirror image across the face's plane of symmetry are two estimates of one motion with
independent errors (landmark labels, holes, scanner noise); their mean halves the
errors' variance. Without it the benchmark scores 0.412 instead of 0.373 (geometry
only; benchmarks/FIDELITY.md).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

__all__ = ["Coverage", "MirroredMotion"]


class Coverage:
    """How well a face's vertices cover points, measured in the x-y plane the face is a
    height field over: 1 within ``reach_mm`` of a vertex, falling to 0 at twice that.

    Parameters
    ----------
    covered_points : (n, 3) array_like
        The face's vertices (non-finite rows are ignored; at least one finite).
    reach_mm : float
        Distance to the nearest vertex below which a point counts as covered.
    """

    def __init__(self, covered_points, reach_mm: float = 3.0):
        covered = np.asarray(covered_points, dtype=np.float64).reshape(-1, 3)
        covered = covered[np.isfinite(covered).all(axis=1)]
        if len(covered) == 0:
            raise ValueError("covered_points has no finite point")
        if not np.isfinite(reach_mm) or reach_mm <= 0:
            raise ValueError(f"reach_mm must be finite and > 0, got {reach_mm!r}")
        self.reach_mm = float(reach_mm)
        # distance to the face over a raster of the x-y plane (a quarter of the reach per
        # cell): one lookup per point instead of a nearest-neighbour search
        self._cell = self.reach_mm / 4.0
        self._origin = covered[:, :2].min(axis=0) - 2.0 * self.reach_mm
        shape = np.ceil((covered[:, :2].max(axis=0) + 2.0 * self.reach_mm - self._origin)
                        / self._cell).astype(int) + 1
        occupied = np.zeros(shape, dtype=bool)
        cells = np.floor((covered[:, :2] - self._origin) / self._cell).astype(int)
        occupied[cells[:, 0], cells[:, 1]] = True
        # the raster's weights, in a ring of zeros that takes every point beyond it: a
        # lookup is then one clipped index (this is asked of every point a transfer moves)
        distance = distance_transform_edt(~occupied) * self._cell
        self._weight = np.pad(np.clip(2.0 - distance / self.reach_mm, 0.0, 1.0), 1)

    def __call__(self, points) -> np.ndarray:
        """(m,) weights in [0, 1] of (m, >=2) finite points."""
        points = np.asarray(points, dtype=np.float64)
        cells = np.floor((points[:, :2] - self._origin) / self._cell)
        # cells beyond the raster fall on the ring (clipped as floats: a far point's
        # cell index may not fit an integer)
        limit = np.array(self._weight.shape, dtype=np.float64) - 1.0
        cells = np.clip(cells + 1.0, 0.0, limit).astype(np.intp)
        return self._weight[cells[:, 0], cells[:, 1]]


class MirroredMotion:
    """The mean of a displacement field and its mirror image: the motion of a bilateral
    expression, which moves both sides of the face alike.

    A point p takes the mean of its own displacement u(p) and of the displacement at its
    mirror point, reflected back: M u(S p), with S the face's mirror map (a plane
    reflection, :func:`tpscore.expression.alignment.fit_mirror_symmetry`) and M its linear part.
    The two sides' independent errors (landmark labels, scanner noise, holes) average
    out. Each term is weighted by how well the registered face covers its point (full
    within ``reach_mm`` of a vertex of the face, none beyond twice that, measured in the
    x-y plane the face is a height field over), so a point whose mirror image falls off
    the scan, or into a hole, keeps its own motion, and a point in a hole takes its
    mirror's.

    Parameters
    ----------
    motion : callable
        The displacement field, (m, 3) points -> (m, 3) displacements.
    mirror : FrameTransform
        The face's mirror map (in the frame of the field).
    covered_points : (n, 3) array_like or Coverage
        The vertices of the face the field was registered on, or their
        :class:`Coverage` (which brings its own reach).
    reach_mm : float
        Distance to the nearest vertex below which a point counts as covered.
    """

    def __init__(self, motion, mirror, covered_points, reach_mm: float = 3.0):
        self.motion = motion
        self.mirror = mirror
        self.coverage = covered_points if isinstance(covered_points, Coverage) else Coverage(covered_points, reach_mm)
        self.reach_mm = self.coverage.reach_mm

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(p.shape, np.nan)
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            return out
        own_points = p[ok]
        mirrored_points = self.mirror.apply(own_points)
        own = self.motion(own_points)
        mirrored = self.mirror.apply_vectors(self.motion(mirrored_points))
        # a point nothing covers keeps its own (extrapolated) motion
        own_weight = np.maximum(self.coverage(own_points), 1e-6)
        mirrored_weight = self.coverage(mirrored_points)
        out[ok] = (own * own_weight[:, None] + mirrored * mirrored_weight[:, None]) \
            / (own_weight + mirrored_weight)[:, None]
        return out
