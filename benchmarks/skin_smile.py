"""How strong a smile the physical skin makes: AU12 against the subject's true full smile.

For each development subject the template head is fitted to the neutral scan
(``physics.fit_head``) and the zygomaticus major contracted at each level
(``Head.contractions_for({"12": level})``), as a user calls ``SkinModel.simulate``
(contractions scaled down when skin triangles would fold). The mouth corners' travel is
the simulated displacement of the head's two mouth-corner vertices projected on the
true one (the scans' ground truth, ``score_transfer.ground_truth``), over the true
one's length: 1 is the subject's own full smile.

    python benchmarks/skin_smile.py [--subjects 0-11] [--levels 0.6 1.0]

Writes bench-output/skin_smile.md and .json. Skips (exit 0) without ../shared.
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

import tpscore
from tpscore import physics
from tpscore.face.landmarks import landmark_index

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from fidelity import AU_CODES, ensure_scans, parse_subjects, scan_path  # noqa: E402
from shared_data import load_module, shared_dir  # noqa: E402
from report import write_report  # noqa: E402

CORNERS = (landmark_index("Left mouth corner"), landmark_index("Right mouth corner"))


def corner_travel(scorer, faces, scans: Path, subject: int, levels) -> list[dict]:
    """One row per level: the corners' travel as a share of the true smile's."""
    scan = tpscore.load_scan(str(scan_path(scans, subject, "N_N_0")) + ".bnt")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        head, _ = physics.fit_head(scan, scan.landmarks)
    model = physics.SkinModel(head)
    corners = head.landmark_vertices[list(CORNERS)]
    start = head.vertices[corners]
    truth, projected, _ = scorer.ground_truth(start, str(scan_path(scans, subject, "N_N_0")) + "_gt.npz",
                                              str(scan_path(scans, subject, AU_CODES["12"])) + "_gt.npz", faces)
    true = truth - projected
    rows = []
    for level in levels:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = model.simulate(head.contractions_for({"12": level}))
        moved = result.vertices[corners] - start
        share = np.einsum("ij,ij->i", moved, true) / np.einsum("ij,ij->i", true, true)
        cosine = np.einsum("ij,ij->i", moved, true) / (np.linalg.norm(moved, axis=1) * np.linalg.norm(true, axis=1))
        rows.append(dict(subject=subject, level=level, share=float(share.mean()), cosine=float(cosine.mean()),
                         true_mm=float(np.linalg.norm(true, axis=1).mean()), scale=result.scale,
                         settled=result.settled, max_speed=result.max_speed, seconds=result.seconds))
        print(f"  bs{subject:03d} AU12 {level:g}: {rows[-1]['share']:.2f} of the full smile "
              f"(scale {result.scale:g}, settled {result.settled})", flush=True)
    return rows


def report(rows: list[dict], subjects, levels) -> str:
    lines = ["| contraction | subjects | corner travel (share of the full smile) | mean | runs scaled down (to) "
             "| not settled within 0.5 s |", "|---|---|---|---:|---|---|"]
    for level in levels:
        mine = [r for r in rows if r["level"] == level]
        scaled = [r for r in mine if r["scale"] < 1]
        unsettled = [r for r in mine if not r["settled"]]
        scale_text = f"{len(scaled)} of {len(mine)}" + (
            f" ({min(r['scale'] for r in scaled):g}-{max(r['scale'] for r in scaled):g})" if scaled else "")
        mean_mm = np.mean([r["share"] * r["true_mm"] for r in mine])
        shares = ", ".join(f"{r['share']:.2f}" for r in mine)
        lines.append(f"| {level:g} | {subjects} | {shares} | "
                     f"{np.mean([r['share'] for r in mine]):.2f} ({mean_mm:.1f} mm) | {scale_text} | "
                     f"{len(unsettled)} of {len(mine)}"
                     + (f" (largest speed {max(r['max_speed'] for r in unsettled):.2g} mm/s)" if unsettled else "")
                     + " |")
    cosines = [r["cosine"] for r in rows]
    lines.append("")
    lines.append(f"Direction: cosine with the true corner motion {min(cosines):.2f}-{max(cosines):.2f}.")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", default="0-11")
    ap.add_argument("--levels", nargs="+", type=float, default=[0.6, 1.0])
    ap.add_argument("--out", default=str(ROOT / "bench-output"))
    args = ap.parse_args(argv)
    shared = shared_dir()
    if shared is None:
        print("skin smile benchmark skipped: ../shared (make_scans.py, score_transfer.py) not found")
        return 0
    scorer = load_module(shared / "tools" / "score_transfer.py", "score_transfer")
    faces = np.load(shared / "data" / "ict-facekit" / "face_model.npz")["faces"]
    out = Path(args.out)
    scans = out / "skin-scans"
    subjects = parse_subjects(args.subjects)
    ensure_scans(shared, scans, subjects)
    rows = [row for s in subjects for row in corner_travel(scorer, faces, scans, s, args.levels)]
    table = report(rows, args.subjects, args.levels)
    write_report(out / "skin_smile.md", table)
    (out / "skin_smile.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
