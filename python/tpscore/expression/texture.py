"""Texture tracking: where the skin of a neutral scan went in the expressive scan, from
the scans' colour images.

The geometry of two scans shows how the skin moves across the surface only where the
surface has shape (lips, nose, brows); on a smooth cheek or forehead it cannot say how
far the skin slid. The skin's pattern (pores, freckles, moles, mottling, brows) moves
with the skin, so the colour images can: this stage tracks the pattern with dense
optical flow and lifts the flow to 3D correspondences, which the dense registration
(:func:`tpscore.expression.registration.register_surfaces`) weighs next to the geometry.

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
   expressive image and back, at half the plane's resolution over the whole face, and
   again at full resolution over a box around each of the caller's fine regions (the
   eyes): there patches half as wide follow a lower lid's small slide beside the upper
   lid's far larger motion.
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
from dataclasses import dataclass, field

import numpy as np
import cv2

from .._threads import side_by_side
from .._validation import as_flag, as_positive
from ..face.image import bilinear, grey_levels
from ..face.grid import FaceGrid
from ..raster import interpolate_pixels, rasterise

__all__ = ["TextureOptions", "TextureMatches", "TextureWarning", "track_texture", "render_texture",
           "TexturePlane", "NeutralView"]


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
    triangle: np.ndarray = None      # (h, w) the grid mesh's triangle under each pixel
    barycentric: np.ndarray = None   # (h, w, 3) the pixel centre's weights on it


def render_texture(grid: FaceGrid, plane: TexturePlane) -> TextureView:
    """Render a face grid's colour image into an image plane through its triangles."""

    if grid.image is None:
        raise ValueError("the face grid has no colour image")
    mesh = grid.mesh()
    pixels = plane.pixels(mesh.vertices) + 0.5      # the rasteriser's centres are at +0.5
    triangle, barycentric = rasterise(pixels, mesh.vertices[:, 2], mesh.faces, plane.width, plane.height)
    # each pixel's surface point and its position in the colour image
    image_pixels = mesh.uv * np.array(grid.image.shape[1::-1], dtype=np.float64) - 0.5
    seen = interpolate_pixels(np.column_stack([mesh.vertices, image_pixels]), mesh.faces, triangle, barycentric)
    covered = triangle >= 0
    where = seen[..., 3:].astype(np.float32)
    where[~covered] = -1.0
    grey = cv2.remap(grey_levels(grid.image), where[..., 0], where[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    grey[~covered] = 0.0
    return TextureView(grey, seen[..., :3], covered, triangle, barycentric)


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
    _tracker: "_Tracker | None" = field(default=None, repr=False)

    def __getstate__(self):
        # the tracker (the two rendered views and the flow) is not pickled: unpickled
        # matches cannot be refined
        state = dict(self.__dict__)
        state["_tracker"] = None
        return state

    @property
    def neutral_view(self) -> "NeutralView | None":
        """How the neutral scan was seen (None for unpickled matches): what a next
        tracking from the same neutral scan and options can start from."""
        return None if self._tracker is None else self._tracker.neutral_view

    def refined(self, displacement, regions=None) -> "TextureMatches":
        """The matches found again with the expressive image warped back by a motion
        estimate, so that the flow only has to find what the estimate missed (large,
        deforming motions fail the consistency check when the flow must find them alone).

        Parameters
        ----------
        displacement : (H, W, 3) array_like
            The estimated motion of each vertex of the neutral grid (mm; NaN where
            unknown).
        regions : sequence of (H, W) bool array_like, optional
            Parts of the neutral grid (each eye's window, say) where the matches are
            wanted: each is matched on its own, at the image plane's full resolution,
            over the box around it (:data:`REGION_MARGIN_MM` wider), and no match is
            made elsewhere. Default: the whole face at the flow's usual resolution.

        Returns
        -------
        TextureMatches; these matches unchanged when the refined flow fails its check.
        """
        if self._tracker is None:
            raise ValueError("these matches were not made by track_texture and cannot be refined")
        if regions is not None:
            regions = _grid_masks(regions, self.confidence.shape, "regions")
        start = time.perf_counter()
        refined = self._tracker.match(np.asarray(displacement, dtype=np.float64), regions)
        if refined is None:
            return self
        refined.seconds = time.perf_counter() - start
        return refined


def _image_pixel_mm(grid: FaceGrid) -> float:
    """The size of one colour-image pixel on the face (mm), from the affine map of the
    valid vertices' x, y to their image pixels."""
    xy = grid.points[grid.mask][:, :2]
    pixels = grid.uv[grid.mask] * np.array(grid.image.shape[1::-1], dtype=np.float64)
    design = np.column_stack([xy - xy.mean(axis=0), np.ones(len(xy))])
    solution, *_ = np.linalg.lstsq(design, pixels, rcond=None)
    return float(1.0 / np.sqrt(abs(np.linalg.det(solution[:2]))))


def _detail(view: TextureView, sigma_px: float) -> np.ndarray:
    """(h, w) float32 grey levels minus their local mean over the surface (0 off it)."""

    valid = view.valid.astype(np.float32)
    grey = np.where(view.valid, view.grey, 0.0).astype(np.float32)
    mean = cv2.GaussianBlur(grey, (0, 0), sigma_px) / np.maximum(cv2.GaussianBlur(valid, (0, 0), sigma_px), 1e-3)
    return np.where(view.valid, grey - mean, 0.0).astype(np.float32)


def _detail_rms(view: TextureView, detail: np.ndarray) -> float:
    """RMS of a view's :func:`_detail` over the surface: the strength of the image's
    pattern in grey levels (0 for a flat image)."""

    inside = detail[view.valid]
    return float(np.sqrt(np.mean(inside * inside))) if inside.size else 0.0


def _pattern(view: TextureView, sigma_px: float, detail: np.ndarray | None = None) -> np.ndarray:
    """The skin's pattern: grey levels minus their local mean over the surface (the
    view's :func:`_detail`, if already computed), over their local rms contrast
    (shading, exposure and white balance drop out)."""

    if detail is None:
        detail = _detail(view, sigma_px)
    valid = view.valid.astype(np.float32)
    # the contrast varies over centimetres: estimate it on a quarter-resolution image
    height, width = detail.shape
    small = (max(width // 4, 1), max(height // 4, 1))
    energy = cv2.resize(detail * detail, small, interpolation=cv2.INTER_AREA)
    weight = cv2.resize(valid, small, interpolation=cv2.INTER_AREA)
    energy = cv2.GaussianBlur(energy, (0, 0), sigma_px) / np.maximum(cv2.GaussianBlur(weight, (0, 0), sigma_px), 1e-3)
    contrast = np.sqrt(np.maximum(cv2.resize(energy, (width, height), interpolation=cv2.INTER_LINEAR), 1e-6))
    return np.where(view.valid, detail / contrast, 0.0).astype(np.float32)


@dataclass
class _Look:
    """A scan seen in the texture plane: its view, how bright it is and how much
    pattern it shows, the pattern itself (None when it is too dark or flat) and, when
    asked for (the neutral scan's), the pattern's texture strength."""

    view: TextureView
    brightness: float
    detail: float
    pattern: np.ndarray | None
    strength: np.ndarray | None = None


@dataclass
class NeutralView:
    """The neutral scan as texture tracking sees it with one :class:`TextureOptions`:
    the image plane (as fine as the scan's colour image), the width of the pattern's
    local mean in the plane's pixels, and the scan's look there (view, pattern, texture
    strength). It depends on the neutral scan alone, so a transfer keeps it with the
    neutral face for the next (:attr:`TextureMatches.neutral_view`, and
    :func:`track_texture`'s ``neutral_view``)."""

    plane: TexturePlane
    sigma_px: float
    look: _Look


def _plane_of(neutral: FaceGrid, options: TextureOptions):
    """The image plane of a neutral scan, the pattern's local mean width and the
    structure tensor's window in its pixels."""
    pixel_mm = _image_pixel_mm(neutral)
    valid_points = neutral.points[neutral.mask]
    # a plane as fine as the neutral image, but never finer than 0.1 mm nor more than
    # 2,048 pixels across, which bounds the flow's time on denser cameras
    extent = np.ptp(valid_points[:, :2], axis=0).max()
    pixel_mm = max(pixel_mm, 0.1, extent / 2048.0)
    plane = TexturePlane.covering(valid_points, pixel_mm)
    return plane, options.shading_sigma_mm / pixel_mm, _STRENGTH_WINDOW_MM / pixel_mm


def _look(grid: FaceGrid, plane: TexturePlane, sigma_px: float, strength_window_px: float | None = None) -> _Look:
    view = render_texture(grid, plane)
    brightness = float(np.median(view.grey[view.valid])) if view.valid.any() else 0.0
    if brightness < 8.0:
        return _Look(view, brightness, 0.0, None)
    detail = _detail(view, sigma_px)
    detail_rms = _detail_rms(view, detail)
    if detail_rms < _MIN_DETAIL_GREY:
        return _Look(view, brightness, detail_rms, None)
    pattern = _pattern(view, sigma_px, detail)
    strength = None if strength_window_px is None else _texture_strength(pattern, strength_window_px)
    return _Look(view, brightness, detail_rms, pattern, strength)


def _eight_bit(pattern: np.ndarray) -> np.ndarray:
    # DIS works on 8-bit images; +-4 local standard deviations span the range
    return np.clip(128.0 + 32.0 * pattern, 0, 255).astype(np.uint8)


# Below this rms of detail (grey levels) an image holds nothing but 8-bit rounding and
# sensor noise: a flat or blurred image has no pattern to follow.
_MIN_DETAIL_GREY = 0.5
# The structure tensor's window (mm): about the flow's patch on the face.
_STRENGTH_WINDOW_MM = 1.4
# The texture strength at which a match gets half its weight.
_STRENGTH_HALF = 0.005


def _texture_strength(pattern: np.ndarray, sigma_px: float) -> np.ndarray:
    """Smaller eigenvalue of the pattern's structure tensor over a Gaussian window: how
    firmly the texture pins a patch down in its weakest direction."""

    gx = cv2.Sobel(pattern, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(pattern, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), sigma_px)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), sigma_px)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), sigma_px)
    return 0.5 * (jxx + jyy - np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy ** 2))


