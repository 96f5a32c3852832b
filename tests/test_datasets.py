"""Procedural faces: determinism, anatomy, action units, scan options, validation."""
from __future__ import annotations

import math

import numpy as np
import pytest

import tpscore
from tpscore.showcase import datasets
from tpscore.showcase.datasets import (
    ACTION_UNITS,
    MIDLINE_RAMP_MM,
    FaceParameters,
    au_displacement,
    demo_triplet,
    embedded_faces,
    face_height,
    face_landmarks,
    make_face,
    random_identity,
    sample_subjects,
)
from tpscore.face.landmarks import LANDMARK_NAMES, MIRROR_LANDMARK, landmark_index

IDENTITIES = [None, 1, 7, 42, 123]
UPPER_FACE_AUS = ("1", "2", "4")
LOWER_FACE_AUS = ("12", "14", "15", "17", "20")


def lm(landmarks, name):
    return landmarks[landmark_index(name)]


def nan_equal(a, b):
    return np.array_equal(a, b, equal_nan=True)


def face_grid(identity=None, step=1.0):
    """Face-frame x, y covering the whole face (mm)."""
    x, y = np.meshgrid(np.arange(-60.0, 60.0 + step, step), np.arange(-80.0, 95.0 + step, step))
    return np.column_stack([x.ravel(), y.ravel()])


# ------------------------------------------------------------------- determinism


def test_same_seed_same_scan_and_different_seed_different_noise():
    options = dict(expression={"12": 0.7, "4L": 0.5}, noise_mm=0.2, holes=4, pose_deg=5.0)
    first = make_face(3, seed=11, **options)
    again = make_face(3, seed=11, **options)
    other = make_face(3, seed=12, **options)
    assert nan_equal(first.points, again.points)
    assert np.array_equal(first.valid, again.valid)
    assert np.array_equal(first.landmarks, again.landmarks)
    assert not nan_equal(first.points, other.points)


def test_random_identity_is_deterministic_plausible_and_varied():
    assert random_identity(5) == random_identity(5)
    assert random_identity(5) != random_identity(6)
    base = FaceParameters()
    for seed in range(30):
        params = random_identity(seed)
        for name, value in vars(params).items():
            ratio = value / getattr(base, name)
            # shared size (2.5 x 4 %) times own variation (2.5 x 6 %): 0.765 .. 1.265
            assert 0.76 < ratio < 1.27, (seed, name, ratio)
    widths = [random_identity(seed).mouth_width for seed in range(30)]
    assert np.std(widths) / np.mean(widths) > 0.03  # identities really vary


def test_sample_subjects_and_embedded_faces_are_deterministic():
    subjects = sample_subjects()
    assert len(subjects) == 8
    assert subjects == sample_subjects()
    assert len(set(subjects)) == 8
    assert sample_subjects(3) == subjects[:3]
    faces = embedded_faces(2, spacing_mm=1.5)
    assert [f.identity for f in faces] == subjects[:2]
    assert all(f.expression == {} for f in faces)


def test_demo_triplet():
    source, expressive, target = demo_triplet("12", 0.5, spacing_mm=1.5)
    assert source.identity == expressive.identity != target.identity
    assert source.expression == {} and target.expression == {}
    assert expressive.expression == {"12": 0.5}
    corner = landmark_index("Left mouth corner")
    assert expressive.landmarks[corner, 1] > source.landmarks[corner, 1] + 1.0


# --------------------------------------------------------------------- anatomy


@pytest.mark.parametrize("identity", IDENTITIES)
def test_landmarks_lie_on_the_surface(identity):
    points = face_landmarks(identity)
    z = face_height(identity, points[:, 0], points[:, 1])
    np.testing.assert_allclose(points[:, 2], z, rtol=0, atol=1e-12)  # same formula


@pytest.mark.parametrize("identity", IDENTITIES)
def test_expressive_landmarks_lie_on_the_expressive_surface(identity):
    expression = {"12": 1.0, "4": 1.0, "17": 0.8}
    points = face_landmarks(identity, expression)
    z = face_height(identity, points[:, 0], points[:, 1], expression)
    # The height is found by inverting the skin motion to 1e-8 mm in x, y; slopes
    # are below 10, so z agrees to well under 1e-6 mm.
    np.testing.assert_allclose(points[:, 2], z, rtol=0, atol=1e-6)


