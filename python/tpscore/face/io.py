"""Reading and writing scans, landmarks and meshes.

Formats:

- Bosphorus ``.bnt`` depth scans (:func:`read_bnt`, :func:`write_bnt`);
- Bosphorus ``.lm3`` landmark files (:func:`read_lm3`, :func:`write_lm3`), and
  landmarks as ``.csv`` or ``.json`` (:func:`read_landmarks`, :func:`write_landmarks`);
- meshes and point clouds through trimesh (:func:`read_mesh`), OBJ / PLY meshes
  with a u,v map and vertex colours (:func:`write_mesh`), and an OBJ textured by an
  image, with its MTL and PNG (:func:`write_textured_obj`).

Landmarks are always a (22, 3) float64 array in Bosphorus order (see
:mod:`tpscore.face.landmarks`) with NaN rows for the ones that are missing. Every reader
raises ValueError naming the file and what is wrong with it; every writer writes to
a temporary file beside the target and renames it, so nothing is left half-written.
Units are millimetres.
"""
from __future__ import annotations

import csv
import io as _stdio
import json
import math
import struct
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .._files import (MAX_TEXT_FILE_BYTES, atomic_write, check_readable, open_for_reading, read_bytes,
                      read_limited, regular_file_size)
from .._validation import MAX_COORDINATE, as_array, as_faces, as_path, as_points
from .image import as_colour_image
from .landmarks import LANDMARK_NAMES, N_LANDMARKS, as_landmarks, empty_landmarks, landmark_index

__all__ = [
    "BntScan",
    "read_npz",
    "write_npz",
    "read_bnt",
    "write_bnt",
    "read_lm3",
    "write_lm3",
    "read_landmarks",
    "landmark_file_beside",
    "write_landmarks",
    "read_mesh",
    "read_mesh_colours",
    "MeshColours",
    "ColourWarning",
    "write_mesh",
    "write_textured_obj",
    "png_bytes",
    "write_png",
    "read_image",
]

#: Largest colour image read, in pixels: far beyond a face scanner's camera, and a guard
#: against a small compressed file that would decompress into gigabytes.
MAX_IMAGE_PIXELS = 64_000_000

#: The largest .bnt grid read, in points (4096 x 4096, 640 MiB of values): far beyond a
#: face scanner (a Bosphorus scan has about 200,000), and a guard against a forged
#: header that asks for up to 65535 x 65535 points.
MAX_BNT_POINTS = 4096 * 4096

#: Landmark coordinates beyond this (mm) are refused (they are the kernels' limit, and
#: a JSON integer of hundreds of digits would not even convert to a float).
MAX_LANDMARK_COORDINATE = MAX_COORDINATE

#: The largest mesh file read (1 GiB): an OBJ of ten million vertices.
MAX_MESH_FILE_BYTES = 2**30

# The background / hole marker that Bosphorus scanners (and make_scans.py) write.
DEFAULT_BNT_ZMIN = -1.0e9

# .bnt header: uint16 nrows, uint16 ncols, float64 zmin, uint16 name length.
_BNT_HEAD = struct.Struct("<HHdH")
_BNT_LEN2 = struct.Struct("<I")


# --------------------------------------------------------------------------- helpers

def _read_text(path, limit: int = MAX_TEXT_FILE_BYTES, what: str = "a landmark file") -> list[str]:
    """Lines of a text file of at most `limit` bytes, without line endings (accepts
    \\n, \\r\\n and \\r)."""
    raw = read_bytes(path, limit, what)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{str(path)!r}: not a UTF-8 text file (byte {exc.start})") from None
    return text.splitlines()


def _format_float(value: float) -> str:
    # repr gives the shortest text that reads back to the same float.
    return repr(float(value))


# --------------------------------------------------------------------------- images

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


# --------------------------------------------------------------------------- .bnt

# eq=False: element-wise array comparison has no single truth value.
@dataclass(eq=False)
class BntScan:
    """A Bosphorus depth scan: a grid of nrows x ncols points, row 0 the top.

    Attributes
    ----------
    nrows, ncols : int
        Grid size.
    zmin : float
        The marker value the file uses for background and holes.
    image_name : str
        Name of the texture image the u,v coordinates refer to.
    points : (nrows, ncols, 3) float64
        x, y, z in mm; NaN where the scan has no point (background or hole).
    uv : (nrows, ncols, 2) float64
        Normalised image coordinates, as stored (also at invalid points).
    valid : (nrows, ncols) bool
        Where the scan has a point.
    """

    nrows: int
    ncols: int
    zmin: float
    image_name: str
    points: np.ndarray
    uv: np.ndarray
    valid: np.ndarray

    @classmethod
    def from_points(cls, points, *, image_name: str = "", zmin: float = DEFAULT_BNT_ZMIN) -> "BntScan":
        """A scan from (nrows, ncols, 3) points with NaN at background and holes; u, v are
        the pixel centres ((c + 0.5) / ncols, (r + 0.5) / nrows)."""
        points = np.array(as_array(points, "points"), dtype=np.float64)
        if points.ndim != 3 or points.shape[2] != 3:
            raise ValueError(f"points must have shape (nrows, ncols, 3), got {points.shape}")
        nrows, ncols = points.shape[:2]
        valid = np.isfinite(points).all(axis=2)
        points[~valid] = np.nan
        rows, cols = np.mgrid[0:nrows, 0:ncols]
        uv = np.stack([(cols + 0.5) / ncols, (rows + 0.5) / nrows], axis=-1)
        return cls(nrows, ncols, float(zmin), image_name, points, uv, valid)

    @property
    def n_valid(self) -> int:
        """Number of valid points."""
        return int(np.count_nonzero(self.valid))

    def __repr__(self) -> str:
        image = f"image {self.image_name!r}" if self.image_name else "no image"
        return f"BntScan({self.nrows}x{self.ncols}, {self.n_valid} valid points, {image})"

    def valid_points(self) -> np.ndarray:
        """The valid points, (n_valid, 3), in row-major pixel order."""
        return self.points[self.valid]


