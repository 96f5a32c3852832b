"""How the cost of a transfer and of one registration grows with the grid and the scan.

Two sweeps over development subjects made by ../shared/tools/make_scans.py (AU12, each
subject's expression put on the next subject):

* **grid**: the default scans (0.7 mm depth pixels) resampled to 150, 225 and 300
  vertices a side;
* **scan**: scans made at 0.7, 0.5 and 0.35 mm depth pixels (about 2 and 4 times the
  points, with colour images as fine), resampled to the default 150 x 150 grid and to a
  grid as fine as the scan.

Each row gives the median over the pairs (wall time, the machine otherwise idle as far
as it can be): the three scans loaded (tpscore.load_scans), the transfer and its
stages, and the registration alone (register_surfaces, the texture matches given),
with the growth against the first row beside the growth of n log n (n the grid's
vertices). Writes bench-output/transfer_scale.md; skips when ../shared is absent.

    python benchmarks/transfer_scale.py [--subjects 0-5] [--repeats 1]
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity import ensure_scans, parse_subjects, scan_path, shared_dir  # noqa: E402

import tpscore  # noqa: E402
from tpscore.expression.action_units import default_library  # noqa: E402
from tpscore.expression.modelling import align_expressive, still_weight  # noqa: E402
from tpscore.expression.registration import register_surfaces  # noqa: E402
from tpscore.expression.texture import track_texture  # noqa: E402
from tpscore.face.average_face import load_average_face  # noqa: E402
from tpscore.face.normalise import normalise_face  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "bench-output"
CODES = ["N_N_0", "LFAU_12_0"]


def one_pair(scans: Path, source: int, target: int, side: int) -> dict:
    """Seconds of each step of one transfer (source's AU12 onto target) on a side x side grid."""
    paths = [f"{scan_path(scans, subject, code)}.bnt"
             for subject, code in ((source, "N_N_0"), (source, "LFAU_12_0"), (target, "N_N_0"))]
    start = time.perf_counter()
    grids = tpscore.load_scans(paths, shape=(side, side))
    loaded = time.perf_counter()
    result = tpscore.transfer(*grids, "12")
    done = time.perf_counter()
    row = {"load": loaded - start, "transfer": done - loaded, "total": done - start}
    row.update({f"stage {name}": seconds for name, seconds in result.timings.items()})
    # the registration alone, as the transfer runs it (texture matches given)
    reference = load_average_face().as_normalised_face()
    neutral = normalise_face(grids[0], reference.landmarks)
    library = default_library()
    still = still_weight(grids[1], library.parse("12"), library, reference.landmarks)
    expressive = align_expressive(neutral, grids[0], grids[1], still)
    texture = track_texture(neutral.grid, expressive.grid)
    surface = expressive.surface()
    begin = time.perf_counter()
    register_surfaces(neutral.grid.points, neutral.grid.mask, neutral.landmarks, surface,
                      expressive.landmarks, texture=texture)
    row["registration"] = time.perf_counter() - begin
    row["vertices"] = int(grids[0].mask.sum())
    row["scan points"] = int(np.isfinite(tpscore.read_bnt(paths[0]).points).all(axis=-1).sum())
    return row


def sweep(label: str, scans: Path, subjects: list[int], side: int, repeats: int) -> dict:
    rows = []
    one_pair(scans, subjects[0], subjects[0] + 1, side)      # warm-up (imports, caches)
    for _ in range(repeats):
        for subject in subjects:
            rows.append(one_pair(scans, subject, subject + 1, side))
    summary = {key: statistics.median(row[key] for row in rows) for key in rows[0]}
    summary["label"] = label
    summary["side"] = side
    print(f"{label:34s} grid {side:3d}: load {summary['load']:.3f} s, transfer {summary['transfer']:.3f} s, "
          f"registration {summary['registration']:.3f} s", flush=True)
    return summary


def table(rows: list[dict]) -> list[str]:
    first = rows[0]

    def n_log_n(row):
        return row["vertices"] * math.log(row["vertices"])

    lines = ["| scans | grid | scan points | grid vertices | load (3 scans) | transfer | of which texture "
             "| registration | total | total / first | registration / first | n log n / first |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(
            f"| {row['label']} | {row['side']} | {round(row['scan points']):,} | {round(row['vertices']):,} "
            f"| {1e3 * row['load']:.0f} ms | {1e3 * row['transfer']:.0f} ms "
            f"| {1e3 * row.get('stage texture', float('nan')):.0f} ms | {1e3 * row['registration']:.0f} ms "
            f"| {1e3 * row['total']:.0f} ms | {row['total'] / first['total']:.2f} "
            f"| {row['registration'] / first['registration']:.2f} | {n_log_n(row) / n_log_n(first):.2f} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", default="0-5", help="source subjects (each onto the next), e.g. 0-5")
    parser.add_argument("--repeats", type=int, default=1, help="times each pair is run")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    shared = shared_dir()
    if shared is None:
        print("transfer scale benchmark skipped: ../shared (make_scans.py, the ICT face model) not found")
        return 0
    warnings.simplefilter("ignore")
    subjects = parse_subjects(args.subjects)
    everyone = sorted(set(subjects) | {s + 1 for s in subjects})
    rows = []
    default_scans = args.out / "scans"
    ensure_scans(shared, default_scans, everyone, codes=CODES)
    for side in (150, 225, 300):
        rows.append(sweep("0.7 mm depth pixels (default)", default_scans, subjects, side, args.repeats))
    for spacing, side in ((0.5, 150), (0.5, 210), (0.35, 150), (0.35, 300)):
        folder = args.out / f"scans-{spacing:g}mm"
        ensure_scans(shared, folder, everyone, ["--spacing-mm", f"{spacing:g}"], codes=CODES)
        rows.append(sweep(f"{spacing:g} mm depth pixels", folder, subjects, side, args.repeats))
    machine = (f"{tpscore.num_threads()} threads; tpscore {tpscore.__version__}; "
               f"{len(subjects)} pairs per row, {args.repeats} run(s) each, median")
    text = "\n".join(["# Transfer cost against grid and scan size", "", machine, "", *table(rows), ""])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "transfer_scale.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
