"""Input validation shared by the public API.

Every public function converts its inputs once, here, into the canonical types the
compiled core expects (C-contiguous float64 points, int64 faces) and raises a
ValueError that names the argument and what is wrong with it.
"""
from __future__ import annotations

import math
import numbers
import os

import numpy as np

__all__ = [
    "Immutable",
    "as_points",
    "as_values",
    "as_faces",
    "as_positive",
    "as_array",
    "as_real",
    "as_count",
    "as_flag",
    "as_vertex_count",
    "as_path",
    "check_finite",
    "check_real",
    "check_rows",
    "row_count",
    "check_result_size",
    "gib",
    "MAX_DENSE_ELEMENTS",
    "MAX_SPARSE_ENTRIES",
    "MAX_POINTS",
    "MAX_COORDINATE",
]

class Immutable:
    """Base of the fitted kernel objects, which never change once made from validated
    inputs: a copy, shallow or deep, is the object itself."""

    __slots__ = ()

    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self


# A dense temporary larger than this (in float64 elements, 2 GiB) is refused or chunked.
MAX_DENSE_ELEMENTS = 2**28

#: The most entries of a sparse result (the pairs a radius query returns, the nonzeros
#: of a CSRBF matrix): the same 2 GiB budget, for each of its float64 and int64 arrays.
MAX_SPARSE_ENTRIES = MAX_DENSE_ELEMENTS

#: The most rows of an (n, 3) point array a kernel copies: 2 GiB of float64 coordinates
#: (89,478,485 points).
MAX_POINTS = MAX_DENSE_ELEMENTS // 3

#: Largest coordinate magnitude (mm) a kernel accepts. Millimetres that far out are
#: quantised to 0.125 mm by float64 itself, so no face geometry survives there; and the
#: kernels' squared distances and r^2 ln r^2 of such points stay finite, while beyond
#: about 1e154 a squared distance overflows and a query answers NaN.
MAX_COORDINATE = 1e15

#: The largest C int: counts handed to the compiled core (leaf sizes, neighbours).
MAX_C_INT = 2**31 - 1


def check_real(array: np.ndarray, name: str) -> None:
    """Refuse complex input: NumPy would cast it to float64, dropping the imaginary
    part with only a warning."""
    if np.iscomplexobj(array):
        raise ValueError(f"{name} must be real numbers, got complex values (dtype {array.dtype})")


def check_finite(array: np.ndarray, name: str) -> None:
    """Raise ValueError naming the first non-finite row of `array`."""
    if array.size and not np.isfinite(array).all():
        flat = array.reshape(len(array), -1) if array.ndim > 1 else array.reshape(-1, 1)
        bad = np.flatnonzero(~np.isfinite(flat).all(axis=1))
        raise ValueError(
            f"{name} contains NaN or infinite values (first at row {bad[0]}, "
            f"{len(bad)} row(s) in all)"
        )


def as_points(points, name: str = "points", *, dim: int = 3, allow_empty: bool = True,
              finite: bool = True) -> np.ndarray:
    """Convert array-like input to a C-contiguous (n, dim) float64 array.

    A single point of shape (dim,) is not accepted silently: callers pass (1, dim).
    """
    array = _as_float_array(points, name, f"a numeric array of shape (n, {dim})")
    if array.ndim != 2 or array.shape[1] != dim:
        raise ValueError(f"{name} must have shape (n, {dim}), got {array.shape}")
    if not allow_empty and len(array) == 0:
        raise ValueError(f"{name} is empty; at least one point is needed")
    if finite and array.size:
        # Two reductions without temporaries; NaN fails both comparisons.
        if not (array.max() <= MAX_COORDINATE and array.min() >= -MAX_COORDINATE):
            check_finite(array, name)
            row = int(np.flatnonzero((np.abs(array) > MAX_COORDINATE).any(axis=1))[0])
            raise ValueError(
                f"{name} has coordinates beyond +-{MAX_COORDINATE:.0e} mm (first at row {row}: "
                f"{array[row].tolist()}); tpscore works in millimetres")
    return np.ascontiguousarray(array)