def _check_bnt_size(where: str, size: int, expected: int, nrows: int, ncols: int, *,
                    stream: bool = False) -> None:
    if size < expected:
        raise ValueError(
            f"{where}: truncated .bnt data: {nrows} x {ncols} points need {expected} bytes, "
            f"the file has {size}"
        )
    if size > expected:
        # a stream is read one byte past the data only
        count = "at least 1" if stream else f"{size - expected}"
        raise ValueError(f"{where}: {count} trailing bytes after the {nrows} x {ncols} .bnt points")


def read_bnt(path) -> BntScan:
    """Read a Bosphorus ``.bnt`` depth scan.

    Layout (little-endian): uint16 nrows; uint16 ncols; float64 zmin; uint16 len;
    len bytes of image name; uint32 len2 (= 5 nrows ncols); len2 float64 values,
    column after column (all x, all y, all z, all u, all v). Point ``i = r*ncols + c``,
    row 0 the top. A point with x, y or z equal to zmin is background or a hole.

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    BntScan

    Raises
    ------
    ValueError
        Naming the file and the problem: missing file, truncated header or data,
        len2 != 5 nrows ncols, zero rows or columns, trailing bytes, a non-ASCII
        image name, non-finite zmin, NaN/infinite values at valid points, or a valid
        coordinate beyond +-1e15 mm. A file shorter than its header promises is
        reported as truncated before a grid larger than :data:`MAX_BNT_POINTS`.
    """
    with open_for_reading(path) as handle:
        where = repr(str(handle.name))
        file_size = regular_file_size(handle)
        raw = read_limited(handle, _BNT_HEAD.size, where)
        size = len(raw)
        if size < _BNT_HEAD.size:
            raise ValueError(
                f"{where}: truncated .bnt header ({size} bytes; the fixed header needs {_BNT_HEAD.size})"
            )
        nrows, ncols, zmin, name_len = _BNT_HEAD.unpack_from(raw, 0)
        if nrows == 0 or ncols == 0:
            raise ValueError(f"{where}: .bnt grid of {nrows} x {ncols} points is empty")
        if not math.isfinite(zmin):
            raise ValueError(f"{where}: .bnt background marker zmin is {zmin}, not a finite number")
        n_points = nrows * ncols
        name_end = _BNT_HEAD.size + name_len
        data_start = name_end + _BNT_LEN2.size
        raw += read_limited(handle, data_start - size, where)
        size = len(raw)
        if size < data_start:
            raise ValueError(
                f"{where}: truncated .bnt header: image name of {name_len} bytes and the value "
                f"count need {data_start} bytes, the file has {size}"
            )
        name_bytes = raw[_BNT_HEAD.size:name_end]
        if not all(32 <= b < 127 for b in name_bytes):
            raise ValueError(
                f"{where}: .bnt image name is not printable ASCII ({name_bytes[:40]!r}); "
                "the header is corrupt or this is not a .bnt file"
            )
        (len2,) = _BNT_LEN2.unpack_from(raw, name_end)
        if len2 != 5 * n_points:
            raise ValueError(
                f"{where}: .bnt value count len2 = {len2} is not 5 * nrows * ncols = "
                f"5 * {nrows} * {ncols} = {5 * n_points}"
            )
        expected = data_start + 8 * len2
        if file_size is not None:
            # A regular file's size is known: judge it before reading the values, and
            # before the grid's size (a small file whose header promises 6000 x 6000
            # points is a truncated or forged file, not a grid too large to read).
            _check_bnt_size(where, file_size, expected, nrows, ncols)
        # judged before the values are read: a forged header can announce 4.3e9 points
        if n_points > MAX_BNT_POINTS:
            raise ValueError(
                f"{where}: .bnt grid of {nrows} x {ncols} points is larger than the "
                f"{MAX_BNT_POINTS:,} points tpscore reads")
        # One byte more than the header announces, to tell a stream's trailing bytes apart.
        body = read_limited(handle, expected - data_start + 1, where)
    if file_size is None:
        _check_bnt_size(where, data_start + len(body), expected, nrows, ncols, stream=True)
    values = np.frombuffer(body, dtype="<f8", count=len2)
    columns = values.reshape(5, nrows, ncols)  # x, y, z, u, v: one block each
    xyz = columns[:3]
    valid = ~((xyz == zmin).any(axis=0))
    points = np.empty((nrows, ncols, 3))
    for axis in range(3):
        points[..., axis] = np.where(valid, xyz[axis], np.nan)
    uv = np.stack([columns[3], columns[4]], axis=-1).astype(np.float64)
    # judged on the five planes as read (contiguous), not on the interleaved copies
    bad = valid & ~np.isfinite(columns).all(axis=0)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ValueError(
            f"{where}: {int(bad.sum())} valid point(s) have NaN or infinite x, y, z, u or v "
            f"(first at row {r}, column {c})"
        )
    # a coordinate that far out is an outlier or a corrupt value, not millimetres: refused
    # here, as every kernel refuses it, rather than left to overflow an index later
    far = valid & (np.abs(xyz) > MAX_COORDINATE).any(axis=0)
    if far.any():
        r, c = np.argwhere(far)[0]
        raise ValueError(
            f"{where}: {int(far.sum())} valid point(s) have coordinates beyond +-{MAX_COORDINATE:.0e} mm "
            f"(first at row {r}, column {c}: {xyz[:, r, c].tolist()}); tpscore works in millimetres"
        )
    return BntScan(
        nrows=int(nrows), ncols=int(ncols), zmin=float(zmin),
        image_name=name_bytes.decode("ascii"), points=points, uv=uv, valid=valid,
    )


