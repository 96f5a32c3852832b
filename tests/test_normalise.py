import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tpscore.face.landmarks import N_LANDMARKS, landmark_index
from tpscore.face.normalise import (
    AFFINE_LANDMARKS,
    FrameTransform,
    NormalisedFace,
    landmark_transform,
    similarity_transform,
    thesis_affine_transform,
)


def _rotation(yaw, pitch, roll):
    """Ry(yaw) Rx(pitch) Rz(roll), degrees."""
    return Rotation.from_euler("YXZ", [yaw, pitch, roll], degrees=True).as_matrix()


@pytest.fixture
def reference():
    return np.random.default_rng(3).normal(scale=40.0, size=(N_LANDMARKS, 3))


def test_similarity_recovers_a_known_pose(reference):
    rotation = _rotation(10, -6, 3)
    scan = 1.1 * reference @ rotation.T + [5.0, -20.0, 300.0]
    transform = similarity_transform(scan, reference)
    # exact data: the closed form is exact up to rounding (1e-9 mm on 100 mm coordinates)
    assert np.abs(transform.apply(scan) - reference).max() < 1e-9
    assert transform.scale == pytest.approx(1 / 1.1, rel=1e-12)
    assert np.abs(transform.apply_inverse(reference) - scan).max() < 1e-9


def test_similarity_ignores_missing_landmarks_and_needs_three(reference):
    scan = reference + [1.0, 2.0, 3.0]
    scan[[0, 5, 9]] = np.nan
    assert np.abs(similarity_transform(scan, reference).apply(reference + [1, 2, 3]) - reference).max() < 1e-9
    scan[3:] = np.nan
    with pytest.raises(ValueError, match="at least 3 landmark pairs"):
        similarity_transform(scan, reference)


def test_similarity_never_returns_a_reflection(reference):
    mirrored = reference * [-1.0, 1.0, 1.0]
    transform = similarity_transform(mirrored, reference)
    assert np.linalg.det(transform.matrix[:3, :3]) > 0


def test_collinear_pairs_are_refused():
    line = np.outer(np.arange(N_LANDMARKS), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="one line"):
        similarity_transform(line, line)


def test_thesis_affine_maps_its_four_landmarks_exactly(reference):
    affine = np.array([[1.1, 0.1, 0.0], [0.05, 0.9, 0.1], [0.0, -0.1, 1.2]])
    scan = reference @ affine.T + [10.0, 0.0, -4.0]
    transform = thesis_affine_transform(scan, reference)
    idx = [landmark_index(n) for n in AFFINE_LANDMARKS]
    assert np.abs(transform.apply(scan[idx]) - reference[idx]).max() < 1e-9
    # an affine scan of the reference is undone everywhere, not only at the four
    assert np.abs(transform.apply(scan) - reference).max() < 1e-8


def test_thesis_affine_names_the_missing_landmark(reference):
    scan = reference.copy()
    scan[landmark_index("Chin middle")] = np.nan
    with pytest.raises(ValueError, match="missing: Chin middle"):
        thesis_affine_transform(scan, reference)


def test_frame_transform_validates_and_composes():
    with pytest.raises(ValueError, match="4 x 4"):
        FrameTransform(np.eye(3))
    with pytest.raises(ValueError, match="singular"):
        FrameTransform(np.diag([1.0, 0.0, 1.0, 1.0]))
    a = FrameTransform(np.diag([2.0, 2.0, 2.0, 1.0]))
    shift = np.eye(4)
    shift[:3, 3] = [1, 2, 3]
    b = FrameTransform(shift)
    p = np.array([[1.0, 1.0, 1.0]])
    assert np.allclose(a.then(b).apply(p), b.apply(a.apply(p)))
    assert np.allclose(a.then(b).apply_inverse(a.then(b).apply(p)), p)


def test_unknown_method_is_refused(reference):
    with pytest.raises(ValueError, match="unknown normalisation method"):
        landmark_transform(reference, reference, "procrustes")


def test_derived_values_are_made_once_and_one_does_not_wait_for_another():
    face = NormalisedFace(None, FrameTransform.identity())  # derived() needs no grid
    started, release = threading.Event(), threading.Event()
    calls = []

    def slow(f):
        calls.append("slow")
        started.set()
        assert release.wait(10.0)
        return 1

    first = threading.Thread(target=face.derived, args=("slow", slow))
    first.start()
    assert started.wait(10.0)
    # while one thread computes "slow", another computes something else without waiting
    other = []
    second = threading.Thread(target=lambda: other.append(face.derived("quick", lambda f: 2)))
    second.start()
    second.join(5.0)
    assert other == [2], "a derived value waited for another name's computation"
    release.set()
    first.join(10.0)
    assert face.derived("slow", slow) == 1 and calls == ["slow"]


def test_the_scan_frames_tree_serves_the_normalised_surface():
    from tpscore import MeshSurface
    from tpscore.face.grid import FaceGrid

    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:30, 0:25].astype(float)
    points = np.stack([2.0 * cols, 2.0 * rows, 5.0 * np.sin(cols / 6.0) + rng.normal(scale=0.1, size=rows.shape)], -1)
    mask = np.ones(rows.shape, dtype=bool)
    mask[10:14, 8:12] = False  # a hole
    scan = FaceGrid.from_points(points, mask)
    matrix = np.eye(4)
    matrix[:3, :3] = 1.05 * _rotation(8, -5, 2)
    matrix[:3, 3] = [3.0, -60.0, 20.0]
    transform = FrameTransform(matrix, "similarity")
    face = NormalisedFace(FaceGrid.from_points(transform.apply(points), mask), transform)

    scan_surface = face.scan_frame_surface(scan)
    assert face.scan_frame_surface(scan) is scan_surface  # built once
    surface = face.surface()
    assert surface.faces is scan_surface.faces  # the scan frame's tree, moved, not a new build
    mesh = face.grid.mesh()
    queries = mesh.vertices + rng.normal(scale=1.5, size=mesh.vertices.shape)
    for got, want in zip(surface.closest_point(queries), MeshSurface(mesh.vertices, mesh.faces).closest_point(queries)):
        assert np.array_equal(got, want)

    other = NormalisedFace(FaceGrid.from_points(points), transform)
    with pytest.raises(ValueError, match="scan_grid is not the grid this face was normalised from"):
        other.scan_frame_surface(scan)
