"""The dense registration's linear systems: tpscore.lattice.LatticeSystem against the
SimplicialLDLT path it replaced and against SciPy.

One registration iteration forms the normal equations of a point-to-plane fit of a
cubic B-spline field to every second vertex of a face grid (110 x 150 mm), adds the
bending energy, and solves. Three problems: the default 150 x 150 grid with the 8 mm
lattice (5,625 samples, 1,242 unknowns), and finer ones, a 225 grid with a 6 mm
lattice (12,769 samples, 2,001 unknowns) and a 300 grid with a 4 mm lattice (22,500
samples, 4,032 unknowns).

* tpscore: the compiled kernel assembles the data term straight into the fixed
  pattern, and the supernodal Cholesky factor (nested-dissection order of the node
  grid, symbolic analysis once) refactorises;
* simplicial: the same assembly, refactorised by Eigen's SimplicialLDLT with its
  symbolic analysis done once (PatternCholesky(method="simplicial"): the path before
  the supernodal factor);
* scipy: the SciPy assembly (tpscore.reference.lattice) and SuperLU (splu) in its
  symmetric mode (minimum degree on A + A^T, no pivoting), SciPy's fastest setting
  for a symmetric positive-definite system.

Each problem has a group for factorise + solve alone and one for the whole iteration.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tpscore.lattice import BSplineLattice, LatticeSystem, symmetric_blocks
from tpscore.reference import lattice as reference
from tpscore.sparse import PatternCholesky

# (grid side, lattice spacing in mm)
PROBLEMS = [(150, 8.0), (225, 6.0), (300, 4.0)]


class Problem:
    def __init__(self, side, spacing):
        rng = np.random.default_rng(0)
        samples = (side + 1) // 2
        x, y = np.meshgrid(np.linspace(-55, 55, samples), np.linspace(-75, 75, samples))
        xy = np.stack([x.ravel(), y.ravel()], axis=1)
        self.lattice = BSplineLattice(xy.min(axis=0), xy.max(axis=0), spacing)
        normals = rng.normal(size=(len(xy), 3)) + [0.0, 0.0, 3.0]
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        weights = rng.uniform(0.2, 1.0, len(xy))
        self.q = weights[:, None, None] * normals[:, :, None] * normals[:, None, :]
        self.blocks = symmetric_blocks(self.q)
        self.system = LatticeSystem(self.lattice, xy)
        self.basis = self.lattice.basis(xy)
        self.bending = sp.block_diag([self.lattice.bending()] * 3).tocsr()
        self.ridge = 1e-6 * sp.identity(self.system.n, format="csr")
        self.fixed_values = self.system.aligned(self.bending) + self.system.aligned(self.ridge)
        self.rhs = rng.normal(size=self.system.n)
        self.simplicial = PatternCholesky(self.system.indptr, self.system.indices, method="simplicial")
        self.values = self.system.data_term(self.blocks) + self.fixed_values
        self.matrix = self.system.matrix(self.values)
        self.label = f"grid {side}, {spacing:g} mm lattice, {self.system.n} unknowns"

    # whole iterations
    def iteration_tpscore(self):
        return self.system.solve(self.system.data_term(self.blocks) + self.fixed_values, self.rhs)

    def iteration_simplicial(self):
        self.simplicial.factorise(self.system.data_term(self.blocks) + self.fixed_values)
        return self.simplicial.solve(self.rhs)

    def iteration_scipy(self):
        return splu_solve(reference.block_gram(self.basis, self.q) + self.bending + self.ridge, self.rhs)

    # factorise + solve of an assembled system
    def factor_solve_tpscore(self):
        return self.system.solve(self.values, self.rhs)

    def factor_solve_simplicial(self):
        self.simplicial.factorise(self.values)
        return self.simplicial.solve(self.rhs)

    def factor_solve_scipy(self):
        return splu_solve(self.matrix, self.rhs)


def splu_solve(matrix, rhs):
    factor = spla.splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
    return factor.solve(rhs)


_PROBLEMS = {}


def problem(side, spacing) -> Problem:
    if (side, spacing) not in _PROBLEMS:
        _PROBLEMS[side, spacing] = Problem(side, spacing)
    return _PROBLEMS[side, spacing]


def _check(solution, p: Problem):
    expected = spla.spsolve(sp.csc_matrix(p.matrix), p.rhs)
    # The systems' condition numbers are ~1e7 (bending against a 1e-6 ridge): two
    # backward-stable solves agree to ~1e-9 relative at worst.
    assert np.abs(solution - expected).max() <= 1e-8 * np.abs(expected).max()


IDS = [f"{side}-{spacing:g}mm" for side, spacing in PROBLEMS]
sizes = pytest.mark.parametrize("side, spacing", PROBLEMS, ids=IDS)


def _factor_solve(benchmark, side, spacing, method):
    p = problem(side, spacing)
    benchmark.group = f"lattice factorise + solve, {p.label}"
    _check(benchmark(getattr(p, f"factor_solve_{method}")), p)


def _iteration(benchmark, side, spacing, method):
    p = problem(side, spacing)
    benchmark.group = f"registration iteration (assemble + factorise + solve), {p.label}"
    _check(benchmark(getattr(p, f"iteration_{method}")), p)


@sizes
def test_factor_solve_tpscore(benchmark, side, spacing):
    _factor_solve(benchmark, side, spacing, "tpscore")


@sizes
def test_factor_solve_simplicial(benchmark, side, spacing):
    _factor_solve(benchmark, side, spacing, "simplicial")


@sizes
def test_factor_solve_scipy_splu(benchmark, side, spacing):
    _factor_solve(benchmark, side, spacing, "scipy")


@sizes
def test_iteration_tpscore(benchmark, side, spacing):
    _iteration(benchmark, side, spacing, "tpscore")


@sizes
def test_iteration_simplicial(benchmark, side, spacing):
    _iteration(benchmark, side, spacing, "simplicial")


@sizes
def test_iteration_scipy_splu(benchmark, side, spacing):
    _iteration(benchmark, side, spacing, "scipy")


def test_data_term_tpscore(benchmark):
    p = problem(*PROBLEMS[0])
    benchmark.group = f"lattice data term, {p.label}"
    values = benchmark(p.system.data_term, p.blocks)
    expected = reference.block_gram(p.basis, p.q)
    assert abs(p.system.matrix(values) - expected).max() <= 1e-12 * abs(expected).max()


def test_data_term_scipy(benchmark):
    p = problem(*PROBLEMS[0])
    benchmark.group = f"lattice data term, {p.label}"
    benchmark(reference.block_gram, p.basis, p.q)
