"""Parsing of the arguments several subcommands share."""
from __future__ import annotations

from ..face.grid import MAX_GRID_VERTICES

__all__ = ["grid_shape"]


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
