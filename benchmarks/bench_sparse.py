"""Sparse direct solve: tpscore.SparseCholesky against SciPy's SuperLU (splu).

The systems are those the elastic face model solves: the bi-Laplacian
L M^-1 L of a face-like height-field grid restricted to its free vertices (the border
rows held fixed), factorised once and solved for 47 right-hand sides (one per control
point). Each benchmark times factorisation plus solve, as the model uses them.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from tpscore import mesh
from tpscore.reference import sparse as reference
from tpscore.sparse import SparseCholesky

SIZES = [60, 100, 150]
RHS = 47


def face_like_grid(rows, cols):
    x, y = np.meshgrid(np.linspace(-75, 75, cols), np.linspace(-90, 90, rows))
    z = 60 * np.exp(-(x**2 / (2 * 55**2) + y**2 / (2 * 70**2))) + 18 * np.exp(
        -(x**2 / (2 * 9**2) + (y + 5) ** 2 / (2 * 16**2)))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return vertices, faces, index


def bilaplacian_system(size):
    vertices, faces, index = face_like_grid(size, size)
    laplacian = mesh.cotan_laplacian(vertices, faces)
    operator = laplacian @ sp.diags(1.0 / mesh.voronoi_areas(vertices, faces)) @ laplacian
    border = np.zeros((size, size), dtype=bool)
    border[:2, :] = border[-2:, :] = border[:, :2] = border[:, -2:] = True
    free = np.flatnonzero(~border.ravel())
    matrix = sp.csc_matrix(operator[free][:, free])
    matrix = (matrix + matrix.T) * 0.5
    rhs = np.random.default_rng(size).normal(size=(len(free), RHS))
    return matrix, rhs


_SYSTEMS = {size: bilaplacian_system(size) for size in SIZES}


def _tpscore(matrix, rhs):
    return SparseCholesky(matrix).solve(rhs)


def _splu(matrix, rhs):
    return reference.SparseLU(matrix).solve(rhs)


@pytest.mark.parametrize("size", SIZES)
def test_factor_solve_tpscore(benchmark, size):
    benchmark.group = f"sparse factor+solve bilaplacian {size}x{size}, {RHS} rhs"
    matrix, rhs = _SYSTEMS[size]
    solution = benchmark(_tpscore, matrix, rhs)
    residual = np.abs(matrix @ solution - rhs).max()
    # The bi-Laplacian's condition number grows like size^4 (~1e9 at 150): a backward-
    # stable solve leaves a residual of ~1e-16 times |A| |x|.
    assert residual < 1e-9 * abs(matrix).max() * np.abs(solution).max()


@pytest.mark.parametrize("size", SIZES)
def test_factor_solve_scipy_splu(benchmark, size):
    benchmark.group = f"sparse factor+solve bilaplacian {size}x{size}, {RHS} rhs"
    matrix, rhs = _SYSTEMS[size]
    solution = benchmark(_splu, matrix, rhs)
    ours = _tpscore(matrix, rhs)
    assert np.abs(solution - ours).max() < 1e-6 * np.abs(ours).max()


@pytest.mark.parametrize("size", SIZES)
def test_solve_only_tpscore(benchmark, size):
    benchmark.group = f"sparse solve only {size}x{size}, {RHS} rhs"
    matrix, rhs = _SYSTEMS[size]
    factor = SparseCholesky(matrix)
    benchmark(factor.solve, rhs)


@pytest.mark.parametrize("size", SIZES)
def test_solve_only_scipy_splu(benchmark, size):
    benchmark.group = f"sparse solve only {size}x{size}, {RHS} rhs"
    matrix, rhs = _SYSTEMS[size]
    factor = reference.SparseLU(matrix)
    benchmark(factor.solve, rhs)
