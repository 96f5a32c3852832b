"""The ``tpscore`` command line.

    tpscore transfer --source-neutral A --source-expr B --target C --au 12 [--magnitude 0.8]
                     [--out result.npz] [--mesh result.obj] [--png result.png] [--gif sweep.gif]
    tpscore demo [--out DIR]
    tpscore build-afm [--out average_face.npz]
    tpscore elastic --face-model face_model.npz --out DIR   (fit and clone expressions)
    tpscore adapt TEMPLATE SCAN --template-landmarks T.lm3 --scan-landmarks S.lm3 --out fitted.obj
    tpscore batch DIR --out OUT [--au 12 4] [--pairs next-2] [--scheduler tcp://host:8786]

Errors are reported as one line on stderr (exit status 2), not as a traceback.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from .. import render
from ..batch.scores import surface_distances
from ..expression import TransferOptions, transfer
from ..face import io
from ..face.average_face import afm_faces, build_average_face
from ..face.grid import load_scan
from .adapt import add_adapt_parser, adapt_command
from .batch import add_batch_parser, batch_command
from .demo import run_demo
from .elastic import add_elastic_parser, elastic_command

__all__ = ["main"]


class _Progress:
    """Prints one line per finished step with its time, so long work shows progress."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.start = time.perf_counter()

    def step(self, message: str) -> None:
        if not self.quiet:
            print(f"[{time.perf_counter() - self.start:7.2f} s] {message}", flush=True)


def _add_transfer(sub) -> None:
    p = sub.add_parser("transfer", help="put a source person's action units on a target person")
    p.add_argument("--source-neutral", required=True, metavar="A", help="neutral scan of the source (.bnt or mesh)")
    p.add_argument("--source-expr", required=True, metavar="B", help="expressive scan of the source")
    p.add_argument("--target", required=True, metavar="C", help="neutral scan of the target")
    p.add_argument("--source-neutral-landmarks", metavar="FILE", help="landmarks of A (default: A's .lm3)")
    p.add_argument("--source-expr-landmarks", metavar="FILE", help="landmarks of B (default: B's .lm3)")
    p.add_argument("--target-landmarks", metavar="FILE", help="landmarks of C (default: C's .lm3)")
    p.add_argument("--au", required=True,
                   help="AU code(s): 12, 12L, 12R, '1,4,15', 'AU12:0.5', or an emotion (sadness, ...)")
    p.add_argument("--magnitude", type=float, default=1.0, help="m in [0, 1] (default 1)")
    p.add_argument("--method", choices=["default", "published"], default="default",
                   help="default (best measured) or published (the method as published)")
    p.add_argument("--grid", default="150x150", help="grid size HxW (default 150x150)")
    p.add_argument("--out", metavar="NPZ", help="write vertices/neutral/mask (target scan frame) and more")
    p.add_argument("--mesh", metavar="OBJ|PLY", help="write the animated target as a mesh with u,v")
    p.add_argument("--png", metavar="PNG", help="write renders of source, expression, target and result")
    p.add_argument("--gif", metavar="GIF", help="write an animation of the magnitude sweep 0 -> m -> 0")
    p.add_argument("--truth", metavar="D",
                   help="a real expressive scan of the target: adds an error heat map to --png "
                        "(surface distance after a rigid alignment) and prints the RMS")
    p.add_argument("--truth-landmarks", metavar="FILE", help="landmarks of D (default: D's .lm3)")
    p.add_argument("--quiet", action="store_true")