def write_bnt(path, scan: BntScan) -> None:
    """Write a :class:`BntScan` as a Bosphorus ``.bnt`` file.

    Invalid points (``~scan.valid``) are written with x = y = z = ``scan.zmin``;
    u, v are written as stored. A file read with :func:`read_bnt` whose invalid points
    carry zmin in all three coordinates is written back byte for byte.

    Raises
    ------
    ValueError
        If the grid is empty or larger than the format holds (65535 rows or columns),
        the arrays disagree in shape, valid points are not finite, zmin is not finite
        or a valid coordinate equals it, or the image name is not printable ASCII.
    """
    nrows, ncols = int(scan.nrows), int(scan.ncols)
    if not (0 < nrows <= 0xFFFF and 0 < ncols <= 0xFFFF):
        raise ValueError(f"scan grid {nrows} x {ncols} does not fit a .bnt (1..65535 each)")
    points = as_array(scan.points, "scan.points")
    uv = as_array(scan.uv, "scan.uv")
    valid = np.asarray(scan.valid, dtype=bool)
    if points.shape != (nrows, ncols, 3) or uv.shape != (nrows, ncols, 2) or valid.shape != (nrows, ncols):
        raise ValueError(
            f"scan arrays must have shapes points ({nrows}, {ncols}, 3), uv ({nrows}, {ncols}, 2), "
            f"valid ({nrows}, {ncols}); got {points.shape}, {uv.shape}, {valid.shape}"
        )
    zmin = float(scan.zmin)
    if not math.isfinite(zmin):
        raise ValueError(f"scan.zmin must be finite, got {zmin}")
    inside = points[valid]
    if not np.isfinite(inside).all() or not np.isfinite(uv[valid]).all():
        raise ValueError("scan.points or scan.uv has NaN or infinite values at valid points")
    if (inside == zmin).any():
        raise ValueError(f"a valid point of the scan has a coordinate equal to zmin = {zmin}")
    try:
        name = str(scan.image_name).encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"scan.image_name {scan.image_name!r} is not ASCII") from None
    if len(name) > 0xFFFF or not all(32 <= b < 127 for b in name):
        raise ValueError(f"scan.image_name {scan.image_name!r} is not printable ASCII of <= 65535 bytes")
    blocks = np.empty((5, nrows, ncols), dtype="<f8")
    for axis in range(3):
        blocks[axis] = np.where(valid, points[..., axis], zmin)
    blocks[3] = uv[..., 0]
    blocks[4] = uv[..., 1]
    header = _BNT_HEAD.pack(nrows, ncols, zmin, len(name)) + name + _BNT_LEN2.pack(blocks.size)
    atomic_write(path, header + blocks.tobytes())


# --------------------------------------------------------------------------- .lm3

#: Landmarks a Bosphorus ``.lm3`` file may list beyond the 22: read past, not kept.
IGNORED_LM3_NAMES = ("Left ear lobe", "Right ear lobe")
_IGNORED_LM3 = {name.lower() for name in IGNORED_LM3_NAMES}


def read_lm3(path, *, return_names: bool = False):
    """Read a Bosphorus ``.lm3`` landmark file.

    Format: a header line; an empty line (or a line ``*`` followed by free text up to
    an empty line); ``<N> landmarks:``; then N pairs of lines: the name, ``x y z``.
    The database labels up to 24 landmarks: the 22 and the two ear lobes
    (:data:`IGNORED_LM3_NAMES`), which are read past and not kept.

    Parameters
    ----------
    path : str or PathLike
    return_names : bool
        Also return the landmark names as found in the file, in file order.

    Returns
    -------
    landmarks : (22, 3) float64
        In Bosphorus order, NaN rows for landmarks the file does not list.
    names : list of str
        Only with ``return_names=True``.

    Raises
    ------
    ValueError
        Naming the file and line: missing header, bad count line, unknown or duplicate
        landmark name, fewer or more landmarks than announced, unparsable or
        non-finite coordinates.
    """
    lines = [line.rstrip() for line in _read_text(path)]
    where = repr(str(path))

    def fail(line_index: int, problem: str):
        raise ValueError(f"{where}, line {line_index + 1}: {problem}")

    if not lines:
        raise ValueError(f"{where}: empty .lm3 file")
    # Line 0 is the header. Then an empty line, or a '*' comment block up to an empty line.
    k = 1
    if k < len(lines) and lines[k].strip() == "*":
        k += 1
        while k < len(lines) and lines[k].strip():
            k += 1
    if k >= len(lines) or lines[k].strip():
        fail(min(k, len(lines) - 1), "expected an empty line after the .lm3 header")
    k += 1
    if k >= len(lines):
        raise ValueError(f"{where}: .lm3 file ends before the '<N> landmarks:' line")
    count_words = lines[k].split()
    if len(count_words) != 2 or count_words[1].lower() != "landmarks:" or not count_words[0].isdigit():
        fail(k, f"expected '<N> landmarks:', got {lines[k][:80]!r}")
    count = int(count_words[0])
    if count > N_LANDMARKS + len(IGNORED_LM3_NAMES):
        fail(k, f"announces {count} landmarks; Bosphorus has {N_LANDMARKS + len(IGNORED_LM3_NAMES)} "
                f"({N_LANDMARKS} and the {' and '.join(IGNORED_LM3_NAMES)})")
    k += 1
    landmarks = empty_landmarks()
    names: list[str] = []
    ignored: set[str] = set()
    for _ in range(count):
        if k + 1 >= len(lines) or not lines[k].strip():
            raise ValueError(
                f"{where}: announces {count} landmarks but lists only {len(names)} "
                f"(ends at line {min(k, len(lines)) + 1})"
            )
        name = lines[k].strip()
        if name.lower() in _IGNORED_LM3:
            if name.lower() in ignored:
                fail(k, f"duplicate landmark {name!r}")
            ignored.add(name.lower())
            k += 2
            continue
        try:
            index = landmark_index(name)
        except ValueError:
            fail(k, f"unknown landmark name {name[:80]!r}")
        if np.isfinite(landmarks[index]).any():
            fail(k, f"duplicate landmark {name!r}")
        words = lines[k + 1].split()
        try:
            coords = [float(w) for w in words]
        except ValueError:
            coords = []
        if len(coords) != 3:
            fail(k + 1, f"expected 'x y z' for {name!r}, got {lines[k + 1][:120]!r}")
        if not all(abs(v) <= MAX_LANDMARK_COORDINATE for v in coords):
            fail(k + 1, f"non-finite or out-of-range coordinates for {name!r}: {lines[k + 1][:120]!r}")
        landmarks[index] = coords
        names.append(LANDMARK_NAMES[index])
        k += 2
    rest = [i for i in range(k, len(lines)) if lines[i].strip()]
    if rest:
        fail(rest[0], f"more content after the {count} announced landmarks: {lines[rest[0]]!r}")
    return (landmarks, names) if return_names else landmarks


