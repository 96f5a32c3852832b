"""Parsing of the arguments several subcommands share."""
from __future__ import annotations

import argparse
from dataclasses import replace

from ..face.grid import MAX_GRID_VERTICES
from ..face.scan_files import read_scan_landmarks, read_scan_surface

__all__ = ["grid_shape", "integer", "read_scan_surface", "read_scan_landmarks", "add_transfer_choices",
           "chosen_transfer_options"]


def integer(least: int):
    """An argparse ``type``: a whole number >= `least`. argparse puts the option's name
    before the message ("argument --source-subject: must be an integer >= 0, got '-1'"),
    where a value checked later would fail without it (NumPy's "expected non-negative
    integer" for a negative seed)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {least}"
    return parse


def grid_shape(text: str) -> tuple[int, int]:
    """``--grid HxW`` as (rows, columns), within the grid sizes tpscore accepts."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--grid must look like 150x150, got {text!r}") from None
    if h < 8 or w < 8 or h * w > MAX_GRID_VERTICES:
        raise ValueError(f"--grid must have at least 8 rows and columns and at most {MAX_GRID_VERTICES:,} "
                         f"vertices (1024x1024), got {text!r}")
    return h, w


def add_transfer_choices(p: argparse.ArgumentParser) -> None:
    """The options of the transfer method that the transfer, batch and rig commands share."""
    p.add_argument("--method", choices=["default", "published"], default="default",
                   help="default (best measured) or published (the method as published)")
    p.add_argument("--correspondence", choices=["landmarks", "adapted"], default="landmarks",
                   help="where each target point reads the source's motion: landmarks (a TPS through the 22 "
                        "landmark pairs; default) or adapted (the target's grid fitted onto the source's "
                        "scan: closer on most expressions, about a second more per pair of faces)")
    p.add_argument("--texture-passes", type=int, choices=[1, 2], default=None,
                   help="how often the skin's texture is matched: 2 (the default) matches it again once the "
                        "registration has found the large motions, with the expressive image warped back by "
                        "them; 1 is about a fifth quicker and follows skin that stretches far less closely")


def chosen_transfer_options(args):
    """The TransferOptions that --method, --correspondence and --texture-passes choose."""
    from ..expression import TransferOptions

    options = TransferOptions.published() if args.method == "published" else TransferOptions()
    if args.texture_passes is not None and args.method == "published":
        raise ValueError(f"--texture-passes {args.texture_passes} needs --method default: the method as published "
                         "registers no dense motion and tracks no texture")
    if args.texture_passes == 1:
        options = replace(options, motion=replace(options.motion, texture_refine_after=0))
    return replace(options, correspondence=args.correspondence)
