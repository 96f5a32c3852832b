"""A scan to fit, read from its files: its surface and its landmarks (the given file,
the one beside the scan, or landmarks detected from the scan). The commands that fit a
template to a scan (``tpscore adapt``, ``tpscore simulate``, adaptation jobs of
``tpscore batch``) read their scans through it."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from . import io
from .detect import LandmarksDetectedWarning, detect_landmarks
from .grid import FaceGrid

__all__ = ["read_scan_surface", "read_scan_landmarks"]


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


def read_scan_landmarks(scan, given=None) -> np.ndarray:
    """The scan's landmarks (22, 3): from ``given`` (a landmark file) if any, else from the
    landmark file beside the scan, else detected from the scan itself
    (:func:`tpscore.detect_landmarks`), which a one-line
    :class:`~tpscore.face.detect.LandmarksDetectedWarning` reports (as ``load_scan``
    does)."""
    path = given if given is not None else io.landmark_file_beside(scan)
    if path is not None:
        return io.read_landmarks(path)
    # a .bnt is detected from its path, so that the colour image beside it is read too
    source = scan if Path(scan).suffix.lower() == ".bnt" else io.read_mesh(scan)[0]
    landmarks = detect_landmarks(source)
    found = int(np.isfinite(landmarks).all(axis=1).sum())
    warnings.warn(f"no landmark file beside {str(scan)!r} (looked for .lm3, .csv, .json): {found} of "
                  f"{len(landmarks)} landmarks detected from the scan (a landmark file gives your own)",
                  LandmarksDetectedWarning, stacklevel=2)
    return landmarks