def _inside(valid: np.ndarray, rim_px: int) -> np.ndarray:

    if rim_px == 0:
        return valid
    kernel = np.ones((2 * rim_px + 1, 2 * rim_px + 1), np.uint8)
    return cv2.erode(valid.astype(np.uint8), kernel) > 0


@dataclass(frozen=True)
class _WarpLayout:
    """A box of the neutral view as :meth:`_Tracker._warp` reads it: the flat indices of
    its pixels that see the surface, their triangles, barycentric weights and surface
    points, and the box's own pixel positions (float32, (h, w, 2): x, y)."""

    seen: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    points: np.ndarray
    identity: np.ndarray

    @classmethod
    def of(cls, view: "TextureView", box) -> "_WarpLayout":
        row0, row1, col0, col1 = box
        seen = np.flatnonzero(view.valid[row0:row1, col0:col1])
        triangle = view.triangle[row0:row1, col0:col1].reshape(-1)[seen]
        barycentric = view.barycentric[row0:row1, col0:col1].reshape(-1, 3)[seen]
        points = view.points[row0:row1, col0:col1].reshape(-1, 3)[seen]
        identity = np.empty((row1 - row0, col1 - col0, 2), dtype=np.float32)
        identity[..., 0] = np.arange(col0, col1, dtype=np.float32)[None, :]
        identity[..., 1] = np.arange(row0, row1, dtype=np.float32)[:, None]
        return cls(seen, triangle, barycentric, points, identity)


