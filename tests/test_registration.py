import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import scipy.sparse as sp

from tpscore import _core
from tpscore.face.landmarks import landmark_index
from tpscore.lattice import BSplineLattice, LatticeSystem, symmetric_blocks
from tpscore.expression import registration
from tpscore.expression.landmark_pairs import refine_landmark_motion, refined_pair_trust
from tpscore.expression.mirror import Coverage, MirroredMotion
from tpscore.expression.registration import MotionOptions, grid_normals, register_surfaces, rest_pull_per_node
from tpscore.face.normalise import FrameTransform
from tpscore.face.grid import FaceGrid
from tpscore.face.resampling import resample_scan
from tpscore.reference import lattice as reference
from tpscore.showcase import datasets
from tpscore.sparse import SparseCholesky
from tpscore.spatial import MeshSurface


def _node_positions(lattice):
    """(n_nodes, 2) x-y positions of a lattice's nodes, in the order of its node values."""
    rows, cols = np.mgrid[0:lattice.shape[0], 0:lattice.shape[1]]
    return lattice.origin + lattice.spacing * np.stack([cols.ravel(), rows.ravel()], axis=1)


def test_bspline_lattice_is_a_partition_of_unity_and_reproduces_affine_fields():
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], 7.0)
    rng = np.random.default_rng(2)
    xy = rng.uniform([-40, -60], [45, 50], size=(500, 2))
    basis = lattice.basis(xy)
    assert np.allclose(basis.sum(axis=1), 1.0, atol=1e-12)  # weights of a point sum to 1
    nodes = _node_positions(lattice)
    affine = 2.0 + 0.3 * nodes[:, 0] - 0.7 * nodes[:, 1]
    # cubic B-splines reproduce polynomials of degree 1 from their node values exactly
    assert np.allclose(basis @ affine, 2.0 + 0.3 * xy[:, 0] - 0.7 * xy[:, 1], atol=1e-10)
    bending = lattice.bending()
    assert abs(affine @ bending @ affine) < 1e-9 * (affine @ affine)
    bump = np.exp(-((nodes ** 2).sum(axis=1)) / 200.0)
    assert bump @ bending @ bump > 1e-4


@pytest.mark.parametrize("spacing,columns", [(4.0, 3), (7.0, 1), (30.0, 2)])
def test_lattice_evaluation_matches_the_numpy_reference_and_the_basis(spacing, columns):
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], spacing)
    rng = np.random.default_rng(3)
    # points beyond the rectangle too: their stencils are clamped to the lattice's edge
    xy = rng.uniform([-70, -90], [75, 80], size=(5000, 2))
    values = rng.normal(size=(lattice.n_nodes, columns)) * 10.0
    compiled = lattice.evaluate(xy, values)
    assert compiled.shape == (5000, columns)
    np.testing.assert_allclose(compiled, reference.evaluate(lattice, xy, values), rtol=0, atol=1e-12)
    np.testing.assert_allclose(compiled, lattice.basis(xy) @ values, rtol=0, atol=1e-12)
    # a point's row does not depend on the others or on the thread count
    _core.set_num_threads(1)
    try:
        assert np.array_equal(lattice.evaluate(xy[::-1], values), compiled[::-1])
    finally:
        _core.set_num_threads(0)
    nan_rows = lattice.evaluate(np.array([[np.nan, 0.0], [0.0, np.inf]]), values)
    assert np.isnan(nan_rows).all()


def _random_symmetric(rng, m):
    q = rng.normal(size=(m, 3, 3))
    return q + q.transpose(0, 2, 1)


