"""Orthographic z-buffer rasterisation: which triangle each pixel of an image sees.

Pictures of faces (:mod:`tpscore.showcase.render`) and the colour images that texture tracking
compares (:mod:`tpscore.expression.texture`) both project a mesh along the view axis and keep,
per pixel, the front-most triangle under the pixel's centre and the barycentric
weights of that centre, from which any vertex quantity (colour, u,v, position) is
interpolated. The compiled kernel works on bands of rows in parallel; the NumPy
reference is :func:`tpscore.reference.raster.rasterise`.
"""
from __future__ import annotations

import numpy as np

from . import _core
from ._validation import as_array, as_faces, as_points, check_finite

__all__ = ["rasterise", "interpolate_pixels", "bilinear", "MAX_RASTER_PIXELS"]

#: Largest image rasterised, in pixels (the outputs take 32 bytes a pixel).
MAX_RASTER_PIXELS = 64_000_000


def rasterise(pixels, depth, faces, width: int, height: int):
    """The front-most triangle under each pixel centre of a width x height image.

    Parameters
    ----------
    pixels : (n, 2) array_like
        Each vertex's continuous image position: x along the columns, y along the rows;
        pixel (r, c) has its centre at (c + 0.5, r + 0.5).
    depth : (n,) array_like
        Larger is nearer the viewer.
    faces : (m, 3) array_like of int
    width, height : int

    Returns
    -------
    triangle : (height, width) int64
        Index of the front-most triangle covering the pixel's centre, -1 where none does.
        Equal depths go to the lower index; a centre on a shared edge belongs to both.
    barycentric : (height, width, 3) float64
        Weights of the centre on that triangle's corners (0 where no triangle).
    """
    pixels = as_points(pixels, "pixels", dim=2)
    depth = np.ascontiguousarray(as_array(depth, "depth")).reshape(-1)
    if depth.shape != (len(pixels),):
        raise ValueError(f"depth must have shape ({len(pixels)},), got {np.shape(depth)}")
    check_finite(depth, "depth")
    faces = as_faces(faces, len(pixels), "faces")
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if int(width) * int(height) > MAX_RASTER_PIXELS:
        raise ValueError(f"width x height = {int(width) * int(height):,} pixels exceeds the limit of "
                         f"{MAX_RASTER_PIXELS:,}")
    triangle, barycentric = _core.rasterise(pixels, depth, faces, int(width), int(height))
    return triangle.reshape(height, width), barycentric.reshape(height, width, 3)


def interpolate_pixels(values, faces, triangle, barycentric) -> np.ndarray:
    """Vertex values interpolated at the pixel centres of a :func:`rasterise` result.

    Parameters
    ----------
    values : (n,) or (n, c) array_like
        One value (or row of c values) per vertex.
    faces : (m, 3) array_like of int
        The faces that were rasterised.
    triangle, barycentric : ndarray
        :func:`rasterise`'s outputs, (h, w) and (h, w, 3).

    Returns
    -------
    (h, w) or (h, w, c) float64 array, NaN where no triangle covers the pixel.
    """
    array = as_array(values, "values")
    flat = array.reshape(len(array), -1) if array.ndim else array.reshape(0, 1)
    faces = as_faces(faces, len(flat), "faces")
    triangle = np.asarray(triangle)
    barycentric = as_array(barycentric, "barycentric")
    if not np.issubdtype(triangle.dtype, np.integer) or barycentric.shape != triangle.shape + (3,):
        raise ValueError(f"triangle (h, w) of integers and barycentric (h, w, 3) must come from rasterise, "
                         f"got {triangle.dtype} {triangle.shape} and {barycentric.shape}")
    index = np.ascontiguousarray(triangle, dtype=np.int64).reshape(-1)
    if index.size and (index.min() < -1 or index.max() >= len(faces)):
        raise ValueError(f"triangle refers to faces outside [-1, {len(faces)})")
    out = _core.interpolate_pixels(np.ascontiguousarray(flat), faces, index,
                                   np.ascontiguousarray(barycentric.reshape(-1, 3)))
    return out.reshape(triangle.shape + array.shape[1:])


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Values of an (h, w) or (h, w, c) array at continuous pixel coordinates (x along
    columns, y along rows, pixel centres at integers), clamped to the image: float64 for
    a float64 array, float32 otherwise.

    Raises
    ------
    ValueError
        If the image is not 2-D or 3-D with h, w >= 2, or a coordinate is not finite.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or min(image.shape[:2]) < 2:
        raise ValueError(f"image must have shape (h, w) or (h, w, c) with h, w >= 2, got {image.shape}")
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("x and y must be finite pixel coordinates")
    dtype = np.float64 if image.dtype == np.float64 else np.float32
    pixels = np.ascontiguousarray(image, dtype=dtype)  # exact for 8-bit and float32 images
    pixels = pixels.reshape(pixels.shape[:2] + (-1,))
    height, width, channels = pixels.shape
    out = _core.bilinear_sample(pixels.reshape(height * width, channels), height, width,
                                np.ascontiguousarray(x).reshape(-1), np.ascontiguousarray(y).reshape(-1))
    return out.reshape(x.shape + image.shape[2:])
