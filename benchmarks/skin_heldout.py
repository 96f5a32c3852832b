"""The physical skin on heads fitted to subjects kept out of development: does it come
to rest, and do the mouth corners, brows and chin move the right way?

For each subject of the held-out scans (``make_scans.py --seed-offset 1000``: other
identities, poses, noise and dropouts than the development subjects) the template head
is fitted to the neutral scan (``physics.fit_head``) and four runs are made as a user
calls ``SkinModel.simulate``: the skin at rest, AU12 at contraction 1, AU4 at
contraction 1, and the jaw opened by 15 degrees. Each row says whether the run settled
within ``max_time`` (0.5 s), by what factor it was scaled down against folding, and the
motion that shows the expression: the mouth corners' rise (AU12), the inner brows'
drop and their approach to each other (AU4), the chin's drop (jaw), in mm along the
face's axes.

    python benchmarks/skin_heldout.py [--subjects 0-9]

Writes bench-output/skin_heldout.md. Skips (exit 0) without ../shared.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

import tpscore
from tpscore import physics
from tpscore.face.landmarks import landmark_index

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity import ensure_scans, parse_subjects, scan_path  # noqa: E402
from shared_data import shared_dir  # noqa: E402
from report import write_report  # noqa: E402

SCAN_ARGS = ["--seed-offset", "1000"]
RUNS = (("rest", None, 0.0), ("AU12 1", {"12": 1.0}, 0.0), ("AU4 1", {"4": 1.0}, 0.0), ("jaw 15 deg", None, 15.0))


def _vertex(head, name: str) -> int:
    return int(head.landmark_vertices[landmark_index(name)])


def subject_row(scans: Path, subject: int) -> list[str]:
    scan = tpscore.load_scan(str(scan_path(scans, subject, "N_N_0")) + ".bnt")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        head, _ = physics.fit_head(scan, scan.landmarks)
    model = physics.SkinModel(head)
    corners = [_vertex(head, f"{side} mouth corner") for side in ("Left", "Right")]
    brows = [_vertex(head, f"Inner {side} eyebrow") for side in ("left", "right")]
    chin = _vertex(head, "Chin middle")
    cells = []
    for name, action_units, jaw in RUNS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = model.simulate(head.contractions_for(action_units) if action_units else None, jaw=jaw)
        moved = result.vertices - head.vertices
        if name == "rest":
            motion = f"largest move {np.abs(moved).max():.3f} mm"
        elif name.startswith("AU12"):
            motion = f"corners up {moved[corners[0], 1]:.1f} / {moved[corners[1], 1]:.1f}"
        elif name.startswith("AU4"):
            closer = np.linalg.norm(head.vertices[brows[0]] - head.vertices[brows[1]]) - np.linalg.norm(
                result.vertices[brows[0]] - result.vertices[brows[1]])
            motion = f"brows down {-moved[brows[0], 1]:.1f} / {-moved[brows[1], 1]:.1f}, closer {closer:.1f}"
        else:
            motion = f"chin down {-moved[chin, 1]:.1f}" if chin >= 0 else "no chin landmark"
        state = "settled" if result.settled else f"**not settled** ({result.max_speed:.0f} mm/s)"
        scale = "" if result.scale == 1.0 else f", scaled {result.scale:g}"
        cells.append(f"{state}{scale}; {motion}")
        print(f"  bs{subject:03d} {name}: {cells[-1]}", flush=True)
    return cells


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", default="0-9")
    ap.add_argument("--out", default=str(ROOT / "bench-output"))
    args = ap.parse_args(argv)
    shared = shared_dir()
    if shared is None:
        print("skin held-out benchmark skipped: ../shared (make_scans.py) not found")
        return 0
    out = Path(args.out)
    scans = out / "scans_seed-offset1000"
    subjects = parse_subjects(args.subjects)
    ensure_scans(shared, scans, subjects, SCAN_ARGS, codes=["N_N_0"])
    lines = ["| subject | " + " | ".join(name for name, _, _ in RUNS) + " |", "|---" * (len(RUNS) + 1) + "|"]
    for s in subjects:
        lines.append(f"| {s} | " + " | ".join(subject_row(scans, s)) + " |")
    table = "\n".join(lines)
    write_report(out / "skin_heldout.md", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