@pytest.mark.parametrize("spacing", [4.0, 7.0, 30.0])
def test_lattice_system_data_term_matches_the_scipy_assembly(spacing):
    rng = np.random.default_rng(int(spacing))
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], spacing)
    # points beyond the rectangle too: their stencils are clipped to the lattice's edge
    xy = rng.uniform([-50, -70], [55, 60], size=(700, 2))
    q = _random_symmetric(rng, len(xy))
    system = LatticeSystem(lattice, xy)
    expected = reference.block_gram(lattice.basis(xy), q).toarray()
    got = system.matrix(system.data_term(symmetric_blocks(q))).toarray()
    assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()
    # a second call overwrites, it does not accumulate
    got_again = system.matrix(system.data_term(symmetric_blocks(2.0 * q))).toarray()
    assert np.allclose(got_again, 2.0 * expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_lattice_data_term_is_the_same_to_the_bit_on_every_simd_level(tmp_path):
    # the AVX2 path adds the same rounded products in the same order as the scalar
    # loop: the registration's result must not depend on the CPU it runs on
    rng = np.random.default_rng(5)
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], 6.0)
    xy = rng.uniform([-50, -70], [55, 60], size=(900, 2))
    blocks = symmetric_blocks(_random_symmetric(rng, len(xy)))
    system = LatticeSystem(lattice, xy)
    np.savez(tmp_path / "in.npz", first=system._first_node, weights=system._weights, blocks=blocks,
             shape=np.array(lattice.shape))
    script = (
        "import sys, numpy as np\n"
        "from tpscore import _core\n"
        "d = np.load(sys.argv[1]); rows, cols = (int(v) for v in d['shape'])\n"
        "out = _core.lattice_block_gram(d['first'], d['weights'], d['blocks'], rows, cols)\n"
        "np.save(sys.argv[2], out)\n")
    results = []
    for level in ("avx2", "baseline"):
        target = tmp_path / f"{level}.npy"
        subprocess.run([sys.executable, "-c", script, str(tmp_path / "in.npz"), str(target)],
                       env={**os.environ, "TPSCORE_SIMD": level}, check=True, timeout=120)
        results.append(np.load(target))
    assert np.any(results[0] != 0)
    np.testing.assert_array_equal(results[0].view(np.int64), results[1].view(np.int64))


