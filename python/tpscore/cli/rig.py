"""The ``tpscore rig`` subcommand: every expression of a source person on a target, as a
rig that animation tools open (the target's face with one morph target per expression).

    tpscore rig --source-dir FOLDER --target NEUTRAL.bnt --out rig.glb [--au 12 4 sadness]
                [--names au|arkit] [--animations] [--grid 150x150] [--method default|published]
                [--correspondence landmarks|adapted]

FOLDER is one source person's scans: ``bsNNN_<CODE>.bnt`` (the Bosphorus layout) or
``source_<name>.bnt`` (as ``tpscore demo`` writes them into ``scans/``), with the neutral
scan among them. The output is glTF 2.0 (``.glb``, ``.gltf``) or, with usd-core
installed, USD (``.usda``, ``.usdc``, ``.usd``).
"""
from __future__ import annotations

from pathlib import Path

from .arguments import add_transfer_choices, chosen_transfer_options, grid_shape
from .progress import StepLog

__all__ = ["add_rig_parser", "rig_command"]

_GLTF_SUFFIXES = (".glb", ".gltf")
_USD_SUFFIXES = (".usda", ".usdc", ".usd")
# The library names its arguments; the command line says which option held them.
_OPTIONS = {"expressions": "--source-dir", "action_units": "--au", "source_neutral": "--source-neutral",
            "path": "--out"}


def add_rig_parser(sub) -> None:
    p = sub.add_parser("rig", help="transfer every expression of a source person onto a target, as a rig of "
                                   "morph targets (glTF .glb, or USD)",
                       description="Each expression scan in the source folder is transferred onto the target "
                                   "(its neutral scan and the source's read once); the rig is the target's "
                                   "neutral face with one morph target per expression.")
    p.add_argument("--source-dir", required=True, metavar="FOLDER",
                   help="the source person's scans: bsNNN_<CODE>.bnt or source_<name>.bnt, neutral included")
    p.add_argument("--target", required=True, metavar="NEUTRAL", help="the target's neutral scan")
    p.add_argument("--out", required=True, metavar="RIG", help="the rig: .glb or .gltf (or .usda/.usdc with usd-core)")
    p.add_argument("--source-neutral", metavar="SCAN",
                   help="the source's neutral scan (default: the one in FOLDER)")
    p.add_argument("--au", nargs="+", metavar="AU",
                   help="only these expressions, in this order (12 12L 4 sadness ...); default every one")
    p.add_argument("--names", choices=["au", "arkit"], default="au",
                   help="morph target names: au (AU12, sadness; default) or arkit (mouthSmileLeft, ...; "
                        "bilateral AUs cut into left and right halves)")
    p.add_argument("--animations", action="store_true",
                   help="add one animation per expression (0 -> 1 -> 0 over a second)")
    p.add_argument("--html", metavar="PAGE", help="also write a page of the rig: a slider per morph target")
    add_transfer_choices(p)
    p.add_argument("--grid", default="150x150", help="grid size HxW (default 150x150)")
    p.add_argument("--quiet", action="store_true")


def rig_command(args) -> int:
    from ..rigging import rig, write_gltf

    suffix = Path(args.out).suffix.lower()
    if suffix not in _GLTF_SUFFIXES + _USD_SUFFIXES:
        raise ValueError(f"--out: {args.out!r}: a rig is written as .glb or .gltf (glTF 2.0), or .usda, .usdc "
                         "or .usd (USD)")
    if suffix in _USD_SUFFIXES:
        from ..rigging.usd import require_usd

        require_usd()  # before the transfers, not after them
    if args.html and Path(args.html).suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"--html: {args.html!r}: a rig's page is an .html file")
    if not Path(args.out).resolve().parent.is_dir():
        raise ValueError(f"--out: {args.out!r}: the folder {str(Path(args.out).parent)!r} does not exist")
    progress = StepLog(args.quiet)
    options = chosen_transfer_options(args)
    try:
        made = rig(args.source_neutral, args.source_dir, args.target, action_units=args.au, names=args.names,
                   grid=grid_shape(args.grid), options=options, progress=progress)
        if suffix in _USD_SUFFIXES:
            from ..rigging.usd import write_usd

            written = write_usd(args.out, made, animations=args.animations)
        else:
            written = write_gltf(args.out, made, animations=args.animations)
        if args.html:
            made.write_html(args.html)
    except ValueError as exc:
        raise _as_option(exc) from None
    progress(f"wrote {written} ({Path(written).stat().st_size / 2**20:.1f} MiB): "
             f"{', '.join(made.target_names)}" + (f"; {args.html}" if args.html else ""))
    return 0


def _as_option(exc: ValueError) -> ValueError:
    text = str(exc)
    for argument, option in _OPTIONS.items():
        if text.startswith(argument + ":") or text.startswith(argument + " ") or text.startswith(argument + "["):
            return ValueError(option + text[len(argument):])
    return exc
