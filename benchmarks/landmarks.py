"""Accuracy of the automatic landmarks (tpscore.detect_landmarks) on generated
Bosphorus-format scans: per landmark, the distance to the true landmarks (the scans'
``_gt.npz`` sidecars, ``landmarks_true``), each scan read with its colour image, for development subjects (0-9, the ones
the detector was tuned on) and held-out subjects (10-19), neutral and expressive.

    python benchmarks/landmarks.py [--scans FOLDER] [--out bench-output/landmarks.md]

The scans are made with ../shared/tools/make_scans.py into bench-output/scans_landmarks
(or --scans) where missing.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from tpscore import detect_landmarks
from tpscore.face.landmarks import LANDMARK_NAMES

from fidelity import ensure_scans
from shared_data import REPOSITORY, shared_dir

NEUTRAL = ("N_N_0",)
EXPRESSIVE = ("LFAU_25_0", "UFAU_43_0", "UFAU_44_0", "UFAU_6_0", "E_HAPPY_0", "E_SADNESS_0",
              "E_SURPRISE_0", "E_FEAR_0", "E_ANGER_0", "E_DISGUST_0")
SPLITS = {"development (subjects 0-9)": range(0, 10), "held-out (subjects 10-19)": range(10, 20)}


def measure(scans: Path, subjects, codes) -> np.ndarray:
    """(scans, 22) errors in mm, NaN where the detector found nothing."""
    rows = []
    for subject in subjects:
        for code in codes:
            stem = scans / f"bs{subject:03d}" / f"bs{subject:03d}_{code}"
            if not stem.with_suffix(".bnt").exists():
                continue
            truth = np.load(f"{stem}_gt.npz")["landmarks_true"]
            found = detect_landmarks(stem.with_suffix(".bnt"))  # with the colour image beside it
            rows.append(np.linalg.norm(found - truth, axis=1))
    return np.array(rows)


def table(errors: np.ndarray) -> list[str]:
    lines = ["| landmark | mean | median | 90th pct | found |", "|---|---:|---:|---:|---:|"]
    for i, name in enumerate(LANDMARK_NAMES):
        column = errors[:, i]
        found = np.isfinite(column)
        if found.any():
            lines.append(f"| {name} | {np.nanmean(column):.1f} | {np.nanmedian(column):.1f} | "
                         f"{np.nanpercentile(column, 90):.1f} | {found.sum()}/{len(column)} |")
        else:
            lines.append(f"| {name} | - | - | - | 0/{len(column)} |")
    per_scan = np.isfinite(errors).sum(axis=1)
    lines.append(f"| **all** | **{np.nanmean(errors):.1f}** | {np.nanmedian(errors):.1f} | "
                 f"{np.nanpercentile(errors, 90):.1f} | fewest on a scan: {per_scan.min()}/22 |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=Path, default=REPOSITORY / "bench-output" / "scans_landmarks")
    parser.add_argument("--out", type=Path, default=REPOSITORY / "bench-output" / "landmarks.md")
    args = parser.parse_args(argv)
    shared = shared_dir()
    if shared is not None:
        ensure_scans(shared, args.scans, list(range(20)), codes=[*NEUTRAL, *EXPRESSIVE])
    elif not args.scans.is_dir():
        print("skipped: needs ../shared (make_scans.py) or --scans with the generated scans")
        return
    start = time.perf_counter()
    out = ["# Automatic landmarks: error against the true landmarks (mm)", ""]
    count = 0
    for split, subjects in SPLITS.items():
        for kind, codes in (("neutral", NEUTRAL), ("expressive", EXPRESSIVE)):
            errors = measure(args.scans, subjects, codes)
            if len(errors) == 0:
                continue
            count += len(errors)
            out += [f"## {split}, {kind} ({len(errors)} scans)", "", *table(errors), ""]
    out.append(f"{count} scans in {time.perf_counter() - start:.0f} s.")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(out) + "\n", encoding="utf-8")
    print("\n".join(out))


if __name__ == "__main__":
    main()
