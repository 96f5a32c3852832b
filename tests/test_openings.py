"""The face's openings and the motion cut at them: the mouth that opens, the eyes that
close (on the demo's faces, which have eye openings and lips that part)."""
import numpy as np
import pytest

import tpscore
from tpscore.expression import CutMotion
from tpscore.expression.cut_motion import moved_openings
from tpscore.expression.modelling import openings
from tpscore.face.landmarks import landmark_index
from tpscore.face.loading import load_scan
from tpscore.face.openings import find_openings, opening_cut, opening_sides
from tpscore.showcase.demo_faces import make_demo_scan

SCAN = dict(noise_mm=0.1, holes=0, pose_deg=3.0, landmark_noise_mm=0.3)
SURPRISE = {"1": 1.0, "2": 1.0, "5": 1.0, "26": 0.4}


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("openings")
    made = {}
    for name, person, expression, seed in (("source", 0, None, 1), ("surprise", 0, SURPRISE, 2),
                                           ("closed", 0, {"43": 1.0}, 3), ("target", 1, None, 4),
                                           ("target_surprise", 1, SURPRISE, 5), ("target_closed", 1, {"43": 1.0}, 6)):
        scan = make_demo_scan(person, expression, seed=seed, **SCAN)
        made[name] = (scan, load_scan(scan.write(folder, name)))
    return made


def _normalised(grid):
    reference = tpscore.load_average_face().as_normalised_face()
    return tpscore.normalise_face(grid, reference.landmarks)


def test_a_neutral_face_has_open_eyes_and_closed_lips(scans):
    face = _normalised(scans["source"][1])
    found = find_openings(face)
    assert set(found) == {"right eye", "left eye", "mouth"}
    for eye in ("right eye", "left eye"):
        assert 3.0 < found[eye].open_mm() < 15.0   # the scan shows the eye as a hole
        assert found[eye].corners[0, 0] < found[eye].corners[1, 0]
    mouth = found["mouth"]
    assert mouth.open_mm() == 0.0                  # closed lips: a contact line, no hole
    # the line runs between the inner-lip landmarks (within a millimetre or two of them)
    inner = face.landmarks[[landmark_index("Upper lip inner middle"), landmark_index("Lower lip inner middle")]]
    a, b = mouth.coordinates(inner.mean(axis=0))
    assert abs(b - mouth.line_at(a)) < 2.0


def test_the_opened_mouth_and_the_closed_eyes_are_seen_as_moved(scans):
    neutral = _normalised(scans["source"][1])
    for name, moved_names in (("surprise", {"mouth"}), ("closed", {"right eye", "left eye"})):
        expressive = tpscore.expression.modelling.align_expressive(neutral, scans["source"][1], scans[name][1])
        moved = {o.name for o in moved_openings(openings(neutral), expressive.grid)}
        assert moved_names <= moved, name
        if name == "closed":
            assert "mouth" not in moved
    # an expression that leaves the openings as they are cuts nothing
    smile = make_demo_scan(0, {"12": 1.0}, seed=7, **SCAN)
    import tempfile
    with tempfile.TemporaryDirectory() as folder:
        grid = load_scan(smile.write(folder, "smile"))
    expressive = tpscore.expression.modelling.align_expressive(neutral, scans["source"][1], grid)
    assert moved_openings(openings(neutral), expressive.grid) == []


def test_sides_split_at_the_line_and_agree_far_from_it(scans):
    face = _normalised(scans["source"][1])
    mouth = find_openings(face)["mouth"]
    middle = mouth.points_at(0.5, mouth.line_at(0.5))
    above, below = np.append(middle + [0, 2.0], 0.0), np.append(middle - [0, 2.0], 0.0)
    far = np.append(middle + [0, 80.0], 0.0)
    share = opening_sides([mouth], np.array([above, below, far]))
    assert share.tolist() == [1.0, 0.0, 0.5]
    beyond = np.append(mouth.points_at(1.3, 0.0), 0.0)
    cut = opening_cut([mouth], np.array([above, below, beyond]))
    assert cut.tolist() == [1, -1, 0]             # the cut ends at the corners