def gib(n_bytes: float) -> str:
    """A size in bytes as GiB, for messages."""
    return f"{n_bytes / 2**30:.1f} GiB"


def row_count(values) -> int | None:
    """len() of an array-like's first axis without converting it (a broadcast view of
    10^9 rows is free until it is copied), or None when it has no such axis."""
    shape = getattr(values, "shape", None)
    if shape is not None:
        try:
            return int(shape[0]) if len(shape) >= 1 else None
        except (TypeError, ValueError, IndexError):  # not an array's shape: as_points says why
            return None
    # a list is measured without converting it (as_points converts it once, later)
    return len(values) if isinstance(values, (list, tuple)) else None


def check_rows(points, name: str, most: int, what: str) -> None:
    """Refuse, before (n, 3) `points` are converted or copied, more than `most` rows: a
    ValueError naming `name`, the rows given, their size and the limit (`what` says
    why the limit is there)."""
    rows = row_count(points)
    if rows is not None and rows > most:
        raise ValueError(f"{name} has {rows:,} rows ({gib(24.0 * rows)} of float64 coordinates); at most "
                         f"{most:,} ({gib(24.0 * most)}) are accepted: {what}")


def check_result_size(points, columns: int, name: str = "points", *, hint: str = "") -> None:
    """Refuse, before `points` is converted, a query whose (m, columns) float64 result
    would pass the dense-array budget (:data:`MAX_DENSE_ELEMENTS`, 2 GiB)."""
    rows = row_count(points)
    if rows is None or columns <= 0 or rows * columns <= MAX_DENSE_ELEMENTS:
        return
    most = max(1, MAX_DENSE_ELEMENTS // columns)
    raise ValueError(
        f"{name}: {rows:,} query points would give a {rows:,} x {columns} float64 result "
        f"({gib(8.0 * rows * columns)}), more than the limit of {MAX_DENSE_ELEMENTS:,} values "
        f"({gib(8.0 * MAX_DENSE_ELEMENTS)}); pass at most {most:,} points at a time{hint}")


def as_array(values, name: str) -> np.ndarray:
    """`values` as a float64 array of any shape; ValueError naming `name` for complex
    or non-numeric input (shape and finiteness are the caller's to check)."""
    return _as_float_array(values, name, "numeric")


def _as_float_array(values, name: str, what: str) -> np.ndarray:
    """`values` as a float64 array, refusing complex and non-numeric input."""
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be {what}: {exc}") from None
    check_real(raw, name)
    if raw.dtype == object:
        # A list mixing Python complex numbers and floats arrives as an object array.
        if any(isinstance(v, complex) for v in raw.reshape(-1)):
            raise ValueError(f"{name} must be real numbers, got complex values")
    try:
        return np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be {what}: {exc}") from None


def as_values(values, n: int, name: str = "values") -> np.ndarray:
    """Convert per-point values to a C-contiguous (n, k) float64 array (1-D becomes (n, 1))."""
    array = _as_float_array(values, name, "numeric")
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2 or array.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) or ({n}, k), got {np.shape(values)}")
    check_finite(array, name)
    return np.ascontiguousarray(array)


