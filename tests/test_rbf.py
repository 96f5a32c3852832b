"""Dense RBF / thin-plate spline: the compiled core against the NumPy reference and
SciPy, analytic properties, degenerate input, and the binding contract."""
from __future__ import annotations

import threading
import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.interpolate import RBFInterpolator

import tpscore
import tpscore._core as core
from tpscore import RBF, TPS
from tpscore._validation import MAX_DENSE_ELEMENTS
from tpscore.reference import rbf as reference

EPS = np.finfo(np.float64).eps
KERNELS = ["tps", "biharmonic", "triharmonic", "multiquadric", "gaussian"]
# A shape parameter of about one over the typical spacing of the unit-cube test clouds.
EPSILON = {"multiquadric": 1.5, "gaussian": 1.5}
# phi(s r) = s^degree phi(r) (up to affine terms for tps): how smoothing must scale
# with the coordinates for the fit to be scale invariant.
KERNEL_DEGREE = {"tps": 2, "biharmonic": 1, "triharmonic": 3, "multiquadric": 0, "gaussian": 0}
# SciPy's name for each kernel and the smoothing factor: ours = factor * SciPy's.
SCIPY_KERNEL = {"tps": ("thin_plate_spline", 2.0), "biharmonic": ("linear", 1.0),
                "triharmonic": ("cubic", 1.0), "multiquadric": ("multiquadric", 1.0),
                "gaussian": ("gaussian", 1.0)}


def random_cloud(rng, n, mode="uniform"):
    """n points in about [-1, 1]^3: uniform, or in a few tight clusters."""
    if mode == "uniform":
        return rng.uniform(-1.0, 1.0, size=(n, 3))
    centres = rng.uniform(-1.0, 1.0, size=(3, 3))
    labels = rng.integers(0, 3, size=n)
    return centres[labels] + 0.02 * rng.normal(size=(n, 3))


def smooth_values(points, rng, k=3):
    """A smooth nonlinear function of the points plus a little noise, (n, k)."""
    mixing = rng.normal(size=(3, k))
    return np.sin(points @ mixing) + 0.5 * points[:, :1] ** 2 + 0.01 * rng.normal(size=(len(points), k))


def epsilon_for(kernel, scale=1.0):
    return EPSILON[kernel] / scale if kernel in EPSILON else None


def face_like_landmarks(rng, n=22):
    """Landmark-like points on a curved surface (a face is not flat), in mm."""
    xy = rng.uniform(-60.0, 60.0, size=(n, 2))
    z = 40.0 - 0.01 * (xy ** 2).sum(axis=1) + rng.normal(scale=2.0, size=n)
    return np.column_stack([xy, z])


# --- core against the reference -------------------------------------------------------

@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(5, 40),
    kernel=st.sampled_from(KERNELS),
    mode=st.sampled_from(["uniform", "clustered"]),
    offset=st.sampled_from([0.0, 1e4]),
    scale=st.sampled_from([1e-3, 1.0, 100.0]),
    smoothing=st.sampled_from([0.0, 1e-3, 1.0]),
)
def test_core_matches_reference(seed, n, kernel, mode, offset, scale, smoothing):
    rng = np.random.default_rng(seed)
    base = random_cloud(rng, n, mode)
    values = smooth_values(base, rng)
    queries_base = np.vstack([base, random_cloud(rng, 30)])
    direction = rng.normal(size=3)
    shift = offset * direction / np.linalg.norm(direction)
    try:
        # The fit sees the cloud moved far from the origin and/or scaled; the
        # reference solves the well-scaled base problem. Shift and scale invariance
        # (with smoothing and epsilon scaled alike) make the two interpolants equal,
        # so this checks the core's normalisation and its mapping back as well.
        fitted = RBF(base * scale + shift, values, kernel,
                     smoothing=smoothing * scale ** KERNEL_DEGREE[kernel],
                     epsilon=epsilon_for(kernel, scale))
    except ValueError as error:
        # Degenerate draws (near-coincident or ill-conditioned clusters) must be
        # refused with a message naming the problem, never fitted to garbage.
        assert "coincide" in str(error) or "singular" in str(error)
        assume(False)
    weights, affine = reference.fit(base, values, kernel, smoothing, epsilon_for(kernel))
    expected = reference.evaluate(queries_base, base, weights, affine, kernel, epsilon_for(kernel))
    got = fitted(queries_base * scale + shift)
    # Forward error of a backward-stable solve is about cond * eps relative to the
    # values; both systems are solved in well-scaled coordinates, so the larger of
    # their condition numbers bounds the difference. Storing the data at an offset o
    # from the origin rounds the centres and queries by eps * o / scale relative to
    # the cloud, a data error the condition number amplifies alike: hence the factor
    # (1 + o / scale). Over 300 seeded draws the error reached 11 * eps * cond * (...)
    # * |values|; the factor 100 leaves ~10x margin.
    reference_condition = np.linalg.cond(_reference_system(base, kernel, smoothing))
    condition = max(fitted.condition_number, reference_condition)
    magnitude = np.abs(values).max()
    tolerance = 1e2 * EPS * condition * magnitude * (1.0 + offset / scale)
    assume(tolerance < 1e-3 * magnitude)  # a hopelessly conditioned draw says nothing
    np.testing.assert_allclose(got, expected, rtol=0, atol=tolerance)
    if offset == 0.0:
        # The exposed coefficients (mapped back to the original coordinates) with the
        # evaluation matrix give the same function; the product sums terms of size
        # |E| |coefficients|, whose rounding adds to the tolerance.
        matrix = fitted.evaluation_matrix(queries_base * scale)
        cancellation = (np.abs(matrix) @ np.abs(fitted.coefficients)).max()
        np.testing.assert_allclose(matrix @ fitted.coefficients, expected, rtol=0,
                                   atol=tolerance + 1e3 * EPS * cancellation)


