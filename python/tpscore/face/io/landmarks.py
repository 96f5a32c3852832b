"""Landmark files: Bosphorus ``.lm3`` (:func:`read_lm3`, :func:`write_lm3`), and ``.lm3``,
``.csv`` or ``.json`` chosen by the suffix (:func:`read_landmarks`,
:func:`write_landmarks`); the landmark file beside a scan (:func:`landmark_file_beside`)."""
from __future__ import annotations

import csv
import io as _stdio
import json
import math
from pathlib import Path

import numpy as np

from ..._files import atomic_write
from ..._validation import MAX_COORDINATE, as_path
from ..landmarks import LANDMARK_NAMES, N_LANDMARKS, as_landmarks, empty_landmarks, landmark_index
from ._common import _read_text


#: Landmark coordinates beyond this (mm) are refused (they are the kernels' limit, and
#: a JSON integer of hundreds of digits would not even convert to a float).
MAX_LANDMARK_COORDINATE = MAX_COORDINATE


def _format_float(value: float) -> str:
    # repr gives the shortest text that reads back to the same float.
    return repr(float(value))


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
