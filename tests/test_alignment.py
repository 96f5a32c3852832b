import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tpscore.expression.alignment import (ANCHOR_PARTS, align_rigid, fit_mirror_symmetry, residual_rigid_motion,
                                         rigid_landmark_fit, stable_weight)
from tpscore.expression.action_units import shipped_library
from tpscore.expression.modelling import needs_realignment, still_weight
from tpscore.face.average_face import load_average_face
from tpscore.face.landmarks import landmark_index
from tpscore.face.normalise import FrameTransform
from tpscore.face.regions import region_weight
from tpscore.face.resampling import resample_scan
from tpscore.showcase import datasets


def _grid(scan):
    return resample_scan(scan.points, scan.landmarks)


def _rotation(yaw, pitch, roll):
    """Ry(yaw) Rx(pitch) Rz(roll), degrees."""
    return Rotation.from_euler("YXZ", [yaw, pitch, roll], degrees=True).as_matrix()


@pytest.fixture(scope="module")
def smiling_pair():
    identity = datasets.random_identity(11)
    neutral = datasets.make_face(identity, None, noise_mm=0.1, seed=3)
    smiling = datasets.make_face(identity, {"12": 1.0}, noise_mm=0.1, pose_deg=10.0, seed=4)
    return neutral, smiling


def test_rigid_landmark_fit_ignores_moved_landmarks():
    rng = np.random.default_rng(5)
    fixed = rng.uniform(-50, 50, size=(22, 3))
    rotation = _rotation(8.0, -6.0, 3.0)
    moving = (fixed - [1.0, 2.0, 3.0]) @ rotation  # moving = R^T (fixed - t)
    moving[[15, 17, 20]] += [0.0, 8.0, 2.0]        # an expression moved three landmarks
    moving[4] = np.nan                              # and one is missing
    fit = rigid_landmark_fit(moving, fixed)
    keep = np.isfinite(moving).all(axis=1)
    keep[[15, 17, 20]] = False
    # exact data on the kept landmarks: only rounding remains once the moved ones are out
    assert np.abs(fit.apply(moving[keep]) - fixed[keep]).max() < 1e-9
    assert abs(np.linalg.det(fit.matrix[:3, :3]) - 1.0) < 1e-12  # rigid: no scale


def test_rigid_landmark_fit_needs_three_landmarks():
    a = np.full((22, 3), np.nan)
    a[:2] = [[0, 0, 0], [1, 0, 0]]
    with pytest.raises(ValueError, match="at least 3 landmarks"):
        rigid_landmark_fit(a, a)


def test_icp_recovers_the_pose_of_an_expressive_scan(smiling_pair):
    neutral, smiling = smiling_pair
    fixed, moving = _grid(neutral), _grid(smiling)
    truth = FrameTransform(neutral.pose @ np.linalg.inv(smiling.pose))
    still = region_weight("upper", moving.points, moving.landmarks, 10.0)
    result = align_rigid(moving, fixed, still_weight=still)
    points = moving.points[moving.mask]

    def error(transform):
        return np.sqrt(np.mean(np.sum((transform.apply(points) - truth.apply(points)) ** 2, axis=1)))

    # the landmarks alone are exact here but the smile moved some of them; the ICP on
    # the still upper face must land within the scan noise (0.1 mm) of the true pose
    assert error(result.transform) < 0.25
    assert error(result.transform) < error(result.landmark_transform)


def test_icp_copes_with_missing_landmarks_and_holes(smiling_pair):
    neutral, smiling = smiling_pair
    fixed, moving = _grid(neutral), _grid(smiling)
    lm = moving.landmarks.copy()
    lm[[0, 6, 13, 21]] = np.nan  # an eyebrow, an eye corner, the nose tip, the chin
    moving = moving.with_landmarks(lm)
    mask = fixed.mask.copy()
    mask[30:50, 20:60] = False   # a hole over an eye
    fixed = type(fixed).from_points(np.where(mask[..., None], fixed.points, np.nan),
                                   landmarks=fixed.landmarks)
    truth = FrameTransform(neutral.pose @ np.linalg.inv(smiling.pose))
    result = align_rigid(moving, fixed,
                         still_weight=region_weight("upper", moving.points, moving.landmarks, 10.0))
    points = moving.points[moving.mask]
    error = np.sqrt(np.mean(np.sum((result.transform.apply(points) - truth.apply(points)) ** 2, axis=1)))
    assert error < 0.25  # measured 0.05 mm; a failed alignment is off by millimetres


def test_mirror_symmetry_finds_the_plane_of_a_posed_face():
    # the procedural faces are symmetric about x = 0 of their own frame; the scan shows
    # the face turned and shifted, with noise and holes
    scan = datasets.make_face(datasets.random_identity(11), None, noise_mm=0.1, holes=3,
                              pose_deg=10.0, seed=7)
    grid = _grid(scan)
    mirror = fit_mirror_symmetry(grid)
    pose = scan.pose  # face frame -> scan frame
    truth = FrameTransform(pose @ np.diag([-1.0, 1.0, 1.0, 1.0]) @ np.linalg.inv(pose))
    points = grid.points[grid.mask]
    error = np.sqrt(np.mean(np.sum((mirror.apply(points) - truth.apply(points)) ** 2, axis=1)))
    assert error < 0.1  # measured 0.013 mm (the landmarks alone: 0.32 mm)
    assert np.linalg.det(mirror.matrix[:3, :3]) == pytest.approx(-1.0, abs=1e-12)
    twice = mirror.matrix @ mirror.matrix
    assert np.abs(twice - np.eye(4)).max() < 1e-9  # an exact reflection


