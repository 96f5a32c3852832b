"""CSRBF fit (assembly + solve) and evaluation: tpscore against the SciPy route.

Centres are 10,000 and 40,000 points on a face-like height field (a dome and a
nose-like bump, 150 x 180 mm), sampled on a jittered grid like the vertices of a
resampled scan; the support gives about 45 neighbours per centre. The values are
three smooth displacement components. The SciPy route: cKDTree.sparse_distance_matrix
for the neighbours, scipy.sparse for the matrix, scipy.sparse.linalg.bicgstab per
column with the matching preconditioner (spilu for "ilu", Jacobi for "diagonal").
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial import cKDTree

from tpscore import CSRBF
from tpscore.reference import csrbf as reference
from tpscore.showcase.datasets import face_point_cloud

SIZES = [10_000, 40_000]
NEIGHBOURS = 45


def problem(n):
    centres = face_point_cloud(n)
    support = float(np.sqrt(NEIGHBOURS * 150 * 180 * 1.15 / (n * np.pi)))
    values = np.stack([np.sin(centres[:, 0] / 20), np.cos(centres[:, 1] / 25), centres[:, 2] / 30], axis=1)
    return centres, values, support


_PROBLEMS = {n: problem(n) for n in SIZES}


def run(benchmark, function, *args, **kwargs):
    # A fit takes 0.1-3 s: a few rounds suffice, and the minimum is what is compared.
    return benchmark.pedantic(function, args=args, kwargs=kwargs, rounds=3, iterations=1, warmup_rounds=0)


def assert_interpolates(evaluate, centres, values):
    # Solves to a relative residual of 1e-10: the centres are reproduced to ~1e-8.
    np.testing.assert_allclose(evaluate(centres), values, atol=1e-7)


@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("preconditioner", ["ilu", "diagonal"])
def test_fit_tpscore(benchmark, n, preconditioner):
    benchmark.group = f"csrbf fit {preconditioner} {n}"
    centres, values, support = _PROBLEMS[n]
    field = run(benchmark, CSRBF, centres, values, support, preconditioner=preconditioner)
    assert 30 < field.nnz / n < 60
    assert_interpolates(field, centres, values)


@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("preconditioner", ["ilu", "diagonal"])
def test_fit_scipy_route(benchmark, n, preconditioner):
    benchmark.group = f"csrbf fit {preconditioner} {n}"
    centres, values, support = _PROBLEMS[n]
    model = run(benchmark, reference.fit, centres, values, support, preconditioner=preconditioner)
    assert (model.residuals <= 1e-10).all()
    np.testing.assert_allclose(model.matrix @ model.coefficients, values, atol=1e-7)


def test_fit_quadric_tpscore(benchmark):
    benchmark.group = "csrbf fit quadric 10000"
    centres, values, support = _PROBLEMS[10_000]
    field = run(benchmark, CSRBF, centres, values, support, quadric=True)
    assert (field.quadric_orders == 2).mean() > 0.99
    assert_interpolates(field, centres, values)


def test_fit_quadric_numpy_reference(benchmark):
    benchmark.group = "csrbf fit quadric 10000"
    centres, values, support = _PROBLEMS[10_000]
    model = benchmark.pedantic(reference.fit, args=(centres, values, support), kwargs={"quadric": True},
                               rounds=1, iterations=1)
    assert (model.residuals <= 1e-10).all()


def _queries(n):
    centres, _, support = _PROBLEMS[n]
    rng = np.random.default_rng(1)
    return centres + rng.normal(0, support / 4, centres.shape)


@pytest.mark.parametrize("n", SIZES)
def test_evaluate_tpscore(benchmark, n):
    benchmark.group = f"csrbf evaluate {n} at {n}"
    centres, values, support = _PROBLEMS[n]
    field = CSRBF(centres, values, support)
    result = benchmark(field, _queries(n))
    expected = scipy_evaluate(cKDTree(centres), field.coefficients, support, _queries(n))
    np.testing.assert_allclose(result, expected, atol=1e-12)


def scipy_evaluate(tree, coefficients, support, queries):
    """The field sum_j c_j phi(|x - p_j| / sigma), vectorised with SciPy."""
    distances = cKDTree(queries).sparse_distance_matrix(tree, support, output_type="coo_matrix")
    weights = sp.csr_matrix((reference.wendland(distances.data / support), (distances.row, distances.col)),
                            shape=(len(queries), tree.n))
    return weights @ coefficients


@pytest.mark.parametrize("n", SIZES)
def test_evaluate_scipy_route(benchmark, n):
    benchmark.group = f"csrbf evaluate {n} at {n}"
    centres, values, support = _PROBLEMS[n]
    coefficients = CSRBF(centres, values, support).coefficients
    tree = cKDTree(centres)
    result = benchmark(scipy_evaluate, tree, coefficients, support, _queries(n))
    assert result.shape == (n, 3)