def as_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    """Convert triangles to a C-contiguous (m, 3) int64 array of valid vertex indices."""
    array = np.asarray(faces)
    check_real(array, name)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (m, 3), got {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        if not np.issubdtype(array.dtype, np.floating) or not np.all(array == np.round(array)):
            raise ValueError(f"{name} must hold integer vertex indices, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.int64)
    if array.size and (array.min() < 0 or array.max() >= n_vertices):
        raise ValueError(
            f"{name} refers to vertex indices outside [0, {n_vertices}): "
            f"min {array.min()}, max {array.max()}"
        )
    return array


def as_real(value, name: str, *, low: float = -math.inf, high: float = math.inf) -> float:
    """A finite real scalar in [low, high]; ValueError naming `name` otherwise.

    Strings are refused even when they spell a number: a number that arrives as text
    is a caller's parsing slip, and float("nan") or float("1e999") would slip through.
    """
    if isinstance(value, (str, bytes, bool, np.bool_)) or isinstance(value, (complex, np.complexfloating)):
        raise ValueError(f"{name} must be a real number, got {value!r:.80}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r:.80}") from None
    if not math.isfinite(number):
        raise ValueError(f"{name} must be finite, got {value!r:.80}")
    if not low <= number <= high:
        raise ValueError(f"{name} must lie in [{low:g}, {high:g}], got {value!r:.80}")
    return number


def as_positive(value, name: str, *, allow_zero: bool = False) -> float:
    """A finite scalar > 0 (or >= 0 with allow_zero)."""
    if isinstance(value, (str, bytes, bool, np.bool_)) or isinstance(value, (complex, np.complexfloating)):
        raise ValueError(f"{name} must be a number, got {value!r:.80}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r:.80}") from None
    if not math.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r:.80}")
    return number


def as_flag(value, name: str) -> bool:
    """True or False (a NumPy bool too); ValueError naming `name` otherwise: 0, 1 and
    "yes" are a caller's slip, not a choice."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def as_count(value, name: str, *, least: int = 1, most: int = MAX_C_INT) -> int:
    """A whole number in [least, most]; ValueError naming `name` otherwise (bools,
    floats such as 2.0 and strings are refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer >= {least}, got {value!r:.80}")
    count = int(value)
    if count < least:
        raise ValueError(f"{name} must be >= {least}, got {count}")
    if count > most:
        raise ValueError(f"{name} must be at most {most}, got {count}")
    return count


#: The most vertices a mesh function's ``n_vertices`` may ask for: a C int (the core's
#: index type), and a mask of that many vertices takes 2 GiB.
MAX_VERTICES = MAX_C_INT


def as_vertex_count(value, name: str = "n_vertices", *, most: int = MAX_VERTICES, what: str = "") -> int:
    """A vertex count in [0, most]: an integer, or a float with a whole value (as an
    array's length may arrive); ValueError naming `name` otherwise, before anything
    that many long is allocated (`what` says what would be)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a non-negative integer, got {value!r:.80}")
    if not isinstance(value, numbers.Integral) and not (math.isfinite(value) and float(value).is_integer()):
        raise ValueError(f"{name} must be a non-negative integer, got {value!r:.80}")
    count = int(value)
    if count < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {count}")
    if count > most:
        raise ValueError(f"{name} = {count:,} is more than the {most:,} vertices tpscore accepts here"
                         f"{' (' + what + ')' if what else ''}")
    return count


def as_path(path, name: str = "path") -> str:
    """A file-system path as text; ValueError for None, numbers and other non-paths
    (open() would raise a TypeError that does not say which argument)."""
    if isinstance(path, bytes):
        path = os.fsdecode(path)
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{name} must be a file path (str or os.PathLike), got {path!r:.80}")
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if not text:
        raise ValueError(f"{name} is an empty path")
    if "\x00" in text:
        raise ValueError(f"{name} {text!r} contains a NUL character")
    return text


def check_options(options, *, positive=(), non_negative=(), counts=(), flags=(), choices=None) -> None:
    """Validate the fields of an options dataclass in one place.

    ``positive`` fields must be finite numbers > 0, ``non_negative`` ones >= 0,
    ``counts`` whole numbers >= 1 (0 allowed where named as ``("field", 0)``),
    ``flags`` booleans, and ``choices`` maps a field to its allowed values. Raises
    ValueError naming the options class, the field and the value.
    """
    owner = type(options).__name__
    for name in positive:
        as_positive(getattr(options, name), f"{owner}.{name}")
    for name in non_negative:
        as_positive(getattr(options, name), f"{owner}.{name}", allow_zero=True)
    for item in counts:
        name, least = (item, 1) if isinstance(item, str) else item
        value = getattr(options, name)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{owner}.{name} must be a whole number >= {least}, got {value!r}")
    for name in flags:
        as_flag(getattr(options, name), f"{owner}.{name}")
    for name, allowed in (choices or {}).items():
        if getattr(options, name) not in allowed:
            raise ValueError(f"{owner}.{name} must be one of {tuple(allowed)}, got {getattr(options, name)!r}")
