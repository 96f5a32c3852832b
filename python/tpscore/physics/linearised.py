"""The skin's springs, anchors and prisms linearised about a configuration: the
stiffness K = -df/dx and the damping D = -df/dv of the spring, anchor, volume and drag
forces, as sparse (3n, 3n) matrices. The simulation takes their largest eigenvalues (against the masses)
for its stable step; the NumPy reference of the compiled step (:mod:`tpscore.reference.skin`)
adds the skull contact's rows and assembles its implicit step from them.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp

__all__ = ["spring_state", "spring_stiffness_matrix", "spring_damping_matrix", "prism_volumes",
           "oriented_prisms", "prism_stiffness_matrix"]

#: The three tetrahedra of a prism (top a b c = corners 0 1 2 over A B C = 3 4 5).
PRISM_TETRAHEDRA = ((0, 1, 2, 3), (1, 2, 3, 4), (2, 3, 4, 5))


def spring_state(arrays, positions):
    """Per spring: unit direction first -> second (s, 3), length, force (tension > 0), slope."""
    delta = positions[arrays.spring_second] - positions[arrays.spring_first]
    length = np.linalg.norm(delta, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.where(length[:, None] > 0, delta / length[:, None], 0.0)
    extension = length - arrays.spring_rest
    limit = arrays.spring_knee * arrays.spring_rest
    beyond = np.abs(extension) > limit
    high = arrays.spring_stiffness * limit + arrays.spring_stiffness_high * (np.abs(extension) - limit)
    force = np.where(beyond, np.sign(extension) * high, arrays.spring_stiffness * extension)
    slope = np.where(beyond, arrays.spring_stiffness_high, arrays.spring_stiffness)
    return direction, length, force, slope


def spring_blocks(arrays, positions, tension_only: bool = True):
    """Per spring: the 3 x 3 stiffness block -dF/dx and the damping direction outer product."""
    direction, length, force, slope = spring_state(arrays, positions)
    along = np.einsum("si,sj->sij", direction, direction)
    geometric = force if not tension_only else np.maximum(force, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(length > 0, geometric / length, 0.0)
    stiffness = slope[:, None, None] * along + ratio[:, None, None] * (np.eye(3) - along)
    return stiffness, along


def assemble_springs(n, first, second, blocks, diagonal_extra):
    """(3n, 3n) matrix with +B on both diagonal blocks and -B off the diagonal, per spring."""
    rows, cols, vals = [], [], []
    r = np.arange(3)
    for a, b, sign in ((first, first, 1.0), (second, second, 1.0), (first, second, -1.0), (second, first, -1.0)):
        rows.append((3 * a[:, None, None] + r[None, :, None]).repeat(3, axis=2).reshape(-1))
        cols.append((3 * b[:, None, None] + r[None, None, :]).repeat(3, axis=1).reshape(-1))
        vals.append(sign * blocks.reshape(-1))
    matrix = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(3 * n, 3 * n)).tocsr()
    return matrix + sp.diags(np.repeat(diagonal_extra, 3))


def spring_stiffness_matrix(arrays, positions, *, tension_only: bool = True) -> sp.csr_matrix:
    """K of the springs and anchors at ``positions`` (3n, 3n); with ``tension_only`` the
    geometric term of compressed springs is dropped, as the implicit step does."""
    n = len(arrays.masses)
    blocks, _ = spring_blocks(arrays, np.asarray(positions, dtype=np.float64), tension_only)
    anchor = np.zeros(n)
    np.add.at(anchor, arrays.anchor_particle, arrays.anchor_stiffness)
    return assemble_springs(n, arrays.spring_first, arrays.spring_second, blocks, anchor)


def spring_damping_matrix(arrays, positions) -> sp.csr_matrix:
    """D of the springs' damping along each spring, the anchors' damping and the drag
    at ``positions`` (3n, 3n)."""
    n = len(arrays.masses)
    _, along = spring_blocks(arrays, np.asarray(positions, dtype=np.float64))
    diagonal = arrays.drag * arrays.masses.copy()
    np.add.at(diagonal, arrays.anchor_particle, arrays.anchor_damping)
    return assemble_springs(n, arrays.spring_first, arrays.spring_second,
                            arrays.spring_damping[:, None, None] * along, diagonal)


def prism_volumes(arrays, positions):
    """Per prism: its volume (p,) as three tetrahedra and the gradient (p, 6, 3) of the
    volume with respect to its six corners."""
    x = np.asarray(positions, dtype=np.float64)[arrays.prism_particles]  # (p, 6, 3)
    volume = np.zeros(len(x))
    gradient = np.zeros_like(x)
    for i0, i1, i2, i3 in PRISM_TETRAHEDRA:
        e1, e2, e3 = x[:, i1] - x[:, i0], x[:, i2] - x[:, i0], x[:, i3] - x[:, i0]
        g1, g2, g3 = np.cross(e2, e3) / 6.0, np.cross(e3, e1) / 6.0, np.cross(e1, e2) / 6.0
        volume += np.einsum("ij,ij->i", e1, g1)
        gradient[:, i1] += g1
        gradient[:, i2] += g2
        gradient[:, i3] += g3
        gradient[:, i0] -= g1 + g2 + g3
    return volume, gradient


def oriented_prisms(particles, positions):
    """(p, 6) prism corners, each read from the other side (the three below first) where
    its volume at ``positions`` is negative, and their volumes (p,) in that order."""
    particles = np.array(particles, dtype=np.int64, copy=True)
    volume, _ = prism_volumes(SimpleNamespace(prism_particles=particles), positions)
    flip = volume < 0
    particles[flip] = particles[flip][:, [3, 4, 5, 0, 1, 2]]
    volume, _ = prism_volumes(SimpleNamespace(prism_particles=particles), positions)
    return particles, volume


def prism_stiffness_matrix(arrays, positions) -> sp.csr_matrix:
    """The Gauss-Newton part k g g^T of the prisms' volume stiffness (3n, 3n), g each
    prism's volume gradient: positive semi-definite, what the implicit step uses."""
    n = len(arrays.masses)
    _, gradient = prism_volumes(arrays, positions)
    flat = gradient.reshape(len(gradient), 18)
    blocks = arrays.prism_stiffness[:, None, None] * np.einsum("pi,pj->pij", flat, flat)
    index = (3 * arrays.prism_particles[:, :, None] + np.arange(3)).reshape(len(gradient), 18)
    rows = np.repeat(index, 18, axis=1).reshape(-1)
    cols = np.tile(index, (1, 18)).reshape(-1)
    return sp.coo_matrix((blocks.reshape(-1), (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