def write_lm3(path, landmarks, *, header: str = "3D landmark points") -> None:
    """Write landmarks as a Bosphorus ``.lm3`` file.

    Only the finite rows are written, in Bosphorus order; coordinates are written with
    the shortest text that reads back to the same float.

    Parameters
    ----------
    path : str or PathLike
    landmarks : (22, 3) array-like, mm; NaN rows are missing landmarks.
    header : str
        The first line of the file.
    """
    array = as_landmarks(landmarks)
    if "\n" in header or "\r" in header:
        raise ValueError("header must be a single line")
    present = np.flatnonzero(np.isfinite(array).all(axis=1))
    lines = [header, "", f"{len(present)} landmarks:"]
    for i in present:
        lines.append(LANDMARK_NAMES[i])
        lines.append(" ".join(_format_float(v) for v in array[i]))
    atomic_write(path, ("\n".join(lines) + "\n").encode("ascii"))


# --------------------------------------------------------------------------- CSV / JSON

def _parse_float(text: str) -> float:
    text = text.strip()
    if text == "" or text.lower() in ("nan", "null", "none"):
        return math.nan
    return float(text)


def _read_landmarks_csv(path) -> np.ndarray:
    where = repr(str(path))
    try:
        rows = list(csv.reader(_stdio.StringIO("\n".join(_read_text(path)))))
    except csv.Error as exc:  # an unclosed quote, a field over the csv module's size limit
        raise ValueError(f"{where}: not a readable CSV file ({exc})") from None
    # A blank line is no row; ",," is a row of empty cells (a missing landmark).
    numbered = [(i, [cell.strip() for cell in row]) for i, row in enumerate(rows) if row]
    if not numbered:
        raise ValueError(f"{where}: no landmarks in the CSV file")

    def is_name(cell: str) -> bool:
        try:
            landmark_index(cell)
            return True
        except ValueError:
            return False

    def is_number(cell: str) -> bool:
        try:
            _parse_float(cell)
            return True
        except ValueError:
            return False

    first = numbered[0][1]
    if not is_name(first[0]) and not any(is_number(cell) and cell for cell in first):
        numbered = numbered[1:]  # a header such as "name,x,y,z" or "x,y,z"
    if not numbered:
        raise ValueError(f"{where}: CSV file has a header but no landmarks")
    landmarks = empty_landmarks()
    # Rows start with a name unless the first cell is a number (or empty: missing).
    named = not is_number(numbered[0][1][0])
    if not named and len(numbered) != N_LANDMARKS:
        raise ValueError(
            f"{where}: a CSV of unnamed x,y,z rows must have {N_LANDMARKS} rows in Bosphorus "
            f"order, got {len(numbered)}"
        )
    for position, (line, row) in enumerate(numbered):
        cells = row[1:] if named else row
        if named:
            try:
                index = landmark_index(row[0])
            except ValueError:
                raise ValueError(f"{where}, line {line + 1}: unknown landmark name {row[0][:80]!r}") from None
            if np.isfinite(landmarks[index]).any():
                raise ValueError(f"{where}, line {line + 1}: duplicate landmark {row[0]!r}")
        else:
            index = position
        if len(cells) != 3:
            raise ValueError(f"{where}, line {line + 1}: expected 3 coordinates, got {len(cells)}")
        try:
            coords = [_parse_float(cell) for cell in cells]
        except ValueError:
            raise ValueError(f"{where}, line {line + 1}: unparsable coordinates {str(cells)[:120]}") from None
        finite = [math.isfinite(v) for v in coords]
        if any(math.isinf(v) for v in coords) or (any(finite) and not all(finite)):
            raise ValueError(f"{where}, line {line + 1}: non-finite coordinates {cells}")
        if any(abs(v) > MAX_LANDMARK_COORDINATE for v in coords if math.isfinite(v)):
            raise ValueError(f"{where}, line {line + 1}: coordinates beyond +-{MAX_LANDMARK_COORDINATE:.0e} mm")
        if named and not all(finite):
            raise ValueError(f"{where}, line {line + 1}: named landmark {row[0]!r} without coordinates")
        landmarks[index] = coords
    return landmarks


