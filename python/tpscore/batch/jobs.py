"""What a batch is made of: its jobs, and where they come from.

A job is one unit of work with one output file: a :class:`TransferJob` (a source
person's expression put on a target person) or an :class:`AdaptJob` (a template mesh
fitted to a scan). Jobs are small frozen descriptions (paths and options, no arrays),
so ten thousand of them cost the client little; the arrays are read where the job
runs.

They come from a folder in the Bosphorus layout, ``bsNNN/bsNNN_<CODE>.bnt`` with the
``.lm3`` beside each scan (:func:`transfer_jobs`, :func:`adapt_jobs`), or from a CSV
manifest with one job a row (:func:`read_manifest`).
"""
from __future__ import annotations

import csv
import hashlib
import math
import os
import re
import zipfile
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..adaptation import AdaptOptions, adapt
from ..expression import TransferOptions, transfer
from ..expression.action_units import shipped_library
from ..face import io
from ..face.landmarks import LANDMARK_NAMES
from .scores import adaptation_rms

__all__ = ["Job", "TransferJob", "AdaptJob", "transfer_jobs", "adapt_jobs", "read_manifest",
           "scan_layout", "code_label", "NEUTRAL_CODE"]

#: The Bosphorus code of the neutral scan a transfer starts from.
NEUTRAL_CODE = "N_N_0"

# Bosphorus expression codes: action units of the lower face, the upper face or both
# (LFAU_12_0, UFAU_1_0), combinations of action units (CAU_A22A25_0: AU22 + AU25; also
# read as CAU_22+25_0), and emotions (E_HAPPY_0).
_AU_CODE = re.compile(r"^(?:LF|UF|C)AU_([0-9]+[LR]?)_0$")
_COMBINATION_CODE = re.compile(r"^CAU_((?:A[0-9]+[LR]?)+|[0-9]+[LR]?(?:\+[0-9]+[LR]?)+)_0$")
_EMOTION_CODE = re.compile(r"^E_([A-Z]+)_0$")
_EMOTIONS = {"HAPPY": "happiness", "SADNESS": "sadness", "SURPRISE": "surprise", "FEAR": "fear",
             "ANGER": "anger", "DISGUST": "disgust"}
_SUBJECT = re.compile(r"^bs(\d+)$")
# A job's name is the stem of its output file: one path component, no hidden files.
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+=-]*$")

#: Template vertices farther than this (mm) from the template's nose tip are left out of
#: an adaptation's score: the scanner does not see the ears and neck a template may have.
ADAPT_SCORE_RADIUS_MM = 80.0


def _path(value, what: str) -> str:
    if value is None or str(value).strip() == "":
        raise ValueError(f"{what}: a path is required")
    return os.path.abspath(os.fspath(value))


def _optional_path(value, what: str) -> str | None:
    return None if value is None or str(value).strip() == "" else _path(value, what)


def _check_name(name) -> str:
    if not isinstance(name, str) or not _NAME.match(name) or len(name) > 200:
        raise ValueError(f"name {name!r} cannot name an output file: use letters, digits and _ . + = - "
                         "(not first), at most 200 characters")
    return name


def _check_grid(grid) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in grid)
    except (TypeError, ValueError):
        raise ValueError(f"grid must be (height, width), got {grid!r}") from None
    if not (8 <= h <= 4096 and 8 <= w <= 4096):
        raise ValueError(f"grid sizes must be between 8 and 4096, got {grid!r}")
    return h, w


def _stem(path: str) -> str:
    return os.path.splitext(path)[0]


class Job:
    """What the engine needs of a job. :class:`TransferJob` and :class:`AdaptJob` are
    the kinds tpscore has; a subclass of either may add fields and wrap the one method
    that calls the library (``transfer``, ``adapt``), and a new kind is a frozen
    dataclass with a ``name`` that implements :meth:`columns` and :meth:`run`. The
    engine runs any of them (a worker must be able to unpickle it).

    Attributes
    ----------
    name : str
        Unique within a batch; the stem of the output file and of the job's record.
    kind : str
        ``"transfer"`` or ``"adapt"``.
    save : bool
        Whether the job writes an output file (else its record is its whole result).
    """

    kind: ClassVar[str] = ""
    suffix: ClassVar[str] = ""
    save = True

    @property
    def output_name(self) -> str:
        """The output file's name, in the batch's output folder."""
        return self.name + self.suffix

    @property
    def spec_hash(self) -> str:
        """A digest of everything the job is (its class, inputs and options): a finished
        job counts as done for a rerun only when its record carries the same digest."""
        return hashlib.sha1(repr(self).encode()).hexdigest()[:16]

    def columns(self) -> dict:
        """The job's inputs, as the results table's columns."""
        raise NotImplementedError

    def run(self, context) -> dict:
        """Compute, write the output at ``context.output_path(self)``, and return the
        row's other columns (scores, stage times)."""
        raise NotImplementedError

    def output_complete(self, path: Path, record: dict) -> bool:
        """Whether the output at `path` is the complete file the record describes."""
        try:
            return path.stat().st_size == record.get("output_bytes")
        except OSError:
            return False


