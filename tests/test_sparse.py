"""Sparse direct solve: SparseCholesky against SciPy's spsolve / splu (the reference),
over sizes and right-hand-side counts, plus the failures it must diagnose."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import tpscore
from tpscore.reference import sparse as reference
from tpscore.sparse import SparseCholesky


def grid_laplacian_system(rows, cols, shift=1e-2):
    """-L + shift I for the 5-point grid Laplacian: SPD, sparse, realistically banded."""
    one_d = lambda n: sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    laplacian = sp.kronsum(one_d(cols), one_d(rows))
    return (laplacian + shift * sp.identity(rows * cols)).tocsr()


def random_spd(n, density, seed):
    """A random sparse SPD matrix: B^T B + diagonal, with random sparsity pattern."""
    rng = np.random.default_rng(seed)
    b = sp.random(n, n, density=density, random_state=rng, format="csr")
    return (b.T @ b + sp.diags(rng.uniform(0.5, 2.0, n))).tocsc()


def relative_error(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


@pytest.mark.parametrize("rows, cols", [(1, 1), (3, 4), (20, 30), (70, 70)])
@pytest.mark.parametrize("k", [1, 3, 17])
def test_matches_spsolve_on_grid_systems(rows, cols, k):
    matrix = grid_laplacian_system(rows, cols)
    rhs = np.random.default_rng(rows * 100 + k).normal(size=(rows * cols, k))
    ours = SparseCholesky(matrix).solve(rhs)
    theirs = reference.sparse_solve(matrix, rhs)
    # The condition number of -L + 0.01 I on a 70 x 70 grid is ~2e3; two backward-stable
    # direct solves then agree to ~1e-16 * 2e3 relative; 1e-10 leaves a wide margin while
    # still catching any wrong entry, permutation or missing fill.
    assert relative_error(ours, theirs) < 1e-10
    assert ours.shape == rhs.shape and ours.flags.c_contiguous


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 120), density=st.floats(0.005, 0.2), k=st.integers(1, 6), seed=st.integers(0, 2**16))
def test_matches_splu_on_random_spd_matrices(n, density, k, seed):
    matrix = random_spd(n, density, seed)
    rhs = np.random.default_rng(seed + 1).normal(size=(n, k))
    ours = SparseCholesky(matrix).solve(rhs)
    theirs = reference.SparseLU(matrix).solve(rhs)
    # Diagonal >= 0.5 and entries of B^T B of order n * density: the condition number
    # stays below ~1e4, so 1e-9 relative agreement is far above rounding noise.
    assert relative_error(ours, theirs) < 1e-9
    # The residual check does not lean on the reference at all.
    assert np.abs(matrix @ ours - rhs).max() < 1e-9 * (np.abs(rhs).max() + 1)


def test_vector_rhs_keeps_its_shape_and_accepts_lists():
    matrix = grid_laplacian_system(5, 5)
    rhs = list(np.linspace(-1, 1, 25))
    x = SparseCholesky(matrix).solve(rhs)
    assert x.shape == (25,)
    # A residual of 1e-12 on entries of order 1: rounding level for a 25 x 25 SPD system.
    assert np.abs(matrix @ x - rhs).max() < 1e-12


def test_dense_array_input_and_only_lower_triangle_matter_after_symmetry_check():
    matrix = grid_laplacian_system(4, 6).toarray()
    rhs = np.arange(24.0)
    x = SparseCholesky(matrix).solve(rhs)
    assert np.abs(matrix @ x - rhs).max() < 1e-11  # rounding level, entries of order 1e2


def test_empty_rhs_columns_and_float32_noncontiguous_rhs():
    matrix = grid_laplacian_system(10, 10)
    solver = SparseCholesky(matrix)
    assert solver.solve(np.zeros((100, 0))).shape == (100, 0)
    rhs = np.random.default_rng(0).normal(size=(100, 8)).astype(np.float32)[:, ::2]
    x = solver.solve(rhs)
    # float32 input is converted once to float64, so the solve itself is float64-exact.
    assert np.abs(matrix @ x - rhs.astype(np.float64)).max() < 1e-10


def test_result_does_not_depend_on_thread_count():
    matrix = grid_laplacian_system(60, 60)
    rhs = np.random.default_rng(3).normal(size=(3600, 9))
    solver = SparseCholesky(matrix)
    previous = tpscore.num_threads()
    try:
        tpscore.set_num_threads(1)
        serial = solver.solve(rhs)
        tpscore.set_num_threads(4)
        threaded = solver.solve(rhs)
    finally:
        tpscore.set_num_threads(previous)
    assert np.array_equal(serial, threaded)  # each column is solved alone: bitwise equal


def test_concurrent_solves_from_python_threads():
    matrix = grid_laplacian_system(40, 40)
    solver = SparseCholesky(matrix)
    rhs = [np.random.default_rng(i).normal(size=(1600, 2)) for i in range(6)]
    expected = [solver.solve(b) for b in rhs]
    results = [None] * len(rhs)

    def work(i):
        results[i] = solver.solve(rhs[i])

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(rhs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for got, want in zip(results, expected):
        assert np.array_equal(got, want)  # the factor is read-only: same bits from any thread


def test_fill_in_and_pivots_are_reported():
    solver = SparseCholesky(grid_laplacian_system(30, 30))
    assert solver.n == 900
    assert solver.factor_nonzeros >= 900 * 2 - 60  # at least the grid's own lower edges
    low, high = solver.pivot_range
    assert 0 < low <= high


@pytest.mark.parametrize(
    "matrix, message",
    [
        (sp.csr_matrix(np.ones((2, 3))), "square"),
        (sp.csr_matrix([[2.0, 1.0], [0.0, 2.0]]), "symmetric"),
        (sp.csr_matrix([[2.0, np.nan], [np.nan, 2.0]]), "NaN"),
        (sp.csr_matrix([[1.0, 1.0], [1.0, 1.0]]), "singular|positive definite"),
        (sp.csr_matrix([[1.0, 0.0], [0.0, -1.0]]), "positive definite"),
        (sp.csr_matrix((3, 3)), "singular|positive definite"),
        (np.ones(3), "2-D"),
    ],
)
def test_bad_matrices_raise_clear_errors(matrix, message):
    with pytest.raises(ValueError, match=message):
        SparseCholesky(matrix)


@pytest.mark.parametrize("n", [5, 40])
def test_graph_laplacian_without_anchor_is_reported_singular(n):
    # A graph Laplacian (degree - adjacency) has the constants in its null space, so
    # its last pivot is rounding noise; the pivot test must catch that, not solve on.
    adjacency = sp.diags([np.ones(n * n - 1)], [1])
    adjacency = adjacency + adjacency.T
    laplacian = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    with pytest.raises(ValueError, match="matrix is (singular|not positive definite)"):
        SparseCholesky(laplacian)


def test_bad_rhs_raise_clear_errors():
    solver = SparseCholesky(grid_laplacian_system(3, 3))
    with pytest.raises(ValueError, match=r"rhs must have shape \(9,\)"):
        solver.solve(np.zeros(8))
    with pytest.raises(ValueError, match="rhs contains NaN"):
        solver.solve(np.full(9, np.nan))
    with pytest.raises(ValueError, match="rhs must be numeric"):
        solver.solve(["a"] * 9)


# --- PatternCholesky: one pattern, many factorisations -------------------------------

def lower_pattern(matrix):
    lower = sp.tril(sp.csc_matrix(matrix), format="csc")
    lower.sort_indices()
    return lower


def test_pattern_cholesky_refactorises_with_new_values_like_a_fresh_factor():
    matrix = random_spd(300, 0.01, seed=4)
    lower = lower_pattern(matrix)
    factor = tpscore.PatternCholesky(lower.indptr, lower.indices)
    rng = np.random.default_rng(5)
    rhs = rng.normal(size=(300, 3))
    for trial in range(3):
        # new values on the same pattern: a positive multiple plus a new diagonal
        values = lower.copy()
        values.data = lower.data * rng.uniform(0.5, 2.0, size=lower.nnz)
        values = values + sp.diags(rng.uniform(5.0, 10.0, 300), format="csc")
        values = lower_pattern(values)
        assert np.array_equal(values.indices, lower.indices)
        factor.factorise(values.data)
        full = values + sp.tril(values, -1).T
        expected = reference.sparse_solve(full, rhs)
        assert relative_error(factor.solve(rhs), expected) < 1e-10
        assert relative_error(SparseCholesky(full).solve(rhs), expected) < 1e-10


def test_pattern_cholesky_keeps_explicit_zeros_of_the_pattern():
    # the pattern couples 0 and 2; the first matrix has 0 there, the second does not
    indptr, indices = [0, 2, 3, 4], [0, 2, 1, 2]
    factor = tpscore.PatternCholesky(indptr, indices)
    factor.factorise([2.0, 0.0, 2.0, 2.0])
    assert np.allclose(factor.solve([2.0, 2.0, 2.0]), [1.0, 1.0, 1.0])
    factor.factorise([2.0, 1.0, 2.0, 2.0])
    dense = np.array([[2.0, 0.0, 1.0], [0.0, 2.0, 0.0], [1.0, 0.0, 2.0]])
    assert np.allclose(factor.solve([1.0, 2.0, 3.0]), np.linalg.solve(dense, [1.0, 2.0, 3.0]))


@pytest.mark.parametrize("indptr, indices, message", [
    ([1, 2], [0], "start with 0"),
    ([0, 2, 1], [0, 1], "nondecreasing"),
    ([0, 1, 2], [0, 0], "above its column"),
    ([0, 2, 3], [1, 0, 1], "strictly increasing"),
    ([0, 1, 2], [0, 2], r"\[0, 2\)"),
    ([0.0, 1.0], [0], "integer"),
])
def test_pattern_cholesky_rejects_malformed_patterns(indptr, indices, message):
    with pytest.raises(ValueError, match=message):
        tpscore.PatternCholesky(indptr, indices)


def test_pattern_cholesky_diagnoses_bad_values_and_keeps_no_factor_after_a_failure():
    factor = tpscore.PatternCholesky([0, 2, 3], [0, 1, 1])
    with pytest.raises(ValueError, match="factorise"):
        factor.solve([1.0, 1.0])
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        factor.factorise([1.0, 2.0])
    with pytest.raises(ValueError, match="NaN|finite"):
        factor.factorise([1.0, np.nan, 1.0])
    factor.factorise([2.0, 1.0, 2.0])
    assert factor.factorised
    with pytest.raises(ValueError, match="positive definite"):
        factor.factorise([1.0, 2.0, 1.0])        # eigenvalues 3 and -1
    assert not factor.factorised
    with pytest.raises(ValueError, match="factorise"):
        factor.solve([1.0, 1.0])
