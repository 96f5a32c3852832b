"""Texture tracking: where the skin of a neutral scan went in the expressive scan, from
the scans' colour images.

The geometry of two scans shows how the skin moves across the surface only where the
surface has shape (lips, nose, brows); on a smooth cheek or forehead it cannot say how
far the skin slid. The skin's pattern (pores, freckles, moles, mottling, brows) moves
with the skin, so the colour images can: this stage tracks the pattern with dense
optical flow and lifts the flow to 3D correspondences, which the dense registration
(:func:`tpscore.motion.register_surfaces`) weighs next to the geometry.

1. **One image plane.** Both scans are already in one frame (the expressive scan
   aligned rigidly onto the neutral one). Each is rendered into the same orthographic
   image plane along the viewing axis, through the z-buffered triangles of its own
   grid, sampling its full-resolution colour image at the interpolated u,v: both images
   then have the same pixels, holes, eye openings and background, whatever the pose of
   the head in each scan.
2. **No shading.** The light is fixed in the scanner while the head turns and the skin
   bends, so shading differs between the scans. The grey levels minus their local mean
   (a Gaussian of ``shading_sigma_mm``), divided by their local contrast, keep the
   skin's pattern and drop shading, exposure and white balance.
3. **Flow.** OpenCV's DIS optical flow (Kroeger et al. 2016) from the neutral to the
   expressive image and back.
4. **Confidence.** A match is kept where the flow is consistent (forward then
   backward returns within ``consistency_px``), starts and lands on the surface away
   from its rims, and is weighted by the strength of the texture under it (the smaller
   eigenvalue of the local structure tensor): flat skin without a pattern says little.
5. **Lifting.** The landing pixel's 3D point on the expressive scan is the match of the
   neutral vertex under the starting pixel.

Measured in ``benchmarks/FIDELITY.md`` (texture section).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from ._validation import as_positive
from .image import bilinear, grey_levels, sample_image
from .preprocess import FaceGrid
from .raster import rasterise

__all__ = ["TextureOptions", "TextureMatches", "TextureWarning", "track_texture", "render_texture",
           "TexturePlane"]


class TextureWarning(UserWarning):
    """The colour images cannot be used; the motion comes from the geometry alone."""


@dataclass(frozen=True)
class TextureOptions:
    """Settings of texture tracking (:func:`track_texture`).

    Attributes
    ----------
    shading_sigma_mm : float
        Width of the local mean removed from the grey levels (shading varies over
        centimetres, the skin's pattern over millimetres).
    consistency_px : float
        Largest forward-backward flow error of a kept match, in image-plane pixels.
    rim_px : int
        Matches must start and land at least this many pixels inside the surface.
    min_matched_fraction : float
        Below this share of consistent matches among the valid vertices the flow has
        failed (another person's scan, a texture it cannot follow): texture is not used.
    """

    shading_sigma_mm: float = 2.0
    consistency_px: float = 0.5
    rim_px: int = 2
    min_matched_fraction: float = 0.25

    def __post_init__(self):
        as_positive(self.shading_sigma_mm, "shading_sigma_mm")
        as_positive(self.consistency_px, "consistency_px")
        if int(self.rim_px) != self.rim_px or self.rim_px < 0:
            raise ValueError(f"rim_px must be an integer >= 0, got {self.rim_px!r}")
        if not 0 <= self.min_matched_fraction < 1:
            raise ValueError(f"min_matched_fraction must be in [0, 1), got {self.min_matched_fraction!r}")


@dataclass(frozen=True)
class TexturePlane:
    """An orthographic image plane over x, y: pixel (r, c) has its centre at
    x = x0 + (c + 0.5) pixel_mm, y = y_top - (r + 0.5) pixel_mm."""

    x0: float
    y_top: float
    pixel_mm: float
    width: int
    height: int

    @classmethod
    def covering(cls, points, pixel_mm: float, margin_mm: float = 2.0) -> "TexturePlane":
        """The plane over the x, y extent of (n, 3) points, with a margin."""
        lower = points[:, :2].min(axis=0) - margin_mm
        upper = points[:, :2].max(axis=0) + margin_mm
        width, height = (np.ceil((upper - lower) / pixel_mm).astype(int) + 1).tolist()
        return cls(float(lower[0]), float(upper[1]), float(pixel_mm), width, height)

    def pixels(self, points) -> np.ndarray:
        """(n, 2) continuous pixel positions (x along columns, y along rows; pixel
        centres at integers) of (n, >=2) points."""
        points = np.asarray(points, dtype=np.float64)
        return np.column_stack([(points[:, 0] - self.x0) / self.pixel_mm - 0.5,
                                (self.y_top - points[:, 1]) / self.pixel_mm - 0.5])


@dataclass
class TextureView:
    """A face's colour and surface as seen in a :class:`TexturePlane`."""

    grey: np.ndarray       # (h, w) float32 grey levels, 0 where nothing is seen
    points: np.ndarray     # (h, w, 3) surface point under each pixel, NaN where none
    valid: np.ndarray      # (h, w) bool


def render_texture(grid: FaceGrid, plane: TexturePlane) -> TextureView:
    """Render a face grid's colour image into an image plane through its triangles."""
    if grid.image is None:
        raise ValueError("the face grid has no colour image")
    mesh = grid.mesh()
    pixels = plane.pixels(mesh.vertices) + 0.5      # the rasteriser's centres are at +0.5
    triangle, barycentric = rasterise(pixels, mesh.vertices[:, 2], mesh.faces, plane.width, plane.height)
    covered = triangle >= 0
    corners = mesh.faces[triangle[covered]]
    weights = barycentric[covered]
    uv = np.einsum("nk,nkd->nd", weights, mesh.uv[corners])
    grey = np.zeros(covered.shape, dtype=np.float32)
    grey[covered] = grey_levels(sample_image(grid.image, uv))
    points = np.full(covered.shape + (3,), np.nan)
    points[covered] = np.einsum("nk,nkd->nd", weights, mesh.vertices[corners])
    return TextureView(grey, points, covered)


@dataclass
class TextureMatches:
    """Where the skin under each vertex of a neutral grid went in the expressive scan.

    Attributes
    ----------
    targets : (H, W, 3) ndarray
        The matched point on the expressive surface (NaN where there is no match).
    confidence : (H, W) ndarray
        Weight of each match in [0, 1] (0 where there is none).
    matched_fraction : float
        Share of the grid's valid vertices with a match.
    seconds : float
        Time taken (rendering, flow, lifting).
    """

    targets: np.ndarray
    confidence: np.ndarray
    matched_fraction: float
    seconds: float


def _image_pixel_mm(grid: FaceGrid) -> float:
    """The size of one colour-image pixel on the face (mm), from the affine map of the
    valid vertices' x, y to their image pixels."""
    xy = grid.points[grid.mask][:, :2]
    pixels = grid.uv[grid.mask] * np.array(grid.image.shape[1::-1], dtype=np.float64)
    design = np.column_stack([xy - xy.mean(axis=0), np.ones(len(xy))])
    solution, *_ = np.linalg.lstsq(design, pixels, rcond=None)
    return float(1.0 / np.sqrt(abs(np.linalg.det(solution[:2]))))


def _pattern(view: TextureView, sigma_px: float) -> np.ndarray:
    """The skin's pattern: grey levels minus their local mean over the surface, over
    their local rms contrast (shading, exposure and white balance drop out)."""
    import cv2

    valid = view.valid.astype(np.float32)
    grey = np.where(view.valid, view.grey, 0.0).astype(np.float32)

    def local_mean(image, sigma):
        return cv2.GaussianBlur(image, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(valid, (0, 0), sigma), 1e-3)

    detail = np.where(view.valid, grey - local_mean(grey, sigma_px), 0.0).astype(np.float32)
    contrast = np.sqrt(np.maximum(local_mean(detail * detail, 4.0 * sigma_px), 1e-6))
    return np.where(view.valid, detail / contrast, 0.0).astype(np.float32)


def _eight_bit(pattern: np.ndarray) -> np.ndarray:
    # DIS works on 8-bit images; +-4 local standard deviations span the range
    return np.clip(128.0 + 32.0 * pattern, 0, 255).astype(np.uint8)


# The structure tensor's window (mm): about the flow's patch on the face.
_STRENGTH_WINDOW_MM = 1.4
# The texture strength at which a match gets half its weight.
_STRENGTH_HALF = 0.005


def _texture_strength(pattern: np.ndarray, sigma_px: float) -> np.ndarray:
    """Smaller eigenvalue of the pattern's structure tensor over a Gaussian window: how
    firmly the texture pins a patch down in its weakest direction."""
    import cv2

    gx = cv2.Sobel(pattern, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(pattern, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), sigma_px)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), sigma_px)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), sigma_px)
    return 0.5 * (jxx + jyy - np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy ** 2))