@dataclass(frozen=True)
class TransferJob(Job):
    """Put the expression of a source person's expressive scan on a target person.

    Parameters
    ----------
    name : str
        Output stem (``OUT/<name>.npz``).
    source_neutral, source_expressive, target : path
        Scans (``.bnt`` or a mesh), each with its landmark file beside it (``.lm3``,
        ``.csv`` or ``.json``) unless given below; a scan without one has its
        landmarks detected (the job's warnings say so).
    action_units : str
        What to transfer: ``"12"``, ``"12L"``, ``"1,4,15"``, ``"12:0.5,15"`` or an
        emotion (``"sadness"``).
    magnitude : float
        m in [0, 1].
    options : TransferOptions
    grid : (int, int)
        The grid every scan is resampled to.
    source_neutral_landmarks, source_expressive_landmarks, target_landmarks : path, optional
    truth : path, optional
        The target's own scan of the expression. With ``_gt.npz`` sidecars beside it
        and beside the target, the job is scored exactly; without, against the scan's
        surface when the batch asks for it.
    save : bool
        Write the output. False scores only: the record is all the job leaves (an
        evaluation over thousands of pairs need not keep a megabyte per pair).

    The output holds ``TransferResult.to_npz_dict()``: ``vertices``, ``neutral`` and
    ``mask`` in the target scan's frame, and more.
    """

    name: str
    source_neutral: str
    source_expressive: str
    target: str
    action_units: str
    magnitude: float = 1.0
    options: TransferOptions = field(default_factory=TransferOptions)
    grid: tuple = (150, 150)
    source_neutral_landmarks: str | None = None
    source_expressive_landmarks: str | None = None
    target_landmarks: str | None = None
    truth: str | None = None
    save: bool = True

    kind: ClassVar[str] = "transfer"
    suffix: ClassVar[str] = ".npz"

    def __post_init__(self):
        set_ = object.__setattr__  # frozen: normalise once, here
        set_(self, "name", _check_name(self.name))
        for attr in ("source_neutral", "source_expressive", "target"):
            set_(self, attr, _path(getattr(self, attr), attr))
        for attr in ("source_neutral_landmarks", "source_expressive_landmarks", "target_landmarks", "truth"):
            set_(self, attr, _optional_path(getattr(self, attr), attr))
        if not isinstance(self.action_units, str) or not self.action_units.strip():
            raise ValueError(f"action_units must be a non-empty string, got {self.action_units!r}")
        shipped_library().parse(self.action_units)  # an unknown AU is refused now, not in a worker
        try:
            magnitude = float(self.magnitude)
        except (TypeError, ValueError):
            raise ValueError(f"magnitude must be a number, got {self.magnitude!r}") from None
        if not math.isfinite(magnitude):
            raise ValueError(f"magnitude must be finite, got {self.magnitude!r}")
        set_(self, "magnitude", magnitude)
        if not isinstance(self.options, TransferOptions):
            raise ValueError(f"options must be a TransferOptions, got {type(self.options).__name__}")
        set_(self, "grid", _check_grid(self.grid))

    def columns(self) -> dict:
        return dict(source_neutral=self.source_neutral, source_expressive=self.source_expressive,
                    target=self.target, action_units=self.action_units, magnitude=self.magnitude,
                    method=self.options.method, truth=self.truth)

    def transfer(self, source_neutral, source_expressive, target):
        """The one call into the expression-transfer pipeline (FaceGrids in, a
        TransferResult out); a subclass may wrap it."""
        return transfer(source_neutral, source_expressive, target, self.action_units, self.magnitude,
                        options=self.options)

    def run(self, context) -> dict:
        grids = [context.face(self.source_neutral, self.source_neutral_landmarks, self.grid),
                 context.face(self.source_expressive, self.source_expressive_landmarks, self.grid),
                 context.face(self.target, self.target_landmarks, self.grid)]
        result = self.transfer(*grids)
        arrays = result.to_npz_dict()
        row = dict(stage_seconds=dict(result.timings))
        row.update(context.score_transfer(self, arrays, grids[2]))
        if self.save:
            io.write_npz(context.output_path(self), **arrays)
        return row

    def output_complete(self, path: Path, record: dict) -> bool:
        if not self.save:
            return True  # the record is the whole result
        if not super().output_complete(path, record):
            return False
        try:  # the zip's directory is at its end: a cut-off file has none
            with zipfile.ZipFile(path) as archive:
                members = set(archive.namelist())
        except (OSError, zipfile.BadZipFile):
            return False
        return {"vertices.npy", "neutral.npy", "mask.npy"} <= members


