"""Ablations of the texture term: each undoes one part of texture tracking or of its
registration term, for the fidelity benchmark to measure what that part is worth.

They are baselines, not options: each patches the stage it undoes for the duration of a
``with`` block, so the library keeps no switch for a variant that measured worse. (The
consistency check and the rim check are real TextureOptions fields; fidelity.py sets
them off as option variants.) A transfer keeps what it computes of its neutral grids,
the texture view among it, so a transfer under an ablation must be given grids nothing
was kept for: fidelity.py gives it copies.
"""
from __future__ import annotations

import contextlib
from unittest import mock

import numpy as np

from tpscore.expression import registration as motion
from tpscore.geometry import robust_scale, tukey_weights
from tpscore.expression import texture


def _without_texture_strength():
    """Every kept match at full confidence, whatever the texture under it."""
    return mock.patch.object(texture, "_texture_strength", lambda pattern, sigma: np.full_like(pattern, 1e6))


def _without_shading_removal():
    """Grey levels normalised over the whole face only: shading stays in the images."""
    def pattern(view, sigma_px, detail=None):
        grey = view.grey[view.valid]
        out = (view.grey - grey.mean()) / max(float(grey.std()), 1e-6)
        return np.where(view.valid, out, 0.0).astype(np.float32)

    return mock.patch.object(texture, "_pattern", pattern)


def _without_common_rendering():
    """The images are not treated alike: each pixel of the plane reads the scan's colour
    image directly, by the affine map of the grid's x, y to its u,v, including where the
    grid has a hole and the background beyond the scan, and the pattern is taken over
    the whole plane. Matches are still lifted only where the surface is."""
    from tpscore.face.image import grey_levels, sample_image

    original_render, original_pattern = texture.render_texture, texture._pattern

    def render(grid, plane):
        view = original_render(grid, plane)
        xy = grid.points[grid.mask][:, :2]
        design = np.column_stack([xy, np.ones(len(xy))])
        affine, *_ = np.linalg.lstsq(design, grid.uv[grid.mask], rcond=None)
        rows, cols = np.mgrid[0:plane.height, 0:plane.width]
        x = plane.x0 + (cols + 0.5) * plane.pixel_mm
        y = plane.y_top - (rows + 0.5) * plane.pixel_mm
        plane_uv = np.stack([x, y, np.ones_like(x)], axis=-1) @ affine
        view.grey = grey_levels(sample_image(grid.image, plane_uv)).astype(np.float32)
        return view

    def pattern(view, sigma_px, detail=None):
        everywhere = texture.TextureView(view.grey, view.points, np.ones_like(view.valid))
        return original_pattern(everywhere, sigma_px)

    stack = contextlib.ExitStack()
    stack.enter_context(mock.patch.object(texture, "render_texture", render))
    stack.enter_context(mock.patch.object(texture, "_pattern", pattern))
    return stack


def _full_point_pull():
    """The match pulls its data point onto the matched point in 3D, normal included."""
    def pull(sample, pairs, targets, prior, floor):
        residual = np.linalg.norm(pairs.moved - targets, axis=1)
        used = prior > 0
        scale = robust_scale(residual[used], floor)
        w = np.where(used, tukey_weights(residual, motion.TUKEY_FACTOR * scale), 0.0) * prior
        return w[:, None] * np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0]), w[:, None] * (targets - sample)

    return mock.patch.object(motion, "_texture_pull", pull)


def _without_robust_weight():
    """Every match pulls with its confidence alone, however far off it is."""
    stack = contextlib.ExitStack()
    for floor in ("TEXTURE_SCALE_FLOOR_START_MM", "TEXTURE_SCALE_FLOOR_END_MM"):
        stack.enter_context(mock.patch.object(motion, floor, 1e9))
    return stack


def _farneback_flow():
    """Farneback's polynomial-expansion flow in place of DIS (OpenCV's defaults for a
    face-sized image: 5 levels, 15-pixel window, 3 iterations)."""
    import cv2

    class Farneback:
        def calc(self, first, second, flow):
            return cv2.calcOpticalFlowFarneback(first, second, None, 0.5, 5, 15, 3, 5, 1.1, 0)

    return mock.patch.object(cv2, "DISOpticalFlow_create", lambda preset: Farneback())


ABLATIONS = {
    "no-texture-strength": _without_texture_strength,
    "no-shading-removal": _without_shading_removal,
    "no-common-rendering": _without_common_rendering,
    "full-point-pull": _full_point_pull,
    "no-robust-weight": _without_robust_weight,
    "farneback-flow": _farneback_flow,
}


def ablation(name: str):
    """The context manager that undoes one part (a name of :data:`ABLATIONS`)."""
    if name not in ABLATIONS:
        return contextlib.nullcontext()
    return ABLATIONS[name]()
