"""The ``tpscore batch`` subcommand: transfers or adaptations over a whole database.

    tpscore batch DIR --out OUT [--au 12 4] [--sources 0-9] [--targets 0-9] [--pairs next-2]
    tpscore batch DIR --out OUT --kind adapt [--template T.obj --template-landmarks T.lm3]
    tpscore batch --manifest jobs.csv --out OUT
    ... [--scheduler tcp://host:8786] [--workers N] [--no-resume] [--gt-faces F.npz] [--truth]

Exit status 0 when every job is done, 1 when some failed, 130 when interrupted
(rerun the same command to resume), 2 on a bad argument.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .arguments import add_transfer_choices, chosen_transfer_options, grid_shape, integer

__all__ = ["add_batch_parser", "batch_command"]


def add_batch_parser(sub) -> None:
    p = sub.add_parser("batch", help="run transfers or adaptations over a folder of scans or a manifest, on Dask",
                       description="Jobs come from a folder in the Bosphorus layout (bsNNN/bsNNN_<CODE>.bnt, "
                                   ".lm3 beside) or a CSV manifest. Runs on a local Dask cluster (one process "
                                   "per core) or on a running one (--scheduler). Reruns skip finished jobs.")
    p.add_argument("folder", nargs="?", metavar="DIR", help="scans in the Bosphorus layout")
    p.add_argument("--manifest", metavar="CSV", help="jobs from a CSV manifest instead of a folder")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder (outputs, records/, results.csv)")
    p.add_argument("--kind", choices=["transfer", "adapt"], default="transfer", help="with DIR (default transfer)")
    p.add_argument("--au", nargs="+", metavar="AU",
                   help="AUs or emotions to transfer (12 12L 1 sadness ...); default every one the folder has")
    p.add_argument("--sources", metavar="LIST", help="source subjects, e.g. 0-9,12 (default all)")
    p.add_argument("--targets", metavar="LIST", help="target subjects (default all)")
    p.add_argument("--pairs", default="all", metavar="all|next-K",
                   help="all: every source to every other target; next-K: to the K targets after the source")
    p.add_argument("--magnitude", type=float, default=1.0)
    add_transfer_choices(p)
    p.add_argument("--grid", default="150x150", help="grid size HxW (default 150x150)")
    p.add_argument("--template", metavar="MESH", help="--kind adapt: the template mesh (default: the shipped template head)")
    p.add_argument("--template-landmarks", metavar="FILE", help="--kind adapt: its landmarks")
    p.add_argument("--subjects", metavar="LIST", help="--kind adapt: subjects whose scans to fit (default all)")
    p.add_argument("--codes", nargs="+", metavar="CODE", help="--kind adapt: expression codes to fit (default all)")
    p.add_argument("--gt-faces", metavar="NPZ",
                   help="triangles of the _gt.npz sidecars' meshes (an .npz with 'faces'): score exactly")
    p.add_argument("--truth", action="store_true",
                   help="score transfers without sidecars against the target's own scan of the expression")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://host:8786)")
    p.add_argument("--workers", type=integer(1), help="local worker processes (default one per core)")
    p.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                   help="skip jobs whose outputs are complete (default; --no-resume reruns all)")
    p.add_argument("--retries", type=integer(0), default=2, help="reruns of a job after an I/O error (default 2)")
    p.add_argument("--cache-scans", type=integer(1), default=8, help="scans each worker keeps between jobs (default 8)")
    p.add_argument("--quiet", action="store_true", help="no progress, no summary")


def _subjects(text, option: str):
    if text is None:
        return None
    out = []
    for part in text.split(","):
        first, dash, last = part.strip().partition("-")
        try:
            out += list(range(int(first), int(last) + 1)) if dash else [int(first)]
        except ValueError:
            raise ValueError(f"{option} must look like 0-9,12, got {text!r}") from None
    return out


def _shipped_template(out) -> tuple[str, str]:
    """The shipped template head (:func:`tpscore.physics.load_template`) written into the
    output folder as a mesh and its landmarks, where every worker that shares the
    folder reads it."""
    from ..face import io
    from ..physics import load_template

    head = load_template()
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    mesh, landmarks = folder / "template_head.ply", folder / "template_head.lm3"
    io.write_mesh(mesh, head.vertices, head.faces)
    io.write_landmarks(landmarks, head.landmarks)
    return str(mesh), str(landmarks)


def _jobs(args):
    from ..batch import adapt_jobs, read_manifest, transfer_jobs

    grid = grid_shape(args.grid)
    if (args.folder is None) == (args.manifest is None):
        raise ValueError("give a folder DIR or --manifest CSV (one of them)")
    if args.manifest:
        return read_manifest(args.manifest, grid=grid)
    if args.kind == "adapt":
        if bool(args.template) != bool(args.template_landmarks):
            raise ValueError("--kind adapt takes --template and --template-landmarks together (or neither: "
                             "the shipped template head)")
        if not args.template:
            args.template, args.template_landmarks = _shipped_template(args.out)
        return adapt_jobs(args.folder, args.template, args.template_landmarks,
                          subjects=_subjects(args.subjects, "--subjects"), codes=args.codes)
    return transfer_jobs(args.folder, action_units=args.au, sources=_subjects(args.sources, "--sources"),
                         targets=_subjects(args.targets, "--targets"), pairs=args.pairs,
                         magnitude=args.magnitude, options=chosen_transfer_options(args), grid=grid)


def batch_command(args) -> int:
    from ..batch import run

    jobs = _jobs(args)
    if not args.quiet:
        print(f"tpscore batch: {len(jobs)} jobs", file=sys.stderr, flush=True)
    report = run(jobs, args.out, scheduler=args.scheduler, workers=args.workers, resume=args.resume,
                 gt_faces=args.gt_faces, truth=args.truth, cache_scans=args.cache_scans, retries=args.retries,
                 progress=not args.quiet)
    if not args.quiet:
        print(report.summary(), flush=True)
    if report.interrupted:
        return 130
    return 1 if report.counts()["failed"] else 0