@lru_cache(maxsize=1)
def _adapt_keywords() -> frozenset:
    return frozenset(item.name for item in fields(AdaptOptions))


@dataclass(frozen=True)
class AdaptJob(Job):
    """Fit a template mesh to a scan (:func:`tpscore.adapt`).

    Parameters
    ----------
    name : str
        Output stem (``OUT/<name>.obj``: the template's faces, fitted vertices in the
        scan's frame).
    scan : path
        A ``.bnt`` scan or a mesh.
    template : path
        The template mesh (any format :func:`tpscore.read_mesh` reads).
    template_landmarks : path
        Its feature points (``.lm3``, ``.csv`` or ``.json``).
    scan_landmarks : path, optional
        Default: the landmark file beside the scan, else landmarks detected from it.
    options : mapping
        Fields of :class:`tpscore.AdaptOptions` (``levels``, ``refinement``, ...).
    save : bool
        Write the fitted mesh (False: score only, as in :class:`TransferJob`).

    With a ``_gt.npz`` sidecar beside the scan whose mesh is the template's (the same
    vertices), the job is scored: the per-vertex RMS (mm) over the template vertices
    within 80 mm of its nose tip.
    """

    name: str
    scan: str
    template: str
    template_landmarks: str
    scan_landmarks: str | None = None
    options: tuple = ()
    save: bool = True

    kind: ClassVar[str] = "adapt"
    suffix: ClassVar[str] = ".obj"

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "name", _check_name(self.name))
        for attr in ("scan", "template", "template_landmarks"):
            set_(self, attr, _path(getattr(self, attr), attr))
        set_(self, "scan_landmarks", _optional_path(self.scan_landmarks, "scan_landmarks"))
        items = dict(self.options).items() if self.options else ()
        unknown = sorted(k for k, _ in items if k not in _adapt_keywords())
        if unknown:
            raise ValueError(f"options: {', '.join(map(repr, unknown))} not a field of tpscore.AdaptOptions "
                             f"(known: {', '.join(sorted(_adapt_keywords()))})")
        # a sorted tuple: hashable, and one order for the job's digest
        set_(self, "options", tuple(sorted(items)))

    def columns(self) -> dict:
        return dict(scan=self.scan, template=self.template,
                    options=";".join(f"{k}={v}" for k, v in self.options))

    def adapt(self, template, scan, template_landmarks, scan_landmarks):
        """The one call into template adaptation; a subclass may wrap it."""
        return adapt(template, scan, template_landmarks, scan_landmarks, options=AdaptOptions(**dict(self.options)))

    def run(self, context) -> dict:
        template_vertices, template_faces = context.mesh(self.template)
        template_landmarks = context.landmarks(self.template_landmarks)
        scan, scan_landmarks = context.scan_mesh(self.scan, self.scan_landmarks)
        start = context.clock()
        result = self.adapt((template_vertices, template_faces), scan, template_landmarks, scan_landmarks)
        row = dict(stage_seconds={"adapt": context.clock() - start}, best_level=int(result.best_level))
        sidecar = Path(_stem(self.scan) + "_gt.npz")
        if sidecar.is_file():
            nose = template_landmarks[LANDMARK_NAMES.index("Nose tip")] if len(template_landmarks) == len(
                LANDMARK_NAMES) else np.full(3, np.nan)
            near = (np.linalg.norm(template_vertices - nose, axis=1) < ADAPT_SCORE_RADIUS_MM
                    if np.isfinite(nose).all() else None)
            try:
                row.update(rms_mm=adaptation_rms(result.vertices, sidecar, near), score_source="sidecar")
            except ValueError:
                pass  # a sidecar of another mesh than the template's: nothing to score against
        if self.save:
            io.write_mesh(context.output_path(self), result.vertices, template_faces)
        return row

    def output_complete(self, path: Path, record: dict) -> bool:
        return True if not self.save else super().output_complete(path, record)


