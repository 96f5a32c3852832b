"""The expression registration's data terms (``cpp/include/tpscore/registration_terms.hpp``):
per data point, the 3 x 3 normal-equation block (as its six symmetric entries) and
right-hand side of the geometry term (point to plane, Tukey-weighted) and of the texture
term (a pull along the surface toward a texture match). The callers
(:mod:`tpscore.expression.registration`) hand arrays that are already checked; this
module makes them contiguous. NumPy reference:
:mod:`tpscore.reference.registration`, which agrees to the bit.
"""
from __future__ import annotations

import numpy as np

from . import _core

__all__ = ["point_to_plane_terms", "texture_pull_terms"]


def _float64(array) -> np.ndarray:
    """A C-contiguous float64 array, as the kernels take it (no copy when it is one)."""
    return np.ascontiguousarray(array, dtype=np.float64)


def point_to_plane_terms(sample, moved, closest, distances, normals, prior, floor: float,
                         tukey_factor: float):
    """Blocks (m, 6), right-hand sides (m, 3), each pair's distance along the normal (m,)
    and weight (m,) of the point-to-plane term; the Tukey scale is the robust scale of
    the distances, at least ``floor`` mm."""
    return _core.point_to_plane_terms(_float64(sample), _float64(moved), _float64(closest), _float64(distances),
                                      _float64(normals), _float64(prior), float(floor), float(tukey_factor))


def texture_pull_terms(sample, moved, targets, normals, prior, floor: float, tukey_factor: float):
    """Blocks (m, 6) and right-hand sides (m, 3) of the texture term: w P and
    w P (q - s), P = I - n n^T, w the match's weight times a Tukey weight of the
    tangential residual (scale at least ``floor`` mm)."""
    return _core.texture_pull_terms(_float64(sample), _float64(moved), _float64(targets), _float64(normals),
                                    _float64(prior), float(floor), float(tukey_factor))
