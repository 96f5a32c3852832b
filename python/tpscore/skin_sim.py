"""The layered skin's compiled system (``cpp/include/tpscore/skin_sim.hpp``): springs,
anchors, muscles and the skull contact of :mod:`tpscore.physics`, stepped and run in
C++. :class:`tpscore.physics.system.SkinArrays` validates every array first; this module
hands them to the core. NumPy reference: :mod:`tpscore.reference.skin`.
"""
from __future__ import annotations

from dataclasses import fields

from . import _core

__all__ = ["compiled_skin_system", "INTEGRATORS"]

#: The integrators a step may use, by name: semi-implicit (symplectic) Euler, or a
#: linearised backward Euler (re-assembled and factorised every step).
INTEGRATORS = {"symplectic": _core.SkinIntegrator.symplectic, "implicit": _core.SkinIntegrator.implicit}


def compiled_skin_system(arrays):
    """The compiled system of validated :class:`~tpscore.physics.system.SkinArrays`:
    ``forces``, ``step``, ``run``, ``project_contacts``, ``skull_heights`` and the
    energies, each releasing the GIL."""
    return _core.SkinSystem(**{f.name: getattr(arrays, f.name) for f in fields(arrays)})