# --------------------------------------------------------------------------- the Bosphorus layout

def code_label(code: str) -> str | None:
    """The action-unit request a Bosphorus expression code shows (``"LFAU_12_0"`` ->
    ``"12"``, ``"CAU_A22A25_0"`` -> ``"22+25"``, ``"E_HAPPY_0"`` -> ``"happiness"``, a
    whole expression), or None for codes that are no AU or emotion (neutral, poses,
    occlusions)."""
    match = _AU_CODE.match(code)
    if match:
        return match.group(1)
    match = _COMBINATION_CODE.match(code)
    if match:
        parts = match.group(1)
        return "+".join(re.findall(r"[0-9]+[LR]?", parts))
    match = _EMOTION_CODE.match(code)
    if match:
        return _EMOTIONS.get(match.group(1))
    return None


def scan_layout(folder) -> dict[int, dict[str, str]]:
    """The scans of a folder in the Bosphorus layout: subject number -> code -> path of
    ``bsNNN/bsNNN_<CODE>.bnt``.

    Raises
    ------
    ValueError
        Naming the folder when it does not exist or holds no ``bsNNN`` folder with scans.
    """
    root = Path(folder)
    if not root.is_dir():
        raise ValueError(f"{str(folder)!r}: folder not found")
    layout: dict[int, dict[str, str]] = {}
    for sub in sorted(root.iterdir()):
        match = _SUBJECT.match(sub.name)
        if not (match and sub.is_dir()):
            continue
        prefix = sub.name + "_"
        scans = {p.stem[len(prefix):]: os.path.abspath(p) for p in sorted(sub.glob(prefix + "*.bnt"))}
        if scans:
            layout[int(match.group(1))] = scans
    if not layout:
        raise ValueError(f"{str(folder)!r}: no bsNNN/bsNNN_<CODE>.bnt scans in it (the Bosphorus layout)")
    return layout


def _normalise_label(label) -> str:
    text = str(label).strip()
    if text.upper().startswith("AU"):
        text = text[2:]
    return text.lower() if text.isalpha() else text.upper()


def _select(wanted, available, what: str) -> list[int]:
    if wanted is None:
        return sorted(available)
    chosen = sorted({int(s) for s in wanted})
    missing = [s for s in chosen if s not in available]
    if missing:
        raise ValueError(f"{what}: subject(s) {missing} have no scans in the folder")
    return chosen


def _pairs(sources, targets, pairs: str) -> list[tuple[int, int]]:
    if pairs == "all":
        return [(s, t) for s in sources for t in targets if s != t]
    match = re.fullmatch(r"next-(\d+)", pairs)
    if not match or int(match.group(1)) < 1:
        raise ValueError(f"pairs must be 'all' or 'next-K' with K >= 1, got {pairs!r}")
    k = int(match.group(1))
    order = sorted(set(targets))
    out = []
    for s in sources:
        # the k targets that follow the source's number, wrapping around
        following = [t for t in order if t > s] + [t for t in order if t < s]
        out += [(s, t) for t in following[:k]]
    return out