@pytest.mark.parametrize("identity", IDENTITIES)
def test_landmarks_are_in_anatomical_order(identity):
    points = face_landmarks(identity)
    y = lambda name: lm(points, name)[1]  # noqa: E731
    for side in ("left", "right"):
        assert y(f"Middle {side} eyebrow") > y(f"Inner {side} eye corner")
        assert y(f"Inner {side} eye corner") > y(f"Nose saddle {side}") > y("Nose tip")
        assert y("Nose tip") > y(f"{side.capitalize()} mouth corner") > y("Chin middle")
    assert (y("Upper lip outer middle") > y("Upper lip inner middle")
            > y("Lower lip inner middle") > y("Lower lip outer middle") > y("Chin middle"))
    for index, name in enumerate(LANDMARK_NAMES):
        mirror = MIRROR_LANDMARK[index]
        if "left" in name.lower():
            assert points[index, 0] > 0, name            # the subject's left is +x
        if mirror == index:
            assert abs(points[index, 0]) < 1e-12, name   # midline
        else:
            # The neutral face is symmetric: mirror pairs differ only in the sign of x.
            np.testing.assert_allclose(points[mirror], points[index] * [-1, 1, 1], atol=1e-9)
    assert np.argmax(points[:, 2]) == landmark_index("Nose tip")


@pytest.mark.parametrize("identity", IDENTITIES)
def test_inter_landmark_distances_are_adult(identity):
    points = face_landmarks(identity)
    params = datasets._as_identity(identity)
    dist = lambda a, b: np.linalg.norm(lm(points, a) - lm(points, b))  # noqa: E731
    assert 75 < dist("Outer left eye corner", "Outer right eye corner") < 105
    assert 28 < dist("Inner left eye corner", "Inner right eye corner") < 46
    assert 40 < dist("Left mouth corner", "Right mouth corner") < 64
    assert 28 < dist("Left nose peak", "Right nose peak") < 42
    nasion_to_chin = params.nose_length - lm(points, "Chin middle")[1]
    assert 90 < nasion_to_chin < 125
    # Nose tip in front of the cheek below the eye centre at the level of the alae.
    cheek = face_height(identity, params.eye_spacing / 2, lm(points, "Left nose peak")[1])
    assert 22 < lm(points, "Nose tip")[2] - cheek < 36


