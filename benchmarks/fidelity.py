"""Fidelity benchmark of expression transfer on synthetic Bosphorus-format scans.

Generates development subjects with ../shared/tools/make_scans.py (scans with their
colour images, cached under bench-output/scans), transfers each AU from a source
subject to other target subjects as one batch (tpscore.batch, on a local Dask cluster
or --scheduler's), scores each prediction against the scans' _gt.npz sidecars (the
arithmetic of ../shared/tools/score_transfer.py, in tpscore.batch.scores), and writes
the per-AU table for each pipeline variant to bench-output/fidelity.md (and .json).

    python benchmarks/fidelity.py [--subjects 0-19] [--offsets 1 2]
        [--variants noop published default geometry-only] [--registration 0-3]
        [--workers N | --scheduler tcp://host:8786]

Variants: ``default`` (texture-aided when the scans have images), ``geometry-only``
(the same scans with their images withheld), ``expressive-without-image`` (only the
source's expressive scan withheld), ``published`` (the method as published), ``noop``
(the target left neutral), each name of benchmarks/texture_ablations.py (the default
with one part of the texture term undone), and parts of the default undone one at a time.
``--registration`` also scores the registration alone (the source's own expressive
scan predicted from its registered field) with and without texture.

Skips (exit 0 with a message) when ../shared is absent.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import warnings
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from texture_ablations import ABLATIONS
from tpscore.batch import TransferJob
from tpscore.batch.jobs import setting_value
from shared_data import shared_dir
from report import write_report

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = Path(__file__).resolve().parent
#: The AUs the benchmark has measured from the start (request -> scan code).
AU_CODES = {"1": "UFAU_1_0", "2": "UFAU_2_0", "4": "UFAU_4_0", "12": "LFAU_12_0",
            "12L": "LFAU_12L_0", "14": "LFAU_14_0", "15": "LFAU_15_0", "17": "LFAU_17_0",
            "20": "LFAU_20_0"}
#: The rest of the database's codes the scan generator writes (--expressions bosphorus),
#: each transferred with its own request: an AU code, or an emotion's name (a whole
#: expression).
MORE_CODES = {"6": "UFAU_6_0", "9": "LFAU_9_0", "10": "LFAU_10_0", "16": "LFAU_16_0", "18": "LFAU_18_0",
              "22": "LFAU_22_0", "23": "LFAU_23_0", "24": "LFAU_24_0", "25": "LFAU_25_0", "26": "LFAU_26_0",
              "27": "LFAU_27_0", "28": "LFAU_28_0", "34": "LFAU_34_0", "43": "UFAU_43_0", "44": "UFAU_44_0",
              "happiness": "E_HAPPY_0", "sadness": "E_SADNESS_0", "surprise": "E_SURPRISE_0",
              "fear": "E_FEAR_0", "anger": "E_ANGER_0", "disgust": "E_DISGUST_0"}
CODES = {**AU_CODES, **MORE_CODES}


# The score of each pair in fidelity.json, under the reference scorer's names.
SCORE_KEYS = ("rms_mm", "noop_rms_mm", "p95_mm", "leak_rms_mm", "leak_oracle_mm", "gt_disp_rms_mm", "n_valid",
              "n_active", "n_far", "n_masked_out", "n_pred_missing", "neutral_offsurface_rms_mm", "residual_ratio")
_BATCH_NAMES = {"leak_rms_mm": "leak_mm", "n_pred_missing": "pred_missing"}


def score_value(score: dict, key: str):
    """A score of a batch row or of tpscore.batch.scores by its reference name; a
    record stores NaN as null."""
    value = score[_BATCH_NAMES.get(key, key)]
    return float("nan") if value is None else value


def parse_subjects(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def ensure_scans(shared: Path, out: Path, subjects: list[int], scan_args: list[str] = (),
                 codes: list[str] | None = None) -> None:
    """Make the scans of the subjects missing from out: every default expression, or only
    the scan codes given."""
    # scans written before the generator drew colour images are written again
    images = "--texture-scale" not in scan_args or scan_args[list(scan_args).index("--texture-scale") + 1] != "0"
    # every code is looked for: a folder written by a run with fewer codes is made again
    wanted = ["N_N_0", *(codes or ["LFAU_20_0"])]
    missing = [s for s in subjects
               if not all(Path(f"{scan_path(out, s, code)}_gt.npz").is_file()
                          and (not images or Path(f"{scan_path(out, s, code)}.png").is_file()) for code in wanted)]
    if missing:
        print(f"generating scans of subjects {missing} in {out} ...", flush=True)
        expressions = ["--expressions", *codes] if codes else []
        subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(out),
                        "--subjects", *map(str, missing), *expressions, *scan_args],
                       check=True, stdout=subprocess.DEVNULL)


def scan_path(out: Path, subject: int, code: str) -> Path:
    return out / f"bs{subject:03d}" / f"bs{subject:03d}_{code}"


@dataclass(frozen=True)
class FidelityJob(TransferJob):
    """A transfer of one variant: some scans' colour images withheld, and a texture
    ablation (which patches the library) around the transfer. Workers unpickle it
    from this script, so it carries what it needs."""

    variant: str = "default"
    withheld: tuple = ()  # roles (neutral, expressive, target) whose images are withheld

    def transfer(self, source_neutral, source_expressive, target):
        if str(BENCHMARKS) not in sys.path:  # a worker `dask worker` started does not have it
            sys.path.insert(0, str(BENCHMARKS))
        from texture_ablations import ABLATIONS, ablation as undo

        # an ablation patches a stage whose result a transfer keeps with the neutral faces
        # (kept_normalisation): it is given copies, which nothing was kept for
        ablated = self.variant in ABLATIONS
        grids = [replace(grid, image=None) if role in self.withheld else replace(grid) if ablated else grid
                 for role, grid in zip(("neutral", "expressive", "target"), (source_neutral, source_expressive, target))]
        with warnings.catch_warnings(), undo(self.variant):
            warnings.simplefilter("ignore")  # missing landmarks are expected here
            return super().transfer(*grids)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", default="0-19")
    ap.add_argument("--offsets", type=int, nargs="+", default=[1, 2],
                    help="target = (source + offset) mod n for each offset: n pairs per offset")
    ap.add_argument("--aus", nargs="+", default=list(CODES),
                    help="requests to transfer (default every code: " + ", ".join(CODES) + ")")
    ap.add_argument("--variants", nargs="+", default=["noop", "published", "default", "geometry-only"],
                    help="noop, published, default, geometry-only, expressive-without-image, a part "
                         "of the default undone (see the variants table in the code), or a texture "
                         "ablation (benchmarks/texture_ablations.py)")
    ap.add_argument("--motion-variants", nargs="*", default=[],
                    help="extra variants NAME=key:value,... changing the default's MotionOptions "
                         "(e.g. lattice6=spacing_mm:6.0); list NAME under --variants too")
    ap.add_argument("--option-variants", nargs="*", default=[],
                    help="extra variants NAME=key:value,... changing the default's TransferOptions "
                         "(e.g. seam5=transition_mm:5.0); list NAME under --variants too")
    ap.add_argument("--out", default=str(ROOT / "bench-output"))
    ap.add_argument("--registration", default="",
                    help="subjects (e.g. 0-3) whose registration alone is scored, with and without texture")
    ap.add_argument("--scan-args", default="",
                    help="extra make_scans.py options, e.g. \"--pose-deg 10 --missing-landmark-p 0.1\" "
                         "(the scans go to a folder named after them)")
    ap.add_argument("--workers", type=int, help="local worker processes (default one per core)")
    ap.add_argument("--scheduler", help="a running Dask scheduler instead (tcp://host:8786)")
    ap.add_argument("--resume", action="store_true",
                    help="keep the scores of transfers an interrupted run finished (only when the code has "
                         "not changed since: a job's record does not know the code that made it)")
    args = ap.parse_args(argv)

    shared = shared_dir()
    if shared is None:
        print("fidelity benchmark skipped: ../shared (make_scans.py, the ICT face model) not found")
        return 0
    import tpscore
    from tpscore import TransferOptions
    from tpscore.batch import score_with_sidecars

    faces_path = shared / "data" / "ict-facekit" / "face_model.npz"
    faces = np.load(faces_path)["faces"]
    out = Path(args.out)
    scan_args = args.scan_args.split()
    scans = out / ("scans" + "".join(scan_args).replace("--", "_"))
    subjects = parse_subjects(args.subjects)
    ensure_scans(shared, scans, subjects, scan_args,
                 codes=["N_N_0", *(CODES[a] for a in args.aus)] if set(args.aus) - set(AU_CODES) else None)

    default = TransferOptions()
    variants = {
        "published": TransferOptions.published(),
        "default": default,
        # the same transfers with colour images withheld (which scans: see `withheld`)
        "geometry-only": default,
        "expressive-without-image": default,
        # parts of the default undone one at a time
        "default-no-mirror": replace(default, mirror_average=False),
        "default-no-spill": replace(default, upper_spill=0.0),
        "default-hard-seam": replace(default, transition_mm=0.0),
        "default-no-rest": replace(default, motion=replace(default.motion, rest_weight=0.0)),
        "one-texture-pass": replace(default, motion=replace(default.motion, texture_refine_after=0)),
    }
    # pipeline and registration settings from the command line: name=key:value,key:value
    def parse_variant(spec):
        name, _, settings = spec.partition("=")
        changes = {k: setting_value(v) for k, v in (item.split(":") for item in settings.split(",") if item)}
        return name, changes

    for spec in args.option_variants:
        name, changes = parse_variant(spec)
        variants[name] = replace(default, **changes)
    for spec in args.motion_variants:
        name, changes = parse_variant(spec)
        variants[name] = replace(default, motion=replace(default.motion, **changes))
    for name in ABLATIONS:
        variants[name] = default
    # the parts of texture tracking that are TextureOptions fields, turned off
    variants["no-consistency-check"] = replace(default, texture=replace(default.texture, consistency_px=1e9))
    variants["no-rim-check"] = replace(default, texture=replace(default.texture, rim_px=0))
    for name in args.variants:
        if name not in variants and name != "noop":
            raise SystemExit(f"unknown variant {name!r}")
    # which scans keep their colour images in each variant
    withheld = {"geometry-only": {"neutral", "expressive", "target"}, "expressive-without-image": {"expressive"}}

    # every transfer of every variant is one job of one batch; the jobs of one pair of
    # subjects are neighbours (every AU, every variant), so that a worker reads the
    # pair's neutral scans once (its scan cache) and the transfers keep what they
    # compute of them (kept_normalisation)
    n = len(subjects)
    pairs = [(au, offset, source, subjects[(i + offset) % n])
             for i, source in enumerate(subjects) for offset in args.offsets for au in args.aus]
    transfers = [v for v in args.variants if v != "noop"]

    def job_name(variant, au, offset, source, target):
        return f"{variant}__AU{au}__o{offset}__bs{source:03d}__bs{target:03d}"

    jobs = [FidelityJob(job_name(variant, au, offset, source, target),
                        f"{scan_path(scans, source, 'N_N_0')}.bnt", f"{scan_path(scans, source, CODES[au])}.bnt",
                        f"{scan_path(scans, target, 'N_N_0')}.bnt", au, options=variants[variant],
                        truth=f"{scan_path(scans, target, CODES[au])}.bnt", save=False, variant=variant,
                        withheld=tuple(sorted(withheld.get(variant, ()))))
            for au, offset, source, target in pairs for variant in transfers]
    stem = "fidelity" + "".join(scan_args).replace("--", "_")
    report = tpscore.batch.run(jobs, out / f"{stem}-jobs", gt_faces=faces_path, workers=args.workers,
                               scheduler=args.scheduler, resume=args.resume)
    print(report.summary(), flush=True)
    done = {row["name"]: row for row in report.rows if row["status"] in ("done", "skipped")}
    failed = {row["name"]: row for row in report.rows if row["status"] not in ("done", "skipped")}

    targets = {}

    def target_neutral(subject):
        """(neutral grid with NaN off the mask, mask) of a target, for the no-op and for
        a failed transfer (scored as a prediction that is missing everywhere)."""
        if subject not in targets:
            grid = tpscore.load_scan(str(scan_path(scans, subject, "N_N_0")) + ".bnt")
            targets[subject] = np.where(grid.mask[..., None], grid.points, np.nan), grid.mask
        return targets[subject]

    timings = defaultdict(list)
    for row in done.values():
        if row.get("loads"):
            timings["load+resample"] += [row["load_seconds"] / row["loads"]] * int(row["loads"])
    for variant in transfers:
        for au, offset, source, target in pairs:
            row = done.get(job_name(variant, au, offset, source, target))
            if row is not None:
                for stage, seconds in row["stage_seconds"].items():
                    timings[f"{variant}: {stage}"].append(seconds)
                timings[f"transfer ({variant})"].append(sum(row["stage_seconds"].values()))

    results = defaultdict(list)  # (variant, au) -> list of score dicts
    for au in args.aus:
        code = CODES[au]
        for offset in args.offsets:
            for i, source in enumerate(subjects):
                target = subjects[(i + offset) % n]
                a_gt = str(scan_path(scans, target, "N_N_0")) + "_gt.npz"
                b_gt = str(scan_path(scans, target, code)) + "_gt.npz"
                for variant in args.variants:
                    name = job_name(variant, au, offset, source, target)
                    if variant == "noop" or name in failed:
                        if name in failed:
                            print(f"  {variant} AU{au} {source}->{target}: {failed[name]['error']}", flush=True)
                        neutral, mask = target_neutral(target)
                        pred = neutral if variant == "noop" else np.full_like(neutral, np.nan)
                        score = score_with_sidecars(pred, neutral, mask, a_gt, b_gt, faces)
                    else:
                        score = done[name]
                    score = {key: score_value(score, key) for key in SCORE_KEYS}
                    score.update(source=source, target=target)
                    results[(variant, au)].append(score)
        line = "  ".join(
            f"{v}: {np.mean([r['residual_ratio'] for r in results[(v, au)]]):.3f}" for v in args.variants)
        print(f"AU{au:4s} {line}", flush=True)

    rows = []
    for variant in args.variants:
        for au in args.aus:
            rs = results[(variant, au)]
            ratio = np.array([r["residual_ratio"] for r in rs])
            rows.append(dict(
                variant=variant, au=au, pairs=len(rs),
                mean_ratio=float(np.nanmean(ratio)), median_ratio=float(np.nanmedian(ratio)),
                worst_ratio=float(np.nanmax(ratio)),
                worse_than_noop=int(np.sum(ratio > 1.0)),
                rms_mm=float(np.nanmean([r["rms_mm"] for r in rs])),
                leak_mm=float(np.nanmean([r["leak_rms_mm"] for r in rs])),
                pred_missing=int(sum(r["n_pred_missing"] for r in rs))))
    lines = ["| variant | AU | pairs | mean ratio | median ratio | worst ratio | worse than no-op | "
             "rms mm | leak mm | pred missing |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['au']} | {r['pairs']} | {r['mean_ratio']:.3f} | "
                     f"{r['median_ratio']:.3f} | {r['worst_ratio']:.3f} | {r['worse_than_noop']} | "
                     f"{r['rms_mm']:.3f} | {r['leak_mm']:.3f} | {r['pred_missing']} |")
    lines.append("")
    lines.append("| variant | mean ratio over AUs | worst AU (mean ratio) | mean leak mm | "
                 "transfers worse than no-op | pred missing |")
    lines.append("|---|---:|---:|---:|---:|---:|")
    for variant in args.variants:
        vr = [r for r in rows if r["variant"] == variant]
        worst = max(vr, key=lambda r: r["mean_ratio"])
        lines.append(f"| {variant} | {np.mean([r['mean_ratio'] for r in vr]):.3f} | "
                     f"AU{worst['au']} ({worst['mean_ratio']:.3f}) | "
                     f"{np.mean([r['leak_mm'] for r in vr]):.3f} | "
                     f"{sum(r['worse_than_noop'] for r in vr)} / {sum(r['pairs'] for r in vr)} | "
                     f"{sum(r['pred_missing'] for r in vr)} |")
    lines.append("")
    lines.append("| stage | mean time per call |")
    lines.append("|---|---:|")
    for stage, ts in timings.items():
        lines.append(f"| {stage} | {1e3 * np.mean(ts):.1f} ms |")
    for variant in args.variants:
        if variant == "noop" or not timings[f"transfer ({variant})"]:
            continue
        three = 3 * np.mean(timings["load+resample"]) + np.mean(timings[f"transfer ({variant})"])
        lines.append(f"| {variant}: 3 scans loaded and resampled + transfer | {1e3 * three:.1f} ms |")
    if args.registration:
        lines += ["", *registration_alone(tpscore, score_with_sidecars, faces, scans, parse_subjects(args.registration),
                                          args.aus)]
    table = "\n".join(lines)
    write_report(out / f"{stem}.md", table)
    pairs = [dict(variant=variant, au=au, **{k: (v.item() if hasattr(v, "item") else v) for k, v in r.items()})
             for (variant, au), rs in results.items() for r in rs]
    (out / f"{stem}.json").write_text(json.dumps(dict(rows=rows, pairs=pairs), indent=1))
    return 0


def registration_alone(tpscore, score_with_sidecars, faces, scans, subjects, aus) -> list[str]:
    """Rows scoring the registration alone: each subject's neutral grid moved by its
    registered field (mirror-averaged as the transfer does) against its own expressive
    scan, with the scans' images and with them withheld."""
    from tpscore import TransferOptions
    from tpscore.expression import transfer_method

    reference = tpscore.load_average_face().as_normalised_face()
    library = tpscore.default_library()
    rows = {}
    for with_texture in (True, False):
        for au in aus:
            ratios, leaks = [], []
            for subject in subjects:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    scans_of = [tpscore.load_scan(str(scan_path(scans, subject, code)) + ".bnt")
                                for code in ("N_N_0", CODES[au])]
                    if not with_texture:
                        scans_of = [replace(g, image=None) for g in scans_of]
                    activations = library.parse(au)
                    method = transfer_method(TransferOptions(), reference, library)
                    neutral = tpscore.normalise_face(scans_of[0], reference.landmarks)
                    expressive = method.align(neutral, scans_of[0], scans_of[1], activations)
                    field = method.model(neutral, expressive, activations).dense
                points = neutral.grid.points.reshape(-1, 3)
                predicted = neutral.transform.apply_inverse(points + field(points)).reshape(neutral.grid.points.shape)
                score = score_with_sidecars(predicted, neutral.transform.apply_inverse(neutral.grid.points),
                                            neutral.grid.mask, str(scan_path(scans, subject, "N_N_0")) + "_gt.npz",
                                            str(scan_path(scans, subject, CODES[au])) + "_gt.npz", faces)
                ratios.append(score["residual_ratio"])
                leaks.append(score["leak_mm"])
            rows[(with_texture, au)] = (np.mean(ratios), np.mean(leaks))
    header = "| registration alone (subjects " + f"{subjects[0]}-{subjects[-1]}) | mean | " + \
        " | ".join(f"AU{au}" for au in aus) + " | leak mm |"
    lines = [header, "|---|---:|" + "---:|" * len(aus) + "---:|"]
    for with_texture, name in ((True, "with texture"), (False, "geometry only")):
        ratios = [rows[(with_texture, au)][0] for au in aus]
        leak = np.mean([rows[(with_texture, au)][1] for au in aus])
        lines.append(f"| {name} | {np.mean(ratios):.3f} | " + " | ".join(f"{r:.3f}" for r in ratios)
                     + f" | {leak:.3f} |")
    return lines


if __name__ == "__main__":
    sys.exit(main())
