"""Elastic surface parameterisation of expressions: a face deforms by minimising a
stretching and bending energy with its facial control points as handles, so that an
expression is a few displacements per control point (method notes: ``docs/elastic.md``).

* :mod:`~tpscore.elastic.control_points` -- the control points, defined relative to the
  landmarks, placed on a mesh and carried onto another face;
* :mod:`~tpscore.elastic.energy` -- the energy, the fixed region and the per-handle basis;
* :mod:`~tpscore.elastic.model` -- :class:`ElasticFace` and its :class:`ElasticOptions`;
* :mod:`~tpscore.elastic.fitting` -- expressions learned by least squares and blended;
* :mod:`~tpscore.elastic.cloning` -- displacements carried between faces' frames;
* :mod:`~tpscore.elastic.muscles` -- linear and sphincter muscles that drive the points.
"""
from .control_points import (ElasticControlPoint, default_control_points, load_control_points, place_control_points,
                             transfer_control_points)
from .energy import ElasticOptions, default_fixed_region
from .fitting import ExpressionSet
from .model import ElasticFace
from .muscles import EMOTIONS, LinearMuscle, MuscleModel, SphincterMuscle, load_muscles

__all__ = [
    "ElasticFace",
    "ElasticOptions",
    "ExpressionSet",
    "ElasticControlPoint",
    "default_control_points",
    "load_control_points",
    "place_control_points",
    "transfer_control_points",
    "default_fixed_region",
    "LinearMuscle",
    "SphincterMuscle",
    "MuscleModel",
    "load_muscles",
    "EMOTIONS",
]
