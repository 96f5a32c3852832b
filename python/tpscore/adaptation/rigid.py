"""Rigid parts of a template (eyes, teeth): they keep their shape and follow the
similarity of the feature points nearest to them."""
from __future__ import annotations

import numpy as np

from ..face.normalise import similarity_transform

__all__ = ["move_rigid_parts"]

# Six feature points around a part fix a similarity and still describe only its
# neighbourhood (an eye's corners and brow, not the chin).
_NEAREST_FEATURE_POINTS = 6


def move_rigid_parts(deformed, template_vertices, parts, feature_points, fitted_feature_points) -> None:
    """Move each part (in place in `deformed`) by the similarity that best maps its
    nearest feature points onto where the fit took them.

    Parameters
    ----------
    deformed : (n, 3) ndarray
        The fitted template's vertices (template frame, mm); changed in place.
    template_vertices : (n, 3) ndarray
        The undeformed template.
    parts : sequence of int ndarray
        Vertex indices of each rigid part.
    feature_points, fitted_feature_points : (f, 3) ndarray
        The template's fitted feature points and where the fit maps them.
    """
    for part in parts:
        if part.size == 0:
            continue
        centre = template_vertices[part].mean(axis=0)
        nearest = np.argsort(np.linalg.norm(feature_points - centre, axis=1))[:_NEAREST_FEATURE_POINTS]
        motion = similarity_transform(feature_points[nearest], fitted_feature_points[nearest])
        deformed[part] = motion.apply(template_vertices[part])