def _read_landmarks_json(path) -> np.ndarray:
    where = repr(str(path))
    try:
        data = json.loads("\n".join(_read_text(path)))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}, line {exc.lineno}: invalid JSON ({exc.msg})") from None
    except RecursionError:
        raise ValueError(f"{where}: JSON nested too deeply to be landmarks") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise ValueError(f"{where}: invalid JSON ({exc})") from None
    landmarks = empty_landmarks()

    def coords_of(value, label: str) -> list[float]:
        if (not isinstance(value, (list, tuple)) or len(value) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise ValueError(f"{where}: {label} must be [x, y, z] numbers, got {value!r}")
        if not all(abs(v) <= MAX_LANDMARK_COORDINATE for v in value):
            raise ValueError(f"{where}: {label} has non-finite or out-of-range coordinates "
                             f"(beyond +-{MAX_LANDMARK_COORDINATE:.0e} mm): {str(value)[:120]}")
        return [float(v) for v in value]

    if isinstance(data, dict):
        seen: dict[int, str] = {}
        for name, value in data.items():
            try:
                index = landmark_index(name)
            except ValueError:
                raise ValueError(f"{where}: unknown landmark name {str(name)[:80]!r}") from None
            if index in seen:
                raise ValueError(f"{where}: duplicate landmark {name!r} (also as {seen[index]!r})")
            seen[index] = name
            if value is not None:
                landmarks[index] = coords_of(value, f"landmark {name!r}")
    elif isinstance(data, list):
        if len(data) != N_LANDMARKS:
            raise ValueError(
                f"{where}: a JSON list of landmarks must have {N_LANDMARKS} entries in Bosphorus "
                f"order, got {len(data)}"
            )
        for index, value in enumerate(data):
            if value is not None:
                landmarks[index] = coords_of(value, f"entry {index} ({LANDMARK_NAMES[index]})")
    else:
        raise ValueError(f"{where}: JSON landmarks must be an object {{name: [x, y, z]}} or a list of 22")
    return landmarks


#: The landmark files a scan may have beside it, in the order they are looked for.
LANDMARK_SUFFIXES = (".lm3", ".csv", ".json")


def landmark_file_beside(path) -> Path | None:
    """The landmark file beside a scan (same name, suffix .lm3, .csv or .json, in that
    order), or None when there is none."""
    path = Path(path)
    return next((c for c in (path.with_suffix(s) for s in LANDMARK_SUFFIXES) if c.is_file()), None)


def read_landmarks(path) -> np.ndarray:
    """Read 22 landmarks from ``.lm3``, ``.csv`` or ``.json``, chosen by the suffix.

    - ``.lm3``: Bosphorus text format (:func:`read_lm3`).
    - ``.csv``: rows ``name,x,y,z`` (any subset, any order, optional header), or exactly
      22 rows ``x,y,z`` in Bosphorus order (optional header; empty or ``nan`` fields
      mark a missing landmark).
    - ``.json``: ``{name: [x, y, z] or null}`` or a list of 22 ``[x, y, z]`` or ``null``.

    Names match case-insensitively.

    Returns
    -------
    (22, 3) float64, mm, NaN rows for missing landmarks.
    """
    suffix = Path(as_path(path)).suffix.lower()
    if suffix == ".lm3":
        return read_lm3(path)
    if suffix == ".csv":
        return _read_landmarks_csv(path)
    if suffix == ".json":
        return _read_landmarks_json(path)
    raise ValueError(f"{str(path)!r}: unknown landmark file type {suffix!r} (use .lm3, .csv or .json)")


def write_landmarks(path, landmarks) -> None:
    """Write 22 landmarks as ``.lm3``, ``.csv`` (``name,x,y,z`` with a header) or ``.json``
    (``{name: [x, y, z]}``), chosen by the suffix. Missing (NaN) landmarks are omitted."""
    suffix = Path(as_path(path)).suffix.lower()
    array = as_landmarks(landmarks)
    present = np.flatnonzero(np.isfinite(array).all(axis=1))
    if suffix == ".lm3":
        write_lm3(path, array)
    elif suffix == ".csv":
        lines = ["name,x,y,z"]
        lines += [",".join([LANDMARK_NAMES[i]] + [_format_float(v) for v in array[i]]) for i in present]
        atomic_write(path, ("\n".join(lines) + "\n").encode("ascii"))
    elif suffix == ".json":
        data = {LANDMARK_NAMES[i]: [float(v) for v in array[i]] for i in present}
        atomic_write(path, (json.dumps(data, indent=1) + "\n").encode("ascii"))
    else:
        raise ValueError(f"{str(path)!r}: unknown landmark file type {suffix!r} (use .lm3, .csv or .json)")


# --------------------------------------------------------------------------- meshes

def read_mesh(path):
    """Read a mesh or point cloud with trimesh, keeping the file's vertex order.

    Any format trimesh reads (OBJ, PLY, STL, OFF, GLB, ...). A scene of several
    geometries is concatenated (with their scene transforms applied).

    Returns
    -------
    vertices : (n, 3) float64, mm
    faces : (m, 3) int64; (0, 3) for a point cloud

    Raises
    ------
    ValueError
        If the file is missing, unreadable, or holds no vertices.
    """
    # trimesh takes a third of a second to import; only mesh files need it
    import trimesh

    path = check_readable(path)
    where = repr(str(path))
    if path.suffix.lower() == ".obj":
        # trimesh drops OBJ vertices no face uses once texture coordinates are present,
        # which would break the correspondence with the file's vertex order.
        return _read_obj(path)
    with open_for_reading(path) as handle:
        size = regular_file_size(handle)
    if size is None:
        raise ValueError(f"{where}: not a regular file (trimesh reads meshes from files only)")
    if size > MAX_MESH_FILE_BYTES:
        raise ValueError(f"{where}: the file is {size:,} bytes; tpscore reads meshes of at most "
                         f"{MAX_MESH_FILE_BYTES:,}")
    try:
        # process=False keeps the vertex order (no merging); fix_texture=False stops the
        # PLY reader from splitting vertices along u,v seams.
        loaded = trimesh.load(str(path), process=False, fix_texture=False)
    except Exception as exc:  # trimesh raises many types for unreadable input
        raise ValueError(f"{where}: cannot be read as a mesh or point cloud ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geometries = list(loaded.geometry.values())
        if not geometries:
            raise ValueError(f"{where}: the file holds no geometry")
        loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
    vertices = np.ascontiguousarray(np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64))
    faces = getattr(loaded, "faces", None)
    faces = np.empty((0, 3), dtype=np.int64) if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"{where}: the file holds no vertices")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{where}: the file has NaN or infinite vertex coordinates")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        # trimesh (with process=False) passes a PLY's indices through unchecked
        bad = int(faces[(faces < 0) | (faces >= len(vertices))][0])
        raise ValueError(f"{where}: a face refers to vertex {bad}, but the file has vertices 0 to "
                         f"{len(vertices) - 1}")
    return vertices, np.ascontiguousarray(faces)