class _Tracker:
    """The two scans' views and patterns in one plane, ready to be matched (again)."""

    def __init__(self, neutral: FaceGrid, neutral_view: NeutralView, views, patterns, strength_image: np.ndarray,
                 options: TextureOptions, fine_regions=()):
        self.neutral, self.neutral_view, self.views, self.options = neutral, neutral_view, views, options
        self.neutral_pattern = _eight_bit(patterns[0])
        self.expressive_pattern = patterns[1]
        self.expressive_inside = _inside(views[1].valid, options.rim_px).astype(np.float32)
        self.valid = neutral.mask.reshape(-1)
        self.begin = self.plane.pixels(neutral.points.reshape(-1, 3)[self.valid])
        inside = _inside(views[0].valid, options.rim_px).astype(np.float32)
        self.begin_inside = bilinear(inside, self.begin[:, 0], self.begin[:, 1]) > 0.999
        strength = bilinear(strength_image, self.begin[:, 0], self.begin[:, 1])
        # a pattern of unit local contrast has strength ~0.02 where it is textured in both
        # directions; flat skin tends to 0
        self.strength_weight = strength / (strength + _STRENGTH_HALF)
        self._fine_regions = fine_regions
        self._fine_boxes = None
        # what every warp reads of the neutral grid (the layouts of the boxes are not
        # kept: the matches, and this tracker with them, live as long as a result)
        self._mesh_index = np.flatnonzero(self.valid)
        self._faces = None

    @property
    def fine_boxes(self) -> list:
        """The fine regions' boxes (:meth:`_box`), the regions asked for when first needed."""
        if self._fine_boxes is None:
            regions = self._fine_regions  # masks track_texture has checked, or a callable
            if callable(regions):
                regions = _grid_masks(regions(), self.neutral.points.shape[:2], "fine_regions")
            self._fine_boxes = [self._box(region) for region in regions]
        return self._fine_boxes

    @property
    def plane(self) -> TexturePlane:
        return self.neutral_view.plane

    def _warp(self, displacement: np.ndarray, box) -> np.ndarray:
        """(h, w, 2) float32 pixel positions, over a box of the plane (rows, then columns,
        end excluded), where each neutral pixel's skin is expected in the expressive
        image: its surface point moved by the per-vertex displacement (interpolated over
        the neutral grid's triangles; identity off the surface)."""
        if self._faces is None:
            self._faces = self.neutral.mesh().faces
        layout = _WarpLayout.of(self.views[0], box)
        # only the pixels that see the surface move: the displacement is interpolated
        # there alone (each pixel's own sum, the same bits as over the whole box)
        moved = interpolate_pixels(np.nan_to_num(displacement.reshape(-1, 3)[self._mesh_index]), self._faces,
                                   layout.triangle, layout.barycentric)
        where = layout.identity.copy()
        where.reshape(-1, 2)[layout.seen] = self.plane.pixels(layout.points + moved).astype(np.float32)
        return where

    def match(self, displacement=None, regions=None, fine: bool = True) -> TextureMatches | None:
        """Flow both ways and lift the consistent matches; None when too few are. With
        ``regions`` (grid masks), only their vertices are matched, each region over its
        own box at full resolution; without, the whole face, then the fine regions
        unless ``fine`` is False."""

        start = time.perf_counter()

        def boxes():
            if regions is not None:
                yield from (self._box(region) for region in regions)
                return
            yield np.arange(len(self.begin)), (0, self.plane.height, 0, self.plane.width), _FINEST_SCALE
            # then the fine regions again over the whole face, asked for only now so that
            # a caller can find them while the whole face is matched
            if fine:
                yield from self.fine_boxes

        land = self.begin.copy()
        consistency = np.full(len(self.begin), np.inf)
        landed_inside = np.zeros(len(self.begin), dtype=bool)
        for chosen, box, finest_scale in boxes():
            if len(chosen) == 0:
                continue
            land[chosen], consistency[chosen], landed_inside[chosen] = self._match_box(
                chosen, box, finest_scale, displacement)
        considered = np.isfinite(consistency)
        matched = (consistency < self.options.consistency_px) & self.begin_inside & landed_inside
        matched_fraction = float(matched.sum() / considered.sum()) if considered.any() else 0.0
        if matched_fraction < self.options.min_matched_fraction:
            return None
        # a match lands inside the eroded surface, so the four pixels around it are
        # all on the surface (none is NaN)
        landed = bilinear(self.views[1].points, land[matched, 0], land[matched, 1])
        shape = self.neutral.points.shape
        targets = np.full((self.valid.size, 3), np.nan)
        targets[np.flatnonzero(self.valid)[matched]] = landed
        confidence = np.zeros(self.valid.shape)
        confidence[self.valid] = np.where(matched, self.strength_weight, 0.0)
        return TextureMatches(targets.reshape(shape), confidence.reshape(shape[:2]), matched_fraction,
                              time.perf_counter() - start, self)

    def _match_box(self, chosen, box, finest_scale: int, displacement=None):
        """The flow over one box of the plane for the vertices ``chosen`` (indices into
        ``begin``): where each lands in the expressive image (plane pixels), its
        forward-backward error, and whether it lands inside the expressive surface.
        With a displacement, the expressive image is first warped back by it."""
        row0, row1, col0, col1 = box
        if displacement is None:
            expressive = self.expressive_pattern[row0:row1, col0:col1]
            inside = self.expressive_inside[row0:row1, col0:col1]
        else:
            warp = self._warp(displacement, box)
            expressive = cv2.remap(self.expressive_pattern, warp, None, cv2.INTER_LINEAR, borderValue=0)
            inside = cv2.remap(self.expressive_inside, warp, None, cv2.INTER_LINEAR, borderValue=0)
        forward, backward = _flow_both_ways(np.ascontiguousarray(self.neutral_pattern[row0:row1, col0:col1]),
                                            _eight_bit(expressive), finest_scale)
        begin = self.begin[chosen] - (col0, row0)
        land = begin + bilinear(forward, begin[:, 0], begin[:, 1])
        consistency = np.linalg.norm(land - begin + bilinear(backward, land[:, 0], land[:, 1]), axis=1)
        landed_inside = bilinear(inside, land[:, 0], land[:, 1]) > 0.999
        if displacement is not None:
            land = bilinear(warp, land[:, 0], land[:, 1]).astype(np.float64)
        else:
            land = land + (col0, row0)
        return land, consistency, landed_inside

    def _box(self, region: np.ndarray):
        """A region's valid vertices (indices into ``begin``), the pixel box (rows, then
        columns, end excluded) around them with a margin, and the flow's finest scale
        there (the full resolution)."""
        chosen = np.flatnonzero(region.reshape(-1)[self.valid])
        if len(chosen) == 0:
            return chosen, (0, 0, 0, 0), 0
        margin = REGION_MARGIN_MM / self.plane.pixel_mm
        low = np.floor(self.begin[chosen].min(axis=0) - margin).astype(int)
        high = np.ceil(self.begin[chosen].max(axis=0) + margin).astype(int) + 1
        col0, row0 = np.maximum(low, 0)
        col1, row1 = np.minimum(high, (self.plane.width, self.plane.height))
        return chosen, (int(row0), int(row1), int(col0), int(col1)), 0