def _reference_system(centres, kernel, smoothing):
    n = len(centres)
    matrix = np.zeros((n + 4, n + 4))
    matrix[:n, :n] = reference.kernel_matrix(kernel, centres, centres, epsilon_for(kernel))
    matrix[:n, :n] += reference.SMOOTHING_SIGN[kernel] * smoothing * np.eye(n)
    matrix[:n, n:] = np.column_stack([np.ones(n), centres])
    matrix[n:, :n] = matrix[:n, n:].T
    return matrix


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("smoothing", [0.0, 0.5])
def test_weights_affine_and_energy_match_reference(kernel, smoothing):
    rng = np.random.default_rng(7)
    centres = face_like_landmarks(rng, 30)
    values = centres + rng.normal(size=(30, 3))
    epsilon = 0.02 if kernel in EPSILON else None
    fitted = RBF(centres, values, kernel, smoothing=smoothing, epsilon=epsilon)
    weights, affine = reference.fit(centres, values, kernel, smoothing, epsilon)
    # Both solve systems with condition numbers below 1e8 here (face-sized cloud in
    # mm); 1e-7 relative leaves two orders of magnitude over cond * eps.
    np.testing.assert_allclose(fitted.weights, weights, rtol=0, atol=1e-7 * np.abs(weights).max())
    np.testing.assert_allclose(fitted.affine, affine, rtol=0, atol=1e-7 * np.abs(affine).max())
    energy = reference.bending_energy(centres, weights, kernel, epsilon)
    # The energy is a quadratic form in the weights: twice their relative error.
    assert fitted.bending_energy == pytest.approx(energy, rel=1e-6)
    if kernel in ("tps", "triharmonic"):
        assert fitted.bending_energy > 0  # conditionally positive definite kernels
    if kernel in ("biharmonic", "multiquadric"):
        assert fitted.bending_energy < 0  # conditionally negative definite kernels
    assert np.isfinite(fitted.condition_number) and fitted.condition_number >= 1.0


# --- analytic properties -----------------------------------------------------------------