@pytest.mark.parametrize("correspondence", ["landmarks", "adapted"])
def test_an_open_mouth_is_carried_with_the_lips_apart_and_an_opening_in_the_mesh(scans, correspondence):
    (source, a), (_, b), (target, c) = scans["source"], scans["surprise"], scans["target"]
    result = tpscore.transfer(a, b, c, "surprise", options=tpscore.TransferOptions(correspondence=correspondence))
    assert isinstance(result.model.dense, CutMotion)
    lm = result.target.grid.landmark_vertices
    field = result.field_in_scan().reshape(-1, 3)
    upper = field[lm[landmark_index("Upper lip outer middle")]]
    lower = field[lm[landmark_index("Lower lip outer middle")]]
    assert lower[1] < -6.0 and abs(upper[1]) < 2.0      # the jaw drops, the upper lip stays
    truth = target.true_positions(result.neutral[result.mask], SURPRISE)
    moving = np.linalg.norm(truth - result.neutral[result.mask], axis=1) > 0.5
    error = np.linalg.norm(result.vertices[result.mask] - truth, axis=1)
    noop = np.linalg.norm(truth - result.neutral[result.mask], axis=1)
    assert np.sqrt(np.mean(error[moving] ** 2)) < 0.4 * np.sqrt(np.mean(noop[moving] ** 2))
    # the result's mesh is open between the lips: no triangle joins the two sides
    torn = len(result.target.grid.triangles()) - len(result.triangles())
    assert torn > 20
    side = result.animation.cut.reshape(-1)[result.triangles()]
    assert not ((side.min(axis=1) < 0) & (side.max(axis=1) > 0)).any()
    assert len(result.mesh().faces) == len(result.triangles())


@pytest.mark.parametrize("correspondence", ["landmarks", "adapted"])
def test_closed_eyes_are_carried_by_moving_the_upper_lids_down(scans, correspondence):
    (_, a), (_, b), (target, c) = scans["source"], scans["closed"], scans["target"]
    result = tpscore.transfer(a, b, c, "43", options=tpscore.TransferOptions(correspondence=correspondence))
    assert isinstance(result.model.dense, CutMotion)
    truth = target.true_positions(result.neutral[result.mask], {"43": 1.0})
    motion = truth - result.neutral[result.mask]
    predicted = (result.vertices - result.neutral)[result.mask]
    lids = np.linalg.norm(motion, axis=1) > 2.0         # the upper lids, which move most
    assert lids.sum() > 20
    # most of the lids' downward travel is carried, and nothing moves far from the eyes
    assert np.median(predicted[lids, 1] / motion[lids, 1]) > 0.5
    still = np.linalg.norm(motion, axis=1) < 0.2
    assert np.sqrt(np.mean(np.sum(predicted[still] ** 2, axis=1))) < 0.3


def test_whole_expressions_carry_all_the_measured_motion(scans):
    (_, a), (_, b), (target, c) = scans["source"], scans["surprise"], scans["target"]
    whole = tpscore.transfer(a, b, c, "all")
    assert whole.animation.labels == ["all"]
    truth = target.true_positions(whole.neutral[whole.mask], SURPRISE)
    moving = np.linalg.norm(truth - whole.neutral[whole.mask], axis=1) > 0.5
    # brows (upper face) and jaw (lower face) both move: no region is cut away
    error = np.linalg.norm(whole.vertices[whole.mask] - truth, axis=1)
    noop = np.linalg.norm(truth - whole.neutral[whole.mask], axis=1)
    assert np.sqrt(np.mean(error[moving] ** 2)) < 0.4 * np.sqrt(np.mean(noop[moving] ** 2))
    # the brows alone (AU1+2, upper face) leave the jaw where it was
    brows = tpscore.transfer(a, b, c, "1,2")
    chin = whole.target.grid.landmark_vertices[landmark_index("Chin middle")]
    assert abs(brows.field_in_scan().reshape(-1, 3)[chin][1]) < 1.0 < abs(whole.field_in_scan().reshape(-1, 3)[chin][1])
    # the method as published animates an emotion's recipe and has no "all"
    published = tpscore.transfer(a, b, c, "surprise", options=tpscore.TransferOptions.published())
    assert set("+".join(published.animation.labels).split("+")) == {"AU1", "AU2", "AU5", "AU26"}
    with pytest.raises(ValueError, match="no recipe"):
        tpscore.transfer(a, b, c, "all", options=tpscore.TransferOptions.published())


