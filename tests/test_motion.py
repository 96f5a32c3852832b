import numpy as np
import pytest

from tpscore import datasets
from tpscore.motion import BSplineLattice, MotionOptions, register_surfaces
from tpscore.preprocess import FaceGrid, resample_scan
from tpscore.spatial import MeshSurface


def test_bspline_lattice_is_a_partition_of_unity_and_reproduces_affine_fields():
    lattice = BSplineLattice([-40.0, -60.0], [45.0, 50.0], 7.0)
    rng = np.random.default_rng(2)
    xy = rng.uniform([-40, -60], [45, 50], size=(500, 2))
    basis = lattice.basis(xy)
    assert np.allclose(basis.sum(axis=1), 1.0, atol=1e-12)  # weights of a point sum to 1
    rows, cols = np.mgrid[0:lattice.shape[0], 0:lattice.shape[1]]
    nodes = lattice.origin + lattice.spacing * np.stack([cols.ravel(), rows.ravel()], axis=1)
    affine = 2.0 + 0.3 * nodes[:, 0] - 0.7 * nodes[:, 1]
    # cubic B-splines reproduce polynomials of degree 1 from their node values exactly
    assert np.allclose(basis @ affine, 2.0 + 0.3 * xy[:, 0] - 0.7 * xy[:, 1], atol=1e-10)
    bending = lattice.bending()
    assert abs(affine @ bending @ affine) < 1e-9 * (affine @ affine)
    bump = np.exp(-((nodes ** 2).sum(axis=1)) / 200.0)
    assert bump @ bending @ bump > 1e-4


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
