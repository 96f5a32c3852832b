"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private. Procedural faces are in
:mod:`tpscore.datasets` and headless rendering in :mod:`tpscore.render`.
"""
from __future__ import annotations

from . import datasets, render
from ._core import num_threads, set_num_threads
from .elastic import ElasticFace, ExpressionSet
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
from .muscles import LinearMuscle, MuscleModel, SphincterMuscle
from .rbf import RBF, RBF_KERNELS, TPS
from .sparse import SparseCholesky
from .spatial import ClosestPoints, KDTree, MeshSurface, RayHits, closest_point_on_mesh

__version__ = "0.1.0"

__all__ = [
    "ClosestPoints",
    "KDTree",
    "MeshSurface",
    "RayHits",
    "closest_point_on_mesh",
    "RBF",
    "RBF_KERNELS",
    "TPS",
    "num_threads",
    "set_num_threads",
    "datasets",
    "render",
    # mesh operators
    "MeanCurvature",
    "boundary_vertices",
    "cotan_laplacian",
    "face_normals",
    "mass_matrix",
    "mean_curvature",
    "vertex_normals",
    "voronoi_areas",
    # sparse direct solve
    "SparseCholesky",
    # elastic expression model
    "ElasticFace",
    "ExpressionSet",
    "LinearMuscle",
    "MuscleModel",
    "SphincterMuscle",
]