def test_mirror_symmetry_needs_landmark_pairs():
    grid = _grid(datasets.make_face(None, None))
    landmarks = np.full_like(grid.landmarks, np.nan)
    landmarks[:2] = grid.landmarks[:2]
    with pytest.raises(ValueError, match="at least 3 landmarks"):
        fit_mirror_symmetry(grid.with_landmarks(landmarks))


def test_residual_rigid_motion_prefers_the_anchored_still_part_over_a_larger_moved_block():
    # a curved patch: the lower 60 % rises 1 mm as one block, the upper 40 % stays still
    # (anger's cheeks and nose rising together under a still bridge)
    x, y = np.meshgrid(np.linspace(-50, 50, 60), np.linspace(-60, 60, 60))
    points = np.column_stack([x.ravel(), y.ravel(), -0.004 * (x.ravel() ** 2 + y.ravel() ** 2)])
    block = points[:, 1] < 12.0
    motion = np.zeros_like(points)
    motion[block, 1] = 1.0
    motion += np.random.default_rng(2).normal(scale=0.05, size=motion.shape)
    prior = np.ones(len(points))
    largest = residual_rigid_motion(points, motion, prior)
    anchored = residual_rigid_motion(points, motion, prior, anchor=(~block).astype(float))
    # without an anchor the larger block is taken as still, and the still part is the one that "moved"
    assert np.allclose(largest.apply(points[~block])[:, 1] - points[~block, 1], 1.0, atol=0.1)
    # counting the still part twice picks it: the motion left is the block's alone
    assert np.abs(anchored.apply(points) - points).max() < 0.1


_CORNERS = ("Inner left eye corner", "Inner right eye corner", "Outer left eye corner", "Outer right eye corner")


def test_the_eye_corners_are_anchors_where_a_corner_landmark_is():
    grid = _grid(datasets.make_face(datasets.random_identity(5), None, noise_mm=0.0, seed=1))
    points, landmarks = grid.points[grid.mask], grid.landmarks
    assert "canthi" in ANCHOR_PARTS
    canthi = stable_weight(points, landmarks, ("canthi",), elsewhere=0.0)
    near = [np.linalg.norm(points - landmarks[landmark_index(name)], axis=1) for name in _CORNERS]
    nearest = np.min(near, axis=0)
    assert np.all(canthi[nearest < 4.0] == 1.0)  # within about 5 mm of a corner: full weight
    assert np.all(canthi[nearest > 9.0] == 0.0)  # beyond about 8 mm: none
    # the default parts leave the corners out: the ICP's weight is what it was
    assert np.array_equal(stable_weight(points, landmarks),
                          stable_weight(points, landmarks, ("bridge", "forehead", "temples")))
    # a missing corner loses its own patch and no other
    missing = landmarks.copy()
    missing[landmark_index(_CORNERS[0])] = np.nan
    partial = stable_weight(points, missing, ("canthi",), elsewhere=0.0)
    assert np.all(partial[near[0] < 4.0] == 0.0) and np.all(np.isfinite(partial))
    assert np.all(partial[np.min(near[1:], axis=0) < 4.0] == 1.0)


def test_stable_weight_refuses_a_part_it_does_not_place():
    grid = _grid(datasets.make_face(datasets.random_identity(5), None, noise_mm=0.0, seed=1))
    with pytest.raises(ValueError, match="parts must name.*'chin'"):
        stable_weight(grid.points, grid.landmarks, ("bridge", "chin"))


def test_an_au_of_a_region_within_one_half_is_aligned_on_the_other_half(smiling_pair):
    # the chin raiser's region lies in the lower face: the upper face is its still part,
    # as for AUs of the lower half, and its motion has no rigid part left to take out;
    # a nose wrinkler's region reaches across the eye line: the stable parts, then a
    # realignment
    library, reference = shipped_library(), load_average_face().landmarks
    grid = _grid(smiling_pair[1])
    upper = region_weight("upper", grid.points, grid.landmarks, 10.0)
    for spec in ("17", "16", "16+12"):
        activations = library.parse(spec)
        np.testing.assert_array_equal(still_weight(grid, activations, library, reference), upper)
        assert not needs_realignment(activations, library, reference)
    for spec in ("9", "17+9", "happiness"):
        activations = library.parse(spec)
        np.testing.assert_array_equal(still_weight(grid, activations, library, reference),
                                      stable_weight(grid.points, grid.landmarks))
        assert needs_realignment(activations, library, reference)
    # AUs of both halves: no part is still, the whole face is aligned robustly
    assert still_weight(grid, library.parse("17+1"), library, reference) is None
