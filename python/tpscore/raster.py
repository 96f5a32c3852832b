"""Orthographic z-buffer rasterisation: which triangle each pixel of an image sees.

Pictures of faces (:mod:`tpscore.render`) and the colour images that texture tracking
compares (:mod:`tpscore.texture`) both project a mesh along the view axis and keep,
per pixel, the front-most triangle under the pixel's centre and the barycentric
weights of that centre, from which any vertex quantity (colour, u,v, position) is
interpolated. The compiled kernel works on bands of rows in parallel; the NumPy
reference is :func:`tpscore.reference.raster.rasterise`.
"""
from __future__ import annotations

import numpy as np

from . import _core
from ._validation import as_faces, as_points, check_finite

__all__ = ["rasterise", "MAX_RASTER_PIXELS"]

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
    depth = np.ascontiguousarray(depth, dtype=np.float64).reshape(-1)
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
