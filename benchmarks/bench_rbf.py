"""TPS fit and evaluation: tpscore against the NumPy reference and SciPy.

Each group times one operation three ways: tpscore (the baseline), the NumPy
reference (tpscore.reference.rbf) and scipy.interpolate.RBFInterpolator with
kernel="thin_plate_spline", degree=1, neighbors=None (the same interpolant). Fit and
evaluation are timed separately, for n in {22, 100, 300, 1000, 3000, 5000} centres
(the fit) and {22, 60, 1000, 3000} centres at 22,500 (150 x 150) or 90,000
(300 x 300) query points on a face-like surface (the evaluation). Every benchmark
checks its own result.

The evaluation's arithmetic limit. A tpscore evaluation benchmark records its flop
count (TPS_FLOPS_PER_PAIR per query-centre pair) and the group "machine peak" times a
float64 matrix product (OpenBLAS through NumPy, all threads, 2 * 1000^3 flops, the
fastest arithmetic this machine does); conftest.py divides the one by the other and
reports each evaluation's time as a multiple of that limit, all from the same run.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from tpscore import TPS
from tpscore.reference import rbf as reference

FIT_COUNTS = [22, 100, 300, 1000, 3000, 5000]
EVALUATION_COUNTS = [22, 60, 1000, 3000]
GRID_SIDES = [150, 300]
# The reference's fit builds the (n, n, 3) difference array and the full system:
# beyond n = 3000 that is several GB and many seconds a round, so it stops there.
REFERENCE_MAX_FIT = 3000
# The reference's evaluation forms an (m, n, 3) difference array and several (m, n)
# temporaries, about 60 bytes per (query, centre) pair: 22,500 x 3000 and 90,000 x
# 1000 already need 4-5 GB and 90,000 x 3000 about 16 GB, with run times of many
# seconds. The reference is left out of those combinations.
REFERENCE_MAX_PAIRS = 3e7
# Results are checked on this many sampled queries against the reference (cheap).
CHECK_SAMPLES = 400
# Values are ~100 mm and the systems' condition numbers stay below ~1e8:
# 1e-6 mm is far above cond * eps * |values| and far below any real error.
TOLERANCE_MM = 1e-6

# Flops per (query, centre) pair of tpscore's tps evaluation on a CPU with AVX-512,
# counted in its loop (rbf.cpp, accumulate_tps_avx512), an FMA as two:
#   the offset to the centre, 3; its squared length plus DBL_MIN (which keeps the log
#   finite at a centre), 3 FMAs, 6; the logarithm, 26 (the table index, 1 FMA, 2; the
#   reduced argument, 1 FMA, 2; ten Taylor terms, 9 FMAs + 1 multiply, 19; the sum
#   k log 2 - log c + log1p, 1 FMA + 1 add, 3); r^2 log r^2, 1; and the three
#   weighted sums (a TPS maps 3 coordinates), 3 FMAs, 6. Total 42.
# Splitting off mantissa and exponent, converting the index and gathering the table
# entries take further instructions that are not counted as flops. The AVX2 loop
# (accumulate_tps_avx2) counts 41 the same way (its logarithm 25: the exponent as a
# double, 1; the reduced argument and its square, 3; the polynomial, 9 FMAs, 18; the
# sum, 3), so one count serves both.
TPS_FLOPS_PER_PAIR = 42
# 2 * 1000^3 = 2 Gflop, ~12 ms a round at full speed: many short rounds give the
# fastest round a fair chance of a moment when no other process holds a core.
PEAK_SIDE = 1000


def face_surface(x, y):
    """Height (mm) of a smooth face-like bump over x, y (mm)."""
    return 40.0 * np.exp(-(x**2 + (1.3 * y) ** 2) / 5000.0) + 8.0 * np.exp(-(x**2 + (y - 5.0) ** 2) / 150.0)


@functools.lru_cache(maxsize=None)
def landmarks(n):
    """n source and target points on the face surface (with depth jitter), in mm."""
    rng = np.random.default_rng(n)
    xy = rng.uniform(-70.0, 70.0, size=(n, 2))
    source = np.column_stack([xy, face_surface(xy[:, 0], xy[:, 1]) + rng.normal(scale=1.0, size=n)])
    target = source + rng.normal(scale=2.0, size=source.shape)
    return source, target


@functools.lru_cache(maxsize=None)
def grid(side):
    """side x side vertices of the face surface, (side^2, 3) mm."""
    x, y = np.meshgrid(np.linspace(-80.0, 80.0, side), np.linspace(-90.0, 90.0, side))
    return np.column_stack([x.ravel(), y.ravel(), face_surface(x, y).ravel()])


@functools.lru_cache(maxsize=None)
def fitted(n):
    source, target = landmarks(n)
    return TPS(source, target), reference.fit(source, target), RBFInterpolator(
        source, target, kernel="thin_plate_spline", degree=1, neighbors=None)


def check_samples(m):
    return np.random.default_rng(m).choice(m, size=min(m, CHECK_SAMPLES), replace=False)


def rounds_for(n, m=0):
    """Fewer rounds for the slow combinations, to keep the run to a few minutes."""
    work = n**3 / 1e9 + n * m / 2e7
    return 3 if work > 1.0 else 5 if work > 0.1 else 20


# --- fit -----------------------------------------------------------------------------------

@pytest.mark.parametrize("n", FIT_COUNTS)
def test_fit_tpscore(benchmark, n):
    benchmark.group = f"TPS fit, n={n}"
    source, target = landmarks(n)
    warp = benchmark.pedantic(TPS, args=(source, target), rounds=rounds_for(n), warmup_rounds=1)
    sample = check_samples(n)
    assert np.abs(warp(source[sample]) - target[sample]).max() < TOLERANCE_MM


@pytest.mark.parametrize("n", FIT_COUNTS)
def test_fit_reference(benchmark, n):
    if n > REFERENCE_MAX_FIT:
        pytest.skip(f"the reference fit needs several GB at n = {n} (see REFERENCE_MAX_FIT)")
    benchmark.group = f"TPS fit, n={n}"
    source, target = landmarks(n)
    weights, affine = benchmark.pedantic(reference.fit, args=(source, target),
                                         rounds=rounds_for(n), warmup_rounds=1)
    sample = check_samples(n)
    assert np.abs(reference.evaluate(source[sample], source, weights, affine) - target[sample]).max() < TOLERANCE_MM


@pytest.mark.parametrize("n", FIT_COUNTS)
def test_fit_scipy_rbfinterpolator(benchmark, n):
    benchmark.group = f"TPS fit, n={n}"
    source, target = landmarks(n)
    interpolator = benchmark.pedantic(
        lambda: RBFInterpolator(source, target, kernel="thin_plate_spline", degree=1, neighbors=None),
        rounds=rounds_for(n), warmup_rounds=1)
    sample = check_samples(n)
    assert np.abs(interpolator(source[sample]) - target[sample]).max() < TOLERANCE_MM


# --- evaluation ----------------------------------------------------------------------------

def _check_evaluation(result, n, side):
    queries = grid(side)
    source, _ = landmarks(n)
    _, (weights, affine), _ = fitted(n)
    sample = check_samples(len(queries))
    expected = reference.evaluate(queries[sample], source, weights, affine)
    assert result.shape == (len(queries), 3)
    assert np.abs(result[sample] - expected).max() < TOLERANCE_MM


@pytest.mark.parametrize("side", GRID_SIDES)
@pytest.mark.parametrize("n", EVALUATION_COUNTS)
def test_evaluate_tpscore(benchmark, n, side):
    benchmark.group = f"TPS evaluate, n={n}, m={side * side}"
    benchmark.extra_info["flops"] = TPS_FLOPS_PER_PAIR * n * side * side
    warp, _, _ = fitted(n)
    queries = grid(side)
    result = benchmark.pedantic(warp, args=(queries,), rounds=rounds_for(n, side * side) * 5,
                                warmup_rounds=1)
    _check_evaluation(result, n, side)


@pytest.mark.parametrize("side", GRID_SIDES)
@pytest.mark.parametrize("n", EVALUATION_COUNTS)
def test_evaluate_reference(benchmark, n, side):
    if n * side * side > REFERENCE_MAX_PAIRS:
        pytest.skip(f"reference needs > 4 GB at {side * side} x {n} (see REFERENCE_MAX_PAIRS)")
    benchmark.group = f"TPS evaluate, n={n}, m={side * side}"
    _, (weights, affine), _ = fitted(n)
    source, _ = landmarks(n)
    queries = grid(side)
    result = benchmark.pedantic(reference.evaluate, args=(queries, source, weights, affine),
                                rounds=rounds_for(n, side * side), warmup_rounds=1)
    _check_evaluation(result, n, side)


@pytest.mark.parametrize("side", GRID_SIDES)
@pytest.mark.parametrize("n", EVALUATION_COUNTS)
def test_evaluate_scipy_rbfinterpolator(benchmark, n, side):
    benchmark.group = f"TPS evaluate, n={n}, m={side * side}"
    _, _, interpolator = fitted(n)
    queries = grid(side)
    result = benchmark.pedantic(interpolator, args=(queries,), rounds=rounds_for(n, side * side),
                                warmup_rounds=1)
    _check_evaluation(result, n, side)


# --- the machine's peak, for the evaluation's arithmetic limit -------------------------------

@pytest.mark.benchmark(group="machine peak")
def test_peak_float64_matrix_product(benchmark):
    # OpenBLAS's DGEMM runs near the FMA units' peak on all threads: the fastest this
    # machine does float64 arithmetic, measured in the same run as the evaluations.
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, PEAK_SIDE, PEAK_SIDE))
    benchmark.extra_info["peak_flops"] = 2 * PEAK_SIDE**3
    product = benchmark.pedantic(np.matmul, args=(a, b), rounds=100, warmup_rounds=2)
    rows = rng.choice(PEAK_SIDE, 5, replace=False)
    np.testing.assert_allclose(product[rows], a[rows] @ b, rtol=1e-12, atol=1e-9)