def test_tps_interpolates_its_centres():
    rng = np.random.default_rng(1)
    source = face_like_landmarks(rng)
    target = source + rng.normal(scale=3.0, size=source.shape)
    warp = TPS(source, target)
    # Values are ~100 mm with condition ~1e3: 1e-9 mm is far above cond * eps * 100.
    np.testing.assert_allclose(warp(source), target, rtol=0, atol=1e-9)
    np.testing.assert_allclose(warp.displacement(source), target - source, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kernel", KERNELS)
def test_affine_maps_are_reproduced_exactly(kernel):
    rng = np.random.default_rng(2)
    centres = face_like_landmarks(rng, 25)
    linear = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    translation = np.array([5.0, -3.0, 12.0])
    values = centres @ linear + translation
    fitted = RBF(centres, values, kernel, epsilon=0.02 if kernel in EPSILON else None)
    # The affine part reproduces affine data with W = 0 exactly in exact arithmetic;
    # rounding leaves weights of order eps * cond * |values| / |phi| (< 1e-9 here).
    assert np.abs(fitted.weights).max() < 1e-9
    # Affine part to 1e-9 relative: values ~ 100 mm, cond < 1e6.
    np.testing.assert_allclose(fitted.affine[0], translation, rtol=0, atol=1e-8)
    np.testing.assert_allclose(fitted.affine[1:], linear, rtol=0, atol=1e-10)
    queries = face_like_landmarks(rng, 200) * 1.5
    np.testing.assert_allclose(fitted(queries), queries @ linear + translation, rtol=0, atol=1e-8)


@pytest.mark.parametrize("kernel", KERNELS)
def test_matches_scipy_rbfinterpolator(kernel):
    rng = np.random.default_rng(3)
    centres = face_like_landmarks(rng, 40)
    values = centres + rng.normal(scale=2.0, size=centres.shape)
    queries = face_like_landmarks(rng, 500) * 1.2
    scipy_name, smoothing_factor = SCIPY_KERNEL[kernel]
    epsilon = 0.02 if kernel in EPSILON else None
    for smoothing in (0.0, 4.0):
        ours = RBF(centres, values, kernel, smoothing=smoothing, epsilon=epsilon)
        theirs = RBFInterpolator(centres, values, kernel=scipy_name, degree=1,
                                 smoothing=smoothing / smoothing_factor,
                                 epsilon=1.0 if epsilon is None else epsilon)
        # Two independent solves of the same interpolant with condition < 1e8 on
        # values of ~100 mm: agreement to 1e-6 mm is well above cond * eps * 100.
        np.testing.assert_allclose(ours(queries), theirs(queries), rtol=0, atol=1e-6)


def test_smoothing_limits():
    rng = np.random.default_rng(4)
    centres = face_like_landmarks(rng, 30)
    values = centres + rng.normal(scale=2.0, size=centres.shape)
    queries = face_like_landmarks(rng, 100)
    exact = TPS(centres, values)
    # smoothing -> 0: the fit tends to interpolation linearly in lambda; 1e-8 mm^2
    # against kernel entries of ~1e4 mm^2 moves it by ~1e-9 mm.
    almost = TPS(centres, values, smoothing=1e-8)
    np.testing.assert_allclose(almost(queries), exact(queries), rtol=0, atol=1e-6)
    # smoothing -> infinity: W -> 0 and A -> the affine least-squares fit; the gap
    # shrinks like |K| / lambda, ~1e-6 relative at lambda = 1e12 mm^2.
    stiff = TPS(centres, values, smoothing=1e12)
    design = np.column_stack([np.ones(len(centres)), centres])
    least_squares = np.linalg.lstsq(design, values, rcond=None)[0]
    np.testing.assert_allclose(stiff.affine, least_squares, rtol=0, atol=1e-4)
    np.testing.assert_allclose(stiff(queries), np.column_stack([np.ones(100), queries]) @ least_squares,
                               rtol=0, atol=1e-4)
    # In between, the residual at the centres grows with smoothing.
    residuals = [np.abs(TPS(centres, values, smoothing=s)(centres) - values).max()
                 for s in (0.0, 1e2, 1e4, 1e6)]
    assert residuals[0] < 1e-9 and all(a < b for a, b in zip(residuals, residuals[1:]))


@pytest.mark.parametrize("kernel", KERNELS)
def test_shift_and_scale_invariance(kernel):
    rng = np.random.default_rng(5)
    centres = face_like_landmarks(rng, 30)
    values = smooth_values(centres / 60.0, rng)
    queries = face_like_landmarks(rng, 100)
    epsilon = 0.02 if kernel in EPSILON else None
    smoothing = 0.1
    original = RBF(centres, values, kernel, smoothing=smoothing, epsilon=epsilon)
    shift = np.array([300.0, -2000.0, 150.0])
    scale = 7.0
    moved = RBF(centres * scale + shift, values, kernel,
                smoothing=smoothing * scale ** KERNEL_DEGREE[kernel],
                epsilon=None if epsilon is None else epsilon / scale)
    # Values ~1, condition ~1e6 at most; the shift of 2000 mm over a 120 mm cloud
    # costs a factor ~20 in query rounding: 1e-8 is ample and still strict.
    np.testing.assert_allclose(moved(queries * scale + shift), original(queries), rtol=0, atol=1e-8)


def test_displacement_is_f_minus_x():
    rng = np.random.default_rng(6)
    source = face_like_landmarks(rng) + np.array([1e4, 0.0, 0.0])
    target = source + rng.normal(scale=2.0, size=source.shape)
    warp = TPS(source, target)
    queries = face_like_landmarks(rng, 1000) + np.array([1e4, 0.0, 0.0])
    # f(x) itself is ~1e4 mm, so f(x) - x computed from it carries ~1e4 * eps * 10.
    np.testing.assert_allclose(warp.displacement(queries), warp(queries) - queries, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kernel", KERNELS)
def test_evaluation_matrix_times_coefficients_is_the_interpolant(kernel):
    rng = np.random.default_rng(8)
    centres = face_like_landmarks(rng, 30)
    values = centres + rng.normal(size=centres.shape)
    fitted = RBF(centres, values, kernel, epsilon=0.02 if kernel in EPSILON else None)
    queries = face_like_landmarks(rng, 300)
    matrix = fitted.evaluation_matrix(queries)
    assert matrix.shape == (300, 34)
    assert fitted.coefficients.shape == (34, 3)
    # The product in original coordinates cancels terms of up to |W| |phi| ~ 1e3
    # larger than f; 1e-8 mm is that cancellation times eps with room to spare.
    np.testing.assert_allclose(matrix @ fitted.coefficients, fitted(queries), rtol=0, atol=1e-8)
    # and E is the reference's evaluation matrix, entry by entry.
    expected = reference.evaluation_matrix(queries, centres, kernel, fitted.epsilon)
    np.testing.assert_allclose(matrix, expected, rtol=1e-13, atol=1e-300)


def test_values_of_any_width():
    rng = np.random.default_rng(9)
    centres = face_like_landmarks(rng, 20)
    for k in (1, 2, 5):
        values = rng.normal(size=(20, k))
        fitted = RBF(centres, values)
        weights, affine = reference.fit(centres, values)
        queries = face_like_landmarks(rng, 70)
        assert fitted(queries).shape == (70, k)
        # Values ~1, condition < 1e6.
        np.testing.assert_allclose(fitted(queries), reference.evaluate(queries, centres, weights, affine),
                                   rtol=0, atol=1e-9)
    one_dimensional = RBF(centres, rng.normal(size=20))
    assert one_dimensional(centres).shape == (20, 1)
    with pytest.raises(ValueError, match="displacement needs values with 3 columns"):
        one_dimensional.displacement(centres)


# --- the blocked, threaded fit -----------------------------------------------------------

def face_like_cloud(rng, n):
    """n points on a face-sized curved surface with depth jitter, in mm (as the pipeline's)."""
    xy = rng.uniform(-70.0, 70.0, size=(n, 2))
    z = 40.0 * np.exp(-(xy ** 2).sum(axis=1) / 5000.0) + rng.normal(scale=1.0, size=n)
    return np.column_stack([xy, z])


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("n, smoothing", [(150, 0.0), (420, 0.0), (420, 1e-3)])
def test_blocked_fit_matches_reference(kernel, n, smoothing):
    # n > 128 takes the factorisation through several panels (and the threaded
    # trailing updates): the compiled fit must still be the reference's interpolant.
    # Unit-sized coordinates keep the reference's own system (solved as written, not
    # normalised) well enough conditioned to be a reference.
    rng = np.random.default_rng(n + 7)
    centres = face_like_cloud(rng, n) / 70.0
    values = smooth_values(centres, rng)
    # About one over the spacing of these clouds: wider shapes make the gaussian and
    # multiquadric systems singular to working precision at n = 420.
    epsilon = 10.0 if kernel in EPSILON else None
    fitted = RBF(centres, values, kernel, smoothing=smoothing, epsilon=epsilon)
    weights, affine = reference.fit(centres, values, kernel, smoothing, epsilon)
    queries = face_like_cloud(rng, 300) / 60.0
    expected = reference.evaluate(queries, centres, weights, affine, kernel, epsilon)
    # Forward error of two backward-stable solves: cond * eps relative to |values|,
    # with the larger of the two systems' condition numbers; factor 100 as in
    # test_core_matches_reference.
    condition = max(fitted.condition_number,
                    np.linalg.cond(_reference_system_with(centres, kernel, smoothing, epsilon)))
    magnitude = np.abs(values).max()
    tolerance = 1e2 * EPS * condition * magnitude
    assert tolerance < 1e-3 * magnitude  # the draw is conditioned well enough to say something
    np.testing.assert_allclose(fitted(queries), expected, rtol=0, atol=tolerance)
    if smoothing == 0.0:
        # And it interpolates: the residual at the centres is of the same order.
        np.testing.assert_allclose(fitted(centres), values, rtol=0, atol=tolerance)


def _reference_system_with(centres, kernel, smoothing, epsilon):
    n = len(centres)
    matrix = np.zeros((n + 4, n + 4))
    matrix[:n, :n] = reference.kernel_matrix(kernel, centres, centres, epsilon)
    matrix[:n, :n] += reference.SMOOTHING_SIGN[kernel] * smoothing * np.eye(n)
    matrix[:n, n:] = np.column_stack([np.ones(n), centres])
    matrix[n:, :n] = matrix[:n, n:].T
    return matrix


def _normalised_equilibrated_system(fitted, centres, kernel, smoothing, epsilon):
    """The saddle-point matrix the fit factorises: centres centred on their bounding
    box and scaled into the unit ball, polynomial rows and columns scaled to the
    kernel block."""
    shift = 0.5 * (centres.min(axis=0) + centres.max(axis=0))
    scale = np.linalg.norm(centres - shift, axis=1).max()
    unit = (centres - shift) / scale
    degree = {"tps": 2, "biharmonic": 1, "triharmonic": 3}.get(kernel, 0)
    n = len(centres)
    kernel_block = reference.kernel_matrix(kernel, unit, unit, None if epsilon is None else epsilon * scale)
    kernel_block += reference.SMOOTHING_SIGN[kernel] * smoothing / scale ** degree * np.eye(n)
    s = np.abs(kernel_block).max()
    matrix = np.zeros((n + 4, n + 4))
    matrix[:n, :n] = kernel_block
    matrix[:n, n:] = s * np.column_stack([np.ones(n), unit])
    matrix[n:, :n] = matrix[:n, n:].T
    return matrix


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("n", [40, 300])
def test_condition_number_estimates_the_solved_system(kernel, n):
    rng = np.random.default_rng(n)
    centres = face_like_cloud(rng, n)
    epsilon = 0.02 if kernel in EPSILON else None
    smoothing = 0.5
    fitted = RBF(centres, centres, kernel, smoothing=smoothing, epsilon=epsilon)
    exact = np.linalg.cond(_normalised_equilibrated_system(fitted, centres, kernel, smoothing, epsilon), 1)
    # The estimator finds ||S^-1||_1 from a few solves: never above the true value
    # (each estimate is |S^-1 x|_1 / |x|_1 for some x; 1e-6 allows for rounding), and
    # rarely below a third of it (Higham, 1988).
    assert fitted.condition_number <= exact * (1 + 1e-6)
    assert fitted.condition_number >= exact / 3


_NARROWER_LEVEL_SCRIPT = """
import numpy as np, tpscore, tpscore._core as core
from tpscore.reference import rbf as reference
print(core.simd_level())
rng = np.random.default_rng(41)
for n in (150, 700):
    xy = rng.uniform(-1.0, 1.0, size=(n, 2))
    centres = np.column_stack([xy, 0.5 * np.exp(-(xy ** 2).sum(axis=1)) + 0.02 * rng.normal(size=n)])
    values = np.sin(centres @ rng.normal(size=(3, 3))) + 0.01 * rng.normal(size=(n, 3))
    fitted = tpscore.TPS(centres, values)
    weights, affine = reference.fit(centres, values)
    queries = rng.uniform(-1.1, 1.1, size=(5000, 3))
    expected = reference.evaluate(queries, centres, weights, affine)
    # As in test_blocked_fit_matches_reference: cond * eps of the values, times 100.
    bound = 1e2 * np.finfo(float).eps * fitted.condition_number * np.abs(values).max()
    print(n, np.abs(fitted(queries) - expected).max(), bound)
"""


@pytest.mark.parametrize("level", ["avx2", "baseline"])
def test_narrower_instruction_sets_fit_and_evaluate_like_the_reference(level):
    # The Cholesky micro-kernels and the tps evaluation are compiled for AVX-512, AVX2
    # and baseline x86-64, and a CPU runs the widest it can; TPSCORE_SIMD makes a fresh
    # process use a narrower one, so each is tested on a machine that has the wider.
    import os
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", _NARROWER_LEVEL_SCRIPT], capture_output=True,
                            text=True, timeout=300, env={**os.environ, "TPSCORE_SIMD": level})
    assert result.returncode == 0, result.stderr
    lines = result.stdout.split("\n")
    # The override only lowers the level: never above what this CPU runs (asked of a
    # process without the override, since this one may itself run under a lower one).
    widest = subprocess.run([sys.executable, "-c", "from tpscore import _core; print(_core.simd_level())"],
                            capture_output=True, text=True, timeout=60,
                            env={k: v for k, v in os.environ.items() if k != "TPSCORE_SIMD"}).stdout.strip()
    order = ["baseline", "avx2", "avx512"]
    assert lines[0] == order[min(order.index(level), order.index(widest))]
    for line in lines[1:]:
        if line:
            n, error, bound = line.split()
            assert float(error) < float(bound), f"n = {n}: error {error} above {bound}"


def test_fit_does_not_depend_on_thread_count():
    rng = np.random.default_rng(21)
    centres = face_like_cloud(rng, 900)
    values = centres + rng.normal(scale=2.0, size=centres.shape)
    fits = []
    try:
        for threads in (1, 2, 3):
            tpscore.set_num_threads(threads)
            fits.append(TPS(centres, values))
    finally:
        tpscore.set_num_threads(0)
    # Every entry of the factor is computed by one thread with the same operations
    # in the same order whatever the thread count: bitwise equal.
    for other in fits[1:]:
        assert np.array_equal(other.weights, fits[0].weights)
        assert np.array_equal(other.affine, fits[0].affine)
        assert other.condition_number == fits[0].condition_number


@pytest.mark.parametrize("k", [1, 3])
def test_evaluation_agrees_with_the_evaluation_matrix_at_every_distance(k):
    # The evaluation loop and the evaluation matrix compute phi with two different
    # logarithms (hand-written ones for AVX-512 and AVX2); queries from 1e-9 mm
    # to 1e5 mm away from the centres, and on them, take every range of r^2 through it.
    rng = np.random.default_rng(30 + k)
    centres = face_like_landmarks(rng, 40)
    fitted = RBF(centres, centres[:, :k] + rng.normal(size=(40, k)))
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distances = 10.0 ** rng.uniform(-9, 5, size=(2000, 1))
    queries = np.vstack([centres, centres[rng.integers(0, 40, 2000)] + distances * directions])
    matrix = fitted.evaluation_matrix(queries)
    # Both sum the same terms; each term carries a rounding of eps |E_ij| |c_j|.
    scale = np.abs(matrix) @ np.abs(fitted.coefficients)
    np.testing.assert_array_less(np.abs(fitted(queries) - matrix @ fitted.coefficients), 64 * EPS * scale + 1e-300)


def test_result_does_not_depend_on_thread_count():
    rng = np.random.default_rng(10)
    source = face_like_landmarks(rng, 60)
    warp = TPS(source, source + rng.normal(size=source.shape))
    queries = rng.uniform(-80, 80, size=(50_003, 3))
    try:
        tpscore.set_num_threads(1)
        serial = warp(queries)
        serial_matrix = warp.evaluation_matrix(queries[:5000])
        tpscore.set_num_threads(3)
        threaded = warp(queries)
        threaded_matrix = warp.evaluation_matrix(queries[:5000])
    finally:
        tpscore.set_num_threads(0)
    # Every row is computed by one thread with the same instructions: bitwise equal.
    assert np.array_equal(serial, threaded)
    assert np.array_equal(serial_matrix, threaded_matrix)


def test_two_threads_calling_one_fit_agree_with_one_call():
    rng = np.random.default_rng(11)
    source = face_like_landmarks(rng)
    warp = TPS(source, source + rng.normal(size=source.shape))
    queries = rng.uniform(-80, 80, size=(200_000, 3))
    expected = warp(queries)
    results = [None] * 4
    barrier = threading.Barrier(len(results))

    def work(slot):
        barrier.wait()
        results[slot] = (warp(queries), warp.displacement(queries))

    threads = [threading.Thread(target=work, args=(slot,)) for slot in range(len(results))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for values, displacement in results:
        assert np.array_equal(values, expected)
        assert np.array_equal(displacement, warp.displacement(queries))


# --- input handling -----------------------------------------------------------------------

def test_array_likes_are_accepted():
    rng = np.random.default_rng(12)
    centres = np.round(face_like_landmarks(rng, 20))
    values = centres + np.round(rng.normal(size=centres.shape))
    expected = TPS(centres, values)
    queries = face_like_landmarks(rng, 50)
    for converted_centres, converted_values in [
        (centres.astype(np.float32), values.astype(np.float32)),  # exact: integers
        (centres.astype(np.int64), values.astype(np.int32)),
        (centres.tolist(), values.tolist()),
        (np.asfortranarray(centres), np.asfortranarray(values)),
        (np.repeat(centres, 2, axis=1)[:, ::2], values[::-1][::-1]),  # strided views
    ]:
        fitted = TPS(converted_centres, converted_values)
        assert np.array_equal(fitted.weights, expected.weights)
    wide = np.zeros((50, 6))
    wide[:, ::2] = queries
    np.testing.assert_array_equal(expected(wide[:, ::2]), expected(queries))
    np.testing.assert_array_equal(expected(queries.astype(np.float32)),
                                  expected(queries.astype(np.float32).astype(np.float64)))
    np.testing.assert_array_equal(expected(queries.tolist()), expected(queries))


def test_empty_queries_give_empty_results():
    rng = np.random.default_rng(13)
    centres = face_like_landmarks(rng, 10)
    fitted = RBF(centres, rng.normal(size=(10, 2)))
    assert fitted(np.empty((0, 3))).shape == (0, 2)
    assert fitted.evaluation_matrix(np.empty((0, 3))).shape == (0, 14)
    warp = TPS(centres, centres)
    assert warp.displacement(np.zeros((0, 3))).shape == (0, 3)


def test_fitted_object_is_immutable():
    rng = np.random.default_rng(14)
    centres = face_like_landmarks(rng, 10)
    warp = TPS(centres, centres + 1.0)
    for array in (warp.weights, warp.affine, warp.coefficients, warp.centres):
        assert not array.flags.writeable
        with pytest.raises(ValueError):
            array[0, 0] = 1.0
    with pytest.raises(AttributeError):
        warp.kernel = "gaussian"
    with pytest.raises(AttributeError):
        warp._model = None
    # the fit does not alias the caller's arrays
    assert not np.shares_memory(warp.centres, centres)


def test_repr_names_the_model():
    rng = np.random.default_rng(15)
    centres = face_like_landmarks(rng, 10)
    text = repr(RBF(centres, centres, "gaussian", epsilon=0.05, smoothing=2.0))
    assert "gaussian" in text and "centres=10" in text and "epsilon=0.05" in text and "smoothing=2" in text
    assert repr(TPS(centres, centres)).startswith("TPS(centres=10")
    assert TPS(centres, centres).kernel == "tps"


# --- degenerate input ----------------------------------------------------------------------

def _good_centres():
    return face_like_landmarks(np.random.default_rng(16), 12)


@pytest.mark.parametrize("bad, message", [
    (lambda c: c[:4], "at least 5 are needed"),
    (lambda c: np.vstack([c[:3], c[:3] * 0 + c[0]]), "coincide"),
])
def test_too_few_or_identical_centres(bad, message):
    centres = bad(_good_centres())
    with pytest.raises(ValueError, match=message):
        RBF(centres, np.zeros(len(centres)))


def test_duplicate_centres_are_reported_by_index():
    centres = _good_centres()
    centres[9] = centres[3] + 1e-12  # coincident to well within 1e-8 of a 120 mm extent
    with pytest.raises(ValueError, match=r"centres 3 and 9 coincide"):
        TPS(centres, centres)
    # With smoothing the system is regular and coincident centres are allowed: the
    # fit passes between their values.
    values = centres.copy()
    values[9] += 1.0
    fitted = TPS(centres, values, smoothing=1.0)
    assert np.all(np.isfinite(fitted(centres)))
    np.testing.assert_allclose(fitted(centres[3:4]), fitted(centres[9:10]), atol=1e-6)


def test_nearly_but_not_coincident_centres_are_accepted():
    centres = _good_centres()
    centres[9] = centres[3] + np.array([1e-3, 0.0, 0.0])  # 1 micron apart, above tolerance
    fitted = TPS(centres, centres)
    np.testing.assert_allclose(fitted(centres), centres, atol=1e-6)


def test_coplanar_and_collinear_centres_are_refused():
    rng = np.random.default_rng(17)
    planar = np.column_stack([rng.uniform(-50, 50, size=(20, 2)), np.zeros(20)])
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    tilted_plane = planar @ rotation.T + np.array([10.0, 20.0, 30.0])
    with pytest.raises(ValueError, match=r"coplanar \(rank 3 of \[1 x y z\]\)"):
        TPS(tilted_plane, tilted_plane)
    line = np.outer(rng.uniform(-50, 50, size=20), [1.0, 2.0, -0.5])
    with pytest.raises(ValueError, match=r"collinear \(rank 2 of \[1 x y z\]\)"):
        RBF(line, np.zeros(20), "biharmonic")
    # The message names the problem even when smoothing could otherwise regularise K.
    with pytest.raises(ValueError, match="affine part is undetermined"):
        TPS(tilted_plane, tilted_plane, smoothing=10.0)


@pytest.mark.parametrize("where", ["centres", "values", "points"])
@pytest.mark.parametrize("bad_value", [np.nan, np.inf])
def test_non_finite_input_is_refused(where, bad_value):
    centres = _good_centres()
    values = centres.copy()
    if where == "centres":
        centres[4, 1] = bad_value
    elif where == "values":
        values[7, 2] = bad_value
    if where != "points":
        with pytest.raises(ValueError, match=rf"{where} contains NaN or infinite values \(first at row"):
            RBF(centres, values)
        with pytest.raises(ValueError, match=r"(source|target) contains NaN or infinite values"):
            TPS(centres, values)
        return
    warp = TPS(centres, values)
    queries = np.zeros((5, 3))
    queries[2, 0] = bad_value
    for method in (warp, warp.displacement, warp.evaluation_matrix):
        with pytest.raises(ValueError, match=r"points contains NaN or infinite values \(first at row 2"):
            method(queries)


def test_wrong_shapes_are_refused():
    centres = _good_centres()
    with pytest.raises(ValueError, match=r"centres must have shape \(n, 3\)"):
        RBF(centres[:, :2], np.zeros(12))
    with pytest.raises(ValueError, match=r"values must have shape \(12,\) or \(12, k\)"):
        RBF(centres, np.zeros(11))
    with pytest.raises(ValueError, match=r"target must have one row per source point"):
        TPS(centres, centres[:-1])
    warp = TPS(centres, centres)
    with pytest.raises(ValueError, match=r"points must have shape \(n, 3\)"):
        warp(np.zeros(3))
    with pytest.raises(ValueError, match=r"points must have shape \(n, 3\)"):
        warp(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="numeric"):
        warp([["a", "b", "c"]])


def test_kernel_epsilon_and_smoothing_are_validated():
    centres = _good_centres()
    with pytest.raises(ValueError, match=r"kernel must be one of 'tps', 'biharmonic'.*got 'thin_plate_spline'"):
        RBF(centres, centres, "thin_plate_spline")
    with pytest.raises(ValueError, match="epsilon .* is required for kernel 'gaussian'"):
        RBF(centres, centres, "gaussian")
    for bad in (0.0, -1.0, np.nan, np.inf, "wide"):
        with pytest.raises(ValueError, match="epsilon"):
            RBF(centres, centres, "multiquadric", epsilon=bad)
    with pytest.raises(ValueError, match="epsilon applies only to kernels .* 'tps' is scale-free"):
        RBF(centres, centres, "tps", epsilon=1.0)
    for bad in (-1e-9, np.nan, np.inf):
        with pytest.raises(ValueError, match="smoothing must be finite and >= 0"):
            TPS(centres, centres, smoothing=bad)


def test_numerically_singular_system_is_reported():
    centres = _good_centres()
    # A gaussian with a width 1e6 times the spread of the centres is flat over them:
    # every kernel entry is 1 - O(1e-12), singular to working precision.
    with pytest.raises(ValueError, match="numerically singular .* epsilon is too small"):
        RBF(centres, centres, "gaussian", epsilon=1e-8)


def test_core_refuses_what_validation_would_catch_without_crashing():
    # The core is not meant to see this input, but must raise rather than crash or
    # return NaN if it does.
    good = _good_centres()
    values = np.zeros((12, 1))
    nan_centres = good.copy()
    nan_centres[0, 0] = np.nan
    duplicated = good.copy()
    duplicated[5] = duplicated[4]
    for centres in (nan_centres, duplicated, good[:1], good[:3], np.zeros((12, 3))):
        with pytest.raises(ValueError):
            core.rbf_fit(centres, values[: len(centres)], core.RbfKernel.tps, 0.0, 0.0)
    nan_values = values.copy()
    nan_values[3] = np.nan
    with pytest.raises(ValueError):
        core.rbf_fit(good, nan_values, core.RbfKernel.tps, 0.0, 0.0)
    with pytest.raises(ValueError):
        core.rbf_fit(good, values[:5], core.RbfKernel.tps, 0.0, 0.0)
    with pytest.raises(ValueError):
        core.rbf_fit(good, values, core.RbfKernel.gaussian, 0.0, 0.0)
    with pytest.raises(ValueError):
        core.rbf_fit(good, values, core.RbfKernel.tps, 0.0, -1.0)


def test_huge_evaluation_matrix_is_refused_without_allocating():
    rng = np.random.default_rng(18)
    centres = face_like_landmarks(rng, 60)
    warp = TPS(centres, centres)
    # 10^7 query rows x 64 columns: 6.4e8 values, over the budget like 10^5 x 10^4.
    # The queries are a broadcast view (no memory), so any conversion would show.
    queries = np.broadcast_to(np.array([1.0, 2.0, 3.0]), (10**7, 3))
    assert 10**7 * 64 > MAX_DENSE_ELEMENTS and 10**5 * (10**4 + 4) > MAX_DENSE_ELEMENTS
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=r"evaluation matrix would be 10000000 x 64 .* chunks"):
            warp.evaluation_matrix(queries)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000  # bytes: nothing of the size of the request was allocated
