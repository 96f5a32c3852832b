"""The published refinement levels (``refinement="interpolate"``, see
:meth:`~tpscore.adaptation.AdaptOptions.published`): each level interpolates the residuals of
the fit so far at the level's correspondences.

The correspondences accumulate: the feature points, the feature mesh's new points at
every level, and the template vertices of largest mean curvature paired by rays along
the deformed normals. A global biharmonic RBF interpolates them while they are few, a
compactly supported RBF with local quadrics after.
"""
from __future__ import annotations

import numpy as np

from ..csrbf import CSRBF
from ..face.landmarks import landmark_index
from ..rbf import RBF
from .correspondence import FeatureMesh, curvature_features
from .levels import LevelFit
from .options import AdaptOptions
from .result import evaluate_fields
from .setup import AdaptSetup

__all__ = ["InterpolatedLevels", "DENSE_PAIRS"]

#: A level with fewer pairs than this is a global RBF, one with more a CSRBF: the dense
#: solve costs O(pairs^3), and a few hundred pairs cannot resolve fine supports anyway.
DENSE_PAIRS = 500


class InterpolatedLevels:
    """The ``"interpolate"`` refinement: the method's correspondences, interpolated."""

    def __init__(self, setup: AdaptSetup, options: AdaptOptions):
        self.setup = setup
        self.options = options
        self.feature_mesh = None
        if len(setup.landmark_sources) >= 3:
            view = setup.view if setup.view is not None else (0.0, 0.0, 1.0)
            try:
                self.feature_mesh = FeatureMesh.build(setup.landmark_sources, setup.landmark_targets, view)
            except ValueError:  # the feature points are collinear in the view: no feature mesh
                self.feature_mesh = None
        self.curvature_vertices = np.zeros(0, dtype=np.int64)
        if options.curvature_count > 0:
            box = feature_box_corners(options.feature_box, setup)
            self.curvature_vertices = curvature_features(setup.template_vertices, setup.template_faces,
                                                         options.curvature_count, box=box,
                                                         spacing=0.01 * setup.width)
        self.mesh_template = np.zeros((0, 3))
        self.mesh_scan = np.zeros((0, 3))

    def finished(self, support: float) -> bool:
        """The published levels run until E rises or the levels run out."""
        return False

    def fit(self, level: int, support: float, fields, deformed: np.ndarray, normals: np.ndarray) -> LevelFit:
        """The offset of one level: the residuals of the levels `fields` at the pairs."""
        setup, options = self.setup, self.options
        new = 0
        if self.feature_mesh is not None:
            self.feature_mesh, new_template, new_scan = self.feature_mesh.subdivide(
                setup.template_surface, setup.target, max_distance=setup.max_ray * 2)
            self.mesh_template = np.vstack([self.mesh_template, new_template])
            self.mesh_scan = np.vstack([self.mesh_scan, new_scan])
            new += len(new_template)
        chosen = self.curvature_vertices
        hit, hit_points = setup.target.cast(deformed[chosen], normals[chosen], max_distance=setup.max_ray,
                                            view_direction=setup.view)
        ray_template, ray_scan = setup.template_vertices[chosen[hit]], hit_points[hit]
        new += len(ray_template)

        template_points = np.vstack([setup.landmark_sources, self.mesh_template, ray_template])
        scan_points = np.vstack([setup.landmark_targets, self.mesh_scan, ray_scan])
        sources = np.array(["landmark"] * len(setup.landmark_sources) + ["feature-mesh"] * len(self.mesh_template)
                           + ["curvature"] * len(ray_template), dtype=object)
        template_points, scan_points, sources = _dedupe(template_points, scan_points, sources, 1e-3 * setup.width)
        residual = scan_points - evaluate_fields(fields, template_points)
        if len(template_points) < DENSE_PAIRS:
            method, support = "rbf", float("nan")
            offset = RBF(template_points, residual, "biharmonic", smoothing=options.rho)
        else:
            method = "csrbf"
            # The quadrics' tangent frames come from the centres themselves (weighted PCA):
            # the pairs lie on the template, so their spread is flattest along its normal.
            offset = CSRBF(template_points, residual, support, quadric=True, smoothing=options.csrbf_smoothing,
                           tolerance=1e-8)
        pairs = (template_points, scan_points, sources)
        return LevelFit(method, support, offset, deformed + offset(setup.template_vertices), pairs, new)


def feature_box_corners(box, setup: AdaptSetup):
    """The curvature search's box (lower, upper corners) in the template frame, or None.

    Named landmarks give their bounding box plus 5 % of the template's width.
    """
    if box is None:
        return None
    if isinstance(box[0], str):
        if setup.names is None:
            raise ValueError("AdaptOptions.feature_box names landmarks, but the feature points are not the 22 "
                             "Bosphorus landmarks; give two corners or None")
        rows = setup.feature_points[[landmark_index(name) for name in box]]
        rows = rows[np.isfinite(rows).all(axis=1)]
        if len(rows) == 0:
            return None
        margin = 0.05 * setup.width
        return rows.min(axis=0) - margin, rows.max(axis=0) + margin
    return tuple(np.asarray(corner, dtype=np.float64) for corner in box)


def _dedupe(template_points, scan_points, sources, tolerance: float):
    """Keep the first of pairs whose template points are closer than `tolerance`."""
    if len(template_points) < 2:
        return template_points, scan_points, sources
    keys = np.floor(template_points / tolerance).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return template_points[first], scan_points[first], sources[first]
