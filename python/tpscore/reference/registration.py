"""NumPy reference for the registration's data terms (the compiled kernels behind
:mod:`tpscore.expression.registration`): the same arithmetic in the same order, so the
two agree to the bit; tests compare them.

Row dot products and lengths are spelled out in the order NumPy's ``einsum("ij,ij->i")``
and ``linalg.norm(axis=1)`` take on x86-64 (which the registration used before it was
compiled), so that the reference does not depend on how another NumPy build orders them.
"""
from __future__ import annotations

import numpy as np

from ..geometry import off_surface, robust_scale, tukey_weights
from ..lattice import SYMMETRIC_ENTRIES

__all__ = ["point_to_plane_terms", "texture_pull_terms"]

_IDENTITY_BLOCK = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])   # I as symmetric entries
_UPPER_I, _UPPER_J = np.array(SYMMETRIC_ENTRIES).T


def _dot(u, v):
    """Row-wise u . v: ((0 + u0 v0) + u2 v2) + u1 v1."""
    p = u * v
    return ((0.0 + p[:, 0]) + p[:, 2]) + p[:, 1]


def _length(x):
    """Row-wise |x|: sqrt((x0^2 + x1^2) + x2^2)."""
    q = x * x
    return np.sqrt((q[:, 0] + q[:, 1]) + q[:, 2])


def point_to_plane_terms(sample, moved, closest, distances, normals, prior, floor, tukey_factor):
    """Blocks (m, 6) w n n^T, right-hand sides (m, 3), distances along the normal (m,)
    and weights (m,) of the point-to-plane pairs (see registration_terms.hpp)."""
    along = _dot(moved - closest, normals)
    rim = off_surface(along, distances)
    scale = robust_scale(distances[~rim], floor)
    w = np.where(rim, 0.0, tukey_weights(distances, tukey_factor * scale)) * prior
    blocks = w[:, None] * (normals[:, _UPPER_I] * normals[:, _UPPER_J])
    to_plane = _dot(closest - sample, normals)
    return blocks, normals * (w * to_plane)[:, None], along, w


def texture_pull_terms(sample, moved, targets, normals, prior, floor, tukey_factor):
    """Blocks (m, 6) w P and right-hand sides (m, 3) w P (q - s) of the texture pulls,
    P = I - n n^T (see registration_terms.hpp)."""
    offset = moved - targets
    offset -= _dot(offset, normals)[:, None] * normals
    residual = _length(offset)
    used = prior > 0
    scale = robust_scale(residual[used], floor)
    w = np.where(used, tukey_weights(residual, tukey_factor * scale), 0.0) * prior
    blocks = w[:, None] * (_IDENTITY_BLOCK - normals[:, _UPPER_I] * normals[:, _UPPER_J])
    to_target = targets - sample
    to_target -= _dot(to_target, normals)[:, None] * normals
    return blocks, w[:, None] * to_target
