"""Colour images of scans: validation, sampling at u,v, and grey levels.

A Bosphorus scan names a colour image; each scan point's u,v are its normalised
coordinates in it (u to the right, v downward, both in [0, 1]). Pixel (r, c) covers
u in [c / w, (c + 1) / w] and v in [r / h, (r + 1) / h]: its centre is at
((c + 0.5) / w, (r + 0.5) / h).
"""
from __future__ import annotations

import numpy as np

from ..raster import bilinear

__all__ = ["as_colour_image", "sample_image", "pixel_coordinates", "grey_levels", "check_image_fits"]

# Rec. 601 luma weights: the grey level a camera's sensor response is closest to.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def as_colour_image(image, name: str = "image") -> np.ndarray:
    """A read-only (h, w, 3) uint8 view of an RGB image (grey images are expanded).

    Raises
    ------
    ValueError
        If it is not an (h, w), (h, w, 3) or (h, w, 4) array of 8-bit values with
        h, w >= 2.
    """
    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise ValueError(f"{name} must hold 8-bit values (uint8), got dtype {array.dtype}")
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=2)
    elif array.ndim == 3 and array.shape[2] == 4:
        array = array[..., :3]
    if array.ndim != 3 or array.shape[2] != 3 or min(array.shape[:2]) < 2:
        raise ValueError(f"{name} must have shape (h, w, 3) with h, w >= 2, got {np.shape(image)}")
    if array.flags.writeable:
        array = array.view()
        array.flags.writeable = False
    return array


def sample_image(image: np.ndarray, uv) -> np.ndarray:
    """Bilinear colour (float32, 0-255 per channel) of an (h, w, c) image at (..., 2) u,v.

    Samples beyond the image take the colour of its border.
    """
    return bilinear(image, *pixel_coordinates(image, uv))


def pixel_coordinates(image: np.ndarray, uv) -> tuple[np.ndarray, np.ndarray]:
    """Column and row (float, pixel centres at integers) of (..., 2) u,v in an (h, w, ...)
    image, held to the image."""
    uv = np.asarray(uv, dtype=np.float64)
    height, width = image.shape[:2]
    x = np.clip(uv[..., 0] * width - 0.5, 0.0, width - 1.0)
    y = np.clip(uv[..., 1] * height - 0.5, 0.0, height - 1.0)
    return x, y


def grey_levels(colours: np.ndarray) -> np.ndarray:
    """(...) float32 grey levels of (..., 3) RGB colours."""
    return np.asarray(colours, dtype=np.float32) @ _LUMA


# An image fits a scan's u,v when its pixels cover about as many mm across as down: a
# camera's pixels are square to within a few per cent, so an image of the wrong width or
# height (another scan's, or a resized one) shows as pixels stretched by its error.
_MAX_PIXEL_ASPECT = 1.5
_FIT_POINTS = 4096


def check_image_fits(image: np.ndarray, points: np.ndarray, uv: np.ndarray, valid: np.ndarray,
                     where: str) -> None:
    """Check that a colour image fits the u,v of a scan's valid points.

    The valid points' u,v must lie in [0, 1], and the affine map from their x, y to
    image pixels must have nearly square pixels (at most 1.5 times as long one way as
    the other): an image of another size than the one the u,v were made for stretches
    them.

    Raises
    ------
    ValueError
        Naming ``where`` (the image file) and what does not fit.
    """
    height, width = image.shape[:2]
    coords = np.asarray(uv, dtype=np.float64)[valid]
    if len(coords) == 0:
        return
    outside = (coords < -1e-6) | (coords > 1.0 + 1e-6)
    if outside.any():
        raise ValueError(f"{where}: {int(outside.any(axis=1).sum())} valid scan point(s) have u,v outside "
                         "[0, 1]; the image cannot belong to this scan")
    if len(coords) < 3:
        return
    # the least-squares affine map's linear part, from the 2 x 2 normal equations of the
    # centred x, y (a lstsq over the whole (n, 3) design took a sixth of a scan's loading),
    # fitted on an even subsample of at most _FIT_POINTS points: a pixel aspect off by
    # the 1.5 refused shows as plainly in a few thousand points as in every one, at half
    # the check's time on a scan of 40,000
    chosen = np.flatnonzero(np.asarray(valid).ravel())
    step = -(-len(chosen) // _FIT_POINTS)
    chosen, coords = chosen[::step], coords[::step]
    xy = np.asarray(points, dtype=np.float64).reshape(-1, np.shape(points)[-1])[chosen, :2]
    centred = xy - xy.mean(axis=0)
    pixels = coords * np.array([width, height])
    try:
        linear = np.linalg.solve(centred.T @ centred, centred.T @ pixels)
    except np.linalg.LinAlgError:
        linear = np.zeros((2, 2))
    singular = np.linalg.svd(linear, compute_uv=False)
    if not (singular[1] > 0) or singular[0] / singular[1] > _MAX_PIXEL_ASPECT:
        raise ValueError(
            f"{where}: the image's size ({width} x {height} pixels) does not fit the scan's u,v: "
            f"its pixels would be {singular[0] / max(singular[1], 1e-12):.2f} times as long one way "
            "as the other")
