"""Fidelity of the physical skin: muscle-driven AUs on adapted scans, against the truth.

For each development subject (make_scans.py scans of the ICT face model), the template
head is fitted to the subject's neutral scan (``tpscore.physics.fit_head``: the
template adaptation, with the skull, muscles and jaw carried along), and each AU is
produced by contracting its muscles (``Head.contractions_for``) until the skin
settles. The settled skin's displacement is read off at each vertex of the neutral
scan's 150 x 150 grid (closest point on the fitted head; no motion where the head
does not cover the grid) and scored with ``score_transfer.py`` against the subject's
own expressive scan: residual ratio 0 is exact, 1 no better than the neutral face.

Next to it, the elastic model's muscles (``tpscore.MuscleModel`` on an
``ElasticFace`` of the same neutral grid) drive the same AUs.

One contraction level per AU and per model is chosen once, on the calibration
subjects (the level with the lowest mean ratio among ``--levels``), never per subject;
every subject is then scored at that level, and the table reports all of them, and
the subjects outside the calibration set on their own.

    python benchmarks/skin_fidelity.py [--subjects 0-19] [--calibrate 0-3]
    # on two cores, two halves of the AUs side by side, then one table:
    python benchmarks/skin_fidelity.py --aus 1 2 4 12 --name skin_a &
    python benchmarks/skin_fidelity.py --aus 14 15 17 20 --name skin_b
    python benchmarks/skin_fidelity.py --report bench-output/skin_a.json bench-output/skin_b.json

Writes bench-output/skin_fidelity.md and .json. Skips (exit 0) without ../shared.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import tpscore
from tpscore import physics

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity import AU_CODES, ensure_scans, parse_subjects, scan_path  # noqa: E402
from shared_data import load_module, shared_dir  # noqa: E402
from report import write_report  # noqa: E402

AUS = ("1", "2", "4", "12", "14", "15", "17", "20")
#: The elastic model's muscles for each AU (tpscore/data/elastic_muscles.json). Its set
#: has no buccinator: the dimpler (AU14) is made with the risorius, its nearest pull.
ELASTIC_AUS = {
    "1": {"frontalis_medial_left": 1.0, "frontalis_medial_right": 1.0},
    "2": {"frontalis_lateral_left": 1.0, "frontalis_lateral_right": 1.0},
    "4": {"corrugator_left": 1.0, "corrugator_right": 1.0, "procerus": 0.5},
    "12": {"zygomatic_major_left": 1.0, "zygomatic_major_right": 1.0},
    "14": {"risorius_left": 1.0, "risorius_right": 1.0},
    "15": {"depressor_anguli_left": 1.0, "depressor_anguli_right": 1.0},
    "17": {"mentalis": 1.0},
    "20": {"risorius_left": 1.0, "risorius_right": 1.0},
}
SKIN_LEVELS = (1 / 3, 2 / 3, 1.0)
ELASTIC_LEVELS = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.6, 0.8)
# Grid vertices farther than this from the fitted head (mm) lie outside what it covers.
COVER_MM = 3.0


class Subject:
    """A subject's neutral scan, its fitted head and physical skin, and its elastic face."""

    def __init__(self, scans: Path, subject: int):
        base = scan_path(scans, subject, "N_N_0")
        self.grid = tpscore.load_scan(str(base) + ".bnt")
        scan = tpscore.read_bnt(str(base) + ".bnt")
        landmarks = tpscore.read_landmarks(str(base) + ".lm3")
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.head, _ = physics.fit_head(scan, landmarks)
        self.fit_seconds = time.perf_counter() - start
        self.skin = physics.SkinModel(self.head)
        self.mask = self.grid.mask
        self.neutral = np.where(self.mask[..., None], self.grid.points, np.nan)
        valid = self.grid.points[self.mask]
        closest = tpscore.MeshSurface(self.head.vertices, self.head.faces).closest_point(valid)
        self.corners = self.head.faces[closest.triangles]
        self.weights = np.where((closest.distances <= COVER_MM)[:, None], closest.barycentric, 0.0)
        mesh = self.grid.mesh()
        self.elastic_index = mesh.grid_index
        # The elastic face needs every landmark of its frame; where the scan lacks one,
        # the fitted head's (the template's landmark vertex, fitted) stands in.
        landmarks = np.where(np.isfinite(self.grid.landmarks), self.grid.landmarks, self.head.landmarks)
        face = tpscore.ElasticFace(mesh.vertices, mesh.faces, landmarks=landmarks,
                                   options=tpscore.ElasticOptions(unanchored="fix"))
        self.muscles = tpscore.MuscleModel(face)

    def skin_prediction(self, au: str, level: float):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = self.skin.simulate(self.head.contractions_for({au: level}))
        moved = result.vertices - self.head.vertices
        predicted = self.neutral.copy()
        predicted[self.mask] += np.einsum("mk,mkd->md", self.weights, moved[self.corners])
        return predicted, result, [str(w.message) for w in caught]

    def elastic_prediction(self, au: str, level: float):
        contractions = {m: level * w for m, w in ELASTIC_AUS[au].items()}
        vertices = self.muscles.deform(contractions)
        predicted = np.full(self.mask.shape + (3,), np.nan)
        predicted.reshape(-1, 3)[self.elastic_index] = vertices
        return predicted


