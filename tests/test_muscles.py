"""Muscles: linear muscles pull toward their bony attachment with cosine fall-offs,
sphincters pull toward their centre, registration is linear in the contractions, and
the six emotion presets move the face."""
from __future__ import annotations

import numpy as np
import pytest

from tpscore.elastic import EMOTIONS, ElasticFace, LinearMuscle, MuscleModel, SphincterMuscle, load_muscles
from tpscore.showcase import datasets, render


@pytest.fixture(scope="module")
def face():
    scan = datasets.make_face(datasets.random_identity(5), spacing_mm=3.0)
    vertices, faces = render.grid_mesh(scan.points, scan.valid)
    used = np.unique(faces)
    renumber = np.full(len(vertices), -1)
    renumber[used] = np.arange(len(used))
    return ElasticFace(vertices[used], renumber[faces], landmarks=scan.landmarks)


def test_contracted_linear_muscle_pulls_control_points_toward_its_bone(face):
    model = MuscleModel(face)
    muscle = model.muscles[model.muscle_names.index("zygomatic_major_left")]
    before = face.control_point_positions
    after = before + model.displacements({"zygomatic_major_left": 0.2})
    moved = np.linalg.norm(after - before, axis=1) > 1e-9
    assert moved[face.control_point_names.index("mouth_corner_left")]
    distance_before = np.linalg.norm(before[moved] - muscle.bone, axis=1)
    distance_after = np.linalg.norm(after[moved] - muscle.bone, axis=1)
    assert np.all(distance_after < distance_before)
    # Every moved point moves exactly along the line to the bone.
    direction = (muscle.bone - before[moved]) / distance_before[:, None]
    step = after[moved] - before[moved]
    assert np.allclose(np.cross(step, direction), 0, atol=1e-12)
    # The muscle's angular zone keeps it to its own side of the mouth.
    right = [i for i, n in enumerate(face.control_point_names) if n.endswith("_right")]
    assert not moved[face.control_point_names.index("mouth_corner_right")]
    step_size = np.linalg.norm(after - before, axis=1)
    assert step_size[face.control_point_names.index("mouth_corner_left")] > 5 * step_size[right].max()


def test_linear_muscle_falloffs():
    muscle = LinearMuscle("m", [0, 0, 0], [10, 0, 0], angular_zone_deg=30, falloff_mm=5)
    points = np.array([[10, 0, 0], [5, 0, 0], [0.0, 0, 0], [15, 0, 0], [12.5, 0, 0],
                       [10 * np.cos(np.radians(15)), 10 * np.sin(np.radians(15)), 0], [0, 10, 0]])
    influence = muscle.influence(points)
    expected = [1.0, np.cos(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4), np.cos(np.pi / 4), 0.0]
    assert np.allclose(influence, expected, atol=1e-12)
    # Displacement per unit contraction: length * influence, toward the bone.
    assert np.allclose(muscle.unit_displacement(points[:1]), [[-10, 0, 0]])


def test_sphincter_pulls_ring_points_toward_its_centre():
    ring = np.array([[10, 0, 0], [0, 5, 0], [-10, 0, 0], [0, -5, 0.0]])
    sphincter = SphincterMuscle.fit("o", ring, np.eye(3), depth_mm=2.0, spokes=8)
    assert np.allclose(sphincter.ring_centre, 0) and np.allclose(sphincter.centre, [0, 0, -2])
    step = sphincter.unit_displacement(ring)
    inward = np.einsum("ij,ij->i", step, -ring)
    assert np.all(inward > 0)
    # Points between spokes move too: the overlapping angular zones leave no gap.
    between = np.array([[10 * np.cos(np.pi / 8), 5 * np.sin(np.pi / 8), 0]])
    assert np.linalg.norm(sphincter.unit_displacement(between)) > 0.5


def test_displacements_are_linear_and_summed_over_muscles(face):
    model = MuscleModel(face)
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 0.3, size=(2, len(model.muscle_names)))
    # Linearity is exact up to rounding of one tensor contraction.
    assert np.allclose(model.displacements(a + b), model.displacements(a) + model.displacements(b), atol=1e-12)
    assert np.allclose(model.displacements(2 * a), 2 * model.displacements(a), atol=1e-12)
    assert np.allclose(model.deform(np.zeros(len(model.muscle_names))), face.vertices)


@pytest.mark.parametrize("emotion", EMOTIONS)
def test_emotion_presets_move_the_face_moderately(face, emotion):
    model = MuscleModel(face)
    assert set(EMOTIONS) <= set(model.emotions)
    motion = np.linalg.norm(model.emotion(emotion) - face.vertices, axis=1)
    # A visible expression: a few mm at the most-moved control point, not a collapse
    # (ICT's full blendshapes move single vertices by 4-16 mm).
    assert 2.0 < motion.max() < 25.0
    assert np.all(motion[face.fixed] == 0)
    assert model.emotion_contractions(emotion)


def test_happiness_raises_the_mouth_corners_and_sadness_lowers_them(face):
    model = MuscleModel(face)
    corners = [face.control_point_names.index(n) for n in ("mouth_corner_left", "mouth_corner_right")]
    up = model.displacements(model.emotion_contractions("happiness"))[corners, 1]
    down = model.displacements(model.emotion_contractions("sadness"))[corners, 1]
    assert np.all(up > 1.0) and np.all(down < -1.0)


def test_bad_muscle_input():
    with pytest.raises(ValueError, match="coincide"):
        LinearMuscle("m", [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="bone must have shape"):
        LinearMuscle("m", [0, 0], [1, 0, 0])
    with pytest.raises(ValueError, match="at least 3 spokes"):
        SphincterMuscle("s", [0, 0, 0], [0, 0, 1], np.eye(3)[:2], spokes=2)


def test_bad_contractions_and_faces(face):
    model = MuscleModel(face)
    with pytest.raises(ValueError, match="unknown muscle 'biceps'"):
        model.displacements({"biceps": 1.0})
    with pytest.raises(ValueError, match="contractions must have shape"):
        model.displacements([0.1, 0.2])
    with pytest.raises(ValueError, match="contractions contains NaN"):
        model.displacements(np.full(len(model.muscle_names), np.nan))
    with pytest.raises(ValueError, match="unknown emotion"):
        model.emotion("boredom")
    bare = ElasticFace(face.vertices, face.faces, face.handles, fixed=face.fixed)
    with pytest.raises(ValueError, match="no landmarks"):
        load_muscles(bare)
