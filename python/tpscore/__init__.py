"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private.
"""
from __future__ import annotations

from ._core import num_threads, set_num_threads
from .io import (
    BntScan,
    read_bnt,
    read_landmarks,
    read_lm3,
    read_mesh,
    write_bnt,
    write_landmarks,
    write_lm3,
    write_mesh,
)
from .preprocess import FaceGrid, GridMesh, LandmarkSnapWarning, load_scan, resample_scan

__version__ = "0.1.0"

__all__ = [
    "num_threads",
    "set_num_threads",
    # io
    "BntScan",
    "read_bnt",
    "write_bnt",
    "read_lm3",
    "write_lm3",
    "read_landmarks",
    "write_landmarks",
    "read_mesh",
    "write_mesh",
    # preprocess
    "FaceGrid",
    "GridMesh",
    "LandmarkSnapWarning",
    "resample_scan",
    "load_scan",
]