# The flow's finest pyramid level over the whole face: half the plane's resolution
# (DIS's medium preset), at a quarter of the full resolution's cost (36 against 139 ms
# a flow on one thread). Fine regions are matched at full resolution
# (benchmarks/FIDELITY.md: AU43 0.464 -> 0.425 with the eyes).
_FINEST_SCALE = 1
#: How far (mm) a region's box reaches beyond its vertices, so that the flow's patches
#: and pyramid see the skin around them.
REGION_MARGIN_MM = 8.0


def _grid_masks(regions, shape, name: str) -> list[np.ndarray]:
    """Masks of a neutral grid as bool arrays, each checked to have the grid's shape."""
    masks = [np.asarray(region, dtype=bool) for region in regions]
    if any(mask.shape != shape for mask in masks):
        raise ValueError(f"{name} must each have the neutral grid's shape {shape}")
    return masks


def _flow_both_ways(first: np.ndarray, second: np.ndarray, finest_scale: int):
    """DIS optical flow (medium preset, at this finest pyramid level) from the first
    8-bit image to the second and back."""

    def flow(one, other):
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setFinestScale(finest_scale)
        return dis.calc(one, other, None)

    # the two directions on two threads (OpenCV releases the GIL; each flow uses
    # OpenCV's own threads only in parts)
    return side_by_side(lambda: flow(first, second), lambda: flow(second, first))