def transfer_jobs(folder, *, action_units=None, sources=None, targets=None, pairs: str = "all",
                  magnitude: float = 1.0, options: TransferOptions = TransferOptions(),
                  grid=(150, 150), neutral: str = NEUTRAL_CODE) -> list[TransferJob]:
    """Transfer jobs over a folder in the Bosphorus layout.

    For each source subject and each expression it has a scan of, the expression is
    put on each of the source's targets: the source's neutral and expressive scans,
    the target's neutral scan, and as truth the target's own scan of the expression
    when it has one.

    Parameters
    ----------
    folder : path
        ``bsNNN/bsNNN_<CODE>.bnt`` with the ``.lm3`` beside each scan.
    action_units : sequence of str, optional
        AU labels (``"12"``, ``"12L"``, ``"AU1"``) or emotions (``"sadness"``) to
        transfer, each matched to its Bosphorus code (``LFAU_12_0``, ``E_SADNESS_0``);
        default every code in the folder that shows an AU or emotion tpscore knows.
    sources, targets : sequence of int, optional
        Subject numbers (default all).
    pairs : str
        ``"all"``: every source to every other target; ``"next-K"``: each source to the
        K targets that follow its number (wrapping around).
    magnitude, options, grid
        As in :class:`TransferJob`.
    neutral : str
        The code of the neutral scans.

    Returns
    -------
    list of TransferJob
        Named ``bsSSS_<CODE>__bsTTT``, ordered by source, expression, target (jobs
        next to each other share scans, which a worker's cache keeps).

    Raises
    ------
    ValueError
        Naming the folder, an unknown AU, a subject with no scans, or a bad `pairs`.
    """
    layout = scan_layout(folder)
    with_neutral = {s for s, scans in layout.items() if neutral in scans}
    sources = _select(sources, layout, "sources")
    targets = _select(targets, layout, "targets")
    wanted = None
    if action_units is not None:
        wanted = {}
        for label in action_units:
            normalised = _normalise_label(label)
            shipped_library().parse(normalised)  # ValueError naming an unknown AU or emotion
            wanted[normalised] = str(label)
    targets_of: dict[int, list[int]] = {}
    for s, t in _pairs(sources, targets, pairs):
        if s in with_neutral and t in with_neutral:
            targets_of.setdefault(s, []).append(t)
    jobs, shown = [], set()
    for s in sources:
        for code, path in layout[s].items():
            label = code_label(code)
            if label is None or (wanted is not None and label not in wanted):
                continue
            if wanted is None:
                try:
                    shipped_library().parse(label)
                except ValueError:
                    continue  # an AU the library does not have (a user's own library may lack some)
            shown.add(label)
            for t in targets_of.get(s, ()):
                name = f"bs{s:03d}_{code}__bs{t:03d}" + (f"_m{magnitude:g}" if magnitude != 1.0 else "")
                jobs.append(TransferJob(name, layout[s][neutral], path, layout[t][neutral], label, magnitude,
                                        options, grid, truth=layout[t].get(code)))
    absent = sorted(set(wanted or ()) - shown)
    if absent:
        raise ValueError(f"action_units: no source scan in {str(folder)!r} shows {', '.join(map(repr, absent))}")
    return jobs


def adapt_jobs(folder, template, template_landmarks, *, subjects=None, codes=None, options=None) -> list[AdaptJob]:
    """One :class:`AdaptJob` per scan of a folder in the Bosphorus layout.

    Parameters
    ----------
    folder : path
    template, template_landmarks : path
        The template mesh and its feature points.
    subjects : sequence of int, optional
        Default all.
    codes : sequence of str, optional
        Expression codes of the scans to fit (``"N_N_0"``, ...); default every scan.
    options : mapping, optional
        Keyword arguments of :func:`tpscore.adapt`.

    Returns
    -------
    list of AdaptJob
        Named after the scans (``bsNNN_<CODE>``).
    """
    layout = scan_layout(folder)
    subjects = _select(subjects, layout, "subjects")
    codes = None if codes is None else set(codes)
    return [AdaptJob(f"bs{s:03d}_{code}", path, template, template_landmarks, options=tuple((options or {}).items()))
            for s in subjects for code, path in layout[s].items() if codes is None or code in codes]


# --------------------------------------------------------------------------- manifests

_TRANSFER_COLUMNS = {"source_neutral", "source_expressive", "target", "au"}
_ADAPT_COLUMNS = {"scan", "template", "template_landmarks"}
_KNOWN_COLUMNS = _TRANSFER_COLUMNS | _ADAPT_COLUMNS | {
    "kind", "name", "magnitude", "method", "options", "truth", "grid", "scan_landmarks",
    "source_neutral_landmarks", "source_expressive_landmarks", "target_landmarks"}