def test_a_lid_rim_pulls_across_the_eye_but_leaves_its_slide_along_it_free(scans):
    # The edge of an opening shows how far across it a rim went, not how far it slid
    # along the edge: a rim pair's slide along the chord must not pull the correction.
    from tpscore.expression.cut_motion import fit_local_correction

    face = _normalised(scans["source"][1])
    eye = find_openings(face)["left eye"]
    grid = face.grid
    rim_from = grid.points.reshape(-1, 3)[eye.rim(grid, "bottom")]
    along, up = eye.axes()
    moved = {}
    for name, offset in (("slid", 2.0 * along + 1.0 * up), ("across", 1.0 * up)):
        rim_to = rim_from.copy()
        rim_to[:, :2] += offset
        correction = fit_local_correction(eye, "bottom", grid.points[grid.mask], lambda p: np.zeros(np.shape(p)),
                                          face.surface(), rim_from, rim_to)
        moved[name] = correction(rim_from)[:, :2]
    assert np.median(moved["slid"] @ up) > 0.5          # pulled most of the way across
    # the 2 mm slide along the chord does not pull: the same correction as without it
    # (what slide there is, a fifth of a millimetre, comes from the lid's curved surface).
    # Not bit for bit: the two rim targets' across parts differ by rounding, and the
    # fit's robust cuts (Tukey, off the surface) drop or keep a data pair on either
    # side of a threshold, so targets 1e-13 mm apart give corrections up to 1e-4 mm
    # apart (2e-5 mm with NumPy 2.4, 1e-4 with 2.5). A slide that pulled would move
    # the rim by tenths of a millimetre.
    np.testing.assert_allclose(moved["slid"], moved["across"], atol=1e-3)
    assert abs(np.median(moved["slid"] @ along)) < 0.3


def test_a_missing_landmark_is_estimated_as_its_partners_mirror_image(scans):
    from tpscore.face.landmarks import mirror_estimate

    landmarks = _normalised(scans["source"][1]).landmarks
    for name in ("Inner left eye corner", "Outer right eye corner", "Left mouth corner"):
        index = landmark_index(name)
        missing = landmarks.copy()
        missing[index] = np.nan
        assert np.linalg.norm(mirror_estimate(missing, index) - landmarks[index]) < 3.0, name
    # a midline landmark has no partner, nor has a landmark whose partner is missing too
    assert mirror_estimate(landmarks, landmark_index("Nose tip")) is None
    both = landmarks.copy()
    both[[landmark_index("Inner left eye corner"), landmark_index("Inner right eye corner")]] = np.nan
    assert mirror_estimate(both, landmark_index("Inner left eye corner")) is None


def test_an_eye_with_a_missing_corner_is_still_found_and_cut(scans):
    full = _normalised(scans["source"][1])
    inner = landmark_index("Inner left eye corner")
    landmarks = scans["source"][1].landmarks.copy()
    landmarks[inner] = np.nan
    neutral = _normalised(scans["source"][1].with_landmarks(landmarks))
    eye, whole = find_openings(neutral)["left eye"], find_openings(full)["left eye"]
    assert abs(eye.open_mm() - whole.open_mm()) < 1.0
    assert np.abs(eye.corners - whole.corners).max() < 3.0
    expressive = tpscore.expression.modelling.align_expressive(neutral, scans["source"][1], scans["closed"][1])
    assert {o.name for o in moved_openings(openings(neutral), expressive.grid)} >= {"left eye", "right eye"}


