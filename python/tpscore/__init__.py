"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private. Procedural faces are in
:mod:`tpscore.datasets` and headless rendering in :mod:`tpscore.render`.
"""
from __future__ import annotations

from . import datasets, landmarks, render
from ._threads import max_threads, num_threads, set_num_threads
from .action_units import ActionUnit, ActionUnitLibrary, ControlPoint, default_library
from .average_face import AverageFace, build_average_face, load_average_face
from .expression_transfer import (
    Animation,
    ExpressionModel,
    NormalisedFace,
    TransferOptions,
    TransferResult,
    animate,
    model_expression,
    normalise_face,
    transfer,
)
from .alignment import RigidAlignment, align_rigid, fit_mirror_symmetry
from .motion import DenseMotion, MirroredMotion, MotionOptions, register_surfaces
from .adaptation import AdaptationWarning, AdaptLevel, AdaptResult, Correspondences, adapt
from .calibration import AxesCalibration, axes_calibration, calibrate
from .correspondence import FeatureMesh, curvature_features
from .csrbf import CSRBF, ConvergenceError, wendland
from .elastic import ElasticFace, ExpressionSet
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
from .normalise import FrameTransform, similarity_transform, thesis_affine_transform
from .preprocess import FaceGrid, GridMesh, LandmarkSnapWarning, load_scan, resample_scan
from .rbf import RBF, RBF_KERNELS, TPS
from .sparse import PatternCholesky, SparseCholesky
from .spatial import ClosestPoints, KDTree, MeshSurface, RayHits, closest_point_on_mesh

__version__ = "0.1.0"

__all__ = [
    # kernels
    "RBF",
    "RBF_KERNELS",
    "TPS",
    "ClosestPoints",
    "KDTree",
    "MeshSurface",
    "RayHits",
    "closest_point_on_mesh",
    "max_threads",
    "num_threads",
    "set_num_threads",
    # scan and mesh files
    "BntScan",
    "read_bnt",
    "write_bnt",
    "read_lm3",
    "write_lm3",
    "read_landmarks",
    "write_landmarks",
    "read_mesh",
    "write_mesh",
    # preprocessing
    "FaceGrid",
    "GridMesh",
    "LandmarkSnapWarning",
    "resample_scan",
    "load_scan",
    # expression transfer
    "ActionUnit",
    "ActionUnitLibrary",
    "ControlPoint",
    "default_library",
    "AverageFace",
    "build_average_face",
    "load_average_face",
    "FrameTransform",
    "similarity_transform",
    "thesis_affine_transform",
    "NormalisedFace",
    "normalise_face",
    "TransferOptions",
    "align_rigid",
    "RigidAlignment",
    "fit_mirror_symmetry",
    "register_surfaces",
    "DenseMotion",
    "MirroredMotion",
    "MotionOptions",
    "ExpressionModel",
    "model_expression",
    "Animation",
    "animate",
    "TransferResult",
    "transfer",
    # submodules
    "datasets",
    "render",
    # compactly supported RBF
    "CSRBF",
    "ConvergenceError",
    "wendland",
    # template adaptation
    "adapt",
    "AdaptResult",
    "AdaptLevel",
    "AdaptationWarning",
    "Correspondences",
    "AxesCalibration",
    "axes_calibration",
    "calibrate",
    "FeatureMesh",
    "curvature_features",
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
    "PatternCholesky",
    "SparseCholesky",
    # elastic expression model
    "ElasticFace",
    "ExpressionSet",
    "LinearMuscle",
    "MuscleModel",
    "SphincterMuscle",
]