def test_lattice_system_solves_the_registration_terms_like_a_fresh_factorisation():
    rng = np.random.default_rng(3)
    lattice = BSplineLattice([0.0, 0.0], [60.0, 50.0], 8.0)
    xy = rng.uniform([0, 0], [60, 50], size=(400, 2))
    normals = rng.normal(size=(len(xy), 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    w = rng.uniform(0, 1, len(xy))
    q = w[:, None, None] * (normals[:, :, None] * normals[:, None, :] + 0.1 * np.eye(3))
    landmarks = lattice.basis(rng.uniform([0, 0], [60, 50], size=(5, 2)))
    fixed = sp.bmat([[landmarks.T @ landmarks * (1.0 + (k == l)) for l in range(3)] for k in range(3)])
    bending = sp.block_diag([lattice.bending()] * 3)
    system = LatticeSystem(lattice, xy)
    rhs = rng.normal(size=system.n)
    for alpha in (10.0, 0.1):
        matrix = reference.block_gram(lattice.basis(xy), q) + alpha * bending + fixed \
            + 1e-8 * sp.identity(system.n)
        values = (system.data_term(symmetric_blocks(q)) + alpha * system.aligned(bending)
                  + system.aligned(fixed + 1e-8 * sp.identity(system.n)))
        expected = SparseCholesky(matrix).solve(rhs)
        assert np.abs(system.solve(values, rhs) - expected).max() <= 1e-8 * np.abs(expected).max()


def test_lattice_system_solves_from_several_threads_at_once_as_from_one():
    # the two sides of a cut register on two threads with one system: each solve must
    # factorise and solve its own matrix, whatever the other thread does meanwhile
    rng = np.random.default_rng(5)
    lattice = BSplineLattice([0.0, 0.0], [120.0, 100.0], 4.0)
    xy = rng.uniform([0, 0], [120, 100], size=(3000, 2))
    system = LatticeSystem(lattice, xy)
    bending = system.aligned(sp.block_diag([lattice.bending()] * 3) + sp.identity(system.n))
    problems = []
    for k in range(8):
        q = rng.uniform(0.1, 1.0, len(xy))[:, None, None] * np.eye(3) * (1.0 + k)
        problems.append((system.data_term(symmetric_blocks(q)) + (0.1 + k) * bending, rng.normal(size=system.n)))
    alone = [system.solve(values, rhs) for values, rhs in problems]
    with ThreadPoolExecutor(max_workers=4) as pool:
        for _ in range(3):
            together = list(pool.map(lambda problem: system.solve(*problem), problems))
            for one, other in zip(alone, together):
                np.testing.assert_array_equal(one, other)


def test_lattice_system_rejects_couplings_beyond_two_stencils_and_bad_blocks():
    lattice = BSplineLattice([0.0, 0.0], [60.0, 50.0], 8.0)
    system = LatticeSystem(lattice, np.array([[10.0, 10.0], [30.0, 20.0]]))
    far = sp.coo_matrix(([1.0, 1.0], ([system.n - 1, 0], [0, system.n - 1])), shape=(system.n, system.n))
    with pytest.raises(ValueError, match="farther apart"):
        system.aligned(far)
    with pytest.raises(ValueError, match=r"blocks must have shape \(2, 6\)"):
        system.data_term(np.zeros((3, 6)))


def test_lattice_gram_kernel_refuses_a_stencil_that_leaves_the_lattice():
    rows, cols = 6, 5
    weights, blocks = np.ones((1, 16)), np.ones((1, 6))
    for first in (-1, 2, 3 * cols):          # before the lattice, past its right, past its foot
        with pytest.raises(ValueError, match="leaves the 6 x 5 lattice"):
            _core.lattice_block_gram(np.array([first]), weights, blocks, rows, cols)
    with pytest.raises(ValueError, match="differ in length"):
        _core.lattice_block_gram(np.array([0, 1]), weights, blocks, rows, cols)


def test_options_are_validated():
    with pytest.raises(ValueError, match="spacing_mm"):
        MotionOptions(spacing_mm=0.0)
    with pytest.raises(ValueError, match="iterations"):
        MotionOptions(iterations=0)


@pytest.mark.parametrize("hole", [False, True])
def test_registration_recovers_a_smooth_motion(hole):
    scan = datasets.make_face(datasets.random_identity(4), None, seed=1)
    neutral = resample_scan(scan.points, scan.landmarks)
    points = neutral.points
    x, y = points[..., 0], points[..., 1]
    # a smooth motion of several mm with normal and tangential parts (a cheek lift)
    bump = np.exp(-((x - 25.0) ** 2 + (y + 15.0) ** 2) / (2 * 15.0 ** 2))
    motion = np.stack([-1.5 * bump, 3.0 * bump, 2.0 * bump], axis=-1)
    moved = points + motion
    mask = neutral.mask.copy()
    if hole:
        mask[60:75, 90:110] = False  # a hole where the motion is largest
    expressive = FaceGrid.from_points(np.where(mask[..., None], moved, np.nan))
    mesh = expressive.mesh()
    landmarks = neutral.landmarks + np.nan_to_num(
        motion.reshape(-1, 3)[np.maximum(neutral.landmark_vertices, 0)])
    field = register_surfaces(points, neutral.mask, neutral.landmarks,
                              MeshSurface(mesh.vertices, mesh.faces), landmarks)
    found = field(points[neutral.mask])
    true = motion[neutral.mask]
    moving = np.linalg.norm(true, axis=1) > 0.5
    error = np.sqrt(np.mean(np.sum((found - true)[moving] ** 2, axis=1)))
    size = np.sqrt(np.mean(np.sum(true[moving] ** 2, axis=1)))
    # no landmark sits on the bump: what the field gets right there comes from the
    # surfaces (the normal part) and the smoothness (the tangential part); measured
    # about 0.3 of the motion, a fit that ignored the surfaces would be near 1
    assert error < 0.5 * size
    still = np.linalg.norm(true, axis=1) < 0.05
    # measured 0.03 mm where nothing moves: the still face stays still
    assert np.sqrt(np.mean(np.sum(found[still] ** 2, axis=1))) < 0.15


def test_lattice_derivatives_match_finite_differences():
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], 7.0)
    rng = np.random.default_rng(5)
    values = rng.normal(size=lattice.n_nodes)
    xy = rng.uniform([-35, -55], [40, 45], size=(200, 2))
    h = 1e-5
    for name, step in (("x", [h, 0.0]), ("y", [0.0, h])):
        numeric = (lattice.basis(xy + step) @ values - lattice.basis(xy - step) @ values) / (2 * h)
        # central differences of a C2 cubic: error O(h^2) plus rounding ~1e-16 / h
        assert np.allclose(lattice.basis(xy, name) @ values, numeric, atol=1e-7)
    with pytest.raises(ValueError, match="derivative"):
        lattice.basis(xy, "z")


