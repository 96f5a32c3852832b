"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private. The showcase (:mod:`tpscore.showcase`) holds
the procedural faces (:mod:`tpscore.showcase.datasets`), the demo's faces
(:mod:`tpscore.showcase.demo_faces`), headless rendering (:mod:`tpscore.showcase.render`)
and the browser page of a result (:mod:`tpscore.showcase.viewer`); ``tpscore.datasets``,
``tpscore.render`` and ``tpscore.viewer`` name the same modules. Rigs of morph targets
for animation tools are in :mod:`tpscore.rigging` (``tpscore.rig(...)`` makes one).
"""
from __future__ import annotations

from . import physics
from .showcase import datasets, render, viewer
from ._version import __version__
from ._threads import max_threads, num_threads, set_num_threads
from .face.average_face import AverageFace, build_average_face, load_average_face
from .expression import (
    ActionUnit,
    ActionUnitLibrary,
    Animation,
    ControlPoint,
    DenseMotion,
    ExpressionModel,
    MirroredMotion,
    MotionOptions,
    PersonMismatchError,
    PersonMismatchWarning,
    RigidAlignment,
    TextureOptions,
    TextureWarning,
    TransferOptions,
    TransferResult,
    align_rigid,
    animate,
    default_library,
    fit_mirror_symmetry,
    model_expression,
    register_surfaces,
    track_texture,
    transfer,
)
from .adaptation import (
    AdaptationWarning,
    AdaptLevel,
    AdaptOptions,
    AdaptResult,
    AxesCalibration,
    Correspondences,
    FeatureMesh,
    adapt,
    axes_calibration,
    calibrate,
    curvature_features,
)
from .csrbf import CSRBF, ConvergenceError, wendland
from .elastic import ElasticFace, ElasticOptions, ExpressionSet, LinearMuscle, MuscleModel, SphincterMuscle
from .face.io import (
    BntScan,
    ColourWarning,
    MeshColours,
    read_bnt,
    read_landmarks,
    read_lm3,
    read_mesh,
    read_mesh_colours,
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
from .face.normalise import FrameTransform, NormalisedFace, normalise_face, similarity_transform, thesis_affine_transform
from .face.detect import LandmarksDetectedWarning, detect_landmarks
from .face.grid import FaceGrid, GridMesh, LandmarkSnapWarning
from .face.loading import load_scan, load_scans
from .face.resampling import resample_scan
from .face.pose import ImplausibleLandmarksError, ImplausibleLandmarksWarning, MirroredLandmarksError, ScanPose, scan_pose
from .rbf import RBF, RBF_KERNELS, TPS
from .sparse import PatternCholesky, SparseCholesky
from .spatial import ClosestPoints, KDTree, MeshSurface, RayHits, closest_point_on_mesh
from . import batch  # after the methods it runs in batches
from .rigging import Rig, rig, write_gltf


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
    "read_mesh_colours",
    "MeshColours",
    "ColourWarning",
    "write_mesh",
    # preprocessing
    "FaceGrid",
    "GridMesh",
    "LandmarkSnapWarning",
    "LandmarksDetectedWarning",
    "detect_landmarks",
    "resample_scan",
    "ScanPose",
    "scan_pose",
    "MirroredLandmarksError",
    "ImplausibleLandmarksError",
    "ImplausibleLandmarksWarning",
    "load_scan",
    "load_scans",
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
    "TextureOptions",
    "track_texture",
    "ExpressionModel",
    "model_expression",
    "Animation",
    "animate",
    "TransferResult",
    "transfer",
    "PersonMismatchError",
    "PersonMismatchWarning",
    "TextureWarning",
    # rigs of morph targets
    "Rig",
    "rig",
    "write_gltf",
    # submodules
    "batch",
    "datasets",
    "physics",
    "render",
    "showcase",
    "viewer",
    # compactly supported RBF
    "CSRBF",
    "ConvergenceError",
    "wendland",
    # template adaptation
    "adapt",
    "AdaptOptions",
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
    "ElasticOptions",
    "ExpressionSet",
    "LinearMuscle",
    "MuscleModel",
    "SphincterMuscle",
]