def _grid_shape(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--grid must look like 150x150, got {text!r}") from None
    if not (8 <= h <= 4096 and 8 <= w <= 4096):
        raise ValueError(f"--grid sizes must be between 8 and 4096, got {text!r}")
    return h, w


def run_transfer(args) -> int:

    progress = _Progress(args.quiet)
    shape = _grid_shape(args.grid)
    grids = []
    for path, lm in ((args.source_neutral, args.source_neutral_landmarks),
                     (args.source_expr, args.source_expr_landmarks), (args.target, args.target_landmarks)):
        grids.append(load_scan(path, lm, shape=shape))
        progress.step(f"read and resampled {path}")
    options = TransferOptions.published() if args.method == "published" else TransferOptions()
    result = transfer(*grids, args.au, args.magnitude, options=options)
    progress.step(f"transferred {'+'.join(result.animation.labels)} at magnitude {args.magnitude:g}")
    if args.out:
        io.write_npz(args.out, **result.to_npz_dict())
        progress.step(f"wrote {args.out}")
    if args.mesh:
        mesh = result.target.grid.with_points(result.vertices).mesh()
        io.write_mesh(args.mesh, mesh.vertices, mesh.faces, uv=mesh.uv)
        progress.step(f"wrote {args.mesh}")
    errors = None
    if args.truth:
        truth = load_scan(args.truth, args.truth_landmarks, shape=shape)
        # distances to the true surface rigidly aligned onto the target's neutral scan
        errors, neutral_errors = surface_distances([result.vertices, result.neutral], result.mask, truth, grids[2])
        # score where the expression shows: the neutral target is off the true surface
        moving = neutral_errors > 0.5
        rms = lambda d: float(np.sqrt(np.mean(d ** 2)))  # noqa: E731
        progress.step(f"distance to the true expressive scan where the neutral target is over 0.5 mm off "
                      f"({int(moving.sum())} vertices): rms {rms(errors[moving]):.2f} mm "
                      f"(the neutral target: {rms(neutral_errors[moving]):.2f} mm)")
    if args.png:
        images = [render.render_grid(g.points, g.mask) for g in grids]
        images.append(render.render_grid(result.vertices, result.mask))
        titles = ["source neutral", "source expressive", "target neutral",
                  f"target {'+'.join(result.animation.labels)} m={args.magnitude:g}"]
        if errors is not None:
            mesh = result.target.grid.with_points(result.vertices).mesh()
            images.append(render.error_heatmap(mesh.vertices, mesh.faces,
                                               np.nan_to_num(errors.reshape(-1)[mesh.grid_index])))
            titles.append("distance to the true scan (mm)")
        render.save_png(args.png, render.side_by_side(images, titles))
        progress.step(f"wrote {args.png}")
    if args.gif:
        ms = np.concatenate([np.linspace(0, args.magnitude, 8), np.linspace(args.magnitude, 0, 8)[1:]])
        frames = [render.render_grid(result.animation.frame_in_scan(m), result.mask) for m in ms]
        render.save_gif(args.gif, frames, fps=12)
        progress.step(f"wrote {args.gif}")
    return 0


def run_build_afm(args) -> int:

    progress = _Progress(args.quiet)
    faces = afm_faces()
    progress.step(f"generated {len(faces)} procedural faces")
    afm = build_average_face(faces, shape=_grid_shape(args.grid))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    afm.save(args.out)
    progress.step(f"wrote {args.out} ({afm.grid.mask.sum()} valid vertices)")
    return 0


def run_demo_command(args) -> int:
    run_demo(args.out, quiet=args.quiet)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tpscore", description="Morph and animate 3D faces with TPS and RBFs.")
    parser.add_argument("--traceback", action="store_true", help="show a full traceback on errors")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_transfer(sub)
    d = sub.add_parser("demo", help="run the whole pipeline on embedded faces; write meshes and pictures")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--quiet", action="store_true")
    add_elastic_parser(sub)
    add_adapt_parser(sub)
    add_batch_parser(sub)
    b = sub.add_parser("build-afm", help="rebuild the average face model from the procedural faces")
    b.add_argument("--out", default="average_face.npz")
    b.add_argument("--grid", default="150x150")
    b.add_argument("--quiet", action="store_true")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handlers = {"transfer": run_transfer, "demo": run_demo_command, "build-afm": run_build_afm,
                "elastic": elastic_command, "adapt": adapt_command,
                "batch": batch_command}
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = lambda message, *_args, **_kw: print(
            f"tpscore: warning: {message}", file=sys.stderr)
        try:
            return handlers[args.command](args)
        except (ValueError, OSError) as exc:
            if args.traceback:
                raise
            print(f"tpscore: error: {exc}", file=sys.stderr)
            return 2