def _read_obj(path, *, extras: bool = False):
    """Vertices and triangles of an OBJ file, in file order (polygons split as fans).

    With ``extras``, also the colour information: a dict with ``corner_uv`` ((m, 3, 2)
    texture coordinates of each triangle's corners as the file stores them, v up; None
    when a face has none), ``colors`` ((n, 3) floats of ``v x y z r g b`` lines, None
    unless every vertex has them), ``mtllib`` (the first material library named) and
    ``material`` (the first material used)."""
    where = repr(str(path))
    vertices: list[list[float]] = []
    colors: list[list[float]] = []
    texcoords: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    face_texcoords: list[tuple[int, int, int]] = []
    every_face_textured = True
    mtllib = material = None
    for number, line in enumerate(_read_text(path, MAX_MESH_FILE_BYTES, "a mesh file"), start=1):
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "v":
                vertices.append([float(w) for w in words[1:4]])
                if len(vertices[-1]) != 3:
                    raise ValueError("a vertex needs x y z")
                if extras and len(words) >= 7:
                    colors.append([float(w) for w in words[4:7]])
            elif words[0] == "vt" and extras:
                texcoords.append([float(w) for w in words[1:3]])
                if len(texcoords[-1]) != 2:
                    raise ValueError("a texture coordinate needs u v")
            elif words[0] == "mtllib" and extras and mtllib is None and len(words) > 1:
                mtllib = line.split(None, 1)[1].strip()
            elif words[0] == "usemtl" and extras and material is None and len(words) > 1:
                material = words[1]
            elif words[0] == "f":
                corners, corner_texcoords = [], []
                for word in words[1:]:
                    parts = word.split("/")
                    index = int(parts[0])
                    # OBJ indices are 1-based; negative ones count back from the last vertex.
                    index = index - 1 if index > 0 else len(vertices) + index
                    if not 0 <= index < len(vertices):
                        raise ValueError(f"face refers to vertex {word!r}, which is not defined")
                    corners.append(index)
                    if extras and len(parts) > 1 and parts[1]:
                        texcoord = int(parts[1])
                        texcoord = texcoord - 1 if texcoord > 0 else len(texcoords) + texcoord
                        if not 0 <= texcoord < len(texcoords):
                            raise ValueError(f"face refers to texture coordinate {word!r}, which is not defined")
                        corner_texcoords.append(texcoord)
                if len(corners) < 3:
                    raise ValueError("a face needs at least 3 vertices")
                faces.extend((corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1))
                if extras:
                    if len(corner_texcoords) == len(corners):
                        face_texcoords.extend((corner_texcoords[0], corner_texcoords[k], corner_texcoords[k + 1])
                                              for k in range(1, len(corners) - 1))
                    else:
                        every_face_textured = False
        except ValueError as exc:
            raise ValueError(f"{where}, line {number}: {exc}") from None
    if not vertices:
        raise ValueError(f"{where}: the file holds no vertices")
    vertices_array = np.array(vertices, dtype=np.float64)
    if not np.isfinite(vertices_array).all():
        raise ValueError(f"{where}: the file has NaN or infinite vertex coordinates")
    faces_array = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if not extras:
        return vertices_array, faces_array
    corner_uv = None
    if every_face_textured and len(faces) and len(face_texcoords) == len(faces):
        corner_uv = np.array(texcoords, dtype=np.float64)[np.array(face_texcoords, dtype=np.int64)]
        if not np.isfinite(corner_uv).all():
            corner_uv = None
    color_array = None
    if len(colors) == len(vertices):
        color_array = np.array(colors, dtype=np.float64)
        if not np.isfinite(color_array).all():
            color_array = None
    return vertices_array, faces_array, {"corner_uv": corner_uv, "colors": color_array,
                                         "mtllib": mtllib, "material": material}


class ColourWarning(UserWarning):
    """A mesh's colour source cannot be used (a missing material or texture file, a
    material without an image, an unreadable image): the scan is read without colour."""


@dataclass
class MeshColours:
    """A mesh with the colours it carries, as :func:`read_mesh_colours` reads it.

    Attributes
    ----------
    vertices : (n, 3) float64, mm
    faces : (m, 3) int64
    image : (h, w, 3) uint8 or None
        The texture image.
    corner_uv : (m, 3, 2) float64 or None
        Each triangle corner's place in ``image`` in tpscore's convention (u to the
        right, v DOWN, as a ``.bnt`` holds it); a file's v = 0 at the image's bottom is
        flipped on reading.
    vertex_colors : (n, 3) uint8 or None
        Colours stored per vertex (PLY, GLB, OBJ ``v x y z r g b``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    image: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None


def _mtl_texture(mtl_path: Path, material: str | None) -> str | None:
    """The diffuse map (``map_Kd``) of `material` in a material library (the first one
    when `material` is None or not found)."""
    current, maps = None, {}
    for line in _read_text(mtl_path, MAX_TEXT_FILE_BYTES, "a material file"):
        words = line.split()
        if not words:
            continue
        if words[0] == "newmtl" and len(words) > 1:
            current = words[1]
        elif words[0].lower() == "map_kd" and len(words) > 1:
            # options (-s 1 1 1, ...) come before the file name, the last word
            maps.setdefault(current, words[-1])
    if material in maps:
        return maps[material]
    return next(iter(maps.values()), None)


def _texture_of_obj(path: Path, mtllib: str | None, material: str | None) -> np.ndarray | None:
    """The texture image an OBJ's material names, or None with a :class:`ColourWarning`."""
    where = repr(str(path))
    if mtllib is None:
        warnings.warn(f"{where} has texture coordinates but names no material library (mtllib): "
                      "read without colour", ColourWarning, stacklevel=4)
        return None
    mtl_path = path.parent / mtllib
    try:
        texture = _mtl_texture(check_readable(mtl_path, "material file"), material)
    except ValueError as exc:
        warnings.warn(f"{where}: its material library cannot be read ({exc}): read without colour",
                      ColourWarning, stacklevel=4)
        return None
    if texture is None:
        warnings.warn(f"{where}: its material library {str(mtl_path)!r} names no texture image (map_Kd): "
                      "read without colour", ColourWarning, stacklevel=4)
        return None
    try:
        return read_image(mtl_path.parent / texture)
    except ValueError as exc:
        warnings.warn(f"{where}: its texture image cannot be used ({exc}): read without colour",
                      ColourWarning, stacklevel=4)
        return None


def read_mesh_colours(path) -> MeshColours:
    """Read a mesh with its colours: an OBJ with its material library and texture image
    (:func:`write_textured_obj`'s output among them) or its vertex colours, a PLY, GLB or
    any other format trimesh reads with its vertex colours or texture.

    The vertices and faces are those :func:`read_mesh` reads. A colour source that
    cannot be used (a missing material or texture file, a material without an image,
    an unreadable image) gives a :class:`ColourWarning` and a mesh without colour.

    Raises
    ------
    ValueError
        As :func:`read_mesh`: a missing or unreadable mesh file.
    """
    path = check_readable(path)
    if path.suffix.lower() == ".obj":
        vertices, faces, extras = _read_obj(path, extras=True)
        result = MeshColours(vertices, faces)
        if extras["corner_uv"] is not None:
            image = _texture_of_obj(path, extras["mtllib"], extras["material"])
            if image is not None:
                flipped = extras["corner_uv"].copy()
                flipped[..., 1] = 1.0 - flipped[..., 1]
                result.image, result.corner_uv = image, flipped
        if result.image is None and extras["colors"] is not None:
            colors = extras["colors"]
            # OBJ colours are floats in [0, 1]; some writers store 0-255
            scale = 255.0 if colors.max() <= 1.0 else 1.0
            result.vertex_colors = np.clip(np.round(colors * scale), 0, 255).astype(np.uint8)
        return result
    vertices, faces = read_mesh(path)
    import trimesh

    result = MeshColours(vertices, faces)
    try:
        loaded = trimesh.load(str(path), process=False, fix_texture=False)
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.to_geometry() if hasattr(loaded, "to_geometry") else loaded.dump(concatenate=True)
        visual = getattr(loaded, "visual", None)
        kind = getattr(visual, "kind", None)
    except Exception:  # read_mesh read it; the colours are a bonus
        return result
    if len(getattr(loaded, "vertices", ())) != len(vertices):
        return result
    try:
        return _trimesh_colours(path, result, visual, kind)
    except Exception as exc:  # a visual trimesh built from a damaged file
        warnings.warn(f"{str(path)!r}: its colours cannot be read ({type(exc).__name__}: {exc}): read without "
                      "colour", ColourWarning, stacklevel=2)
        return MeshColours(vertices, faces)


