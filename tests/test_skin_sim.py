"""The compiled skin simulation against its NumPy reference and against analytic cases:
one damped spring, energy conservation, a static equilibrium against the linearised
system's direct solve, rest, skull contact, thread-count independence."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import tpscore
from tpscore.physics import SimulationOptions, SkinMaterial, SkinModel, load_template
from tpscore.physics.linearised import prism_volumes
from tpscore.physics.system import INTEGRATORS, SkinArrays
from tpscore.reference import skin as reference
from tpscore.sparse import SparseCholesky

from skin_helpers import flat_head, linear_muscle, random_arrays, sphincter


@pytest.fixture(scope="module")
def system():
    arrays = random_arrays()
    rng = np.random.default_rng(3)
    # particles above the skull plane z = 0, some within the contact margin
    positions = np.column_stack([rng.uniform(-4, 4, arrays.particles), rng.uniform(-4, 4, arrays.particles),
                                 rng.uniform(0.1, 3.0, arrays.particles)])
    velocities = rng.normal(size=positions.shape)
    # each particle's nearest skull vertex, found by the contact search's walk
    foot = reference.project_contacts(arrays, positions, velocities, arrays.particle_foot, 0.0)[2]
    return replace(arrays, particle_foot=foot), arrays.core(), positions, velocities


def test_forces_and_energy_match_the_reference(system):
    arrays, core, x, v = system
    contractions = np.array([0.7, 0.4])
    for jaw in (0.0, 0.3):
        expected = reference.forces(arrays, x, v, contractions, jaw, arrays.particle_foot)
        got = core.forces(x, v, arrays.particle_foot, contractions, jaw)
        # The sums run in a different order: agreement to rounding of the largest force.
        assert np.abs(got - expected).max() < 1e-12 * np.abs(expected).max()
        assert core.potential_energy(x, contractions, jaw) == pytest.approx(
            reference.potential_energy(arrays, x, jaw), rel=1e-13)
    # the contact penalty acts: some particle lies within the margin
    height, _, _ = reference.locate(arrays, x, arrays.particle_foot)
    assert np.any(height < arrays.contact_margin)
    assert core.kinetic_energy(v) == pytest.approx(reference.kinetic_energy(arrays, v), rel=1e-14)


def test_free_forces_match_the_reference(system):
    # What the rest detector tests: the net force less what the skull bears. Particles
    # projected onto the skull (their inward force removed) and particles above it.
    arrays, core, x, v = system
    contractions = np.array([0.8, 0.3])
    inside = x.copy()
    inside[:, 2] -= 1.5
    x_on, v_on, foot = reference.project_contacts(arrays, inside, v, arrays.particle_foot, 0.2)
    height, _, _ = reference.locate(arrays, x_on, foot, 0.2)
    assert np.any(np.abs(height) <= 1e-9) and np.any(height > 1e-3)  # both kinds present
    expected = reference.free_forces(arrays, x_on, v_on, foot, contractions, 0.2)
    got = core.free_forces(x_on, v_on, foot, contractions, 0.2)
    full = reference.forces(arrays, x_on, v_on, contractions, 0.2, foot)
    assert not np.allclose(expected, full)  # the skull bears something
    assert np.abs(got - expected).max() < 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("integrator", list(INTEGRATORS))
def test_steps_match_the_reference(system, integrator):
    arrays, core, x, v = system
    contractions = np.array([0.9, 0.6])
    foot = arrays.particle_foot
    got = core.step(x, v, foot, contractions, 0.2, 2e-3, INTEGRATORS[integrator], 40)
    expected = (x, v, foot)
    for _ in range(40):
        expected = reference.step(arrays, *expected, contractions, 0.2, 2e-3, integrator)
    # 40 steps of a chaotic-free, damped system: rounding differences stay near 1e-13.
    assert np.abs(got[0] - expected[0]).max() < 1e-9
    assert np.abs(got[1] - expected[1]).max() < 1e-7
    assert np.array_equal(got[2], expected[2])


def test_contact_projection_matches_the_reference(system):
    arrays, core, x, v = system
    inside = x.copy()
    inside[:, 2] -= 1.5  # some particles now below the skull plane z = 0
    got = core.project_contacts(inside, v, arrays.particle_foot, 0.1)
    expected = reference.project_contacts(arrays, inside, v, arrays.particle_foot, 0.1)
    for a, b in zip(got, expected):
        assert np.allclose(a, b, atol=1e-12)
    assert np.any(inside[:, 2] < 0)


def test_skull_heights_match_the_reference(system):
    arrays, core, x, _ = system
    inside = x.copy()
    inside[:, 2] -= 1.5  # heights of both signs
    for jaw in (0.0, 0.25):
        expected = reference.locate(arrays, inside, arrays.particle_foot, jaw)[0]
        got = core.skull_heights(inside, arrays.particle_foot, jaw)
        assert np.any(expected < 0) and np.any(expected > 0)
        assert np.allclose(got, expected, rtol=0, atol=1e-12)
    # a particle without a skull vertex has no height
    foot = arrays.particle_foot.copy()
    foot[0] = -1
    assert core.skull_heights(inside, foot, 0.0)[0] == 0.0


def test_run_loop_matches_the_reference(system):
    arrays, core, x, _ = system
    zero = np.zeros_like(x)
    contractions = np.array([0.5, 0.5])
    settings = dict(dt=5e-2, max_steps=500, ramp_time=0.1, velocity_tolerance=1e-2, force_tolerance=1e-3,
                    patience=3, check_every=2, divergence_distance=100.0, record_every=7, record_count=3)
    got = core.run(x, zero, arrays.particle_foot, contractions, 0.2, 0, settings["dt"], settings["max_steps"],
                   settings["ramp_time"], settings["velocity_tolerance"], settings["force_tolerance"],
                   settings["patience"], settings["check_every"], settings["divergence_distance"],
                   settings["record_every"], settings["record_count"])
    positions, _, _, report, times, frames = reference.run(arrays, x, zero, arrays.particle_foot, contractions, 0.2,
                                                           integrator="symplectic", **settings)
    assert got[3] == report["steps"] and got[4] == report["settled"] is True and not got[5]
    assert np.abs(got[0] - positions).max() < 1e-9
    assert np.allclose(got[9], times) and np.abs(got[10].reshape(frames.shape) - frames).max() < 1e-9


def _two_particles(k=100.0, c=0.2, masses=(1.0, 3.0), rest=10.0):
    return SkinArrays(masses=np.array(masses), spring_first=np.array([0]), spring_second=np.array([1]),
                      spring_rest=np.array([rest]), spring_stiffness=np.array([k]),
                      spring_stiffness_high=np.array([4 * k]), spring_knee=np.array([1.0]),
                      spring_damping=np.array([c])).validated()


def test_one_damped_spring_oscillates_at_its_frequency_and_decays_at_its_rate():
    k, c, masses = 100.0, 0.2, (1.0, 3.0)
    reduced = masses[0] * masses[1] / sum(masses)
    rate = c / (2 * reduced)                      # envelope exp(-rate t)
    omega = np.sqrt(k / reduced - rate**2)        # damped angular frequency; sqrt(k/mu) undamped
    arrays = _two_particles(k, c, masses)
    x = np.array([[0.0, 0.0, 0.0], [10.5, 0.0, 0.0]])  # 5 % stretch: below the knee, linear
    dt = 1e-4
    out = arrays.core().run(x, np.zeros_like(x), np.full(2, -1), np.zeros(0), 0.0, 0, dt, 60000, 0.0,
                            0.0, 0.0, 3, 1, 100.0, 5, 2)
    times, frames = out[9], out[10].reshape(-1, 2, 3)
    extension = np.linalg.norm(frames[:, 1] - frames[:, 0], axis=1) - 10.0
    # zero crossings (linear interpolation) give the period
    sign = np.signbit(extension)
    cross = np.flatnonzero(sign[1:] != sign[:-1])
    t0 = times[cross] - extension[cross] * (times[cross + 1] - times[cross]) / (extension[cross + 1] - extension[cross])
    period = 2 * np.mean(np.diff(t0))
    # The semi-implicit step shifts the frequency by O((omega dt)^2) ~ 1e-6.
    assert 2 * np.pi / period == pytest.approx(omega, rel=1e-4)
    # peaks of |extension| decay as exp(-rate t)
    peaks = [np.argmax(np.abs(extension[a:b])) + a for a, b in zip(cross[:-1], cross[1:])]
    slope = np.polyfit(times[peaks], np.log(np.abs(extension[peaks])), 1)[0]
    assert -slope == pytest.approx(rate, rel=2e-3)


def _undamped_patch():
    head = flat_head(size=7)
    material = SkinMaterial(damping_ratio=0.0, drag=0.0)
    return SkinModel(head, material)


def _energy_trace(model, dt, steps, seed=0):
    arrays = model.layers.arrays
    core = arrays.core()
    rng = np.random.default_rng(seed)
    x = model.layers.rest + rng.normal(scale=0.02, size=model.layers.rest.shape)  # linear regime, no contact
    v = np.zeros_like(x)
    zero = np.zeros(arrays.muscles)
    foot = arrays.particle_foot
    energies = []
    chunk = max(1, steps // 400)
    for _ in range(steps // chunk):
        energies.append(core.potential_energy(x, zero, 0.0) + core.kinetic_energy(v))
        x, v, foot = core.step(x, v, foot, zero, 0.0, dt, 0, chunk)
    return np.array(energies)


def test_undamped_energy_is_conserved_within_the_semi_implicit_steps_first_order_error():
    model = _undamped_patch()
    dt = 0.5 * model.stable_step
    coarse = _energy_trace(model, dt, 8000)
    fine = _energy_trace(model, dt / 2, 16000)
    for trace in (coarse, fine):
        # no drift: the energy oscillates about its start (a symplectic method's
        # modified energy is conserved exactly)
        window = len(trace) // 5
        assert abs(trace[-window:].mean() - trace[:window].mean()) < 0.02 * trace[0]
    # The energy oscillates by O(dt) (the modified energy a symplectic method conserves
    # differs from the true one by O(dt)); its spread halves with the step.
    swing = [np.std(t) / t[0] for t in (coarse, fine)]
    assert swing[0] < 0.02
    assert 1.7 < swing[0] / swing[1] < 2.4


def test_implicit_step_dissipates_energy_of_an_undamped_system():
    model = _undamped_patch()
    arrays = model.layers.arrays
    core = arrays.core()
    rng = np.random.default_rng(0)
    x = model.layers.rest + rng.normal(scale=0.02, size=model.layers.rest.shape)
    v = np.zeros_like(x)
    zero = np.zeros(arrays.muscles)
    foot = arrays.particle_foot
    energies = []
    for _ in range(20):
        energies.append(core.potential_energy(x, zero, 0.0) + core.kinetic_energy(v))
        x, v, foot = core.step(x, v, foot, zero, 0.0, 20 * model.stable_step, 1, 1)
    energies = np.array(energies)
    # backward Euler's numerical damping: the energy never rises and ends far lower
    assert np.all(np.diff(energies) <= 1e-12 * energies[0])
    assert energies[-1] < 0.5 * energies[0]


def test_static_equilibrium_under_a_muscle_matches_the_linearised_direct_solve():
    head = flat_head(size=9, muscles=[linear_muscle(flat_head(size=9), force=0.005)])
    model = SkinModel(head)
    arrays = model.layers.arrays
    rest = model.layers.rest
    contraction = np.array([1.0])
    result = model.simulate(contraction, options=SimulationOptions(ramp_time=0.0, max_time=3.0,
                                                                   velocity_tolerance=1e-6, force_tolerance=1e-9))
    assert result.settled
    displacement = result.layers - rest
    # K u = f: K the springs' and anchors' stiffness at rest, f the muscle's pull there
    stiffness = reference.stiffness_matrix(arrays, rest)
    pull = reference.forces(arrays, rest, np.zeros_like(rest), contraction, 0.0)
    linear = SparseCholesky(stiffness).solve(pull.reshape(-1)).reshape(-1, 3)
    scale = np.abs(linear).max()
    assert 1e-3 < scale < 0.1  # small enough to be linear, large enough to measure
    # the difference is second order (the pull turns as the tissue moves) plus the
    # rest detector's residual (1e-9 mm of force-equivalent length per particle)
    assert np.abs(displacement - linear).max() < 1e-3 * scale


def test_relaxed_skin_stays_exactly_at_rest():
    head = flat_head(size=7, muscles=[linear_muscle(flat_head(size=7), attachment=(0.0, 6.0))])
    model = SkinModel(head)
    result = model.simulate(None, options=SimulationOptions(ramp_time=0.0))
    assert result.settled
    assert np.array_equal(result.layers, model.layers.rest)
    assert result.steps <= 20


def test_no_particle_ends_inside_the_skull():
    # A muscle attached to the skull right under the middle of the patch pulls the
    # tissue straight down into it, harder than the (weakened) contact penalty holds.
    base = flat_head(size=9, depth=6.0)
    muscle = linear_muscle(base, attachment=(0.0, 0.0), insertion=(0.0, 2.5), force=2.0, angular_zone_deg=80.0,
                           falloff_mm=6.0)
    head = flat_head(size=9, depth=6.0, muscles=[muscle])
    model = SkinModel(head, SkinMaterial(contact_stiffness=0.05))
    result = model.simulate(np.array([1.0]), options=SimulationOptions(max_time=0.3))
    assert result.settled and np.isfinite(result.layers).all()
    arrays = model.layers.arrays
    foot = reference.project_contacts(arrays, result.layers, np.zeros_like(result.layers), arrays.particle_foot,
                                      0.0)[2]
    height, _, _ = reference.locate(arrays, result.layers, foot)
    # the pull drove tissue onto the skull (so the test could fail) ...
    assert height.min() <= 1e-9
    # ... and the projection kept every particle out of it
    assert height.min() >= -1e-9
    over = np.all(np.abs(result.layers[:, :2]) < 10.0, axis=1)  # over the skull's outline
    assert result.layers[over, 2].min() >= -6.0 - 1e-9


def test_results_do_not_depend_on_the_thread_count():
    head = load_template()
    model = SkinModel(head)
    arrays = model.layers.arrays
    contractions = model.contraction_vector(head.contractions_for({"12": 0.5, "4": 0.5}))
    outputs = []
    try:
        for threads in (1, 2):
            tpscore.set_num_threads(threads)
            core = arrays.core()
            x, v, foot = core.step(model.layers.rest, np.zeros_like(model.layers.rest), arrays.particle_foot,
                                   contractions, 0.1, 5e-5, 0, 30)
            outputs.append((core.forces(x, v, foot, contractions, 0.1), x, v))
    finally:
        tpscore.set_num_threads(0)
    for a, b in zip(*outputs):
        assert np.array_equal(a, b)


def test_arrays_validation_names_the_field():
    arrays = random_arrays()
    with pytest.raises(ValueError, match="spring_rest"):
        replace(arrays, spring_rest=-arrays.spring_rest).validated()
    with pytest.raises(ValueError, match="spring_second"):
        replace(arrays, spring_second=arrays.spring_second + 100).validated()
    with pytest.raises(ValueError, match="itself"):
        replace(arrays, spring_second=arrays.spring_first.copy()).validated()
    with pytest.raises(ValueError, match="masses"):
        replace(arrays, masses=np.zeros(arrays.particles)).validated()
    with pytest.raises(ValueError, match="spring_stiffness_high"):
        replace(arrays, spring_stiffness_high=0.5 * arrays.spring_stiffness).validated()
    with pytest.raises(ValueError, match="jaw_axis"):
        replace(arrays, jaw_axis=np.array([2.0, 0.0, 0.0])).validated()
    with pytest.raises(ValueError, match="anchor_target"):
        replace(arrays, anchor_target=np.full((2, 3), np.nan)).validated()
    with pytest.raises(ValueError, match="muscle_axes"):
        replace(arrays, muscle_axes=2 * arrays.muscle_axes).validated()


def test_a_sphincter_draws_its_ring_toward_the_epicentre_within_its_plane():
    head = flat_head(size=11, muscles=[sphincter(centre=(0.0, 0.0, 0.0), force=0.05)])
    model = SkinModel(head)
    result = model.simulate(np.array([1.0]))
    assert result.settled
    n = len(head.vertices)
    rest = model.layers.rest[2 * n:]
    moved = result.layers[2 * n:] - rest
    radius = np.hypot(rest[:, 0] / 6.0, rest[:, 1] / 4.0)  # elliptic radius of the ring (6 x 4 mm)
    ring = (radius > 0.5) & (radius < 1.3)
    inward = -np.einsum("ij,ij->i", moved[ring, :2], rest[ring, :2]) / np.linalg.norm(rest[ring, :2], axis=1)
    assert np.all(inward > 0)
    # the pull itself lies in the ellipse's plane (z = const); what rises is the
    # compressed tissue bulging
    pull = reference.forces(model.layers.arrays, model.layers.rest, np.zeros_like(model.layers.rest),
                            np.array([1.0]), 0.0)[2 * n:]
    assert np.abs(pull[:, 2]).max() < 1e-9 * np.abs(pull).max()
    assert np.abs(pull).max() > 0


def test_prism_forces_are_the_volume_energys_gradient():
    # Only the prisms: their forces against central differences of their energy.
    arrays = random_arrays()
    prisms_only = replace(arrays, spring_stiffness=np.zeros_like(arrays.spring_stiffness),
                          spring_stiffness_high=np.zeros_like(arrays.spring_stiffness),
                          spring_damping=np.zeros_like(arrays.spring_damping),
                          anchor_stiffness=np.zeros_like(arrays.anchor_stiffness),
                          particle_foot=np.full(arrays.particles, -1), drag=0.0).validated()
    core = prisms_only.core()
    rng = np.random.default_rng(5)
    x = arrays.anchor_target + rng.normal(scale=0.4, size=arrays.anchor_target.shape)
    relaxed = np.zeros(arrays.muscles)
    force = core.forces(x, np.zeros_like(x), prisms_only.particle_foot, relaxed, 0.0)
    assert np.abs(force).max() > 1.0  # the prisms are strained
    h = 1e-5
    numeric = np.zeros_like(x)
    for i in range(len(x)):
        for d in range(3):
            up, down = x.copy(), x.copy()
            up[i, d] += h
            down[i, d] -= h
            numeric[i, d] = -(core.potential_energy(up, relaxed, 0.0) - core.potential_energy(down, relaxed, 0.0)) / (2 * h)
    assert np.abs(force - numeric).max() < 1e-6 * np.abs(force).max()
    # a rigid motion keeps every volume: no force
    turn = reference.jaw_rotation(np.array([0.0, 0.6, 0.8]), 0.7)
    moved = x @ turn.T + np.array([3.0, -1.0, 2.0])
    rigid = reference.forces(prisms_only, moved, np.zeros_like(x), relaxed, 0.0)
    assert np.allclose(np.linalg.norm(rigid, axis=1), np.linalg.norm(force, axis=1), rtol=1e-9, atol=1e-9)


def test_squeezed_tissue_keeps_its_volume_and_thickens():
    # A ring muscle squeezes a flat patch toward its centre. Without the prisms' volume
    # term the squeezed tissue loses volume; with it the tissue keeps most of it, and
    # the squeezed middle thickens more.
    head = flat_head(size=11, muscles=[sphincter(centre=(0.0, 0.0, 0.0), force=0.5)])
    n = len(head.vertices)
    prisms = SkinModel(head, SkinMaterial(bulk_ratio=1.0)).layers.arrays  # the same prisms for both
    results = {}
    for bulk in (0.0, 1.0):
        model = SkinModel(head, SkinMaterial(bulk_ratio=bulk))
        result = model.simulate(np.array([1.0]))
        assert result.settled and result.scale == 1.0
        rest = model.layers.rest
        volume_change = prism_volumes(prisms, result.layers)[0] / prism_volumes(prisms, rest)[0] - 1
        middle = np.hypot(rest[:n, 0] / 6.0, rest[:n, 1] / 4.0) < 1.0  # inside the ring
        thickening = ((result.layers[:n, 2] - result.layers[2 * n:, 2]) / (rest[:n, 2] - rest[2 * n:, 2]))[middle]
        results[bulk] = (np.abs(volume_change).max(), thickening.mean())
    assert results[0.0][0] > 0.2  # the squeeze is strong enough to lose a fifth
    assert results[1.0][0] < 0.5 * results[0.0][0]
    assert results[1.0][1] - 1 > 1.5 * (results[0.0][1] - 1) > 0


def test_prism_validation_names_the_field():
    arrays = random_arrays()
    twice = arrays.prism_particles.copy()
    twice[0, 5] = twice[0, 0]
    with pytest.raises(ValueError, match="prism_particles: prism 0 uses a particle twice"):
        replace(arrays, prism_particles=twice).validated()
    with pytest.raises(ValueError, match="prism_rest_volume"):
        replace(arrays, prism_rest_volume=-arrays.prism_rest_volume).validated()
    with pytest.raises(ValueError, match="prism_particles"):
        replace(arrays, prism_particles=arrays.prism_particles[:, :5]).validated()
    with pytest.raises(ValueError, match="prism_stiffness"):
        replace(arrays, prism_stiffness=-arrays.prism_stiffness).validated()


def test_the_contact_direction_turns_continuously_across_a_concave_crease():
    # A skull folded into a valley along x = 0 (z = |x| / 2): over the valley's middle the
    # closest skull point jumps from one slope to the other. The penalty's direction is
    # blended over the nearly-as-close triangles, so it turns continuously there (a
    # particle held in such a crease once chattered from side to side without end);
    # the core and the reference agree on it.
    arrays = random_arrays()
    skull = arrays.skull_vertices.copy()
    skull[:, 2] = 0.5 * np.abs(skull[:, 0])
    slope = np.column_stack([-0.5 * np.sign(skull[:, 0]), np.zeros(len(skull)), np.ones(len(skull))])
    arrays = replace(arrays, skull_vertices=skull,
                     skull_normals=slope / np.linalg.norm(slope, axis=1, keepdims=True)).validated()
    middle = int(np.argmin(np.linalg.norm(skull[:, :2], axis=1)))
    core = arrays.core()
    normals, forces = [], []
    for x in (-1e-4, 1e-4, 0.05):
        positions = arrays.anchor_target.copy()
        positions[0] = (x, 0.0, 0.3)  # 0.27 mm from each slope: inside the 0.5 mm margin
        foot = arrays.particle_foot.copy()
        foot[0] = middle
        height, normal, _ = reference.locate(arrays, positions[:1], foot[:1])
        assert 0 < height[0] < arrays.contact_margin[0]
        normals.append(normal[0])
        zero = np.zeros_like(positions)
        expected = reference.forces(arrays, positions, zero, np.zeros(2), 0.0, foot)
        got = core.forces(positions, zero, foot, np.zeros(2), 0.0)
        assert np.abs(got - expected).max() < 1e-12 * np.abs(expected).max()
        forces.append(got[0])
    # each slope alone would point 27 degrees to its own side: 0.89 apart
    assert np.linalg.norm(normals[1] - normals[0]) < 1e-3
    assert np.linalg.norm(forces[1] - forces[0]) < 1e-3 * np.linalg.norm(forces[0])
    # and away from the middle it leans toward the nearer slope's normal
    assert normals[2][0] < -1e-3


def test_the_skull_rim_is_a_rounded_lip_tissue_cannot_slip_behind():
    # The flat skull of random_arrays ends at x = 8. A particle 0.3 mm behind the
    # skull's plane is inside while over the bone; past the rim it stays inside near
    # the edge (the lip curves back only gradually), so its height runs on without a
    # jump. (Counted as beside the edge at its distance from it, the height jumped from
    # -0.3 to +0.3 mm there, and tissue that slipped round the edge was thrown back to
    # the front one step later, without end.) In front, the height rises smoothly; far
    # beyond the lip, a particle is beside the bone. Core and reference agree.
    arrays = random_arrays()
    core = arrays.core()
    edge_vertex = int(np.argmin(np.linalg.norm(arrays.skull_vertices - [8.0, 0.0, 0.0], axis=1)))
    rounding = reference.RIM_ROUNDING * arrays.contact_margin.max()
    across = np.linspace(7.0, 8.0 + rounding + 1.0, 600)
    for depth in (-0.3, 0.3):
        points = np.column_stack([across, np.full_like(across, 0.5), np.full_like(across, depth)])
        foot = np.full(len(points), edge_vertex)
        height, normal, _ = reference.locate(arrays, points, foot)
        assert np.allclose(core.skull_heights(points, foot, 0.0), height, rtol=0, atol=1e-12)
        step = across[1] - across[0]
        over, near, far = across < 8.0, (across > 8.0) & (across < 8.5), across > 8.0 + rounding
        # continuous over the bone, at the edge and along the lip wherever contact is
        # near; where the lip ends the height may step, far beyond any contact margin
        low = (height[:-1] < 4 * arrays.contact_margin.max()) | (height[1:] < 4 * arrays.contact_margin.max())
        assert np.abs(np.diff(height)[low]).max() < 3 * step
        assert height[far].min() > 4 * arrays.contact_margin.max()
        assert np.allclose(height[over], depth)
        if depth < 0:
            assert (height[near] < 0).all()  # inside: pushed back to the front
            assert (normal[near, 2] > 0.5).all()  # toward the front (and out round the lip)
        else:
            rising = ~over[1:] & low
            assert (np.diff(height)[rising] >= 0).all()  # rising along the lip
        # beyond the lip: beside the bone, at about its distance from the edge (averaged
        # with the nearly-as-close rim triangles')
        beside = np.hypot(across[far] - 8.0, depth)
        blend = reference.CONTACT_BLEND * arrays.contact_margin.max()
        assert (height[far] >= beside - 1e-9).all() and (height[far] <= beside + blend).all()
    # the core's forces on a particle in the lip agree with the reference's
    positions = arrays.anchor_target.copy()
    positions[0] = (8.3, 0.5, -0.2)
    foot = arrays.particle_foot.copy()
    foot[0] = edge_vertex
    zero = np.zeros_like(positions)
    expected = reference.forces(arrays, positions, zero, np.zeros(2), 0.0, foot)
    got = core.forces(positions, zero, foot, np.zeros(2), 0.0)
    assert np.abs(got - expected).max() < 1e-12 * np.abs(expected).max()
    assert expected[0, 2] - reference.forces(replace(arrays, contact_stiffness=np.zeros(arrays.particles)).validated(),
                                              positions, zero, np.zeros(2), 0.0, foot)[0, 2] > 0
