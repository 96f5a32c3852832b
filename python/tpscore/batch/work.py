"""Running one job where it lands: in a Dask worker, or in this process.

:func:`execute` is the task the engine submits. It runs the job, catches what the job's
inputs can do wrong, writes the job's record beside its output and returns that record
(a small dict: the engine never moves arrays). Each worker process keeps a bounded
cache of recently read scans, so jobs that share a source read it once.
"""
from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._threads import set_num_threads
from ..face import io
from .._files import atomic_write
from ..face.detect import LandmarksDetectedWarning
from ..face.grid import FaceGrid
from ..face.loading import load_scan
from ..face.scan_files import read_scan_landmarks, read_scan_surface
from .scores import score_with_scan, score_with_sidecars

__all__ = ["WorkSettings", "ScanCache", "JobContext", "execute", "read_record", "record_path",
           "RECORDS_FOLDER"]

#: The records of finished jobs, one JSON file per job, in this folder of the output.
RECORDS_FOLDER = "records"

# Errors that say nothing about the job's inputs (a full disk, a network share gone, a
# worker out of memory): they are raised to the engine, which retries the job.
_TRANSIENT = (OSError, MemoryError)


@dataclass(frozen=True)
class WorkSettings:
    """What every job of a batch shares, sent with each task.

    Attributes
    ----------
    out : str
        The output folder (absolute; every worker must see it at this path).
    gt_faces : str or None
        An ``.npz`` with ``faces``: the triangles of the ``_gt.npz`` sidecars' meshes.
        With it, transfers whose target has sidecars are scored exactly.
    truth : bool
        Score transfers without sidecars against the target's real scan of the
        expression (``TransferJob.truth``).
    cache_scans : int
        The most scans (and meshes) a worker process keeps between jobs.
    kernel_threads : dict
        Threads of the compiled kernels per worker host name (the host's cores shared
        among the jobs that run on it at once); hosts not named keep their default,
        and ``TPSCORE_NUM_THREADS`` in a worker's environment wins.
    """

    out: str
    gt_faces: str | None = None
    truth: bool = False
    cache_scans: int = 8
    kernel_threads: tuple = ()


