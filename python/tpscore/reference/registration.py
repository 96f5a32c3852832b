"""NumPy reference for the registration's data terms (the compiled kernels behind
:mod:`tpscore.expression.registration`): the same arithmetic in the same order, so the
two agree to the bit; tests compare them."""
from __future__ import annotations

import numpy as np

from ..geometry import off_surface, robust_scale, tukey_weights
from ..lattice import SYMMETRIC_ENTRIES

__all__ = ["point_to_plane_terms", "texture_pull_terms"]

_IDENTITY_BLOCK = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])   # I as symmetric entries
_UPPER_I, _UPPER_J = np.array(SYMMETRIC_ENTRIES).T


def point_to_plane_terms(sample, moved, closest, distances, normals, prior, floor, tukey_factor):
    """Blocks (m, 6) w n n^T, right-hand sides (m, 3), distances along the normal (m,)
    and weights (m,) of the point-to-plane pairs (see registration_terms.hpp)."""
    along = np.einsum("ij,ij->i", moved - closest, normals)
    rim = off_surface(along, distances)
    scale = robust_scale(distances[~rim], floor)
    w = np.where(rim, 0.0, tukey_weights(distances, tukey_factor * scale)) * prior
    blocks = w[:, None] * (normals[:, _UPPER_I] * normals[:, _UPPER_J])
    to_plane = np.einsum("ij,ij->i", closest - sample, normals)
    return blocks, normals * (w * to_plane)[:, None], along, w


def texture_pull_terms(sample, moved, targets, normals, prior, floor, tukey_factor):
    """Blocks (m, 6) w P and right-hand sides (m, 3) w P (q - s) of the texture pulls,
    P = I - n n^T (see registration_terms.hpp)."""
    offset = moved - targets
    offset -= np.einsum("ij,ij->i", offset, normals)[:, None] * normals
    residual = np.linalg.norm(offset, axis=1)
    used = prior > 0
    scale = robust_scale(residual[used], floor)
    w = np.where(used, tukey_weights(residual, tukey_factor * scale), 0.0) * prior
    blocks = w[:, None] * (_IDENTITY_BLOCK - normals[:, _UPPER_I] * normals[:, _UPPER_J])
    to_target = targets - sample
    to_target -= np.einsum("ij,ij->i", to_target, normals)[:, None] * normals
    return blocks, w[:, None] * to_target
