"""The ``tpscore`` command line.

    tpscore transfer --source-neutral A --source-expr B --target C --au 12 [--magnitude 0.8]
                     [--out result.npz] [--mesh result.obj|.ply] [--png result.png] [--gif sweep.gif]
                     [--html result.html]
    tpscore demo [--out DIR]
    tpscore --version
    tpscore build-afm [--out average_face.npz]
    tpscore elastic --face-model face_model.npz --out DIR   (fit and clone expressions)
    tpscore adapt TEMPLATE SCAN --template-landmarks T.lm3 --scan-landmarks S.lm3 --out fitted.obj
    tpscore batch DIR --out OUT [--au 12 4] [--pairs next-2] [--scheduler tcp://host:8786]
    tpscore simulate SCAN --au 12:0.6 [--jaw 10] --out settled.npz [--gif smile.gif]   (physical skin)
    tpscore rig --source-dir FOLDER --target NEUTRAL.bnt --out rig.glb [--au 12 4] [--names au|arkit]

Errors are reported as one line on stderr (exit status 2), not as a traceback.
"""
from __future__ import annotations

from dataclasses import replace

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from .._version import __version__
from ..batch.scores import surface_distances
from ..expression import transfer
from ..face import io
from ..face.average_face import build_average_face
from ..face.loading import load_scan, load_scans
from ..showcase.datasets import afm_faces
from .adapt import add_adapt_parser, adapt_command
from .arguments import add_transfer_choices, chosen_transfer_options, grid_shape
from .batch import add_batch_parser, batch_command
from .demo import run_demo
from .elastic import add_elastic_parser, elastic_command
from .outputs import transfer_picture, write_result_mesh, write_result_page, write_sweep_gif
from .progress import StepLog
from .rig import add_rig_parser, rig_command
from .simulate import add_simulate_parser, simulate_command

__all__ = ["main"]


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
    add_transfer_choices(p)
    p.add_argument("--grid", default="150x150", help="grid size HxW (default 150x150)")
    p.add_argument("--out", metavar="NPZ", help="write vertices/neutral/mask (target scan frame) and more")
    p.add_argument("--mesh", metavar="OBJ|PLY",
                   help="write the animated target: an OBJ textured by the target's image (with NAME.mtl "
                        "and NAME_texture.png beside it), or a PLY with vertex colours")
    p.add_argument("--png", metavar="PNG",
                   help="write pictures of source, expression, measured motion, target and result")
    p.add_argument("--gif", metavar="GIF", help="write an animation of the magnitude sweep 0 -> m -> 0")
    p.add_argument("--html", metavar="HTML",
                   help="write a page to open in a browser: the animated target in its colours, to turn "
                        "and zoom, with a slider for the magnitude")
    p.add_argument("--truth", metavar="D",
                   help="a real expressive scan of the target: adds an error heat map to --png "
                        "(surface distance after a rigid alignment) and prints the RMS")
    p.add_argument("--truth-landmarks", metavar="FILE", help="landmarks of D (default: D's .lm3)")
    p.add_argument("--no-landmark-check", action="store_true",
                   help="carry on with landmarks that fit no face (only warned)")
    p.add_argument("--allow-other-person", action="store_true",
                   help="carry on when the expressive scan looks like another person's (only warned)")
    p.add_argument("--quiet", action="store_true")


def run_transfer(args) -> int:

    progress = StepLog(args.quiet)
    shape = grid_shape(args.grid)
    paths = [args.source_neutral, args.source_expr, args.target]
    grids = load_scans(paths, [args.source_neutral_landmarks, args.source_expr_landmarks, args.target_landmarks],
                       shape=shape)
    progress(f"read and resampled {', '.join(paths)}")
    options = replace(chosen_transfer_options(args), check_landmarks=not args.no_landmark_check,
                      allow_other_person=args.allow_other_person)
    result = transfer(*grids, args.au, args.magnitude, options=options, progress=progress)
    progress(f"transferred {'+'.join(result.animation.labels)} at magnitude {args.magnitude:g}")
    if args.out:
        io.write_npz(args.out, **result.to_npz_dict())
        progress(f"wrote {args.out}")
    if args.mesh:
        written = write_result_mesh(result, args.mesh)
        progress(f"wrote {', '.join(str(p) for p in written)}")
    errors = None
    if args.truth:
        truth = load_scan(args.truth, args.truth_landmarks, shape=shape)
        # distances to the true surface rigidly aligned onto the target's neutral scan
        # in the target grid's frame, where the truth is aligned (a scan resampled from
        # another frame has its vertices in that frame)
        animation = result.animation
        errors, neutral_errors = surface_distances(
            [animation.frame_in_grid(result.magnitude), animation.frame_in_grid(0.0)], result.mask, truth, grids[2])
        # score where the expression shows: the neutral target is off the true surface
        moving = neutral_errors > 0.5
        rms = lambda d: float(np.sqrt(np.mean(d ** 2)))  # noqa: E731
        progress(f"distance to the true expressive scan where the neutral target is over 0.5 mm off "
                      f"({int(moving.sum())} vertices): rms {rms(errors[moving]):.2f} mm "
                      f"(the neutral target: {rms(neutral_errors[moving]):.2f} mm)")
    if args.png:
        picture = transfer_picture(grids, result, errors=errors,
                                   titles={"error": "distance to the true scan (mm)"})
        io.write_png(args.png, picture)
        progress(f"wrote {args.png}")
    if args.gif:
        write_sweep_gif(result, args.gif, frames=16)
        progress(f"wrote {args.gif}")
    if args.html:
        write_result_page(result, args.html)
        progress(f"wrote {args.html}")
    return 0


def run_build_afm(args) -> int:

    progress = StepLog(args.quiet)
    faces = afm_faces()
    progress(f"generated {len(faces)} procedural faces")
    afm = build_average_face(faces, shape=grid_shape(args.grid))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    afm.save(args.out)
    progress(f"wrote {args.out} ({afm.grid.mask.sum()} valid vertices)")
    return 0


def run_demo_command(args) -> int:
    run_demo(args.out, quiet=args.quiet)
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: the message and where to find the usage, not the
    whole usage text (sub-commands inherit it)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tpscore", description="Morph and animate 3D faces with TPS and RBFs.")
    parser.add_argument("--version", action="version", version=f"tpscore {__version__}")
    parser.add_argument("--traceback", action="store_true", help="show a full traceback on errors")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_transfer(sub)
    d = sub.add_parser("demo", help="transfer expressions between two real faces shipped with tpscore; "
                                    "write meshes, pictures and pages, scored against the truth")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--quiet", action="store_true")
    add_elastic_parser(sub)
    add_adapt_parser(sub)
    add_batch_parser(sub)
    add_simulate_parser(sub)
    add_rig_parser(sub)
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
                "batch": batch_command,
                "simulate": simulate_command, "rig": rig_command}
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
        except MemoryError as exc:
            if args.traceback:
                raise
            print(f"tpscore: error: out of memory{': ' + str(exc) if str(exc) else ''} "
                  "(a smaller --grid needs less)", file=sys.stderr)
            return 2

