"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private.
"""
from __future__ import annotations

from ._core import num_threads, set_num_threads
from .csrbf import CSRBF, ConvergenceError, wendland
from .mesh import (
    MeanCurvature,
    boundary_vertices,
    cotan_laplacian,
    face_normals,
    mass_matrix,
    mean_curvature,
    vertex_normals,
    voronoi_areas,
)
from .spatial import KDTree

__version__ = "0.1.0"

__all__ = [
    "KDTree",
    "num_threads",
    "set_num_threads",
    # compactly supported RBF
    "CSRBF",
    "ConvergenceError",
    "wendland",
    # mesh operators
    "MeanCurvature",
    "boundary_vertices",
    "cotan_laplacian",
    "face_normals",
    "mass_matrix",
    "mean_curvature",
    "vertex_normals",
    "voronoi_areas",
]
