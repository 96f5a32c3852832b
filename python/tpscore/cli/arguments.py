"""Parsing of the arguments several subcommands share."""
from __future__ import annotations

from pathlib import Path

from ..face import io
from ..face.grid import MAX_GRID_VERTICES, FaceGrid

__all__ = ["grid_shape", "read_scan_surface", "scan_landmarks_path"]


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
