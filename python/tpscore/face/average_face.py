"""The average face model (AFM): the reference face every scan is normalised against.

Built the way the method builds it: the landmarks of a set of faces are brought to a
consensus by generalised Procrustes analysis; each face is aligned to the consensus
and morphed onto it with the landmark TPS; the morphed surfaces are sampled on one
regular x-y grid (depth along a ray from the viewer) and their depths averaged.

tpscore ships an AFM built by :func:`build_average_face` from the procedural faces of
:mod:`tpscore.showcase.datasets` (``tpscore build-afm`` rebuilds it); users build their own from
any database of faces.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from typing import Sequence

import numpy as np

from .landmarks import LANDMARK_NAMES, N_LANDMARKS, landmark_index, landmark_map
from .normalise import FrameTransform, NormalisedFace, similarity_transform
from .grid import FaceGrid
from .io import read_npz, write_npz
from ..spatial import MeshSurface

__all__ = ["AverageFace", "build_average_face", "load_average_face", "consensus_landmarks",
           "canonical_frame"]


def _side_indices(side: str) -> list[int]:
    return [i for i, n in enumerate(LANDMARK_NAMES) if side in n.lower().split()]


@dataclass
class AverageFace:
    """A reference face: a grid surface in its own canonical frame, with landmarks.

    The frame: nose tip at the origin, +x toward the subject's left (the line between
    the left and right landmarks), +y up (from the chin toward the eyes), +z out of the
    face toward the viewer; millimetres.
    """

    grid: FaceGrid
    n_faces: int
    _normalised: object = field(default=None, init=False, repr=False, compare=False)

    @property
    def landmarks(self) -> np.ndarray:
        return self.grid.landmarks

    def as_normalised_face(self):
        """The AFM as a face already in the reference frame (built once: it caches the
        surface queries every transfer makes on it)."""
        if self._normalised is None:
            self._normalised = NormalisedFace(self.grid, FrameTransform.identity())
        return self._normalised

    def save(self, path) -> None:
        """Write the AFM as a compressed .npz."""
        write_npz(path, points=self.grid.points.astype(np.float32), mask=self.grid.mask,
                  landmarks=self.grid.landmarks, n_faces=self.n_faces)

    @classmethod
    def load(cls, path) -> "AverageFace":
        what = "an average face model"
        data = read_npz(path, ("points", "mask", "landmarks", "n_faces"), what=what)
        try:
            n_faces = data["n_faces"]
            if n_faces.shape != () or not np.issubdtype(n_faces.dtype, np.integer) or n_faces < 1:
                raise ValueError(f"n_faces must be a whole number >= 1, got {n_faces!r}")
            grid = FaceGrid.from_points(data["points"], data["mask"], data["landmarks"])
        except ValueError as exc:
            raise ValueError(f"{str(path)!r}: not {what}: {exc}") from None
        return cls(grid, int(n_faces))


def canonical_frame(landmarks) -> FrameTransform:
    """Rigid transform putting landmarks in the canonical frame (see AverageFace)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    tip = lm[landmark_index("Nose tip")]
    left = np.nanmean(lm[_side_indices("left")], axis=0)
    right = np.nanmean(lm[_side_indices("right")], axis=0)
    chin = lm[landmark_index("Chin middle")]
    eyes = np.nanmean(lm[[landmark_index(n) for n in ("Inner left eye corner", "Inner right eye corner",
                                                       "Outer left eye corner", "Outer right eye corner")]],
                      axis=0)
    if not np.isfinite(np.concatenate([tip, left, right, chin, eyes])).all():
        raise ValueError("the canonical frame needs the nose tip, chin middle, eye corners and "
                         "left/right landmarks")
    x = left - right
    x /= np.linalg.norm(x)
    y = eyes - chin
    y -= (y @ x) * x
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    rotation = np.vstack([x, y, z])
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = -rotation @ tip
    return FrameTransform(m, "rigid")