def _trimesh_colours(path, result: MeshColours, visual, kind) -> MeshColours:
    """The vertex colours or the texture of a mesh trimesh read."""
    vertices, faces = result.vertices, result.faces
    if kind == "vertex":
        colors = np.asarray(visual.vertex_colors)
        if colors.shape[:1] == (len(vertices),) and colors.shape[1] >= 3:
            result.vertex_colors = np.ascontiguousarray(colors[:, :3], dtype=np.uint8)
    elif kind == "texture":
        uv = getattr(visual, "uv", None)
        material = getattr(visual, "material", None)
        picture = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if uv is None or picture is None or len(faces) == 0:
            warnings.warn(f"{str(path)!r} has a texture but no image or texture coordinates tpscore can use: "
                          "read without colour", ColourWarning, stacklevel=3)
            return result
        try:
            image = as_colour_image(np.asarray(picture.convert("RGB"), dtype=np.uint8))
        except Exception as exc:
            warnings.warn(f"{str(path)!r}: its texture image cannot be used ({exc}): read without colour",
                          ColourWarning, stacklevel=3)
            return result
        corner_uv = np.asarray(uv, dtype=np.float64)[faces].copy()
        corner_uv[..., 1] = 1.0 - corner_uv[..., 1]
        if np.isfinite(corner_uv).all():
            result.image, result.corner_uv = image, corner_uv
    return result


def _colors_uint8(vertex_colors, n: int) -> np.ndarray:
    colors = np.asarray(vertex_colors)
    if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] not in (3, 4):
        raise ValueError(f"vertex_colors must have shape ({n}, 3) or ({n}, 4), got {colors.shape}")
    if np.issubdtype(colors.dtype, np.floating):
        if not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 1:
            raise ValueError("float vertex_colors must lie in [0, 1]")
        colors = np.round(colors * 255.0)
    elif not np.issubdtype(colors.dtype, np.integer) or colors.min() < 0 or colors.max() > 255:
        raise ValueError("integer vertex_colors must lie in [0, 255]")
    colors = colors.astype(np.uint8)
    if colors.shape[1] == 3:
        colors = np.concatenate([colors, np.full((n, 1), 255, np.uint8)], axis=1)
    return colors


def write_mesh(path, vertices, faces, *, uv=None, vertex_colors=None) -> None:
    """Write a triangle mesh (or, with no faces, a point cloud) as ``.obj`` or ``.ply``.

    Parameters
    ----------
    path : str or PathLike
        ``.obj`` (text) or ``.ply`` (binary little-endian, float64 coordinates).
    vertices : (n, 3) array-like, mm, all finite (drop masked vertices first, for
        example with :meth:`tpscore.face.grid.FaceGrid.mesh`).
    faces : (m, 3) integer array-like (m may be 0).
    uv : (n, 2) array-like, optional
        Per-vertex texture coordinates, written as given: OBJ ``vt`` lines with
        ``f v/vt`` faces, PLY ``texture_u``/``texture_v`` vertex properties. Viewers take
        v = 0 at the bottom of the image; pass ``1 - v`` for image-row coordinates such
        as those of a ``.bnt``.
    vertex_colors : (n, 3) or (n, 4), optional
        uint8 in [0, 255] or float in [0, 1]: OBJ ``v x y z r g b``, PLY red/green/blue/alpha.
    """

    vertices = as_points(vertices, "vertices")
    faces = as_faces(np.asarray(faces).reshape(-1, 3) if np.size(faces) == 0 else faces, len(vertices))
    n = len(vertices)
    if uv is not None:
        uv = as_points(uv, "uv", dim=2)
        if len(uv) != n:
            raise ValueError(f"uv must have shape ({n}, 2), got {uv.shape}")
    if n >= 2**31:
        raise ValueError(f"write_mesh stores vertex indices as int32; {n} vertices are too many")
    colors = None if vertex_colors is None else _colors_uint8(vertex_colors, n)
    suffix = Path(as_path(path)).suffix.lower()
    if suffix == ".obj":
        data = _obj_bytes(vertices, faces, uv, colors)
    elif suffix == ".ply":
        data = _ply_bytes(vertices, faces, uv, colors)
    else:
        raise ValueError(f"{str(path)!r}: write_mesh writes .obj or .ply, not {suffix!r}")
    atomic_write(path, data)