def test_scan_size_and_layout():
    scan = make_face()
    nrows, ncols = scan.valid.shape
    assert scan.points.shape == (nrows, ncols, 3)
    assert 28_000 < scan.valid.sum() < 42_000       # about a real scan's 35k points
    assert np.isnan(scan.points[~scan.valid]).all()
    assert np.isfinite(scan.points[scan.valid]).all()
    # Rows run toward -y, columns toward +x, on the given spacing.
    assert np.allclose(np.diff(scan.points[nrows // 2, :, 0][scan.valid[nrows // 2]]), 0.7)
    column = scan.points[:, ncols // 2, 1][scan.valid[:, ncols // 2]]
    assert np.allclose(np.diff(column), -0.7)
    uv = scan.uv()
    assert uv.shape == (nrows, ncols, 2) and 0 < uv.min() and uv.max() < 1
    assert nan_equal(scan.to_grid_points(), scan.points)
    # The face frame puts the nose tip at x = y = 0, and it is the front-most point.
    front = np.unravel_index(np.nanargmax(scan.points[..., 2]), scan.valid.shape)
    assert np.hypot(*scan.points[front][:2]) < 3.0


def test_scan_points_lie_on_the_clean_surface():
    expression = {"12": 1.0, "17": 0.5}
    scan = make_face(7, expression, spacing_mm=1.0)
    points = scan.points[scan.valid]
    z = face_height(7, points[:, 0], points[:, 1], expression)
    np.testing.assert_allclose(points[:, 2], z, atol=1e-6)  # inversion tolerance, as above
    # skin_xy is the neutral position of each pixel's skin: moving it by the AU field
    # lands on the pixel.
    skin = scan.skin_xy[scan.valid]
    neutral = np.column_stack([skin, face_height(7, skin[:, 0], skin[:, 1])])
    moved = neutral + au_displacement(7, expression, skin)
    np.testing.assert_allclose(moved, points, atol=1e-6)


# -------------------------------------------------------------------- action units


def landmark_motion(au, weight=1.0, identity=None):
    return face_landmarks(identity, {au: weight}) - face_landmarks(identity)


@pytest.mark.parametrize("identity", [None, 42])
def test_each_au_moves_what_it_should(identity):
    inner_brow = landmark_index("Inner left eyebrow")
    outer_brow = landmark_index("Outer left eyebrow")
    corner = landmark_index("Left mouth corner")
    chin = landmark_index("Chin middle")
    lower_lip = landmark_index("Lower lip outer middle")

    au1 = landmark_motion("1", identity=identity)
    assert au1[inner_brow, 1] > 2.5 and au1[inner_brow, 1] > 2 * au1[outer_brow, 1]
    au2 = landmark_motion("2", identity=identity)
    assert au2[outer_brow, 1] > 2.5 and au2[outer_brow, 1] > 2 * au2[inner_brow, 1]
    au4 = landmark_motion("4", identity=identity)
    assert au4[inner_brow, 1] < -2.0 and au4[inner_brow, 0] < -1.0  # down and together
    au12 = landmark_motion("12", identity=identity)
    assert au12[corner, 1] > 3.0 and au12[corner, 0] > 1.5          # up and out
    au14 = landmark_motion("14", identity=identity)
    assert au14[corner, 2] < -2.0                                     # into the face
    au15 = landmark_motion("15", identity=identity)
    assert au15[corner, 1] < -3.0                                     # down
    au17 = landmark_motion("17", identity=identity)
    assert au17[chin, 1] > 2.5 and au17[lower_lip, 1] > 1.5          # chin and lower lip up
    au20 = landmark_motion("20", identity=identity)
    assert au20[corner, 0] > 3.0 and abs(au20[corner, 1]) < 1.0       # laterally
    # Mirror symmetry of two-sided AUs: the right corner mirrors the left.
    right = landmark_index("Right mouth corner")
    np.testing.assert_allclose(au12[right], au12[corner] * [-1, 1, 1], atol=1e-9)


@pytest.mark.parametrize("au", ACTION_UNITS)
def test_upper_and_lower_face_aus_stay_in_their_region(au):
    params = FaceParameters()
    xy = face_grid()
    motion = np.linalg.norm(au_displacement(params, {au: 1.0}, xy), axis=1)
    assert motion.max() > 2.0  # a few mm at full strength
    if au in UPPER_FACE_AUS:
        still = xy[:, 1] < -0.2 * params.nose_length   # below the nose
    else:
        still = xy[:, 1] > params.eye_height           # above the eye corners
    # Gaussian tails 4+ spreads away: negligible against scan noise (~0.1 mm).
    assert motion[still].max() < 0.01, motion[still].max()


@pytest.mark.parametrize("au", ACTION_UNITS)
def test_one_sided_versions_move_their_own_side_only(au):
    xy = face_grid()
    left = au_displacement(None, {au + "L": 1.0}, xy)
    right = au_displacement(None, {au + "R": 1.0}, xy)
    both = au_displacement(None, {au: 1.0}, xy)
    assert np.abs(left[xy[:, 0] <= -MIDLINE_RAMP_MM]).max() == 0.0
    assert np.abs(right[xy[:, 0] >= MIDLINE_RAMP_MM]).max() == 0.0
    assert np.linalg.norm(left, axis=1).max() > 1.0
    np.testing.assert_allclose(left + right, both, atol=1e-12)  # the halves add up


def test_au12L_moves_only_the_left_mouth_corner():
    motion = landmark_motion("12L")
    assert motion[landmark_index("Left mouth corner"), 1] > 3.0
    np.testing.assert_array_equal(motion[landmark_index("Right mouth corner")], 0.0)


def test_displacement_is_linear_in_the_weights():
    xy = face_grid(step=3.0)
    unit = au_displacement(9, {"12": 1.0, "4": 1.0}, xy)
    np.testing.assert_allclose(au_displacement(9, {"12": 0.3, "4": 0.3}, xy), 0.3 * unit, atol=1e-12)
    combined = au_displacement(9, {"12": 0.5, "AU4": -0.25, "17L": 2.0}, xy)
    parts = (0.5 * au_displacement(9, {"12": 1}, xy) - 0.25 * au_displacement(9, {"4": 1}, xy)
             + 2.0 * au_displacement(9, {"17L": 1}, xy))
    np.testing.assert_allclose(combined, parts, atol=1e-12)
    # Landmarks move linearly too.
    np.testing.assert_allclose(landmark_motion("15", 0.4), 0.4 * landmark_motion("15"), atol=1e-12)


def test_strong_expression_keeps_the_scan_whole():
    neutral = make_face(spacing_mm=1.0)
    everything = make_face(expression={au: 1.0 for au in ACTION_UNITS}, spacing_mm=1.0)
    # The fixed-point inversion converges everywhere: no pixels lost to it.
    assert abs(int(everything.valid.sum()) - int(neutral.valid.sum())) < 0.03 * neutral.valid.sum()


def test_au_keys_are_normalised():
    scan = make_face(expression={"AU12": 0.5, "au4l": 1, 17: 0.25}, spacing_mm=2.0)
    assert scan.expression == {"12": 0.5, "4L": 1.0, "17": 0.25}


# ------------------------------------------------------------------- scan options


def test_holes_remove_points():
    plain = make_face(spacing_mm=1.0)
    holey = make_face(spacing_mm=1.0, holes=6, seed=4)
    lost = plain.valid & ~holey.valid
    # six ellipses with semi-axes >= 2 mm: at least 6 * pi * 4 mm^2 at 1 point per mm^2
    assert lost.sum() > 60
    assert not (holey.valid & ~plain.valid).any()
    assert np.isnan(holey.points[lost]).all()


def test_noise_is_in_depth_with_the_requested_spread():
    scan = make_face(spacing_mm=1.0, noise_mm=0.3, seed=2)
    clean = make_face(spacing_mm=1.0)
    assert np.array_equal(scan.valid, clean.valid)
    delta = scan.points[scan.valid] - clean.points[clean.valid]
    np.testing.assert_array_equal(delta[:, :2], 0.0)
    # ~14k samples: the sample sd is within 3 % of 0.3 far beyond 5 sigma.
    assert abs(delta[:, 2].std() - 0.3) < 0.01
    assert abs(delta[:, 2].mean()) < 0.01
    np.testing.assert_array_equal(scan.clean_points[scan.valid], clean.points[clean.valid])


def test_pose_is_a_rigid_motion_of_the_face():
    scan = make_face(4, {"12": 1.0}, spacing_mm=1.0, pose_deg=10.0, seed=8)
    rotation, shift = scan.pose[:3, :3], scan.pose[:3, 3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert not np.allclose(rotation, np.eye(3))
    expected = face_landmarks(4, {"12": 1.0}) @ rotation.T + shift
    np.testing.assert_allclose(scan.landmarks, expected, atol=1e-9)
    # Back in the face frame, the scan points lie on the expressive surface.
    face_frame = (scan.points[scan.valid] - shift) @ rotation
    z = face_height(4, face_frame[:, 0], face_frame[:, 1], {"12": 1.0})
    np.testing.assert_allclose(face_frame[:, 2], z, atol=1e-5)


# -------------------------------------------------------------------- bad input


@pytest.mark.parametrize("expression", [{"13": 1.0}, {"AU99": 1}, {"12X": 1}, {"12": float("nan")},
                                        {"12": "strong"}, [("12", 1.0)]])
def test_bad_expressions_are_rejected(expression):
    with pytest.raises(ValueError, match="expression"):
        make_face(expression=expression, spacing_mm=2.0)


@pytest.mark.parametrize("field, value", [("nose_width", float("nan")), ("mouth_width", -3.0),
                                          ("eye_width", math.inf), ("chin_height", 0.0)])
def test_bad_parameters_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        FaceParameters(**{field: value})


def test_inconsistent_parameters_are_rejected():
    with pytest.raises(ValueError, match="eye_width"):
        FaceParameters(eye_width=70.0)


@pytest.mark.parametrize("options, name", [
    (dict(spacing_mm=-0.7), "spacing_mm"), (dict(spacing_mm=0.0), "spacing_mm"),
    (dict(spacing_mm=float("nan")), "spacing_mm"), (dict(noise_mm=-1.0), "noise_mm"),
    (dict(holes=-1), "holes"), (dict(holes=2.5), "holes"), (dict(pose_deg=90.0), "pose_deg"),
])
def test_bad_scan_options_are_rejected(options, name):
    with pytest.raises(ValueError, match=name):
        make_face(**options)


def test_bad_identity_is_rejected():
    with pytest.raises(ValueError, match="identity"):
        make_face("alice")


def test_public_names_are_exported():
    for name in ("make_face", "FaceParameters", "SyntheticScan", "random_identity",
                 "sample_subjects", "embedded_faces", "demo_triplet", "au_displacement"):
        assert name in datasets.__all__ and tpscore.datasets is datasets
