"""Rigs: every expression of a source person transferred onto one target person, as the
target's neutral face with one morph target per expression, written as glTF 2.0 (or
USD), which animation tools open as shape keys (docs/rig.md).

``tpscore.rig(source_neutral, expressions, target, ...)`` makes one
(:func:`tpscore.rigging.build.rig`). One module per stage: where the source's
scans come from (:mod:`~tpscore.rigging.sources`), the transfers and the rig made of them
(:mod:`~tpscore.rigging.build`), the targets' names with ARKit's table
(:mod:`~tpscore.rigging.names`), and the writers (:mod:`~tpscore.rigging.gltf`,
:mod:`~tpscore.rigging.usd`).
"""
from __future__ import annotations

from .build import MorphTarget, Rig, rig
from .gltf import write_gltf
from .names import ARKIT_NAMES, ARKIT_TABLE, plan_targets
from .sources import source_scans

__all__ = ["rig", "Rig", "MorphTarget", "write_gltf", "source_scans", "plan_targets", "ARKIT_NAMES",
           "ARKIT_TABLE"]