def setting_value(text: str):
    """A setting's value written as text (a manifest's options, a benchmark's command
    line): a flag (``true``/``false``), an int, a float, or else the word itself."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text.strip()


def _parse_settings(text: str) -> dict:
    """``"key=value; key=value"`` as a dict of typed values."""
    out = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"options item {item!r} is not key=value")
        out[key.strip()] = setting_value(value)
    return out


def transfer_options(method: str = "default", settings: str = "") -> TransferOptions:
    """TransferOptions from a method name and ``"key=value; motion.key=value"`` text
    (nested options as ``motion.`` or ``texture.``)."""
    if method not in ("default", "published"):
        raise ValueError(f"method must be 'default' or 'published', got {method!r}")
    base = TransferOptions.published() if method == "published" else TransferOptions()
    top, nested = {}, {"motion": {}, "texture": {}}
    names = {f.name for f in fields(TransferOptions)}
    for key, value in _parse_settings(settings).items():
        group, dot, inner = key.partition(".")
        if dot and group in nested:
            nested[group][inner] = value
        elif not dot and key in names and key not in nested:
            top[key] = value
        else:
            raise ValueError(f"options: {key!r} is not a TransferOptions field "
                             "(use motion.NAME or texture.NAME for the nested ones)")
    try:
        motion = replace(base.motion, **nested["motion"])
        texture = replace(base.texture, **nested["texture"])
    except TypeError as exc:  # an unknown field of MotionOptions or TextureOptions
        raise ValueError(f"options: {exc}") from None
    return replace(base, motion=motion, texture=texture, **top)


def read_manifest(path, *, grid=(150, 150)) -> list[Job]:
    """Jobs from a CSV manifest, one a row.

    The header names the columns. ``kind`` is ``transfer`` (the default) or ``adapt``.
    A transfer row needs ``source_neutral``, ``source_expressive``, ``target`` and
    ``au``, and may give ``magnitude``, ``method`` (``default`` or ``published``),
    ``options`` (``key=value; motion.key=value``), ``truth``, ``grid`` (``150x150``)
    and the three ``*_landmarks``. An adapt row needs ``scan``, ``template`` and
    ``template_landmarks``, and may give ``scan_landmarks`` and ``options``
    (keywords of :func:`tpscore.adapt`). Both may give ``name`` (default: from the
    file names). Relative paths are relative to the manifest's folder; blank rows and
    rows whose first cell starts with ``#`` are skipped.

    Raises
    ------
    ValueError
        Naming the manifest and the line: a missing column, a bad value, a duplicate
        name.
    """
    where = repr(str(path))
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise ValueError(f"{where}: manifest not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{where}: cannot read the manifest ({exc})") from None
    if not rows:
        raise ValueError(f"{where}: the manifest is empty (it needs a header row)")
    header = [h.strip().lower() for h in rows[0]]
    unknown = [h for h in header if h not in _KNOWN_COLUMNS]
    if unknown:
        raise ValueError(f"{where}: unknown column(s) {unknown}; known: {', '.join(sorted(_KNOWN_COLUMNS))}")
    base = Path(path).resolve().parent
    jobs: list[Job] = []
    seen: dict[str, int] = {}
    for number, cells in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if len(cells) > len(header):
            raise ValueError(f"{where}: line {number}: {len(cells)} cells, the header has {len(header)}")
        row = {h: c.strip() for h, c in zip(header, cells) if c.strip()}

        def at(key, _row=row):
            return str(base / _row[key]) if key in _row else None

        try:
            kind = row.get("kind", "transfer")
            required = {"transfer": _TRANSFER_COLUMNS, "adapt": _ADAPT_COLUMNS}.get(kind)
            if required is None:
                raise ValueError(f"kind must be 'transfer' or 'adapt', got {kind!r}")
            missing = sorted(required - row.keys())
            if missing:
                raise ValueError(f"a {kind} row needs {', '.join(missing)}")
            if kind == "transfer":
                magnitude = float(row.get("magnitude", 1.0))
                name = row.get("name") or (Path(row["source_expressive"]).stem + "__" + Path(row["target"]).stem
                                           + (f"_m{magnitude:g}" if magnitude != 1.0 else ""))
                row_grid = grid
                if "grid" in row:
                    row_grid = tuple(int(v) for v in row["grid"].lower().split("x"))
                job = TransferJob(name, at("source_neutral"), at("source_expressive"), at("target"), row["au"],
                                  magnitude, transfer_options(row.get("method", "default"), row.get("options", "")),
                                  row_grid, at("source_neutral_landmarks"), at("source_expressive_landmarks"),
                                  at("target_landmarks"), at("truth"))
            else:
                name = row.get("name") or Path(row["scan"]).stem
                job = AdaptJob(name, at("scan"), at("template"), at("template_landmarks"), at("scan_landmarks"),
                               tuple(_parse_settings(row.get("options", "")).items()))
        except ValueError as exc:
            raise ValueError(f"{where}: line {number}: {exc}") from None
        if job.name in seen:
            raise ValueError(f"{where}: line {number}: name {job.name!r} is already the name of line "
                             f"{seen[job.name]}; give the rows distinct names (a 'name' column)")
        seen[job.name] = number
        jobs.append(job)
    if not jobs:
        raise ValueError(f"{where}: the manifest has no job rows")
    return jobs
