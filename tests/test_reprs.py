"""What a user sees at the prompt: one-line summaries, not pages of arrays."""
import numpy as np
import pytest

from tpscore import AdaptLevel, AdaptResult, Correspondences, FrameTransform, resample_scan, transfer
from tpscore.showcase import datasets


@pytest.fixture(scope="module")
def result():
    scans = datasets.demo_triplet("12")
    grids = [resample_scan(s.points, s.landmarks) for s in scans]
    return grids, transfer(*grids, "12", 0.5)


def _one_line(text: str, limit: int = 200) -> str:
    assert "\n" not in text and len(text) < limit and "array" not in text, text
    return text


def test_face_grid(result):
    grids, _ = result
    text = _one_line(repr(grids[0]))
    assert text == f"FaceGrid(150x150, {grids[0].n_valid} valid vertices, 22/22 landmarks, no image)"
    missing = grids[0].with_landmarks(np.where(np.arange(22)[:, None] < 3, np.nan, grids[0].landmarks))
    assert "19/22 landmarks" in repr(missing)


def test_transfer_result(result):
    _, transferred = result
    text = _one_line(repr(transferred))
    assert text.startswith("TransferResult(AU12 at m=0.5 on a 150x150 target (")
    assert "no colour" in text and "similarity normalisation" in text


def test_adapt_result():
    level = AdaptLevel(level=0, method="rbf", support=float("nan"), pairs=22, new_pairs=22, distance_error=0.5,
                       marker_error=float("nan"), error=0.25, coverage=1.0, seconds=0.1)
    pairs = Correspondences(np.zeros((22, 3)), np.zeros((22, 3)), np.array(["landmark"] * 22))
    fitted = AdaptResult(np.zeros((500, 3)), np.zeros((500, 3)), FrameTransform.identity(), [level], 0, pairs)
    assert _one_line(repr(fitted)) == ("AdaptResult(500 vertices, best level 0 of 1, E 0.25, 22 pairs, "
                                       "0 outlier landmarks, 0 warnings)")
