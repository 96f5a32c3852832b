"""tpscore: thin-plate splines and radial basis functions for 3D faces.

The public API lives in the submodules and is re-exported here; the compiled
kernels in ``tpscore._core`` are private.
"""
from __future__ import annotations

from ._core import num_threads, set_num_threads
from .datasets import (
    ACTION_UNITS,
    FaceParameters,
    SyntheticScan,
    au_displacement,
    demo_triplet,
    embedded_faces,
    face_height,
    face_landmarks,
    make_face,
    random_identity,
    sample_subjects,
)
from .render import (
    Camera,
    error_heatmap,
    fit_camera,
    grid_mesh,
    heatmap_colors,
    render_grid,
    render_mesh,
    save_gif,
    save_png,
    side_by_side,
)

__version__ = "0.1.0"

__all__ = [
    "num_threads",
    "set_num_threads",
    # procedural faces
    "ACTION_UNITS",
    "FaceParameters",
    "SyntheticScan",
    "au_displacement",
    "demo_triplet",
    "embedded_faces",
    "face_height",
    "face_landmarks",
    "make_face",
    "random_identity",
    "sample_subjects",
    # headless rendering
    "Camera",
    "error_heatmap",
    "fit_camera",
    "grid_mesh",
    "heatmap_colors",
    "render_grid",
    "render_mesh",
    "save_gif",
    "save_png",
    "side_by_side",
]