def test_landmark_refinement_recovers_a_translation_from_noisy_pairs():
    scan = datasets.make_face(datasets.random_identity(2), None, seed=3)
    neutral = resample_scan(scan.points, scan.landmarks)
    shift = np.array([1.5, -1.0, 0.5])
    expressive = FaceGrid.from_points(np.where(neutral.mask[..., None], neutral.points + shift, np.nan))
    mesh = expressive.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    rng = np.random.default_rng(0)
    labelled = neutral.landmarks + shift + rng.normal(0.0, 0.8, neutral.landmarks.shape)
    refined, fit_rms = refine_landmark_motion(neutral.points, neutral.mask, neutral.landmarks, surface,
                                              labelled, radius_mm=10.0)
    ok = np.isfinite(fit_rms)
    assert ok.sum() >= 15
    raw_error = np.linalg.norm(labelled - neutral.landmarks - shift, axis=1)[ok]
    error = np.linalg.norm(refined - neutral.landmarks - shift, axis=1)[ok]
    # the labelling noise is ~1.4 mm per landmark; the patches pin the motion down to
    # a fraction of it where the face has shape (the median over the landmarks), and
    # a patch whose shape is flat in some direction keeps at most the labelled error
    assert np.median(error) < 0.35 * np.median(raw_error)
    assert np.all(error < raw_error + 0.2)


def test_landmark_patch_fit_ignores_a_hole_and_skips_a_patch_mostly_in_one():
    # the expressive scan is the neutral one translated, with two holes: one cut into
    # the patch of the nose tip (a quarter of it), one covering the patch of the chin
    scan = datasets.make_face(datasets.random_identity(2), None, seed=3)
    neutral = resample_scan(scan.points, scan.landmarks)
    shift = np.array([0.5, 1.0, -0.3])
    nose, chin = landmark_index("Nose tip"), landmark_index("Chin middle")
    xy = neutral.points[..., :2]
    beside_nose = neutral.landmarks[nose, :2] + np.array([6.0, 0.0])
    hole = (np.linalg.norm(xy - beside_nose, axis=-1) < 5.0) \
        | (np.linalg.norm(xy - neutral.landmarks[chin, :2], axis=-1) < 12.0)
    keep = neutral.mask & ~hole
    expressive = FaceGrid.from_points(np.where(keep[..., None], neutral.points + shift, np.nan))
    mesh = expressive.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    refined, fit_rms = refine_landmark_motion(neutral.points, neutral.mask, neutral.landmarks, surface,
                                              neutral.landmarks + shift, radius_mm=10.0)
    patch = neutral.mask & (np.linalg.norm(neutral.points - neutral.landmarks[nose], axis=-1) < 10.0)
    assert 0.1 < (patch & hole).sum() / patch.sum() < 0.5
    # the points over the hole (millimetres from the surface) do not count as misfit
    assert fit_rms[nose] < 0.05
    assert np.linalg.norm(refined[nose] - neutral.landmarks[nose] - shift) < 0.1
    assert np.isnan(fit_rms[chin]) and np.isnan(refined[chin]).all()


def test_landmark_patch_shape_says_which_directions_it_pins_down():
    # a tilted plane pins its patches down along its normal only; a sphere cap in
    # every direction
    x, y = np.meshgrid(np.linspace(-40, 40, 81), np.linspace(-40, 40, 81))
    normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    plane = np.dstack([x, y, -(normal[0] * x + normal[1] * y) / normal[2]])
    landmarks = np.full((22, 3), np.nan)
    landmarks[0] = plane[40, 40]
    landmarks[1] = plane[30, 50]
    grid = FaceGrid.from_points(plane)
    mesh = grid.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    _, fit_rms, shape = refine_landmark_motion(plane, grid.mask, landmarks, surface, landmarks + 0.3,
                                               return_shape=True)
    for k in (0, 1):
        values, vectors = np.linalg.eigh(shape[k])
        assert values[-1] > 0.99 and values[:2].max() < 1e-6
        assert abs(vectors[:, -1] @ normal) > 0.999
    assert np.isnan(shape[2:]).all() and np.isnan(fit_rms[2:]).all()
    r = 60.0
    sphere = np.dstack([x, y, np.sqrt(r * r - x * x - y * y)])
    grid = FaceGrid.from_points(sphere)
    mesh = grid.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    landmarks[:2] = sphere[[40, 30], [40, 50]]
    _, _, shape = refine_landmark_motion(sphere, grid.mask, landmarks, surface, landmarks, return_shape=True)
    # a 10 mm cap of a 60 mm sphere: normals spread by up to 1/6 rad around the centre
    assert 1e-3 < np.linalg.eigvalsh(shape[0])[0] < 0.02


