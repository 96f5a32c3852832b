"""Input validation shared by the public API.

Every public function converts its inputs once, here, into the canonical types the
compiled core expects (C-contiguous float64 points, int64 faces) and raises a
ValueError that names the argument and what is wrong with it.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "as_points",
    "as_values",
    "as_faces",
    "as_positive",
    "check_finite",
    "MAX_DENSE_ELEMENTS",
]

# A dense temporary larger than this (in float64 elements, 2 GiB) is refused or chunked.
MAX_DENSE_ELEMENTS = 2**28


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
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape (n, {dim}): {exc}") from None
    if array.ndim != 2 or array.shape[1] != dim:
        raise ValueError(f"{name} must have shape (n, {dim}), got {array.shape}")
    if not allow_empty and len(array) == 0:
        raise ValueError(f"{name} is empty; at least one point is needed")
    if finite:
        check_finite(array, name)
    return np.ascontiguousarray(array)


def as_values(values, n: int, name: str = "values") -> np.ndarray:
    """Convert per-point values to a C-contiguous (n, k) float64 array (1-D becomes (n, 1))."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from None
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2 or array.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) or ({n}, k), got {np.shape(values)}")
    check_finite(array, name)
    return np.ascontiguousarray(array)


def as_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    """Convert triangles to a C-contiguous (m, 3) int64 array of valid vertex indices."""
    array = np.asarray(faces)
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


def as_positive(value, name: str, *, allow_zero: bool = False) -> float:
    """A finite scalar > 0 (or >= 0 with allow_zero)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return number


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
        if not isinstance(getattr(options, name), (bool, np.bool_)):
            raise ValueError(f"{owner}.{name} must be True or False, got {getattr(options, name)!r}")
    for name, allowed in (choices or {}).items():
        if getattr(options, name) not in allowed:
            raise ValueError(f"{owner}.{name} must be one of {tuple(allowed)}, got {getattr(options, name)!r}")
