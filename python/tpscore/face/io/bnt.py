"""Bosphorus ``.bnt`` depth scans: :class:`BntScan`, :func:`read_bnt`, :func:`write_bnt`."""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from ..._files import atomic_write, open_for_reading, read_limited, regular_file_size
from ..._validation import MAX_COORDINATE, as_array


#: The largest .bnt grid read, in points (4096 x 4096, 640 MiB of values): far beyond a
#: face scanner (a Bosphorus scan has about 200,000), and a guard against a forged
#: header that asks for up to 65535 x 65535 points.
MAX_BNT_POINTS = 4096 * 4096


# The background / hole marker that Bosphorus scanners (and make_scans.py) write.
DEFAULT_BNT_ZMIN = -1.0e9

# .bnt header: uint16 nrows, uint16 ncols, float64 zmin, uint16 name length.
_BNT_HEAD = struct.Struct("<HHdH")
_BNT_LEN2 = struct.Struct("<I")


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
