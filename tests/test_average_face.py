import numpy as np
import pytest

from tpscore.face.average_face import (
    AverageFace,
    build_average_face,
    consensus_landmarks,
    load_average_face,
)
from tpscore.face.landmarks import landmark_index
from tpscore.face.resampling import resample_scan
from tpscore.showcase import datasets
from tpscore.showcase.datasets import afm_faces


def test_consensus_of_posed_copies_is_the_shape_in_the_canonical_frame():
    lm = datasets.face_landmarks(datasets.random_identity(5))
    angle = np.radians(12)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    copies = [lm, lm @ rot.T + [3, 4, 5], 1.0 * lm - 10]
    consensus = consensus_landmarks(copies)
    tip = consensus[landmark_index("Nose tip")]
    assert np.abs(tip).max() < 1e-9
    # the same shape: pairwise distances preserved (mean size equals the inputs' size)
    d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=2)
    assert np.abs(d(consensus) - d(lm)).max() < 1e-6
    # canonical axes: left landmarks at +x, eyes above the chin
    assert consensus[landmark_index("Left mouth corner"), 0] > 0
    assert consensus[landmark_index("Inner left eye corner"), 1] > consensus[landmark_index("Chin middle"), 1]


def test_shipped_model_is_what_the_builder_makes():
    shipped = load_average_face()
    rebuilt = build_average_face(afm_faces())
    assert rebuilt.n_faces == shipped.n_faces
    assert np.array_equal(rebuilt.grid.mask, shipped.grid.mask)
    # shipped depths are float32: 1e-5 relative rounding of ~100 mm coordinates
    assert np.nanmax(np.abs(rebuilt.grid.points - shipped.grid.points)) < 1e-3


def test_average_of_one_face_is_that_face(tmp_path):
    scan = datasets.make_face(3)
    grid = resample_scan(scan.points, scan.landmarks)
    afm = build_average_face([grid], shape=(80, 80))
    # the face, moved to the canonical frame: its landmarks are the face's up to a rigid map
    d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=2)
    # each landmark is snapped twice (face grid ~0.9 mm, AFM grid ~1.7 mm), each snap
    # moving it up to about a cell diagonal on sloped skin: distances agree to 3 mm
    assert np.nanmax(np.abs(d(afm.landmarks) - d(grid.landmarks))) < 3.0
    path = tmp_path / "afm.npz"
    afm.save(path)
    loaded = AverageFace.load(path)
    assert np.array_equal(loaded.grid.mask, afm.grid.mask)


def test_builder_validates_input():
    with pytest.raises(ValueError, match="at least one face"):
        build_average_face([])
    with pytest.raises(ValueError, match="coverage"):
        build_average_face(afm_faces()[:1], coverage=0)
