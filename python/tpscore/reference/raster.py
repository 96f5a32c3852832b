"""NumPy reference of the z-buffer rasteriser (:func:`tpscore.raster.rasterise`) and of
the bilinear image sampler (:func:`tpscore.face.image.bilinear`)."""
from __future__ import annotations

import numpy as np

# Pixel-triangle candidates handled at once: bounds the temporaries to ~100 MB.
CHUNK_CANDIDATES = 2_000_000


def rasterise(pixels, depth, faces, width: int, height: int):
    """Same contract as :func:`tpscore.raster.rasterise`: every candidate pixel of every
    triangle's bounding box is tested, and the deepest-in-front candidate wins, the
    lower triangle index on equal depths."""
    pixels = np.asarray(pixels, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    zbuffer = np.full(width * height, -np.inf)
    winner = np.full(width * height, -1, dtype=np.int64)
    bary = np.zeros((width * height, 3))
    corner_col = pixels[faces, 0]
    corner_row = pixels[faces, 1]
    c0 = np.maximum(np.ceil(corner_col.min(axis=1) - 0.5), 0).astype(np.int64)
    c1 = np.minimum(np.floor(corner_col.max(axis=1) - 0.5), width - 1).astype(np.int64)
    r0 = np.maximum(np.ceil(corner_row.min(axis=1) - 0.5), 0).astype(np.int64)
    r1 = np.minimum(np.floor(corner_row.max(axis=1) - 0.5), height - 1).astype(np.int64)
    counts = np.maximum(c1 - c0 + 1, 0) * np.maximum(r1 - r0 + 1, 0)
    area2 = ((corner_col[:, 1] - corner_col[:, 0]) * (corner_row[:, 2] - corner_row[:, 0])
             - (corner_col[:, 2] - corner_col[:, 0]) * (corner_row[:, 1] - corner_row[:, 0]))
    counts[np.abs(area2) < 1e-12] = 0
    candidates = np.flatnonzero(counts)
    cumulative = np.cumsum(counts[candidates])
    start = 0
    while start < len(candidates):
        base = cumulative[start - 1] if start else 0
        stop = max(int(np.searchsorted(cumulative, base + CHUNK_CANDIDATES, side="right")), start + 1)
        chunk = candidates[start:stop]
        start = stop
        n = counts[chunk]
        tri = np.repeat(chunk, n)
        local = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        box_w = (c1 - c0 + 1)[tri]
        col = c0[tri] + local % box_w
        row = r0[tri] + local // box_w
        px, py = col + 0.5, row + 0.5
        ax, bx, cx = corner_col[tri].T
        ay, by, cy = corner_row[tri].T
        inv_area = 1.0 / area2[tri]
        w1 = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) * inv_area
        w2 = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) * inv_area
        w0 = 1.0 - w1 - w2
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        tri, w0, w1, w2 = tri[inside], w0[inside], w1[inside], w2[inside]
        pid = row[inside] * width + col[inside]
        z = (np.column_stack([w0, w1, w2]) * depth[faces[tri]]).sum(axis=1)
        # per pixel: the largest depth, then the lowest triangle index
        order = np.lexsort((-tri, z, pid))
        last = np.r_[pid[order][1:] != pid[order][:-1], True]
        best = order[last]
        closer = z[best] > zbuffer[pid[best]]
        best = best[closer]
        zbuffer[pid[best]] = z[best]
        winner[pid[best]] = tri[best]
        bary[pid[best]] = np.column_stack([w0[best], w1[best], w2[best]])
    return winner.reshape(height, width), bary.reshape(height, width, 3)


def interpolate_pixels(values, faces, triangle, barycentric):
    """Same contract as :func:`tpscore.raster.interpolate_pixels`."""
    values = np.asarray(values, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = np.full(triangle.shape + values.shape[1:], np.nan)
    covered = triangle >= 0
    corners = faces[triangle[covered]]
    out[covered] = np.einsum("pk,pk...->p...", barycentric[covered], values[corners])
    return out


def bilinear(image, x, y):
    """Same contract as :func:`tpscore.face.image.bilinear`, in NumPy's arithmetic
    (which the compiled sampler follows to the bit)."""
    image = np.asarray(image)
    height, width = image.shape[:2]
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, width - 1.0)
    y = np.clip(np.asarray(y, dtype=np.float64), 0.0, height - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), width - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), height - 2)
    dtype = np.float64 if image.dtype == np.float64 else np.float32
    fx = (x - x0).astype(dtype)
    fy = (y - y0).astype(dtype)
    if image.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    top = image[y0, x0].astype(dtype) * (1 - fx) + image[y0, x0 + 1].astype(dtype) * fx
    bottom = image[y0 + 1, x0].astype(dtype) * (1 - fx) + image[y0 + 1, x0 + 1].astype(dtype) * fx
    return top * (1 - fy) + bottom * fy