def _flat_face():
    """A flat 120 mm square face in the z = 0 plane: its shape pins nothing along it."""
    x, y = np.meshgrid(np.linspace(-60, 60, 91), np.linspace(-60, 60, 91))
    flat = np.dstack([x, y, np.zeros_like(x)])
    grid = FaceGrid.from_points(flat)
    mesh = grid.mesh()
    return flat, grid, MeshSurface(mesh.vertices, mesh.faces)


def test_a_loose_early_scale_bound_lets_a_block_motion_be_found(monkeypatch):
    # a disc of the flat face raised by 4 mm with steep sides (a chin pushed forward)
    # and no landmark on it: most of the face is still, so the robust scale is its
    # lower bound, and a tight bound at the first, stiff iterations cuts the disc's
    # pairs off before the field comes near them
    flat, grid, _ = _flat_face()
    distance = np.hypot(flat[..., 0] - 25.0, flat[..., 1] + 25.0)
    raised = flat.copy()
    raised[..., 2] += 4.0 / (1.0 + np.exp(distance - 20.0))
    mesh = FaceGrid.from_points(raised).mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    landmarks = np.full((22, 3), np.nan)
    landmarks[0] = [-30.0, 30.0, 0.0]
    centre = np.array([[25.0, -25.0, 0.0]])

    def lift(start):
        monkeypatch.setattr(registration, "SCALE_FLOOR_START_MM", start)
        field = register_surfaces(flat, grid.mask, landmarks, surface, landmarks)
        return field(centre)[0, 2]

    default = lift(registration.SCALE_FLOOR_START_MM)
    constant, loose = lift(registration.SCALE_FLOOR_END_MM), lift(2.0)
    assert constant < 2.5 and loose > 3.5
    assert constant < default < loose


def test_the_pull_toward_rest_gives_way_where_the_surface_has_shape():
    # a flat face with a round bump (a nose): the flat part cannot show a slide and
    # keeps the whole pull; the bump's turning normals show it and are left to the data
    flat, grid, _ = _flat_face()
    bumped = flat.copy()
    bumped[..., 2] += 15.0 * np.exp(-(flat[..., 0] ** 2 + flat[..., 1] ** 2) / (2 * 8.0 ** 2))
    bumped[40:45, 60:70] = np.nan  # a hole: its points say nothing
    mask = np.isfinite(bumped).all(axis=-1)
    lattice = BSplineLattice([-60.0, -60.0], [60.0, 60.0], 8.0)
    basis, normals = lattice.basis(bumped[mask][:, :2]), grid_normals(bumped)[mask]
    pull = rest_pull_per_node(basis, normals, 0.01, 0.1)
    nodes = _node_positions(lattice)
    radius = np.hypot(*nodes.T)
    assert np.all(np.isfinite(pull)) and np.all((pull > 0) & (pull <= 0.01 + 1e-15))
    assert np.allclose(pull[(radius > 40) & (radius < 55)], 0.01, rtol=0.02)
    assert pull[radius < 12].max() < 0.3 * 0.01
    assert np.all(rest_pull_per_node(basis, normals, 0.01, 0.0) == 0.01)