def _stats(rows, held_out):
    ratio = np.array([x["residual_ratio"] for x in rows])
    held = np.array([x["residual_ratio"] for x in rows if x["subject"] in held_out])
    return dict(mean=float(ratio.mean()), median=float(np.median(ratio)),
                held_out=float(held.mean()) if len(held) else float("nan"), worst=float(ratio.max()),
                rms=float(np.mean([x["rms_mm"] for x in rows])), leak=float(np.mean([x["leak_rms_mm"] for x in rows])))


def report(parts: list[dict]) -> str:
    """The tables of one or more runs (each over its own AUs)."""
    aus = [au for part in parts for au in part["aus"]]
    by_au = {au: part for part in parts for au in part["aus"]}
    calibration = parts[0]["calibration"]
    held_out = [s for s in parts[0]["subjects"] if s not in calibration]
    lines = [f"Subjects {parts[0]['subjects'][0]}-{parts[0]['subjects'][-1]} ({len(parts[0]['subjects'])}); "
             f"levels chosen on subjects {', '.join(map(str, calibration))}; held out: the other "
             f"{len(held_out)}.", "",
             "| AU | skin level | skin mean / median ratio | held-out mean | worst | rms mm | leak mm | clamped | "
             "elastic level | elastic mean / median ratio | held-out mean | worst | rms mm | leak mm |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    summary = []
    for au in aus:
        part = by_au[au]
        skin_level, elastic_level = part["chosen"][au]
        sk = [r for r in part["skin"] if r["au"] == au and r["level"] == skin_level and r["subject"] in part["subjects"]]
        el = part["elastic"][au]
        a, b = _stats(sk, held_out), _stats(el, held_out)
        clamped = sum(bool(x["clamped"]) for x in sk)
        lines.append(f"| {au} | {skin_level:.2f} | {a['mean']:.3f} / {a['median']:.3f} | {a['held_out']:.3f} | "
                     f"{a['worst']:.3f} | {a['rms']:.2f} | {a['leak']:.2f} | {clamped} | {elastic_level:g} | "
                     f"{b['mean']:.3f} / {b['median']:.3f} | {b['held_out']:.3f} | {b['worst']:.3f} | "
                     f"{b['rms']:.2f} | {b['leak']:.2f} |")
        summary.append((a, b))
    mean = lambda key, k: float(np.mean([pair[k][key] for pair in summary]))  # noqa: E731
    lines.append(f"| **mean** | | **{mean('mean', 0):.3f}** | {mean('held_out', 0):.3f} | | | {mean('leak', 0):.2f} "
                 f"| | | **{mean('mean', 1):.3f}** | {mean('held_out', 1):.3f} | | | {mean('leak', 1):.2f} |")
    skin_levels = sorted({r["level"] for part in parts for r in part["skin"]})
    lines += ["", "Calibration: mean ratio on the calibration subjects per contraction level:", "",
              "| AU | " + " | ".join(f"skin {lv:.2f}" for lv in skin_levels) + " | "
              + " | ".join(f"elastic {lv:g}" for lv in ELASTIC_LEVELS) + " |",
              "|---|" + "---:|" * (len(skin_levels) + len(ELASTIC_LEVELS))]
    for au in aus:
        part = by_au[au]
        sm, em = part["calibration_means"][au]
        lines.append(f"| {au} | " + " | ".join(f"{sm[str(lv)]:.3f}" for lv in skin_levels) + " | "
                     + " | ".join(f"{em[str(lv)]:.3f}" for lv in ELASTIC_LEVELS) + " |")
    runs = [r for part in parts for r in part["skin"]]
    fits = [t for part in parts for t in part["fit_seconds"]]
    lines += ["", f"Physical skin: {len(runs)} simulations, {sum(bool(r['settled']) for r in runs)} settled, "
              f"{sum(bool(r['clamped']) for r in runs)} scaled down against inverted elements; per simulation "
              f"{np.mean([r['seconds'] for r in runs]):.1f} s wall time, {np.mean([r['steps'] for r in runs]):.0f} "
              f"steps ({np.mean([r['sim_ms'] for r in runs]):.0f} ms simulated); template fit "
              f"{np.mean(fits):.1f} s per subject."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", default="0-19")
    ap.add_argument("--calibrate", default="0-3", help="subjects on which each AU's contraction level is chosen")
    ap.add_argument("--aus", nargs="+", default=list(AUS))
    ap.add_argument("--out", default=str(ROOT / "bench-output"))
    ap.add_argument("--name", default="skin_fidelity",
                    help="output stem (bench-output/NAME.md and .json); parts of a split run get their own")
    ap.add_argument("--report", nargs="+", metavar="JSON",
                    help="only merge the .json of runs over different AUs into one table (NAME.md)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if args.report:
        parts = [json.loads(Path(p).read_text()) for p in args.report]
        table = report(parts)
        write_report(out / f"{args.name}.md", table)
        return 0
    shared = shared_dir()
    if shared is None:
        print("skin fidelity benchmark skipped: ../shared (make_scans.py, score_transfer.py) not found")
        return 0
    scorer = load_module(shared / "tools" / "score_transfer.py", "score_transfer")
    faces = np.load(shared / "data" / "ict-facekit" / "face_model.npz")["faces"]
    scans = out / "skin-scans"
    subjects = parse_subjects(args.subjects)
    calibration = parse_subjects(args.calibrate)
    ensure_scans(shared, scans, sorted(set(subjects) | set(calibration)))

    cache: dict[int, Subject] = {}

    def subject(s: int) -> Subject:
        if s not in cache:
            cache[s] = Subject(scans, s)
            print(f"  bs{s:03d}: fitted in {cache[s].fit_seconds:.1f} s", flush=True)
        return cache[s]

    def score(s: int, au: str, predicted, neutral):
        a_gt = str(scan_path(scans, s, "N_N_0")) + "_gt.npz"
        b_gt = str(scan_path(scans, s, AU_CODES[au])) + "_gt.npz"
        return scorer.score(predicted, neutral, a_gt, b_gt, faces, mask=subject(s).mask)

    skin_runs: dict[tuple, dict] = {}

    def skin_run(s, au, level):
        key = (s, au, level)
        if key not in skin_runs:
            predicted, result, messages = subject(s).skin_prediction(au, level)
            row = score(s, au, predicted, subject(s).neutral)
            row.update(subject=s, au=au, level=level, applied=result.scale * level, seconds=result.seconds,
                       steps=result.steps, settled=result.settled, sim_ms=1e3 * result.simulated_time,
                       clamped=result.scale < 1.0, warnings=messages)
            skin_runs[key] = row
        return skin_runs[key]

    def elastic_run(s, au, level):
        row = score(s, au, subject(s).elastic_prediction(au, level), subject(s).neutral)
        row.update(subject=s, au=au, level=level)
        return row

    chosen, calibration_means, elastic_rows = {}, {}, {}
    for au in args.aus:
        skin_means = {lv: float(np.mean([skin_run(s, au, lv)["residual_ratio"] for s in calibration]))
                      for lv in SKIN_LEVELS}
        elastic_means = {lv: float(np.mean([elastic_run(s, au, lv)["residual_ratio"] for s in calibration]))
                         for lv in ELASTIC_LEVELS}
        chosen[au] = (min(skin_means, key=skin_means.get), min(elastic_means, key=elastic_means.get))
        calibration_means[au] = ({str(k): v for k, v in skin_means.items()},
                                 {str(k): v for k, v in elastic_means.items()})
        print(f"AU{au}: calibration skin " + ", ".join(f"{k:.2f}: {v:.3f}" for k, v in skin_means.items())
              + " | elastic " + ", ".join(f"{k:g}: {v:.3f}" for k, v in elastic_means.items()), flush=True)
        skin_level, elastic_level = chosen[au]
        rows = [skin_run(s, au, skin_level) for s in subjects]
        elastic_rows[au] = [elastic_run(s, au, elastic_level) for s in subjects]
        print(f"AU{au}: skin {np.mean([r['residual_ratio'] for r in rows]):.3f} (level {skin_level:.2f}), elastic "
              f"{np.mean([r['residual_ratio'] for r in elastic_rows[au]]):.3f} (level {elastic_level:g})", flush=True)

    part = dict(aus=list(args.aus), subjects=subjects, calibration=calibration, chosen=chosen,
                calibration_means=calibration_means, skin=list(skin_runs.values()), elastic=elastic_rows,
                fit_seconds=[c.fit_seconds for c in cache.values()])
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(part, indent=1, default=float))
    table = report([part])
    write_report(out / f"{args.name}.md", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
