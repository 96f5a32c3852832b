"""Template adaptation on the ICT development subjects: per-level Ed, Em, true RMS and time.

The template is the ICT model's generic neutral face area with its 22 landmarks; each
scan is a make_scans.py neutral scan (.bnt, noisy .lm3). The defaults were tuned on
subjects 0-11; subjects 12-19 are held out, and the bar is judged on them. The true per-vertex RMS is taken against the
sidecar mesh (never shown to the fit) over the template vertices within 80 mm of the
template's nose tip. Writes bench-output/adaptation.md and prints it. Skips without
../shared (set TPSCORE_SHARED).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import tpscore
from tpscore.adaptation import AdaptOptions

ROOT = Path(__file__).resolve().parents[1]
TUNING = tuple(range(12))
HELD_OUT = tuple(range(12, 20))
SUBJECTS = HELD_OUT + TUNING
DETAIL = (12, 13)
HOLES_SUBJECT = 12
MOVED_LANDMARK = "Left mouth corner"


def _shared() -> Path | None:
    env = os.environ.get("TPSCORE_SHARED")
    for path in ([Path(env)] if env else []) + [ROOT.parent / "shared"]:
        if (path / "tools" / "make_scans.py").is_file() and (path / "data" / "ict-facekit").is_dir():
            return path
    return None


def _generate(shared: Path, out: Path, subjects, *extra) -> None:
    missing = [s for s in subjects if not (out / f"bs{s:03d}" / f"bs{s:03d}_N_N_0_gt.npz").is_file()]
    if missing:
        subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(out), "--subjects",
                        *map(str, missing), "--expressions", "N_N_0", *extra], check=True,
                       stdout=subprocess.DEVNULL)


def _run(template, scan, landmarks, truth, near, options: AdaptOptions = AdaptOptions()):
    # Every level is run and scored, with the two nose saddles held out as Em markers.
    options = replace(options, stop_at_minimum=False, held_out_landmarks=("Nose saddle left", "Nose saddle right"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.perf_counter()
        result = tpscore.adapt(template[:2], scan, template[2], landmarks, options=options)
        seconds = time.perf_counter() - start
    per_level = []
    for k in range(len(result.levels)):
        fitted = result.deform(template[0], level=k)
        per_level.append(float(np.sqrt(np.mean(np.sum((fitted[near] - truth[near]) ** 2, axis=1)))))
    final = float(np.sqrt(np.mean(np.sum((result.vertices[near] - truth[near]) ** 2, axis=1))))
    return result, per_level, final, seconds, [str(w.message) for w in caught]


# The variants retired from the library, with their last scores, are listed in
# benchmarks/FIDELITY.md ("Retired variants of the adaptation"). The published method's
# axes calibration needs the chin, which make_scans.py leaves out on bs000 and bs010, so
# its row calibrates by the similarity over all feature pairs, as the default does.
VARIANTS = {
    "landmark RBF only (level 0)": AdaptOptions(levels=1),
    "published, similarity calibration": AdaptOptions.published(calibration="similarity"),
    "surface, no snap, no fill": AdaptOptions(snap=False, fill_unseen=False),
    "surface + harmonic fill, no snap": AdaptOptions(snap=False),
    "surface + snap + harmonic fill (defaults)": AdaptOptions(),
}
DEFAULT = "surface + snap + harmonic fill (defaults)"


def test_adaptation_table():
    shared = _shared()
    if shared is None:
        pytest.skip("needs ../shared (make_scans.py, ICT face model); set TPSCORE_SHARED")

    cache = ROOT / "bench-output" / "adaptation-scans"
    _generate(shared, cache / "default", SUBJECTS)
    _generate(shared, cache / "holes", [HOLES_SUBJECT], "--hole-rate", "15")
    model = np.load(shared / "data" / "ict-facekit" / "face_model.npz")
    vertices = model["neutral"].astype(np.float64)
    faces = model["faces"].astype(np.int64)
    index = model["bosphorus_index"].astype(np.int64)
    template = (vertices, faces, index)
    near = np.linalg.norm(vertices - vertices[index[13]], axis=1) < 80.0

    lines = ["# Template adaptation on ICT development subjects", "",
             f"Held-out subjects {list(HELD_OUT)} (defaults tuned on 0-11, also shown), neutral scans as make_scans.py writes them "
             "(0.15 mm depth noise, holes, landmark noise 0.8 mm per axis). True RMS: per template vertex "
             "within 80 mm of the nose tip, against the sidecar mesh. Ed, Em in mm^2 (Em over the two nose "
             "saddles, held out of the fit). * marks the level E chose.", ""]
    summary = {name: [] for name in VARIANTS}
    rigid = {}

    def scan_of(folder, subject):
        base = cache / folder / f"bs{subject:03d}" / f"bs{subject:03d}_N_N_0"
        scan = tpscore.read_bnt(str(base) + ".bnt")
        landmarks = tpscore.read_landmarks(str(base) + ".lm3")
        gt = np.load(str(base) + "_gt.npz")
        return scan, landmarks, gt["vertices"].astype(np.float64)

    for subject in SUBJECTS:
        scan, landmarks, truth = scan_of("default", subject)
        align = tpscore.similarity_transform(landmarks, vertices[index]).apply_inverse(vertices)
        rigid[subject] = float(np.sqrt(np.mean(np.sum((align[near] - truth[near]) ** 2, axis=1))))
        for name, options in VARIANTS.items():
            result, per_level, final, seconds, _ = _run(template, scan, landmarks, truth, near, options)
            summary[name].append((final, per_level[result.best_level], seconds))
            if subject in DETAIL and (name == DEFAULT or subject == DETAIL[0]):
                lines += [f"## bs{subject:03d}, {name} (rigid landmark alignment: {rigid[subject]:.2f} mm)", "",
                          "| level | method | sigma | pairs | Ed | Em | true RMS (mm) | time (s) |",
                          "|---|---|---|---|---|---|---|---|"]
                for lv, rms in zip(result.levels, per_level):
                    mark = " *" if lv.level == result.best_level else ""
                    lines.append(f"| {lv.level}{mark} | {lv.method} | {lv.support:.1f} | {lv.pairs} | "
                                 f"{lv.distance_error:.2f} | {lv.marker_error:.2f} | {rms:.2f} | {lv.seconds:.3f} |")
                surface = options.refinement == "surface" and result.best_level > 0
                lines += [f"Returned (level {result.best_level}"
                          + (", then the snap onto the scan" if surface and options.snap else "")
                          + (", then the fill of unseen vertices" if surface and options.fill_unseen else "")
                          + f"): true RMS {final:.2f} mm.", ""]
            assert np.isfinite(final)

    lines += ["## Summary (true RMS in mm at the level E chose)", "",
              "| variant | " + " | ".join(f"bs{s:03d}" for s in HELD_OUT)
              + " | held-out mean (12-19) | tuning mean (0-11) | mean time (s) |",
              "|---|" + "---|" * (len(HELD_OUT) + 3)]
    held = [SUBJECTS.index(s) for s in HELD_OUT]
    tuning = [SUBJECTS.index(s) for s in TUNING]
    lines.append("| rigid landmark alignment | " + " | ".join(f"{rigid[s]:.2f}" for s in HELD_OUT)
                 + f" | {np.mean([rigid[s] for s in HELD_OUT]):.2f} | {np.mean([rigid[s] for s in TUNING]):.2f} | |")
    for name, rows in summary.items():
        lines.append(f"| {name} | " + " | ".join(f"{rows[i][0]:.2f}" for i in held)
                     + f" | {np.mean([rows[i][0] for i in held]):.2f} | {np.mean([rows[i][0] for i in tuning]):.2f}"
                     f" | {np.mean([r[2] for r in rows]):.2f} |")
    lines.append("")
    lines += ["Tuning subjects (0-11), " + DEFAULT + ": "
              + ", ".join(f"bs{s:03d} {summary[DEFAULT][SUBJECTS.index(s)][0]:.2f}" for s in TUNING), ""]

    # defective data: extra holes, and one landmark moved by 10 mm
    scan, landmarks, truth = scan_of("holes", HOLES_SUBJECT)
    result, per_level, final, seconds, messages = _run(template, scan, landmarks, truth, near)
    lines += [f"## Defective data (bs{HOLES_SUBJECT:03d})", "", "| case | true RMS (mm) | best level | "
              "coverage | time (s) | warnings |", "|---|---|---|---|---|---|"]
    lines.append(f"| hole rate 15 | {final:.2f} | {result.best_level} | {result.levels[result.best_level].coverage:.2f}"
                 f" | {seconds:.2f} | {'; '.join(messages) or '-'} |")
    scan, landmarks, truth = scan_of("default", HOLES_SUBJECT)
    moved = landmarks.copy()
    row = tpscore.face.landmarks.landmark_index(MOVED_LANDMARK)
    moved[row] += np.array([10.0, 0.0, 0.0])
    result, per_level, final, seconds, messages = _run(template, scan, moved, truth, near)
    lines.append(f"| {MOVED_LANDMARK} moved 10 mm | {final:.2f} | {result.best_level} | "
                 f"{result.levels[result.best_level].coverage:.2f} | {seconds:.2f} | {'; '.join(messages) or '-'} |")
    lines.append("")

    # speed: a 150 x 150 grid template (the scan resampled) onto the same scan
    scan, landmarks, truth = scan_of("default", HELD_OUT[0])
    grid = tpscore.resample_scan(scan, landmarks, (150, 150))
    mesh = grid.mesh()
    remap = {int(g): i for i, g in enumerate(mesh.grid_index)}
    grid_landmarks = np.array([remap.get(int(v), -1) for v in grid.landmark_vertices])
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fast = tpscore.adapt((mesh.vertices, mesh.faces), scan, grid_landmarks, landmarks,
                             options=AdaptOptions(calibration="none"))
    seconds = time.perf_counter() - start
    lines += [f"150 x 150 grid template ({len(mesh.vertices)} vertices) onto the native scan: "
              f"{seconds:.2f} s for {len(fast.levels)} levels.", ""]
    text = "\n".join(lines)
    (ROOT / "bench-output").mkdir(exist_ok=True)
    # Full precision, so that two runs can be compared beyond the table's two decimals.
    scores = {name: {f"bs{s:03d}": rows[SUBJECTS.index(s)][0] for s in SUBJECTS} for name, rows in summary.items()}
    (ROOT / "bench-output" / "adaptation.json").write_text(json.dumps(scores, indent=1))
    (ROOT / "bench-output" / "adaptation.md").write_text(text)
    print("\n" + text)