def test_refined_pairs_keep_the_labelled_motion_along_a_flat_surface():
    # a flat face moved along itself: the surface cannot say how far it slid, so the
    # labelled motion decides along it, and the surface across it
    flat, grid, surface = _flat_face()
    rng = np.random.default_rng(1)
    landmarks = np.column_stack([rng.uniform(-40, 40, (22, 2)), np.zeros(22)])
    slide = np.array([2.0, 0.0, 0.0])
    field = register_surfaces(flat, grid.mask, landmarks, surface, landmarks + slide)
    moved = field(landmarks)
    assert np.allclose(moved[:, 0], 2.0, atol=0.25) and np.abs(moved[:, 2]).max() < 0.05


def test_rest_weight_lets_an_unobserved_slide_fade_away_from_its_landmark():
    # a flat face slid along itself with one labelled pair: nothing but the priors say
    # how the rest of the face moves (the point-to-point pull, a prior of no slide, is
    # off here so that the pull toward rest is seen on its own)
    flat, grid, surface = _flat_face()
    landmarks = np.full((22, 3), np.nan)
    landmarks[0] = [0.0, 0.0, 0.0]
    slide = np.array([2.0, 0.0, 0.0])
    far = np.array([[50.0, 50.0, 0.0], [-50.0, 45.0, 0.0]])
    carried = register_surfaces(flat, grid.mask, landmarks, surface, landmarks + slide,
                                MotionOptions(rest_weight=0.0))
    faded = register_surfaces(flat, grid.mask, landmarks, surface, landmarks + slide,
                              MotionOptions(rest_weight=0.01))
    # without the pull toward rest the bending energy carries the slide on
    assert np.all(carried(far)[:, 0] > 1.2)
    # with it the landmark keeps its motion, the face far from it comes to rest, and
    # half way the motion is in between
    assert faded(landmarks[:1])[0, 0] > 1.8
    assert np.abs(faded(far)).max() < 0.2
    assert 0.2 < faded(np.array([[20.0, 0.0, 0.0]]))[0, 0] < 1.5
    with pytest.raises(ValueError, match="rest_weight"):
        MotionOptions(rest_weight=-1.0)


def _ridge(shift=(0.0, 0.0, 0.0)):
    """A cylindrical ridge along x (radius 20 mm), optionally moved: its shape pins a
    patch down across the ridge and along its normal, not along the ridge."""
    x, y = np.meshgrid(np.linspace(-50, 50, 101), np.linspace(-16, 16, 33))
    points = np.dstack([x, y, np.sqrt(20.0 ** 2 - y * y)]) + np.asarray(shift)
    grid = FaceGrid.from_points(points)
    mesh = grid.mesh()
    return points, grid.mask, MeshSurface(mesh.vertices, mesh.faces)


def test_refined_pairs_are_trusted_only_along_the_directions_their_patch_pins_down():
    points, mask, _ = _ridge()
    true_motion = np.array([2.0, 1.0, 0.0])
    _, _, moved = _ridge(true_motion)
    landmarks = np.full((22, 3), np.nan)
    landmarks[0] = points[16, 50]                       # on the crest
    # the label is off by 1.5 mm across the ridge and 0.6 mm along it
    labelled = landmarks + true_motion + np.array([0.6, 1.5, 0.0])
    refined, fit_rms, shape = refine_landmark_motion(points, mask, landmarks, moved, labelled,
                                                     return_shape=True)
    # the surface corrects the label across the ridge; along it nothing can
    assert abs(refined[0, 1] - landmarks[0, 1] - 1.0) < 0.1
    trust = refined_pair_trust(fit_rms, shape, 0.35)
    along, across, normal = np.eye(3)
    assert along @ trust[0] @ along < 0.05
    assert across @ trust[0] @ across > 0.9 and normal @ trust[0] @ normal > 0.9
    assert np.allclose(trust[0], trust[0].T) and np.all(trust[1:] == 0.0)
    # a pair whose patch fits badly (it deforms) is not trusted in any direction
    worse = refined_pair_trust(np.array([1.0]), shape[:1], 0.35)
    assert np.abs(worse).max() < 1e-12
    # the registration takes the ridge's correction across it and the label along it
    field = register_surfaces(points, mask, landmarks, moved, labelled)
    at = field(landmarks[:1])[0]
    assert abs(at[1] - 1.0) < 0.25 and abs(at[0] - 2.6) < 0.3