def consensus_landmarks(landmark_sets: Sequence[np.ndarray], iterations: int = 10) -> np.ndarray:
    """Generalised Procrustes consensus of (22, 3) landmark sets (NaN = missing).

    Each set is aligned to the running mean by a least-squares similarity; the mean
    is rescaled to the average size of the inputs (so the consensus stays in mm) and
    put in the canonical frame.
    """
    sets = [np.asarray(s, dtype=np.float64) for s in landmark_sets]
    if len(sets) < 1:
        raise ValueError("consensus_landmarks needs at least one landmark set")
    for k, s in enumerate(sets):
        if s.shape != (N_LANDMARKS, 3):
            raise ValueError(f"landmark set {k} has shape {s.shape}, expected ({N_LANDMARKS}, 3)")

    def size(s):
        c = s - np.nanmean(s, axis=0)
        return np.sqrt(np.nanmean((c**2).sum(axis=1)))

    target_size = np.mean([size(s) for s in sets])
    mean = sets[0].copy()
    for _ in range(iterations):
        aligned = [similarity_transform(s, mean).apply(s) for s in sets]
        with np.errstate(invalid="ignore"):
            new = np.nanmean(np.stack(aligned), axis=0)
        new = (new - np.nanmean(new, axis=0)) * (target_size / size(new))
        converged = np.nanmax(np.abs(new - mean)) < 1e-6 if _ else False
        mean = new
        if converged:
            break
    if not np.isfinite(mean).all():
        raise ValueError("some landmark is missing in every face: no consensus for it")
    return canonical_frame(mean).apply(mean)


def build_average_face(faces: Sequence[FaceGrid], shape=(150, 150), *, coverage: float = 0.75,
                       margin_mm: float = 0.0) -> AverageFace:
    """Build an average face model from face grids with landmarks.

    Parameters
    ----------
    faces : sequence of FaceGrid
        At least one face, each with the nose tip and at least five landmarks.
    shape : (H, W)
        Grid of the AFM.
    coverage : float in (0, 1]
        A grid node is valid when at least this fraction of the faces covers it.
    """
    if len(faces) < 1:
        raise ValueError("build_average_face needs at least one face")
    if not 0 < coverage <= 1:
        raise ValueError(f"coverage must be in (0, 1], got {coverage}")
    consensus = consensus_landmarks([f.landmarks for f in faces])
    morphed = []
    for k, face in enumerate(faces):
        to_consensus = similarity_transform(face.landmarks, consensus)
        moved_landmarks = to_consensus.apply(face.landmarks)
        # coincident landmarks (the lips of a closed mouth) are merged, not fitted twice
        warp = landmark_map(moved_landmarks, consensus, merge_mm=1.0, what=f"face {k} -> consensus")
        points = face.points.reshape(-1, 3)
        valid = face.mask.ravel()
        out = np.full_like(points, np.nan)
        out[valid] = warp(to_consensus.apply(points[valid]))
        morphed.append((out, face.triangles()))

    all_points = np.vstack([m[0][np.isfinite(m[0]).all(axis=1)] for m in morphed])
    lo, hi = all_points[:, :2].min(axis=0) - margin_mm, all_points[:, :2].max(axis=0) + margin_mm
    h, w = shape
    xs = np.linspace(lo[0], hi[0], w)
    ys = np.linspace(hi[1], lo[1], h)  # row 0 at the top, as in a scan
    gx, gy = np.meshgrid(xs, ys)
    top = all_points[:, 2].max() + 100.0
    origins = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, top)])
    down = np.tile([0.0, 0.0, -1.0], (gx.size, 1))
    depth_sum = np.zeros(gx.size)
    count = np.zeros(gx.size)
    for points, triangles in morphed:
        vertices = np.where(np.isfinite(points), points, 0.0)
        hits = MeshSurface(vertices, triangles).intersect_rays(origins, down)
        depth_sum[hits.hit] += hits.points[hits.hit, 2]
        count[hits.hit] += 1
    mask = count >= coverage * len(faces)
    depth = np.where(mask, depth_sum / np.maximum(count, 1), np.nan)
    points = np.stack([gx, gy, depth.reshape(h, w)], axis=-1)
    points[~mask.reshape(h, w)] = np.nan
    return AverageFace(FaceGrid.from_points(points, mask.reshape(h, w), consensus), len(faces))


@lru_cache(maxsize=1)
def load_average_face() -> AverageFace:
    """The AFM shipped with tpscore (built from the procedural faces of tpscore.showcase.datasets)."""
    path = resources.files("tpscore").joinpath("data/average_face.npz")
    with resources.as_file(path) as real:
        return AverageFace.load(real)
