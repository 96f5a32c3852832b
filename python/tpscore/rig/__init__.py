"""Rigs: every expression of a source person transferred onto one target person, as the
target's neutral face with one morph target per expression, written as glTF 2.0 (or
USD), which animation tools open as shape keys (docs/rig.md).

``tpscore.rig(source_neutral, expressions, target, ...)`` makes one: the package is
callable as :func:`tpscore.rig.build.rig`. One module per stage: where the source's
scans come from (:mod:`~tpscore.rig.sources`), the transfers and the rig made of them
(:mod:`~tpscore.rig.build`), the targets' names with ARKit's table
(:mod:`~tpscore.rig.names`), and the writers (:mod:`~tpscore.rig.gltf`,
:mod:`~tpscore.rig.usd`).
"""
from __future__ import annotations

import inspect
import sys
import types

from . import build
from .build import MorphTarget, Rig, rig
from .gltf import write_gltf
from .names import ARKIT_NAMES, ARKIT_TABLE, plan_targets
from .sources import source_scans

__all__ = ["rig", "Rig", "MorphTarget", "write_gltf", "source_scans", "plan_targets", "ARKIT_NAMES",
           "ARKIT_TABLE"]


class _CallablePackage(types.ModuleType):
    # ``tpscore.rig`` is both the package and its main function: a function bound to the
    # package's name in tpscore would hide the package's modules from attribute access
    # and from ``import tpscore.rig.names as names``, so the package itself is callable.
    def __call__(self, *args, **kwargs) -> Rig:
        return build.rig(*args, **kwargs)

    __call__.__doc__ = build.rig.__doc__
    __call__.__signature__ = inspect.signature(build.rig).replace(parameters=[
        inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY),
        *inspect.signature(build.rig).parameters.values()])


sys.modules[__name__].__class__ = _CallablePackage