def _plane_points(x_min=-40.0, x_max=40.0):
    x, y = np.meshgrid(np.arange(x_min, x_max + 0.5, 1.0), np.arange(-30.0, 30.5, 1.0))
    return np.stack([x.ravel(), y.ravel(), 0.05 * y.ravel() ** 2], axis=1)


def _x_mirror():
    return FrameTransform(np.diag([-1.0, 1.0, 1.0, 1.0]), "mirror")


def test_mirrored_motion_keeps_the_symmetric_part_and_drops_the_rest():
    def symmetric(p):   # M u(S p) = u(p) for the mirror x -> -x
        return np.stack([0.1 * p[:, 0], 1.0 + 0.01 * p[:, 0] ** 2, np.cos(p[:, 0] / 9.0)], axis=1)

    def antisymmetric(p):
        return np.stack([np.full(len(p), 0.7), 0.02 * p[:, 0], np.sin(p[:, 0] / 7.0)], axis=1)

    points = _plane_points()
    mirrored = MirroredMotion(lambda p: symmetric(p) + antisymmetric(p), _x_mirror(), points)
    assert np.abs(mirrored(points) - symmetric(points)).max() < 1e-12
    assert np.abs(MirroredMotion(symmetric, _x_mirror(), points)(points) - symmetric(points)).max() < 1e-12
    assert np.isnan(mirrored(np.array([[np.nan, 0.0, 0.0]]))).all()


def test_mirrored_motion_keeps_its_own_motion_where_the_mirror_is_off_the_face():
    def field(p):
        return np.stack([np.full(len(p), 1.0), 0.01 * p[:, 0], np.zeros(len(p))], axis=1)

    covered = _plane_points(x_min=-10.0)      # the face's right side is mostly missing
    mirrored = MirroredMotion(field, _x_mirror(), covered, reach_mm=3.0)
    far = np.array([[30.0, 0.0, 0.0]])        # its mirror image is off the face
    assert np.abs(mirrored(far) - field(far)).max() < 1e-12
    missing = np.array([[-30.0, 5.0, 1.25]])  # off the face, its mirror image on it
    assert np.abs(mirrored(missing) - field(missing @ np.diag([-1.0, 1.0, 1.0])) * [-1.0, 1.0, 1.0]
                  ).max() < 1e-5
    inner = np.array([[5.0, 2.0, 0.2]])       # both sides covered: the mean
    assert np.abs(mirrored(inner) - [[0.0, 0.0, 0.0]]).max() < 1e-12
    with pytest.raises(ValueError, match="reach_mm"):
        MirroredMotion(field, _x_mirror(), covered, reach_mm=0.0)
    with pytest.raises(ValueError, match="finite"):
        MirroredMotion(field, _x_mirror(), np.full((4, 3), np.nan))


def test_coverage_follows_the_distance_to_the_nearest_vertex_within_its_raster():
    # 1 within reach of a vertex (in x, y), 0 beyond twice the reach, linear between;
    # the raster's cells are a quarter of the reach, so a weight may be off by the
    # cells' diagonal over the reach
    rng = np.random.default_rng(7)
    vertices = np.column_stack([rng.uniform(-40, 40, 3000), rng.uniform(-50, 50, 3000), rng.normal(0, 5, 3000)])
    vertices = vertices[np.hypot(vertices[:, 0] - 10, vertices[:, 1]) > 15]  # a hole
    coverage = Coverage(vertices, reach_mm=3.0)
    points = np.column_stack([rng.uniform(-60, 60, 5000), rng.uniform(-70, 70, 5000), np.zeros(5000)])
    nearest = np.min(np.hypot(points[:, None, 0] - vertices[None, :, 0], points[:, None, 1] - vertices[None, :, 1]),
                     axis=1)
    exact = np.clip(2.0 - nearest / 3.0, 0.0, 1.0)
    weights = coverage(points)
    assert weights.shape == (5000,) and ((weights >= 0) & (weights <= 1)).all()
    assert np.abs(weights - exact).max() <= 2 * np.sqrt(2) * 0.75 / 3.0
    assert (weights[nearest < 1e-9] == 1.0).all() and (weights[nearest > 6.0 + 1.5] == 0.0).all()
    assert (coverage(vertices) == 1.0).all()
    # points far beyond the raster, in every direction, are not covered
    far = np.array([[1e6, 0, 0], [-1e6, 0, 0], [0, 1e300, 0], [-1e300, -1e300, 0], [41.0, 51.0, 0.0]])
    assert (coverage(far)[:4] == 0.0).all()