def _inside(valid: np.ndarray, rim_px: int) -> np.ndarray:
    import cv2

    if rim_px == 0:
        return valid
    kernel = np.ones((2 * rim_px + 1, 2 * rim_px + 1), np.uint8)
    return cv2.erode(valid.astype(np.uint8), kernel) > 0


def _warp_map(view: TextureView, plane: TexturePlane, prewarp) -> np.ndarray:
    """(h, w, 2) float32 pixel positions where each neutral pixel's skin is expected in the
    expressive image: its surface point moved by ``prewarp`` (identity off the surface)."""
    rows, cols = np.mgrid[0:plane.height, 0:plane.width].astype(np.float32)
    where = np.stack([cols, rows], axis=-1)
    seen = view.points[view.valid]
    moved = seen + np.asarray(prewarp(seen), dtype=np.float64)
    ok = np.isfinite(moved).all(axis=1)
    target = where[view.valid]
    target[ok] = plane.pixels(moved[ok]).astype(np.float32)
    where[view.valid] = target
    return where


def track_texture(neutral: FaceGrid, expressive: FaceGrid,
                  options: TextureOptions = TextureOptions(), prewarp=None) -> TextureMatches | None:
    """Match each vertex of a neutral grid to the expressive scan by its skin texture.

    Parameters
    ----------
    neutral, expressive : FaceGrid
        Two scans of one person in one frame (the expressive one aligned rigidly onto the
        neutral one), each with its colour image.
    options : TextureOptions
    prewarp : callable, optional
        A first guess of the motion, (m, 3) neutral points -> (m, 3) displacements (mm):
        the expressive image is warped back by it before the flow, so the flow only
        has to find what the guess missed.

    Returns
    -------
    TextureMatches, or None with a :class:`TextureWarning` saying why when the images
    cannot be used (a grid without an image, an image too dark or without texture, or a
    flow that fails its consistency check on most of the face).
    """
    import cv2

    start = time.perf_counter()
    for name, grid in (("neutral", neutral), ("expressive", expressive)):
        if grid.image is None:
            warnings.warn(f"the {name} scan has no colour image: the motion comes from the "
                          "geometry alone", TextureWarning, stacklevel=2)
            return None
    pixel_mm = _image_pixel_mm(neutral)
    valid_points = neutral.points[neutral.mask]
    # a plane as fine as the neutral image, but never finer than 0.1 mm nor more than
    # 2,048 pixels across, which bounds the flow's time on denser cameras
    extent = np.ptp(valid_points[:, :2], axis=0).max()
    pixel_mm = max(pixel_mm, 0.1, extent / 2048.0)
    plane = TexturePlane.covering(valid_points, pixel_mm)
    views = [render_texture(grid, plane) for grid in (neutral, expressive)]
    for name, view in zip(("neutral", "expressive"), views):
        brightness = float(np.median(view.grey[view.valid])) if view.valid.any() else 0.0
        if brightness < 8.0:
            warnings.warn(f"the {name} scan's colour image is too dark (median grey {brightness:.1f} of "
                          "255): the motion comes from the geometry alone", TextureWarning, stacklevel=2)
            return None
    sigma_px = options.shading_sigma_mm / pixel_mm
    patterns = [_pattern(view, sigma_px) for view in views]
    expressive_pattern = patterns[1]
    expressive_inside = _inside(views[1].valid, options.rim_px).astype(np.float32)
    warp = None
    if prewarp is not None:
        warp = _warp_map(views[0], plane, prewarp)
        expressive_pattern = cv2.remap(patterns[1], warp, None, cv2.INTER_LINEAR, borderValue=0)
        expressive_inside = cv2.remap(expressive_inside, warp, None, cv2.INTER_LINEAR, borderValue=0)
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    forward = flow.calc(_eight_bit(patterns[0]), _eight_bit(expressive_pattern), None)
    backward = flow.calc(_eight_bit(expressive_pattern), _eight_bit(patterns[0]), None)

    flat_valid = neutral.mask.reshape(-1)
    points = neutral.points.reshape(-1, 3)[flat_valid]
    begin = plane.pixels(points)
    step = bilinear(forward, begin[:, 0], begin[:, 1])
    land = begin + step
    back = bilinear(backward, land[:, 0], land[:, 1])
    consistency = np.linalg.norm(step + back, axis=1)
    inside_neutral = bilinear(_inside(views[0].valid, options.rim_px).astype(np.float32), begin[:, 0], begin[:, 1])
    inside_expressive = bilinear(expressive_inside, land[:, 0], land[:, 1])
    matched = (consistency < options.consistency_px) & (inside_neutral > 0.999) & (inside_expressive > 0.999)
    matched_fraction = float(matched.mean()) if len(matched) else 0.0
    if matched_fraction < options.min_matched_fraction:
        warnings.warn(f"texture tracking matched only {100 * matched_fraction:.0f} % of the face "
                      f"(at least {100 * options.min_matched_fraction:.0f} % needed): the motion comes "
                      "from the geometry alone", TextureWarning, stacklevel=2)
        return None
    strength = bilinear(_texture_strength(patterns[0], _STRENGTH_WINDOW_MM / pixel_mm), begin[:, 0], begin[:, 1])
    # a pattern of unit local contrast has strength ~0.02 where it is textured in both
    # directions; flat skin tends to 0
    confidence = np.where(matched, strength / (strength + _STRENGTH_HALF), 0.0)
    if warp is not None:
        land = bilinear(warp, land[:, 0], land[:, 1]).astype(np.float64)
    landed = bilinear(np.nan_to_num(views[1].points), land[:, 0], land[:, 1])
    targets = np.full(neutral.points.shape, np.nan).reshape(-1, 3)
    targets[np.flatnonzero(flat_valid)[matched]] = landed[matched]
    full_confidence = np.zeros(flat_valid.shape)
    full_confidence[flat_valid] = confidence
    return TextureMatches(targets.reshape(neutral.points.shape), full_confidence.reshape(neutral.mask.shape),
                          matched_fraction, time.perf_counter() - start)
