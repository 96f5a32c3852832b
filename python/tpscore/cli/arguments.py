"""Parsing of the arguments several subcommands share."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..face import io
from ..face.grid import MAX_GRID_VERTICES, FaceGrid

__all__ = ["grid_shape", "integer", "read_scan_surface", "scan_landmarks_path"]


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


def read_scan_surface(path) -> tuple:
    """A scan as (vertices, faces): a Bosphorus .bnt triangulated on its grid, or a mesh
    with faces (a point cloud cannot be fitted)."""
    if Path(path).suffix.lower() == ".bnt":
        mesh = FaceGrid.from_points(io.read_bnt(path).points).mesh()
        return mesh.vertices, mesh.faces
    scan = io.read_mesh(path)
    if len(scan[1]) == 0:
        raise ValueError(f"{str(path)!r}: the scan has no faces; give a mesh or a .bnt grid")
    return scan


def scan_landmarks_path(scan, given=None):
    """``--scan-landmarks`` if given, else the landmark file beside the scan."""
    if given is not None:
        return given
    found = io.landmark_file_beside(scan)
    if found is None:
        raise ValueError(f"no landmark file beside {str(scan)!r}; pass --scan-landmarks")
    return found
