"""Colour images: reading any format Pillow reads, writing PNG."""
from __future__ import annotations

import io as _stdio

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..._files import atomic_write, check_readable
from ..image import as_colour_image


#: Largest colour image read, in pixels: far beyond a face scanner's camera, and a guard
#: against a small compressed file that would decompress into gigabytes.
MAX_IMAGE_PIXELS = 64_000_000


def read_image(path) -> np.ndarray:
    """Read a colour image (PNG, JPEG, BMP, TIFF: what Pillow reads) as (h, w, 3) uint8.

    Grey and palette images are expanded to RGB; an alpha channel is dropped.

    Raises
    ------
    ValueError
        Naming the file: missing, a folder, not an image, truncated or corrupt, or
        larger than :data:`MAX_IMAGE_PIXELS`.
    """

    path = check_readable(path, "image_path")
    where = repr(str(path))
    try:
        with Image.open(path) as opened:
            width, height = opened.size
            if width * height > MAX_IMAGE_PIXELS:
                raise ValueError(f"{where}: image of {width} x {height} pixels is larger than the "
                                 f"{MAX_IMAGE_PIXELS:,} pixels tpscore reads")
            if min(width, height) < 2:
                raise ValueError(f"{where}: image of {width} x {height} pixels is too small")
            rgb = np.asarray(opened.convert("RGB"), dtype=np.uint8)
    except UnidentifiedImageError:
        raise ValueError(f"{where}: not an image file Pillow can read") from None
    except (OSError, SyntaxError, Image.DecompressionBombError) as exc:
        raise ValueError(f"{where}: truncated or corrupt image ({exc})") from None
    return rgb


def png_bytes(image) -> bytes:
    """An (h, w, 3) uint8 RGB image encoded as PNG (for a file, or a container such
    as a glTF binary that embeds it)."""
    picture = np.ascontiguousarray(as_colour_image(image))
    buffer = _stdio.BytesIO()
    Image.fromarray(picture, "RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def write_png(path, image) -> None:
    """Write an (h, w, 3) uint8 RGB image as PNG (atomically)."""
    atomic_write(path, png_bytes(image))
