"""Speed of the physical skin: steps per second and time to settle, compiled core
against the NumPy reference of the same step (tpscore.reference.skin).

Skins: the template head at 1.25 mm (10,254 vertices, 30,762 particles in three
layers, 262k springs) and at 5 mm (642 vertices), both made by
``tpscore.showcase.datasets.skin_template``; the muscles of a smile (AU12 at 0.35: at 0.5 the
10k skin's finer triangles fold, and the simulation would be repeated at a smaller
contraction, timing two runs instead of one). Every benchmark checks that the core
and the reference agree. Steps, simulated time and steps per second of each settle
are in the benchmark's extra_info (``--benchmark-json``).

The reference needs about a third of a second per semi-implicit step at 10k
vertices, so its time to settle there (some 1,400 steps, eight minutes) is not run:
the settle group at 10k times the core alone (benchmarks/SKIN.md multiplies its steps
by the reference's step time), and the settle group with both is the 642-vertex
skin. The implicit step is compared at 642 vertices.
"""
from __future__ import annotations

import numpy as np
import pytest

from tpscore.physics import SkinModel
from tpscore.physics.system import INTEGRATORS
from tpscore.reference import skin as reference
from tpscore.showcase.datasets import skin_template

SMILE = {"12": 0.35}


def _model(spacing):
    head = skin_template(spacing)
    model = SkinModel(head)
    contractions = model.contraction_vector(head.contractions_for(SMILE))
    return model, contractions


@pytest.fixture(scope="module")
def large():
    return _model(1.25)


@pytest.fixture(scope="module")
def small():
    return _model(5.0)


def _state(model, contractions, steps=200):
    """A state part-way through a smile (moving, stretched), to step from."""
    arrays = model.layers.arrays
    rest = model.layers.rest
    return model._system.step(rest, np.zeros_like(rest), arrays.particle_foot, contractions, 0.0,
                              model.stable_step, INTEGRATORS["symplectic"], steps)


# ---------------------------------------------------------------- one step, 10k vertices
def test_step_10k_tpscore(benchmark, large):
    model, contractions = large
    benchmark.group = "skin step, 10k vertices (semi-implicit)"
    x, v, foot = _state(model, contractions)
    dt = model.stable_step
    got = benchmark(model._system.step, x, v, foot, contractions, 0.0, dt, 0, 1)
    expected = reference.step(model.layers.arrays, x, v, foot, contractions, 0.0, dt, "symplectic")
    assert np.abs(got[0] - expected[0]).max() < 1e-9


def test_step_10k_numpy_reference(benchmark, large):
    model, contractions = large
    benchmark.group = "skin step, 10k vertices (semi-implicit)"
    x, v, foot = _state(model, contractions)
    result = benchmark.pedantic(reference.step, args=(model.layers.arrays, x, v, foot, contractions, 0.0,
                                                      model.stable_step, "symplectic"), rounds=3, iterations=1)
    assert np.isfinite(result[0]).all()


# ---------------------------------------------------------------- time to settle
def _settle_core(model, contractions):
    return model.simulate(contractions)


def test_settle_10k_tpscore(benchmark, large):
    model, contractions = large
    benchmark.group = "skin settle, 10k vertices (semi-implicit)"
    model.stable_step  # estimated once, outside the timing
    result = benchmark.pedantic(_settle_core, args=(model, contractions), rounds=1, iterations=1)
    assert result.settled and result.scale == 1.0  # one run, not clamped and repeated
    benchmark.extra_info.update(steps=result.steps, simulated_ms=1e3 * result.simulated_time,
                                steps_per_second=result.steps_per_second, particles=model.particles)


def _settle_reference(model, contractions):
    arrays = model.layers.arrays
    rest = model.layers.rest
    dt = model.stable_step
    return reference.run(arrays, rest, np.zeros_like(rest), arrays.particle_foot, contractions, 0.0,
                         integrator="symplectic", dt=dt, max_steps=int(np.ceil(0.5 / dt)), ramp_time=0.03,
                         velocity_tolerance=1.0, force_tolerance=2e-3, patience=3,
                         check_every=max(1, int(round(5e-4 / dt))), divergence_distance=100.0)


def test_settle_640_tpscore(benchmark, small):
    model, contractions = small
    benchmark.group = "skin settle, 642 vertices (semi-implicit)"
    model.stable_step
    result = benchmark.pedantic(_settle_core, args=(model, contractions), rounds=3, iterations=1)
    assert result.settled and result.scale == 1.0
    benchmark.extra_info.update(steps=result.steps, simulated_ms=1e3 * result.simulated_time,
                                steps_per_second=result.steps_per_second, particles=model.particles)


def test_settle_640_numpy_reference(benchmark, small):
    model, contractions = small
    benchmark.group = "skin settle, 642 vertices (semi-implicit)"
    positions, _, _, report, _, _ = benchmark.pedantic(_settle_reference, args=(model, contractions), rounds=1,
                                                       iterations=1)
    assert report["settled"]
    core = model.simulate(contractions)
    # the same loop, step for step: the settled skins agree to rounding
    assert report["steps"] == core.steps
    assert np.abs(positions - core.layers).max() < 1e-6
    benchmark.extra_info.update(steps=report["steps"])


# ---------------------------------------------------------------- implicit step
def test_implicit_step_640_tpscore(benchmark, small):
    model, contractions = small
    benchmark.group = "skin implicit step, 642 vertices"
    x, v, foot = _state(model, contractions)
    got = benchmark(model._system.step, x, v, foot, contractions, 0.0, 2e-3, INTEGRATORS["implicit"], 1)
    expected = reference.step(model.layers.arrays, x, v, foot, contractions, 0.0, 2e-3, "implicit")
    assert np.abs(got[0] - expected[0]).max() < 1e-8


def test_implicit_step_640_numpy_reference(benchmark, small):
    model, contractions = small
    benchmark.group = "skin implicit step, 642 vertices"
    x, v, foot = _state(model, contractions)
    result = benchmark.pedantic(reference.step, args=(model.layers.arrays, x, v, foot, contractions, 0.0, 2e-3,
                                                      "implicit"), rounds=3, iterations=1)
    assert np.isfinite(result[0]).all()
