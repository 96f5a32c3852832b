"""The physical skin of the head-adaptation method: a layered mass-spring-damper skin
over a skull, driven by muscles and the jaw, carried onto any fitted head.
"""
from __future__ import annotations

from .fitting import carry_head, deform_from_vertices, fit_head
from .head import Head, build_template, load_template
from .layers import SkinLayers, SkinMaterial, build_layers
from .muscles import SkinLinearMuscle, SkinSphincterMuscle, SurfacePoint, place_muscles
from .simulation import SimulationError, SimulationOptions, SkinModel, SkinSimulation, SkinWarning
from .system import SkinArrays

__all__ = [
    "Head",
    "build_template",
    "load_template",
    "SkinMaterial",
    "SkinLayers",
    "build_layers",
    "SkinLinearMuscle",
    "SkinSphincterMuscle",
    "SurfacePoint",
    "place_muscles",
    "SkinModel",
    "SimulationOptions",
    "SkinSimulation",
    "SkinWarning",
    "SimulationError",
    "SkinArrays",
    "carry_head",
    "deform_from_vertices",
    "fit_head",
]