def _obj_bytes(vertices, faces, uv, colors, header: tuple[str, ...] = ()) -> bytes:
    out = _stdio.StringIO()
    out.write("# written by tpscore; units mm\n")
    for line in header:
        out.write(line + "\n")
    # %.17g round-trips float64 exactly; np.savetxt formats the whole block in C.
    if colors is None:
        np.savetxt(out, vertices, fmt="v %.17g %.17g %.17g")
    else:
        block = np.concatenate([vertices, colors[:, :3] / 255.0], axis=1)
        np.savetxt(out, block, fmt="v %.17g %.17g %.17g %.6g %.6g %.6g")
    if uv is not None:
        np.savetxt(out, uv, fmt="vt %.17g %.17g")
    if len(faces):
        one_based = faces + 1
        if uv is not None:
            np.savetxt(out, np.repeat(one_based, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
        else:
            np.savetxt(out, one_based, fmt="f %d %d %d")
    return out.getvalue().encode("ascii")


def write_textured_obj(path, vertices, faces, uv, image, *, material: str = "skin") -> tuple[Path, Path, Path]:
    """Write a mesh textured by an image: ``NAME.obj``, ``NAME.mtl`` and ``NAME_texture.png``.

    MeshLab, Blender, trimesh and most viewers show the mesh in the image's colours. The
    image and the material are written first, the OBJ last (each atomically), so an OBJ
    on disk always finds its material and image beside it.

    Parameters
    ----------
    path : str or PathLike
        The ``.obj`` file; the ``.mtl`` and the ``_texture.png`` take its stem, in its
        folder (the image's name differs from the stem so that a picture named like the
        mesh, ``result.obj`` beside ``result.png``, does not overwrite the texture).
    vertices : (n, 3) array-like, mm, finite
    faces : (m, 3) integer array-like
    uv : (n, 2) array-like
        Each vertex's place in the image in tpscore's convention (u to the right, v
        DOWN, in [0, 1], as :attr:`FaceGrid.uv <tpscore.face.grid.FaceGrid.uv>` and a
        ``.bnt`` hold it). The OBJ stores ``1 - v``, since OBJ viewers put v = 0 at the
        bottom of the image.
    image : (h, w, 3) uint8
        The texture, for example :attr:`FaceGrid.image <tpscore.face.grid.FaceGrid.image>`.
    material : str
        The material's name (letters, digits, ``_`` and ``-``).

    Returns
    -------
    (obj_path, mtl_path, png_path)
    """
    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"{str(path)!r}: write_textured_obj writes an .obj (with .mtl and .png beside it)")
    if not isinstance(material, str) or not material or not all(c.isalnum() or c in "_-" for c in material):
        raise ValueError(f"material must be a name of letters, digits, _ and -, got {material!r}")
    vertices = as_points(vertices, "vertices")
    faces = as_faces(np.asarray(faces).reshape(-1, 3) if np.size(faces) == 0 else faces, len(vertices))
    uv = as_points(uv, "uv", dim=2)
    if len(uv) != len(vertices):
        raise ValueError(f"uv must have shape ({len(vertices)}, 2), got {uv.shape}")
    picture = as_colour_image(image, "image")
    mtl_path, png_path = path.with_suffix(".mtl"), path.with_name(f"{path.stem}_texture.png")
    write_png(png_path, picture)
    atomic_write(mtl_path, (
        "# written by tpscore\n"
        f"newmtl {material}\n"
        "Ka 1 1 1\nKd 1 1 1\nKs 0 0 0\nNs 1\nd 1\nillum 1\n"
        f"map_Kd {png_path.name}\n").encode("utf-8"))
    flipped = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    atomic_write(path, _obj_bytes(vertices, faces, flipped, None,
                                   (f"mtllib {mtl_path.name}", f"usemtl {material}")))
    return path, mtl_path, png_path


def _ply_bytes(vertices, faces, uv, colors) -> bytes:
    n, m = len(vertices), len(faces)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = ["ply", "format binary_little_endian 1.0", "comment written by tpscore; units mm",
              f"element vertex {n}", "property double x", "property double y", "property double z"]
    if uv is not None:
        fields += [("texture_u", "<f8"), ("texture_v", "<f8")]
        header += ["property double texture_u", "property double texture_v"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue", "property uchar alpha"]
    header += [f"element face {m}", "property list uchar int vertex_indices", "end_header"]
    table = np.empty(n, dtype=np.dtype(fields))
    table["x"], table["y"], table["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    if uv is not None:
        table["texture_u"], table["texture_v"] = uv[:, 0], uv[:, 1]
    if colors is not None:
        for k, name in enumerate(("red", "green", "blue", "alpha")):
            table[name] = colors[:, k]
    face_table = np.empty(m, dtype=np.dtype([("count", "u1"), ("indices", "<i4", (3,))]))
    face_table["count"] = 3
    face_table["indices"] = faces
    return ("\n".join(header) + "\n").encode("ascii") + table.tobytes() + face_table.tobytes()


#: The largest .npz read, and the most its arrays may hold once decompressed (2 GiB each):
#: a compressed archive can announce gigabytes in a few bytes.
MAX_NPZ_BYTES = 2**31


def read_npz(path, fields=(), *, what: str = "an .npz file") -> dict:
    """All arrays of a NumPy ``.npz`` archive, read eagerly and safely.

    Pickled objects are refused (they could run code); an archive larger than
    :data:`MAX_NPZ_BYTES`, or whose members announce more than that decompressed, is
    refused before anything is inflated.

    Parameters
    ----------
    path : str or PathLike
    fields : sequence of str
        Names that must be present.
    what : str
        What the file should be, for the messages ("an average face model").

    Returns
    -------
    dict of name -> ndarray

    Raises
    ------
    ValueError
        Naming the file: missing, not an .npz archive, corrupt, too large, pickled
        data, or lacking one of `fields`.
    """
    raw = read_bytes(path, MAX_NPZ_BYTES, what)
    where = repr(str(path))
    try:
        with zipfile.ZipFile(_stdio.BytesIO(raw)) as archive:
            announced = sum(info.file_size for info in archive.infolist())
            if announced > MAX_NPZ_BYTES:
                raise ValueError(f"{where}: its arrays would take {announced:,} bytes decompressed; "
                                 f"{what} holds at most {MAX_NPZ_BYTES:,}")
        with np.load(_stdio.BytesIO(raw), allow_pickle=False) as data:
            arrays = {name: np.asarray(data[name]) for name in data.files}
    except ValueError as exc:
        if str(exc).startswith(where):
            raise
        raise ValueError(f"{where}: not {what}: {exc}") from None
    except Exception as exc:  # zipfile, zlib and the .npy header parser raise many types
        raise ValueError(f"{where}: not {what}: corrupt .npz archive ({type(exc).__name__}: {exc})") from None
    missing = [name for name in fields if name not in arrays]
    if missing:
        raise ValueError(f"{where}: not {what}: lacks the array(s) {', '.join(missing)}")
    return arrays


def write_npz(path, **arrays) -> None:
    """Write arrays to a compressed ``.npz`` (atomically, like every writer here)."""

    buffer = _stdio.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write(path, buffer.getvalue())