@pytest.mark.parametrize("m", [1, 2, 7, 2000, 2001])
def test_registration_terms_match_the_numpy_reference_to_the_bit(m):
    # the compiled data terms follow the NumPy arithmetic step by step: a registration
    # gives the same field whichever computes them
    from tpscore import _core
    from tpscore.reference import registration as terms

    rng = np.random.default_rng(m)
    sample = rng.normal(scale=30.0, size=(m, 3))
    moved = sample + rng.normal(scale=1.0, size=(m, 3))
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    # closest points below the moved points (on the surface) and off to the side (rims)
    along = rng.normal(scale=0.8, size=m)
    sideways = np.cross(normals, rng.normal(size=(m, 3))) * (rng.random(m) < 0.2)[:, None] * 3.0
    closest = moved - along[:, None] * normals + sideways
    distances = np.linalg.norm(moved - closest, axis=1)
    prior = np.where(rng.random(m) < 0.1, 0.0, rng.uniform(0.2, 2.0, m))
    targets = moved + rng.normal(scale=0.7, size=(m, 3))
    for floor in (0.5, 5.0):
        expected = terms.point_to_plane_terms(sample, moved, closest, distances, normals, prior, floor, 3.0)
        got = _core.point_to_plane_terms(sample, moved, closest, distances, normals, prior, floor, 3.0)
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)
        expected = terms.texture_pull_terms(sample, moved, targets, normals, prior, floor, 3.0)
        got = _core.texture_pull_terms(sample, moved, targets, normals, prior, floor, 3.0)
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)


def test_detected_landmark_pairs_keep_only_the_ends_the_texture_gives():
    """With texture matches and detected landmarks, a pair's expressive end must come
    from the texture: the detected expressive landmarks do not enter the term, and a
    landmark whose vertex has no match has no pair."""
    from tpscore.expression.landmark_pairs import landmark_term
    from tpscore.expression.texture import TextureMatches

    scan = datasets.make_face(datasets.random_identity(2), None, seed=3)
    neutral = resample_scan(scan.points, scan.landmarks)
    shift = np.array([0.0, 1.5, 0.5])
    expressive = FaceGrid.from_points(np.where(neutral.mask[..., None], neutral.points + shift, np.nan))
    mesh = expressive.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    lattice = BSplineLattice(neutral.points[neutral.mask][:, :2].min(axis=0),
                             neutral.points[neutral.mask][:, :2].max(axis=0), 8.0)
    # the texture matched every vertex but those of the first five landmarks
    confidence = neutral.mask.astype(float)
    rows, cols = np.divmod(neutral.landmark_vertices[:5], neutral.shape[1])
    confidence[rows, cols] = 0.0
    texture = TextureMatches(np.where(neutral.mask[..., None], neutral.points + shift, np.nan), confidence,
                             float(confidence[neutral.mask].mean()), 0.0)
    off = neutral.landmarks + shift + 4.0  # a detector's expressive landmarks, 4 mm off

    def term(expressive_landmarks, **kw):
        matrix, rhs = landmark_term(lattice, neutral.points, neutral.mask, neutral.landmarks, expressive_landmarks,
                                    surface, 3.0, texture, **kw)
        return matrix.toarray(), rhs

    matrix, rhs = term(off, landmarks_detected=True)
    again, rhs_again = term(neutral.landmarks + shift, landmarks_detected=True)
    assert np.array_equal(matrix, again) and np.array_equal(rhs, rhs_again)
    # the same as labelled pairs of the matched landmarks alone, whose ends are the matches
    kept = neutral.landmarks.copy()
    kept[:5] = np.nan
    labelled, labelled_rhs = term(kept + shift)
    assert np.allclose(matrix, labelled, atol=1e-12) and np.allclose(rhs, labelled_rhs, atol=1e-12)
    # labelled landmarks keep their pairs, the unmatched ones ending at the labels
    assert not np.allclose(term(off)[1], rhs)
