"""Where a rig's source scans come from: one source person's folder, in either of the
layouts tpscore writes or reads.

- The Bosphorus layout (one subject's folder of the database): ``bsNNN_<CODE>.bnt``,
  the neutral ``bsNNN_N_N_0.bnt``, each code read as an AU request by
  :func:`tpscore.batch.jobs.code_label` (``LFAU_12_0`` -> ``12``, ``E_SADNESS_0`` ->
  ``sadness``).
- A flat folder as ``tpscore demo`` writes (``demo-output/scans``): ``source_<name>.bnt``,
  the neutral ``source_neutral.bnt``, each name an AU (``au12``, ``12L``), an emotion
  (``sadness``) or a Bosphorus code.

Landmarks and images are found beside each scan, as :func:`tpscore.load_scan` finds them.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from ..batch.jobs import NEUTRAL_CODE, code_label

__all__ = ["SourceScans", "source_scans", "request_name"]

_BOSPHORUS = re.compile(r"^bs(\d+)_(.+)\.bnt$", re.IGNORECASE)
_FLAT = re.compile(r"^source_(.+)\.bnt$", re.IGNORECASE)
_FLAT_NEUTRAL = "neutral"


class SourceScans(dict):
    """{AU request: expressive scan path} of one source person, with ``neutral`` (the
    path of the neutral scan, None when the folder has none) and ``folder``."""

    def __init__(self, folder: str, neutral: str | None, expressions: dict):
        super().__init__(expressions)
        self.folder = folder
        self.neutral = neutral


def request_name(text: str) -> str | None:
    """The AU request a scan's name shows (``au12`` -> ``12``, ``AU12l`` -> ``12L``,
    ``Sadness`` -> ``sadness``, ``LFAU_12_0`` -> ``12``), or None for a name that is no
    AU or emotion (a pose, an occlusion)."""
    from_code = code_label(text)
    if from_code is not None:
        return from_code
    name = text.strip()
    if name.upper().startswith("AU"):
        name = name[2:]
    if re.fullmatch(r"[0-9]+[LRlr]?", name):
        return name.upper()
    if re.fullmatch(r"[A-Za-z]+", name):
        return name.lower()
    return None


def source_scans(folder, name: str = "expressions") -> SourceScans:
    """The source person's scans in a folder (see the module's description): the
    neutral scan's path, and the expressive scans' paths by the request each shows, in
    the order of their file names. A second scan of the same request is left out (the
    first in name order is kept).

    Raises
    ------
    ValueError
        Naming `name` and the folder: it does not exist, holds several Bosphorus
        subjects, or no expressive scan of either layout.
    """
    text = os.fspath(folder) if isinstance(folder, (str, os.PathLike)) else None
    if text is None:
        raise ValueError(f"{name} must be a folder of source scans or a mapping {{AU request: scan}}, "
                         f"got {type(folder).__name__}")
    root = Path(text)
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "folder not found"
        raise ValueError(f"{name}: {text!r}: {what}")
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() == ".bnt")
    bosphorus = [(m, p) for p in files if (m := _BOSPHORUS.match(p.name))]
    if bosphorus:
        subjects = sorted({int(m.group(1)) for m, _ in bosphorus})
        if len(subjects) > 1:
            raise ValueError(f"{name}: {text!r} holds the scans of {len(subjects)} subjects "
                             f"({', '.join(f'bs{s:03d}' for s in subjects[:5])}); a rig is made of one "
                             "source person's scans: give that person's folder")
        neutral, found = None, {}
        for match, path in bosphorus:
            code = match.group(2)
            if code == NEUTRAL_CODE:
                neutral = str(path)
            else:
                _add(found, request_name(code), path)
        return _checked(SourceScans(text, neutral, found), name, files)
    neutral, found = None, {}
    for path in files:
        match = _FLAT.match(path.name)
        if not match:
            continue
        stem = match.group(1)
        if stem.lower() == _FLAT_NEUTRAL:
            neutral = str(path)
        else:
            _add(found, request_name(stem), path)
    return _checked(SourceScans(text, neutral, found), name, files)


def _add(found: dict, request: str | None, path: Path) -> None:
    if request is not None and request not in found:
        found[request] = str(path)


def _checked(scans: SourceScans, name: str, files) -> SourceScans:
    if scans:
        return scans
    root = Path(scans.folder)
    hint = ""
    if any(p.is_dir() and re.fullmatch(r"bs\d+", p.name) for p in root.iterdir()):
        hint = " (it holds bsNNN folders: give one subject's folder, e.g. bs000)"
    raise ValueError(f"{name}: no expressive scan in {scans.folder!r}{hint}: a rig needs files named "
                     f"bsNNN_<CODE>.bnt (the Bosphorus layout) or source_<name>.bnt (as tpscore demo writes "
                     f"them), {len(files)} .bnt file(s) found")