def track_texture(neutral: FaceGrid, expressive: FaceGrid, options: TextureOptions = TextureOptions(),
                  fine_regions=(), neutral_view: NeutralView | None = None,
                  fine_regions_later: bool = False) -> TextureMatches | None:
    """Match each vertex of a neutral grid to the expressive scan by its skin texture.

    Parameters
    ----------
    neutral, expressive : FaceGrid
        Two scans of one person in one frame (the expressive one aligned rigidly onto the
        neutral one), each with its colour image.
    options : TextureOptions
    fine_regions : sequence of (H, W) bool array_like, or a callable returning one
        Parts of the neutral grid (the eyes, say) matched at the image plane's full
        resolution, each over a box around it, rather than at half resolution with the
        rest of the face; so again whenever the matches are refined over the whole face.
        A callable is called once, when the whole face has been flowed, so that the
        caller can find the regions meanwhile.
    neutral_view : NeutralView, optional
        The neutral scan as an earlier tracking with these options saw it
        (:attr:`TextureMatches.neutral_view`): only the expressive scan is rendered then.
    fine_regions_later : bool, default False
        Match the fine regions only when the matches are refined over the whole face
        (:meth:`TextureMatches.refined`), not now: for a registration that refines its
        matches (``MotionOptions.texture_refine_after``) before its fine iterations.

    Returns
    -------
    TextureMatches, or None with a :class:`TextureWarning` saying why when the images
    cannot be used (a grid without an image, an image too dark or without texture, or a
    flow that fails its consistency check on most of the face).
    """
    start = time.perf_counter()
    as_flag(fine_regions_later, "fine_regions_later")
    if neutral_view is not None and not isinstance(neutral_view, NeutralView):
        raise ValueError(f"neutral_view must be a NeutralView (TextureMatches.neutral_view of an earlier tracking "
                         f"of this neutral scan), got {type(neutral_view).__name__}")
    for name, grid in (("neutral", neutral), ("expressive", expressive)):
        if grid.image is None:
            warnings.warn(f"the {name} scan has no colour image: the motion comes from the "
                          "geometry alone", TextureWarning, stacklevel=2)
            return None
    if neutral_view is None:
        plane, sigma_px, strength_px = _plane_of(neutral, options)
        # the two scans are seen on two threads: rendering and filtering release the
        # GIL; the neutral pattern's texture strength is computed beside the expressive view
        looks = side_by_side(lambda: _look(neutral, plane, sigma_px, strength_px),
                             lambda: _look(expressive, plane, sigma_px))
        neutral_view = NeutralView(plane, sigma_px, looks[0])
    else:
        looks = (neutral_view.look, _look(expressive, neutral_view.plane, neutral_view.sigma_px))
    for name, look in zip(("neutral", "expressive"), looks):
        if look.brightness < 8.0:
            warnings.warn(f"the {name} scan's colour image is too dark (median grey {look.brightness:.1f} of "
                          "255): the motion comes from the geometry alone", TextureWarning, stacklevel=2)
            return None
    for name, look in zip(("neutral", "expressive"), looks):
        if look.detail < _MIN_DETAIL_GREY:
            warnings.warn(f"the {name} scan's colour image shows no texture (detail of {look.detail:.2f} grey "
                          f"levels rms, at least {_MIN_DETAIL_GREY} needed): the motion comes from the "
                          "geometry alone", TextureWarning, stacklevel=2)
            return None
    if not callable(fine_regions):
        fine_regions = _grid_masks(fine_regions, neutral.points.shape[:2], "fine_regions")
    tracker = _Tracker(neutral, neutral_view, [look.view for look in looks], [look.pattern for look in looks],
                       looks[0].strength, options, fine_regions)
    matches = tracker.match(fine=not fine_regions_later)
    if matches is None:
        warnings.warn(f"texture tracking matched less than {100 * options.min_matched_fraction:.0f} % of the "
                      "face (the flow failed its consistency check): the motion comes from the geometry "
                      "alone", TextureWarning, stacklevel=2)
        return None
    matches.seconds = time.perf_counter() - start
    return matches
