"""The results of a batch: one row per job, written as a table, and a summary that fits
on a screen."""
from __future__ import annotations

import csv
import io as _stdio
import json
import math
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from .._files import atomic_write
from .scores import SCORE_COLUMNS

__all__ = ["BatchReport", "STATUSES", "write_table", "read_table"]

#: What became of a job: computed now, failed now, done by an earlier run (``skipped``),
#: or not run (the batch was interrupted first).
STATUSES = ("done", "failed", "skipped", "not run")

_FIRST = ("name", "kind", "status", "error", "seconds", "cpu_seconds", "worker", "action_units", "magnitude", "method",
          "source_neutral", "source_expressive", "target", "truth", "scan", "template", "options",
          *SCORE_COLUMNS, "best_level")
_LAST = ("load_seconds", "loads", "stage_seconds", "warnings", "output", "output_bytes", "started", "host",
         "tpscore_version", "spec_hash")


def _columns(rows) -> list[str]:
    present = set().union(*(row.keys() for row in rows)) if rows else set()
    middle = sorted(present - set(_FIRST) - set(_LAST))
    return [c for c in _FIRST if c in present] + middle + [c for c in _LAST if c in present]


def _cell(value):
    if value is None:
        return ""
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return value  # floats print as repr: the CSV reads back to the same numbers


def write_table(rows, stem) -> list[Path]:
    """Write the rows as ``<stem>.csv``, and as ``<stem>.parquet`` when pyarrow is
    installed; each file atomically. Returns the paths written."""
    stem = Path(stem)
    columns = _columns(rows)
    buffer = _stdio.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in columns])
    paths = [stem.with_suffix(".csv")]
    atomic_write(paths[0], buffer.getvalue().encode("utf-8"))
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return paths
    table = pa.Table.from_pylist([{c: (json.dumps(row[c], sort_keys=True) if isinstance(row.get(c), dict)
                                       else row.get(c)) for c in columns} for row in rows])
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    paths.append(stem.with_suffix(".parquet"))
    atomic_write(paths[1], sink.getvalue().to_pybytes())
    return paths


def read_table(path) -> list[dict]:
    """The rows of a results CSV, as text (ValueError naming the file when it cannot be
    read)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            return list(csv.DictReader(fh))
    except OSError as exc:
        raise ValueError(f"{str(path)!r}: cannot read the results table ({exc.strerror or exc})") from None


def _mean(values) -> float:
    values = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    return sum(values) / len(values) if values else math.nan


@dataclass
class BatchReport:
    """What a batch did.

    Attributes
    ----------
    rows : list of dict
        One per job, in the jobs' order: inputs, ``status`` (see :data:`STATUSES`),
        ``error``, ``seconds``, ``worker``, scores.
    out : Path
        The output folder.
    seconds : float
        Wall time of the run, engine start included.
    startup_seconds : float
        Time to start or reach the engine.
    workers : int
        Worker processes at the start.
    interrupted : bool
        The run was stopped (Ctrl-C) before every job was done.
    tables : list of Path
        The results tables written.
    """

    rows: list
    out: Path
    seconds: float = 0.0
    startup_seconds: float = 0.0
    workers: int = 0
    interrupted: bool = False
    tables: list = field(default_factory=list)

    def counts(self) -> dict:
        """Jobs by status."""
        counts = Counter(row["status"] for row in self.rows)
        return {status: counts.get(status, 0) for status in STATUSES}

    @property
    def throughput(self) -> float:
        """Jobs finished (done or failed) per second of this run, engine start excluded."""
        ran = self.counts()["done"] + self.counts()["failed"]
        busy = self.seconds - self.startup_seconds
        return ran / busy if ran and busy > 0 else 0.0

    def scores_by_action_unit(self) -> list[dict]:
        """Mean scores of the scored transfers, by AU request and score source."""
        groups = defaultdict(list)
        for row in self.rows:
            if row.get("kind") == "transfer" and row["status"] in ("done", "skipped") and row.get("score_source"):
                groups[(row["action_units"], row["score_source"])].append(row)
        return [dict(action_units=au, score_source=source, jobs=len(rows),
                     residual_ratio=_mean(r.get("residual_ratio") for r in rows),
                     rms_mm=_mean(r.get("rms_mm") for r in rows), leak_mm=_mean(r.get("leak_mm") for r in rows))
                for (au, source), rows in sorted(groups.items(), key=lambda item: (item[0][1], _au_order(item[0][0])))]

    def summary(self, max_errors: int = 5) -> str:
        """A one-screen summary: counts, time, throughput, the first errors, mean scores
        per AU."""
        counts = self.counts()
        lines = [f"tpscore batch: {len(self.rows)} jobs, output in {self.out}"
                 + ("  (interrupted: rerun the same command to resume)" if self.interrupted else ""),
                 f"  done {counts['done']}, failed {counts['failed']}, skipped {counts['skipped']} (done before), "
                 f"not run {counts['not run']}"]
        ran = counts["done"] + counts["failed"]
        if ran:
            lines.append(f"  time {self.seconds:.1f} s (engine start {self.startup_seconds:.1f} s); "
                         f"{self.throughput:.2f} jobs/s over the {ran} run on {self.workers} worker(s)")
        elif not self.interrupted:
            lines.append("  nothing to run: every job was done by an earlier run")
        failed = [row for row in self.rows if row["status"] == "failed"]
        if failed:
            lines.append(f"  failed ({len(failed)}):")
            lines += [f"    {row['name']}: {row['error']}"[:160] for row in failed[:max_errors]]
            if len(failed) > max_errors:
                lines.append(f"    ... {len(failed) - max_errors} more in the table")
        scores = self.scores_by_action_unit()
        if scores:
            lines.append("  scores (residual ratio: 0 exact, 1 no better than the neutral target; "
                         "sidecar: exact, scan: a lower bound)")
            lines.append(f"    {'AU':12s} {'truth':8s} {'jobs':>5s} {'ratio':>7s} {'rms mm':>7s} {'leak mm':>8s}")
            for s in scores:
                lines.append(f"    {s['action_units']:12s} {s['score_source']:8s} {s['jobs']:5d} "
                             f"{s['residual_ratio']:7.3f} {s['rms_mm']:7.2f} {s['leak_mm']:8.2f}")
        fitted = [row for row in self.rows if row.get("kind") == "adapt" and row["status"] in ("done", "skipped")
                  and row.get("rms_mm") is not None]
        if fitted:
            lines.append(f"  adaptation: {len(fitted)} scored against their sidecars, mean RMS "
                         f"{_mean(r['rms_mm'] for r in fitted):.2f} mm")
        if self.tables:
            lines.append("  table: " + ", ".join(str(p) for p in self.tables))
        return "\n".join(lines)


def _au_order(label: str):
    # AUs by number (1, 2, 4, 12, 12L, ...), emotions after them
    digits = "".join(ch for ch in label if ch.isdigit())
    return (0, int(digits), label) if digits and label[0].isdigit() else (1, 0, label)
