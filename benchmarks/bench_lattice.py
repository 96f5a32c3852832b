"""The dense registration's linear systems: tpscore.motion.LatticeSystem against the
SciPy assembly (tpscore.reference.lattice) with a fresh factorisation.

One registration iteration forms the normal equations of a point-to-plane fit of a
cubic B-spline field (8 mm node spacing) to every second vertex of a 150 x 150 face
grid (5625 samples over 110 x 150 mm, about 1400 unknowns), adds the bending energy,
and solves. tpscore assembles the data term with the compiled kernel straight into
the fixed pattern and refactorises without a new symbolic analysis; the reference
forms the sparse products with SciPy and factorises from scratch
(tpscore.SparseCholesky, so the two differ only in what the pattern saves).
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from tpscore.motion import BSplineLattice, LatticeSystem, symmetric_blocks
from tpscore.reference import lattice as reference
from tpscore.sparse import SparseCholesky

GROUP_ASSEMBLY = "lattice data term, 5625 samples, 8 mm lattice"
GROUP_ITERATION = "registration iteration (assemble + factorise + solve), 5625 samples"


def _problem():
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.linspace(-55, 55, 75), np.linspace(-75, 75, 75))
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    lattice = BSplineLattice(xy.min(axis=0), xy.max(axis=0), 8.0)
    normals = rng.normal(size=(len(xy), 3)) + [0.0, 0.0, 3.0]
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    w = rng.uniform(0.2, 1.0, len(xy))
    q = w[:, None, None] * normals[:, :, None] * normals[:, None, :]
    bending = sp.block_diag([lattice.bending()] * 3).tocsr()
    rhs = rng.normal(size=3 * lattice.n_nodes)
    return lattice, xy, q, bending, rhs


LATTICE, XY, Q, BENDING, RHS = _problem()
SYSTEM = LatticeSystem(LATTICE, XY)
BASIS = LATTICE.basis(XY)
BENDING_VALUES = SYSTEM.aligned(BENDING)
RIDGE = 1e-6 * sp.identity(SYSTEM.n, format="csr")
RIDGE_VALUES = SYSTEM.aligned(RIDGE)


def _tpscore_iteration():
    values = SYSTEM.data_term(symmetric_blocks(Q)) + BENDING_VALUES + RIDGE_VALUES
    return SYSTEM.solve(values, RHS)


def _scipy_iteration():
    matrix = reference.block_gram(BASIS, Q) + BENDING + RIDGE
    return SparseCholesky(sp.csc_matrix(matrix)).solve(RHS)


def test_data_term_tpscore(benchmark):
    benchmark.group = GROUP_ASSEMBLY
    blocks = symmetric_blocks(Q)
    values = benchmark(SYSTEM.data_term, blocks)
    expected = reference.block_gram(BASIS, Q)
    assert abs(SYSTEM.matrix(values) - expected).max() <= 1e-12 * abs(expected).max()


def test_data_term_scipy(benchmark):
    benchmark.group = GROUP_ASSEMBLY
    benchmark(reference.block_gram, BASIS, Q)


def test_iteration_tpscore(benchmark):
    benchmark.group = GROUP_ITERATION
    solution = benchmark(_tpscore_iteration)
    expected = _scipy_iteration()
    assert np.abs(solution - expected).max() <= 1e-8 * np.abs(expected).max()


def test_iteration_scipy(benchmark):
    benchmark.group = GROUP_ITERATION
    benchmark(_scipy_iteration)