class ScanCache:
    """The most recently used scans, meshes and landmark sets of a process, at most
    `size` of them, keyed by path, file size and modification time (a rewritten file
    is read again). Thread-safe: a Dask worker may run several jobs at once."""

    def __init__(self, size: int):
        self.size = size
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, load):
        """The cached value for `key`, else ``load()`` (timed), cached. Returns (value,
        seconds spent loading: 0 on a hit)."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key], 0.0
        start = time.perf_counter()
        value = load()  # outside the lock: two threads may read one file, never block each other
        seconds = time.perf_counter() - start
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value, seconds

    def __len__(self) -> int:
        return len(self._items)


_CACHE: ScanCache | None = None
_CACHE_LOCK = threading.Lock()


def _process_cache(size: int) -> ScanCache:
    global _CACHE
    with _CACHE_LOCK:
        if _CACHE is None or _CACHE.size != size:
            _CACHE = ScanCache(size)
        return _CACHE


def _file_key(kind: str, path: str, *extra):
    try:
        stat = os.stat(path)
    except OSError:
        raise ValueError(f"{path!r}: file not found") from None
    return (kind, path, stat.st_size, stat.st_mtime_ns, *extra)


class JobContext:
    """What a job may ask of the process it runs in: cached inputs, its output path,
    scoring, and the time spent reading."""

    def __init__(self, settings: WorkSettings, cache: ScanCache):
        self.settings = settings
        self.cache = cache
        self.load_seconds = 0.0
        self.loads = 0

    @staticmethod
    def clock() -> float:
        return time.perf_counter()

    def output_path(self, job) -> Path:
        return Path(self.settings.out) / job.output_name

    def _cached(self, key, load, counted: bool = True):
        value, seconds = self.cache.get(key, load)
        if seconds and counted:
            self.load_seconds += seconds
            self.loads += 1
        return value

    def face(self, path: str, landmarks: str | None, shape) -> FaceGrid:
        """A scan resampled to a face grid, with its landmarks: the given file, else the
        one beside the scan, else detected from the scan, which the job's warnings
        say (every job that uses the scan, though it is detected once)."""
        key = _file_key("face", path, tuple(shape))  # a missing scan is the error to report first
        landmarks = landmarks or io.landmark_file_beside(path)
        if landmarks is None:
            warnings.warn(f"{path!r}: no landmark file beside it (looked for .lm3, .csv, .json): landmarks "
                          "detected from the scan", LandmarksDetectedWarning, stacklevel=2)
            return self._cached(key + ("detected landmarks",), lambda: load_scan(path, "auto", shape=shape))
        key += _file_key("landmarks", str(landmarks))
        return self._cached(key, lambda: load_scan(path, landmarks, shape=shape))

    def mesh(self, path: str):
        """(vertices, faces) of a mesh file; a mesh without faces is refused."""
        def load():
            vertices, faces = io.read_mesh(path)
            if len(faces) == 0:
                raise ValueError(f"{path!r}: the template has no faces; adaptation needs a mesh")
            return vertices, faces
        return self._cached(_file_key("mesh", path), load)

    def landmarks(self, path: str) -> np.ndarray:
        return self._cached(_file_key("landmarks", path), lambda: io.read_landmarks(path))

    def scan_mesh(self, path: str, landmarks: str | None):
        """((vertices, faces), landmarks) of a scan to fit: a ``.bnt``'s own lattice
        triangulated, or a mesh file."""
        surface = self._cached(_file_key("scan-mesh", path), lambda: read_scan_surface(path))
        landmarks = landmarks or io.landmark_file_beside(path)
        if landmarks is None:
            return surface, read_scan_landmarks(path)  # detected, with a warning
        return surface, self.landmarks(str(landmarks))

    def gt_faces(self) -> np.ndarray:
        path = self.settings.gt_faces

        def load():
            try:
                with np.load(path, allow_pickle=False) as data:
                    return np.asarray(data["faces"], dtype=np.int64)
            except KeyError:
                raise ValueError(f"{path!r}: gt_faces file has no 'faces' array") from None
            except (OSError, ValueError) as exc:
                raise ValueError(f"{path!r}: gt_faces is not a readable .npz ({exc})") from None
        # not an input of the job: kept out of its reading time
        return self._cached(_file_key("gt-faces", path), load, counted=False)

    def score_transfer(self, job, arrays: dict, target: FaceGrid) -> dict:
        """The scores of a finished transfer: exact where the target's sidecars and the
        sidecars' triangles are known, else against the truth scan when asked, else
        none."""
        if job.truth is None:
            return {}
        sidecars = [os.path.splitext(p)[0] + "_gt.npz" for p in (job.target, job.truth)]
        if self.settings.gt_faces and all(os.path.isfile(p) for p in sidecars):
            scores = score_with_sidecars(arrays["vertices"], arrays["neutral"], arrays["mask"], *sidecars,
                                         self.gt_faces())
            return dict(scores, score_source="sidecar")
        if self.settings.truth and os.path.isfile(job.truth):
            truth = self.face(job.truth, None, target.shape)
            scores = score_with_scan(arrays["vertices"], arrays["neutral"], arrays["mask"], truth, target)
            return dict(scores, score_source="scan")
        return {}


def record_path(out, name: str) -> Path:
    return Path(out) / RECORDS_FOLDER / f"{name}.json"


def read_record(out, name: str) -> dict | None:
    """A job's record, or None when it has none or it is unreadable."""
    try:
        with open(record_path(out, name), encoding="utf-8") as fh:
            record = json.load(fh)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _json_value(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(value) else float(value)
    if isinstance(value, dict):
        return {str(k): _json_value(v) for k, v in value.items()}
    return value


def _worker_name() -> str:
    try:
        from distributed import get_worker
        worker = get_worker()
    except (ImportError, ValueError):
        return f"local-{os.getpid()}"
    return str(worker.name)


def _version() -> str:
    import tpscore  # the package's own __init__ sets it, after this module is imported

    return tpscore.__version__


def _set_kernel_threads(settings: WorkSettings) -> None:
    if os.environ.get("TPSCORE_NUM_THREADS"):
        return
    threads = dict(settings.kernel_threads).get(socket.gethostname())
    if threads:
        set_num_threads(int(threads))


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    # a ValueError of tpscore names the file or argument already; other types say what broke
    return text if type(exc) is ValueError else f"{type(exc).__name__}: {text}"


def execute(job, settings: WorkSettings) -> dict:
    """Run one job and write its record; return the record.

    A job whose inputs are bad (a truncated file, a missing landmark file, ...) or that
    fails in the computation gets status ``"failed"`` and a one-line ``error``, and
    leaves no output. Errors of the machine rather than the job (``OSError``,
    ``MemoryError``) are raised, so that the engine retries the job.

    Parameters
    ----------
    job : Job
    settings : WorkSettings

    Returns
    -------
    dict
        The job's row of the results table.
    """
    _set_kernel_threads(settings)
    context = JobContext(settings, _process_cache(settings.cache_scans))
    output = context.output_path(job)
    started = time.time()
    clock = time.perf_counter()
    cpu = time.process_time()
    row = dict(name=job.name, kind=job.kind, status="done", error="", **job.columns())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            row.update(job.run(context))
        except _TRANSIENT:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of one job must not stop the batch
            row.update(status="failed", error=_one_line(exc))
    seconds = time.perf_counter() - clock
    # the process's CPU time: well below `seconds` when the machine's cores are shared
    cpu_seconds = time.process_time() - cpu
    if row["status"] == "done" and job.save and not output.is_file():
        row.update(status="failed", error=f"the job wrote no output at {str(output)!r}")
    messages = list(dict.fromkeys(" ".join(str(w.message).split()) for w in caught))
    if row["status"] == "failed":
        # an output of an earlier run would be taken for this job's
        output.unlink(missing_ok=True)
    saved = row["status"] == "done" and job.save
    row.update(
        seconds=seconds, cpu_seconds=cpu_seconds, worker=_worker_name(), host=socket.gethostname(), started=started,
        output=str(output) if saved else "", output_bytes=output.stat().st_size if saved else None,
        tpscore_version=_version(),
        load_seconds=context.load_seconds, loads=context.loads,
        warnings=" | ".join(messages)[:500], spec_hash=job.spec_hash)
    row = {key: _json_value(value) for key, value in row.items()}
    # written after the output: a record says the output beside it is complete
    path = record_path(settings.out, job.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(row, indent=1).encode())
    return row