def _with_hole_over(grid, centre_xy, radii, colour=None):
    """The grid with an elliptical hole in its depth around a point (x, y in the grid's
    frame) and, given a colour, that colour painted into its image there."""
    from tpscore.face.grid import FaceGrid

    offset = (grid.points[..., :2] - centre_xy) / np.asarray(radii)
    hole = grid.mask & ((offset ** 2).sum(axis=-1) < 1.0)
    image = grid.image
    if colour is not None:
        image = np.array(image)
        height, width = image.shape[:2]
        uv = grid.uv[hole]
        rows = np.clip((uv[:, 1] * height).astype(int), 0, height - 1)
        columns = np.clip((uv[:, 0] * width).astype(int), 0, width - 1)
        for dr in range(-2, 3):
            for dc in range(-2, 3):
                image[np.clip(rows + dr, 0, height - 1), np.clip(columns + dc, 0, width - 1)] = colour
    points = np.where(hole[..., None], np.nan, grid.points)
    return FaceGrid(points, grid.mask & ~hole, grid.uv, grid.landmarks, grid.landmark_vertices, image)


def test_a_dropout_over_a_closed_eye_is_no_open_eye_unless_it_shows_the_eye(scans):
    # A scanner drops the depth of skin it sees at a grazing angle: a hole whose colour
    # is the skin's around it is not an opening; one that shows something else is.
    neutral = _normalised(scans["source"][1])
    closed = scans["closed"][1]
    eye = find_openings(neutral)["left eye"]
    corners = closed.landmarks[[landmark_index("Inner left eye corner"), landmark_index("Outer left eye corner")]]
    centre = corners.mean(axis=0)[:2]
    width = np.linalg.norm(corners[0] - corners[1])
    for colour, seen_open in ((None, False), ((20, 20, 20), True)):
        scan = _with_hole_over(closed, centre, (0.35 * width, 3.0), colour)
        expressive = tpscore.expression.modelling.align_expressive(neutral, scans["source"][1], scan)
        seen = eye.seen_in(expressive.grid)
        hole_mm = np.nanmedian(seen.top - seen.bottom)
        moved = {o.name for o in moved_openings(openings(neutral), expressive.grid)}
        if seen_open:
            assert hole_mm > 3.0 and "left eye" not in moved
        else:
            assert "left eye" in moved and not hole_mm > 0.5 * eye.open_mm()


def test_closed_lids_meet_at_the_dark_line_the_image_shows(scans):
    # Where the scan shows a closed eye without a hole, the upper lid's rim went to the
    # top of the dark line where the lids meet (lashes, a slit the scan does not resolve)
    neutral = _normalised(scans["source"][1])
    eye = find_openings(neutral)["left eye"]
    expressive = tpscore.expression.modelling.align_expressive(neutral, scans["source"][1], scans["closed"][1])
    plain = eye.seen_in(expressive.grid)
    middle = (eye.knots > 0.3) & (eye.knots < 0.7)
    assert not np.isfinite(plain.bottom[middle]).all() or np.allclose(plain.bottom[middle], eye.bottom[middle])
    # paint a dark line 1 mm above the open eye's lower edge into the closed eye's image
    grid = expressive.grid
    a, b = eye.coordinates(grid.points)
    line = grid.mask & (a > 0.1) & (a < 0.9) & (np.abs(b - (np.interp(a, eye.knots, np.nan_to_num(eye.bottom)) + 1.0)) < 0.4)
    image = np.array(grid.image)
    height, width = image.shape[:2]
    uv = grid.uv[line]
    for dr in (-1, 0, 1):
        rows = np.clip((uv[:, 1] * height).astype(int) + dr, 0, height - 1)
        image[rows, np.clip((uv[:, 0] * width).astype(int), 0, width - 1)] = (15, 10, 10)
    from tpscore.face.grid import FaceGrid
    seen = eye.seen_in(FaceGrid(grid.points, grid.mask, grid.uv, grid.landmarks, grid.landmark_vertices, image))
    found = middle & np.isfinite(seen.top)
    assert found.sum() >= 0.8 * middle.sum()
    # the rim ends at the line's top (within a millimetre at most knots), the lower lid stays
    off = np.abs(seen.top[found] - (eye.bottom[found] + 1.4))
    assert np.median(off) < 0.6 and (off < 1.0).mean() >= 0.75
    assert np.allclose(seen.bottom[found], eye.bottom[found])
