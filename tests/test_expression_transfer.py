import copy
import gc
import warnings
import weakref
from dataclasses import replace

import numpy as np
import pytest

import tpscore
from tpscore.expression import TransferOptions
from tpscore.expression.texture import TextureOptions
from tpscore.face.landmarks import landmark_index
from tpscore.expression import DenseMotion, MirroredMotion, modelling, pipeline
from tpscore.face.regions import region_boundary
from tpscore.face.resampling import resample_scan
from tpscore.showcase import datasets

VARIANTS = {"default": TransferOptions(), "published": TransferOptions.published(),
            "adapted": TransferOptions(correspondence="adapted")}


def _grid(scan):
    return resample_scan(scan.points, scan.landmarks)


@pytest.fixture(scope="module")
def smile():
    scans = datasets.demo_triplet("12")
    return scans, [_grid(s) for s in scans]


@pytest.fixture(scope="module")
def brows():
    scans = datasets.demo_triplet({"1": 1.0, "2": 1.0})
    return scans, [_grid(s) for s in scans]


def _truth(scan, expression, points):
    return points + datasets.au_displacement(scan.identity, expression, points[:, :2])


@pytest.mark.parametrize("variant", ["default"])
def test_transfer_onto_itself_reproduces_the_expression(smile, variant):
    (src, _, _), (gs, ge, _) = smile
    result = tpscore.transfer(gs, ge, gs, "12", options=VARIANTS[variant])
    neutral, predicted = result.neutral[result.mask], result.vertices[result.mask]
    truth = _truth(src, {"12": 1.0}, neutral)
    moving = np.linalg.norm(truth - neutral, axis=1) > 0.5
    rms = np.sqrt(np.mean(np.sum((predicted - truth) ** 2, axis=1)[moving]))
    noop = np.sqrt(np.mean(np.sum((neutral - truth) ** 2, axis=1)[moving]))
    # measured 0.47 of the no-op error: a dozen control points cannot carry the whole
    # cheek motion of the procedural smile, but most of the expression must come across
    assert rms < 0.6 * noop


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_zero_magnitude_leaves_the_target_unchanged(smile, variant):
    _, (gs, ge, gt) = smile
    result = tpscore.transfer(gs, ge, gt, "12", 0.0, options=VARIANTS[variant])
    assert np.array_equal(np.isnan(result.vertices), np.isnan(result.neutral))
    assert np.nanmax(np.abs(result.vertices - result.neutral)) == 0.0
    # the neutral comes back in the target scan's own frame (rounding of the round trip only)
    assert np.nanmax(np.abs(result.neutral - gt.points)) < 1e-9


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_upper_face_au_leaves_the_lower_face_still(brows, variant):
    _, (gs, ge, gt) = brows
    result = tpscore.transfer(gs, ge, gt, "1,2", options=VARIANTS[variant])
    target = result.target
    slope, intercept = region_boundary(target.landmarks)
    points = target.grid.points
    below = points[..., 1] < slope * points[..., 0] + intercept - VARIANTS[variant].transition_mm
    motion = np.linalg.norm(result.animation.displacement(1.0), axis=2)
    assert np.nanmax(motion[below & target.grid.mask]) == 0.0
    assert np.nanmax(motion) > 1.0  # and the brows do move


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_lower_face_au_leaves_the_upper_face_still(smile, variant):
    _, (gs, ge, gt) = smile
    result = tpscore.transfer(gs, ge, gt, "12", options=VARIANTS[variant])
    target = result.target
    slope, intercept = region_boundary(target.landmarks)
    points = target.grid.points
    above = points[..., 1] > slope * points[..., 0] + intercept + VARIANTS[variant].transition_mm
    motion = np.linalg.norm(result.animation.displacement(1.0), axis=2)
    assert np.nanmax(motion[above & target.grid.mask]) == 0.0
    assert np.nanmax(motion) > 2.0


def test_one_sided_au_moves_one_side(smile):
    _, (gs, ge, gt) = smile
    result = tpscore.transfer(gs, ge, gt, "12L")
    points = result.target.grid.points  # reference frame: +x is the subject's left
    motion = np.linalg.norm(result.animation.displacement(1.0), axis=2)
    left = np.nanmax(np.where(points[..., 0] > 15, motion, np.nan))
    right = np.nanmax(np.where(points[..., 0] < -15, motion, np.nan))
    # measured: 5.2 mm on the left, 0.04 mm on the right
    assert left > 2.0 and right < 0.05 * left


def test_a_bilateral_expression_averages_its_field_with_the_mirror_image(smile):
    (src, _, _), (gs, ge, _) = smile
    landmarks = ge.landmarks.copy()
    landmarks[landmark_index("Left mouth corner")] += [3.0, 3.0, 0.0]  # mislabelled
    mislabelled = ge.with_landmarks(landmarks)

    def ratio(result):
        neutral, predicted = result.neutral[result.mask], result.vertices[result.mask]
        truth = _truth(src, {"12": 1.0}, neutral)
        moving = np.linalg.norm(truth - neutral, axis=1) > 0.5
        return np.sqrt(np.mean(np.sum((predicted - truth) ** 2, axis=1)[moving])
                       / np.mean(np.sum((neutral - truth) ** 2, axis=1)[moving]))

    mirrored = tpscore.transfer(gs, mislabelled, gs, "12")
    plain = tpscore.transfer(gs, mislabelled, gs, "12", options=TransferOptions(mirror_average=False))
    assert isinstance(mirrored.model.dense, MirroredMotion)
    assert not isinstance(plain.model.dense, MirroredMotion)
    # measured 0.66 against 0.77: the right side's motion makes up for the left label
    assert ratio(mirrored) < ratio(plain) - 0.05
    # a one-sided AU keeps the field as registered
    assert not isinstance(tpscore.transfer(gs, ge, gs, "12L").model.dense, MirroredMotion)


def _fresh(*grids):
    """New grid objects with the same arrays: a transfer then finds nothing kept of them
    (:func:`tpscore.face.normalise.kept_normalisation`)."""
    return [replace(grid) for grid in grids]


def test_what_the_second_thread_prepares_changes_nothing(smile, monkeypatch):
    (_, _, _), (gs, ge, gt) = smile
    ahead = tpscore.transfer(*_fresh(gs, ge, gt), "12")
    # the same transfer with nothing made ahead: each face's surface, registration grid
    # and mirror plane are then made where they are used
    monkeypatch.setattr(pipeline, "_prepare", lambda *args: None)
    monkeypatch.setattr(pipeline, "_mirror_planes", lambda *args: None)
    in_turn = tpscore.transfer(*_fresh(gs, ge, gt), "12")
    assert np.array_equal(ahead.vertices, in_turn.vertices, equal_nan=True)


def test_transfers_from_the_same_grids_reuse_each_face_and_give_the_same_bits(smile, brows):
    (_, _, _), (gs, ge, gt) = smile
    gs, gt = _fresh(gs, gt)
    first = tpscore.transfer(gs, ge, gt, "12")
    second = tpscore.transfer(gs, brows[1][1], gt, "1,2")   # another expression of the same source
    # the neutral faces were normalised once, and what the first transfer computed of
    # each alone (surfaces, mirror planes, openings, registration grid) is theirs
    assert second.target is first.target and second.model.source is first.model.source
    assert "mirror" in first.target._derived and ("registration", TransferOptions().motion) in \
        first.model.source._derived
    again = tpscore.transfer(gs, ge, gt, "12")
    afresh = tpscore.transfer(*_fresh(gs, ge, gt), "12")
    assert afresh.target is not first.target
    for result in (again, afresh):
        assert np.array_equal(result.vertices, first.vertices, equal_nan=True)
    assert np.array_equal(second.vertices, tpscore.transfer(*_fresh(gs, brows[1][1], gt), "1,2").vertices,
                          equal_nan=True)


def test_transfers_with_colour_images_keep_the_neutral_view(scan_files):
    neutral, expressive, target = tpscore.load_scans(scan_files)
    first = tpscore.transfer(neutral, expressive, target, "12")
    seen = ("texture view", TextureOptions())
    view = first.model.source.derived_so_far(seen)
    assert view is not None and view is first.model.texture.neutral_view
    second = tpscore.transfer(neutral, expressive, target, "12")
    assert second.model.texture.neutral_view is view
    assert np.array_equal(second.vertices, first.vertices, equal_nan=True)
    assert np.array_equal(second.vertices, tpscore.transfer(*_fresh(neutral, expressive, target), "12").vertices,
                          equal_nan=True)


def test_a_grid_changed_in_place_is_normalised_again(smile):
    (_, _, _), (gs, ge, gt) = smile
    gs, gt = _fresh(gs, gt)
    first = tpscore.transfer(gs, ge, gt, "12")
    gt.points[..., 2] += 1.0     # the target moved 1 mm toward the camera, in place
    moved = tpscore.transfer(gs, ge, gt, "12")
    assert moved.target is not first.target and moved.model.source is first.model.source
    assert np.allclose(moved.neutral, gt.points, atol=1e-9, equal_nan=True)
    assert np.array_equal(moved.vertices, tpscore.transfer(*_fresh(gs, ge, gt), "12").vertices, equal_nan=True)
    gt.landmarks_detected = True  # not an array, but it changes the transfer too
    assert tpscore.transfer(gs, ge, gt, "12").target is not moved.target


def test_a_normalisation_that_falls_back_warns_every_time(smile):
    (_, _, _), (gs, ge, gt) = smile
    lm = gt.landmarks.copy()
    lm[landmark_index("Chin middle")] = np.nan
    fewer = gt.with_landmarks(lm)
    for _ in range(2):
        with pytest.warns(UserWarning, match="using the similarity normalisation"):
            tpscore.transfer(gs, ge, fewer, "12", options=TransferOptions.published())


def test_what_is_kept_of_a_face_goes_with_its_grid(smile):
    (_, _, _), (gs, ge, gt) = smile
    target = copy.deepcopy(gt)
    face = weakref.ref(tpscore.transfer(gs, ge, target, "12").target)
    gc.collect()
    assert face() is not None     # kept while the grid lives
    del target
    gc.collect()
    assert face() is None


def test_only_the_grids_used_most_recently_keep_their_faces(smile):
    from tpscore.face import normalise
    (_, _, _), (gs, ge, gt) = smile
    (gs,) = _fresh(gs)
    targets = _fresh(*[gt] * normalise.MAX_KEPT_GRIDS)
    faces = [tpscore.transfer(gs, ge, target, "12").target for target in targets]
    # the source and the last targets are the grids used most recently: the first
    # target's face is no longer kept, the last's is
    assert tpscore.transfer(gs, ge, targets[-1], "12").target is faces[-1]
    assert tpscore.transfer(gs, ge, targets[0], "12").target is not faces[0]
    assert len(normalise._kept) <= normalise.MAX_KEPT_GRIDS


def test_no_face_is_kept_when_none_may_be(smile, monkeypatch):
    from tpscore.face import normalise
    monkeypatch.setattr(normalise, "MAX_KEPT_GRIDS", 0)
    (_, _, _), (gs, ge, gt) = smile
    gs, gt = _fresh(gs, gt)
    first = tpscore.transfer(gs, ge, gt, "12")
    second = tpscore.transfer(gs, ge, gt, "12")
    assert second.target is not first.target and len(normalise._kept) == 0
    assert np.array_equal(second.vertices, first.vertices, equal_nan=True)


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    """A source's neutral and smiling scans and a target's, as .bnt + .lm3 + .png."""
    from tpscore.showcase import demo_faces

    folder = tmp_path_factory.mktemp("scans")
    return [demo_faces.make_demo_scan(person, expression, seed=seed).write(folder, name)
            for person, expression, seed, name in ((0, None, 1, "a"), (0, {"12": 1.0}, 2, "b"), (1, None, 3, "c"))]


def test_a_transfer_from_paths_is_the_transfer_of_the_scans_read(scan_files):
    # read in the background (the target while the source's motion is measured), the
    # same scans give the same result to the bit
    from_paths = tpscore.transfer(*[str(p) for p in scan_files[:2]], scan_files[2], "12")
    from_grids = tpscore.transfer(*tpscore.load_scans(scan_files), "12")
    assert np.array_equal(from_paths.vertices, from_grids.vertices, equal_nan=True)
    assert from_paths.image is not None and np.array_equal(from_paths.image, from_grids.image)
    assert from_paths.timings["read"] > 0 and "read" not in from_grids.timings
    # a grid and paths mixed
    grids = tpscore.load_scans(scan_files)
    mixed = tpscore.transfer(grids[0], scan_files[1], grids[2], "12")
    assert np.array_equal(mixed.vertices, from_grids.vertices, equal_nan=True)


@pytest.mark.parametrize("broken", [0, 1, 2])
def test_a_transfer_from_paths_names_the_scan_it_cannot_read(scan_files, tmp_path, broken):
    paths = list(scan_files)
    paths[broken] = tmp_path / "truncated.bnt"
    paths[broken].write_bytes(scan_files[broken].read_bytes()[:1000])
    with pytest.raises(ValueError, match="truncated.bnt"):
        tpscore.transfer(*paths, "12")


def test_a_transfer_from_paths_checks_the_landmarks_of_what_it_read(scan_files, tmp_path):
    # a target whose landmark file lost most of its rows fails as a FaceGrid would,
    # naming the scan
    from tpscore.face import io

    landmarks = io.read_landmarks(scan_files[2].with_suffix(".lm3"))
    landmarks[3:] = np.nan
    sparse = tmp_path / "c.bnt"
    sparse.write_bytes(scan_files[2].read_bytes())
    (tmp_path / "c.png").write_bytes(scan_files[2].with_suffix(".png").read_bytes())
    io.write_lm3(tmp_path / "c.lm3", landmarks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match="target: only 3 of the 22 landmarks"):
            tpscore.transfer(scan_files[0], scan_files[1], sparse, "12")
    with pytest.raises(ValueError, match="target must be a FaceGrid .* or a scan's path, got int"):
        tpscore.transfer(scan_files[0], scan_files[1], 3, "12")


def test_a_mirror_plane_that_cannot_be_fitted_is_warned_about_where_it_is_used(smile, monkeypatch):
    (_, _, _), (gs, ge, gt) = smile
    gs, gt = _fresh(gs, gt)   # planes not fitted yet

    fit = modelling.fit_mirror_symmetry
    calls = []

    def plane_for_the_first_face_only(grid, **options):
        # the source's plane is fitted first, then the target's
        calls.append(grid)
        if len(calls) > 1:
            raise ValueError("no plane here")
        return fit(grid, **options)

    monkeypatch.setattr(modelling, "fit_mirror_symmetry", plane_for_the_first_face_only)
    with pytest.warns(UserWarning, match="not averaged with its mirror image: no plane here") as caught:
        result = tpscore.transfer(gs, ge, gt, "12")
    assert len(calls) == 2 and sum("no plane here" in str(w.message) for w in caught) == 1
    assert isinstance(result.model.dense, MirroredMotion)    # the source's field is mirrored
    assert np.isfinite(result.vertices[result.mask]).all()

    def no_plane(grid, **options):
        raise ValueError("no plane here")

    monkeypatch.setattr(modelling, "fit_mirror_symmetry", no_plane)
    with pytest.warns(UserWarning, match="not averaged with its mirror image: no plane here") as caught:
        result = tpscore.transfer(*_fresh(gs, ge, gt), "12")
    # without the source's plane the field is not mirrored, so the target's is not needed
    assert sum("no plane here" in str(w.message) for w in caught) == 1
    assert not isinstance(result.model.dense, MirroredMotion)
    assert np.isfinite(result.vertices[result.mask]).all()


def test_frames_are_linear_in_magnitude(smile):
    _, (gs, ge, gt) = smile
    animation = tpscore.transfer(gs, ge, gt, "12,1").animation
    neutral = animation.frame(0.0)
    half = animation.frame(0.5) - neutral
    full = animation.frame(1.0) - neutral
    assert np.allclose(half, 0.5 * full, equal_nan=True, atol=1e-12)
    both = animation.frame({"AU12": 1.0, "AU1": 0.0}) - neutral
    mask = animation.target.grid.mask
    assert np.allclose(both[mask], animation.fields[0][mask], atol=1e-12)


def test_magnitude_outside_unit_interval_warns(smile):
    _, (gs, ge, gt) = smile
    result = tpscore.transfer(gs, ge, gt, "12", 1.5)
    with pytest.warns(UserWarning, match="outside"):
        result.vertices


@pytest.mark.parametrize("method", ["published", "default"])
def test_aus_of_different_regions_add(smile, method):
    _, (gs, ge, gt) = smile
    # the boundary alone splits the regions (the spill lets a brow AU take a little of
    # what lies below it: see the spill's tests)
    options = TransferOptions(method=method, upper_spill=0.0)
    a = tpscore.transfer(gs, ge, gt, "12", options=options).animation.displacement(1.0)
    b = tpscore.transfer(gs, ge, gt, "1", options=options).animation.displacement(1.0)
    ab = tpscore.transfer(gs, ge, gt, "12,1", options=options).animation.displacement(1.0)
    if method == "published":
        assert np.allclose(ab, a + b, equal_nan=True, atol=1e-9)
    else:
        # the rigid alignment leans on the region the AUs leave still, which differs
        # between the three transfers: additive up to that small difference in pose
        # (measured 0.24 mm at most; a wrong region split would move several mm)
        difference = np.linalg.norm((ab - a - b)[gt.mask], axis=1)
        assert difference.max() < 0.5


def test_a_point_shared_by_two_aus_moves_once(brows):
    # AU1 and AU4 share the inner-brow points; modelled from one scan, the brow motion
    # must come across once, not once per AU
    _, (gs, ge, gt) = brows
    one = tpscore.transfer(gs, ge, gt, "1").animation
    both = tpscore.transfer(gs, ge, gt, "1,4").animation
    assert both.labels == ["AU1+AU4"]
    inner = one.moved_control_points[0][:2] - one.control_points[0][:2]
    shared = both.moved_control_points[0][:2] - both.control_points[0][:2]
    assert np.allclose(inner, shared, atol=1e-9)
    peak_one = np.nanmax(np.linalg.norm(one.displacement(1.0), axis=2))
    peak_both = np.nanmax(np.linalg.norm(both.displacement(1.0), axis=2))
    assert peak_both < 1.3 * peak_one  # a double count would nearly double it


def test_animations_from_separate_scans_combine(smile, brows):
    (_, _, _), (gs, ge, gt) = smile
    (_, _, _), (bs, be, _) = brows
    smile_anim = tpscore.transfer(gs, ge, gt, "12").animation
    brow_anim = tpscore.transfer(bs, be, gt, "2").animation
    both = tpscore.Animation.combine([smile_anim, brow_anim])
    assert both.labels == ["AU12", "AU2"]
    expected = smile_anim.displacement(1.0) + brow_anim.displacement(0.5)
    assert np.allclose(both.displacement({"AU12": 1.0, "AU2": 0.5}), expected, atol=1e-12)
    with pytest.raises(ValueError, match="repeat"):
        tpscore.Animation.combine([smile_anim, smile_anim])


def test_missing_landmarks_are_coped_with_then_reported(smile):
    _, (gs, ge, gt) = smile
    lm = gt.landmarks.copy()
    lm[[landmark_index("Chin middle"), landmark_index("Outer left eyebrow")]] = np.nan
    fewer = gt.with_landmarks(lm)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for options in VARIANTS.values():  # the affine one falls back to the similarity
            result = tpscore.transfer(gs, ge, fewer, "12", options=options)
            assert np.isfinite(result.vertices[result.mask]).all()
    lm[5:] = np.nan
    # the message says which of the three faces lacks them
    with pytest.raises(ValueError, match=r"target: only 4 of the 22 landmarks are present"):
        tpscore.transfer(gs, ge, gt.with_landmarks(lm), "12")


def test_detected_landmarks_do_not_hold_the_registration(smile):
    """The source's landmark pairs pull the registration only when they were read from a
    file: moving the expressive scan's landmarks changes a transfer, unless they are
    marked detected."""
    from dataclasses import replace

    _, (gs, ge, gt) = smile
    lm = ge.landmarks.copy()
    lm[:, 1] += 3.0  # every landmark 3 mm up, as a detector's error could be
    moved = ge.with_landmarks(lm)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        given = [tpscore.transfer(gs, e, gt, "12").vertices for e in (ge, moved)]
        detected = [tpscore.transfer(replace(gs, landmarks_detected=True), replace(e, landmarks_detected=True),
                                     gt, "12").vertices for e in (ge, moved)]
    mask = np.isfinite(given[0]).all(axis=-1)
    moved_given = np.linalg.norm(given[1] - given[0], axis=-1)[mask]
    moved_detected = np.linalg.norm(detected[1] - detected[0], axis=-1)[mask]
    assert moved_given.max() > 1.0
    # the moved labels still enter the rigid alignment's first guess, which the surface
    # fit then refines until a step moves no point by 1e-3 mm: from another start it
    # stops elsewhere along the face's shallow directions, by an amount that depends on
    # the floating-point paths (under 0.1 of the labelled case's largest change on an
    # AVX-512 CPU, 0.14 on an AVX2 one). The labels move the result a fifth as much at most.
    assert moved_detected.max() < 0.2 * moved_given.max()
    assert np.sqrt(np.mean(moved_detected ** 2)) < 0.2 * np.sqrt(np.mean(moved_given ** 2))


def test_results_carry_the_frame_transform(smile):
    _, (gs, ge, gt) = smile
    result = tpscore.transfer(gs, ge, gt, "12")
    arrays = result.to_npz_dict()
    assert arrays["vertices"].shape == gt.points.shape and arrays["mask"].shape == gt.mask.shape
    back = tpscore.FrameTransform(arrays["scan_to_normalised"]).apply(arrays["vertices"])
    assert np.allclose(back, arrays["vertices_normalised"], equal_nan=True, atol=1e-9)


def test_options_are_validated():
    with pytest.raises(ValueError, match="TransferOptions.method"):
        TransferOptions(method="nearest")
    with pytest.raises(ValueError, match="TransferOptions.motion"):
        TransferOptions(motion="dense")
    with pytest.raises(ValueError, match="transition_mm"):
        TransferOptions(transition_mm=-1.0)
    with pytest.raises(ValueError, match="TransferOptions.correspondence"):
        TransferOptions(correspondence="nearest")
    with pytest.raises(ValueError, match="TransferOptions.correspondence='adapted' needs method='default'"):
        replace(TransferOptions.published(), correspondence="adapted")



def test_default_copes_with_holes_missing_landmarks_and_pose():
    # holes over an eye and between the lips of the expressive scan, the chin (a
    # normalisation landmark) and an eyebrow missing, and 10 degrees of pose between
    # the scans. (A missing mouth corner costs more: it is what tells the registration
    # how far the corners of a smile slide along the skin.)
    scans = datasets.demo_triplet("12", pose_deg=10.0)
    gs, ge, gt = (_grid(s) for s in scans)
    points = ge.points.copy()
    mouth = ge.landmarks[[landmark_index("Left mouth corner"), landmark_index("Right mouth corner")]]
    lips = ((np.abs(points[..., 1] - ge.landmarks[landmark_index("Upper lip inner middle"), 1]) < 2.5)
            & (points[..., 0] > mouth[:, 0].min() + 3) & (points[..., 0] < mouth[:, 0].max() - 3))
    eye = np.linalg.norm(points[..., :2] - ge.landmarks[landmark_index("Outer left eye corner"), :2],
                         axis=-1) < 6
    points[lips | eye] = np.nan
    lm = ge.landmarks.copy()
    lm[[landmark_index("Chin middle"), landmark_index("Outer left eyebrow")]] = np.nan
    holed = type(ge).from_points(points, landmarks=lm)
    target_lm = gt.landmarks.copy()
    target_lm[landmark_index("Chin middle")] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = tpscore.transfer(gs, holed, gt.with_landmarks(target_lm), "12")
    assert np.isfinite(result.vertices[result.mask]).all()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clean = tpscore.transfer(gs, ge, gt, "12")
    motion = clean.vertices - clean.neutral
    change = (result.vertices - clean.vertices)[gt.mask]
    size = np.sqrt(np.mean(np.sum(motion[gt.mask] ** 2, axis=1)))
    # measured: the defects change the transferred smile by 0.49 of its size, most of it
    # from the hole between the lips, which the registration bridges by smoothness alone;
    # a failed transfer (no motion, or motion elsewhere) changes it by 1 or more
    assert np.sqrt(np.mean(np.sum(change ** 2, axis=1))) < 0.65 * size
    moved = np.linalg.norm((result.vertices - result.neutral)[gt.mask], axis=1)
    assert np.sqrt(np.mean(moved ** 2)) > 0.6 * size


def test_upper_spill_keeps_strong_upper_face_motion_below_the_boundary():
    from tpscore.expression.animation import _spill
    # a column of nine grid vertices, the top three in the upper region
    valid = np.ones((9, 1), dtype=bool)
    upper = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    sizes = np.array([10.0, 10.0, 10.0, 3.0, 1.5, 0.5, 0.0, 5.0, 5.0])
    carried = np.column_stack([np.zeros(9), sizes, np.zeros(9)])
    spilled = _spill(upper, carried, 0.1, valid)
    # joined to the upper motion: 30 % of the peak kept, 15 % half way up the ramp,
    # 5 % cut; the strong motion further down, apart from it, stays cut
    assert np.allclose(spilled, [1.0, 1.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    assert np.array_equal(_spill(upper, np.zeros((9, 3)), 0.1, valid), upper)
    # motion larger than the upper face's own (a smile's, seen from the brows) is not
    # a continuation of it, and what lies beyond it is cut off with it
    sizes[3] = 16.0
    carried = np.column_stack([np.zeros(9), sizes, np.zeros(9)])
    assert np.array_equal(_spill(upper, carried, 0.1, valid), upper)
    with pytest.raises(ValueError, match="upper_spill"):
        TransferOptions(upper_spill=-0.1)


def test_upper_spill_moves_the_split_between_regions_not_the_total():
    # one scan showing a brow raise and a smile: the two regions share its motion, so
    # keeping upper-face motion below the boundary takes it from the lower region
    scans = datasets.demo_triplet({"1": 1.0, "12": 1.0})
    gs, ge, gt = (_grid(s) for s in scans)
    cut = tpscore.transfer(gs, ge, gt, "1,12", options=TransferOptions(upper_spill=0.0)).animation
    spilled = tpscore.transfer(gs, ge, gt, "1,12", options=TransferOptions(upper_spill=0.1)).animation
    assert cut.labels == spilled.labels == ["AU1", "AU12"]
    assert np.allclose(cut.displacement(1.0), spilled.displacement(1.0), atol=1e-9, equal_nan=True)
    moved = np.abs(spilled.displacement({"AU1": 1.0, "AU12": 0.0})
                   - cut.displacement({"AU1": 1.0, "AU12": 0.0}))
    assert np.nanmax(moved) > 0.1


def test_upper_spill_takes_no_lower_face_motion_apart_from_the_brows(smile):
    # a brow AU asked of a smile scan: below the eyes the spill may keep what continues
    # the (small, stray) motion above them, never the smile itself
    _, (gs, ge, gt) = smile
    cut = tpscore.transfer(gs, ge, gt, "1", options=TransferOptions(upper_spill=0.0))
    spilled = tpscore.transfer(gs, ge, gt, "1", options=TransferOptions(upper_spill=0.1))
    smile_peak = np.nanmax(np.linalg.norm(tpscore.transfer(gs, ge, gt, "12").animation.displacement(1.0),
                                          axis=2))
    cut_field = cut.animation.displacement(1.0)
    added = np.nanmax(np.linalg.norm(spilled.animation.displacement(1.0) - cut_field, axis=2))
    # measured: 0.19 mm added to a 0.19 mm brow field, against a 4 mm smile
    assert added <= 1.5 * np.nanmax(np.linalg.norm(cut_field, axis=2))
    assert added < 0.1 * smile_peak


def test_published_warp_through_nearly_flat_control_points_moves_by_their_mean():
    # Five lip points almost in one plane: the exact TPS's affine part would extrapolate
    # their different motions across the face without bound.
    from tpscore.expression.published import control_point_warp

    rng = np.random.default_rng(3)
    control = np.column_stack([rng.uniform(-20, 20, 6), rng.uniform(-5, 5, 6), rng.uniform(-0.3, 0.3, 6)])
    motion = rng.normal(scale=3.0, size=(6, 3))
    far = np.array([[0.0, 0.0, 80.0], [60.0, -40.0, 0.0]])
    np.testing.assert_allclose(control_point_warp(control, motion)(far), np.tile(motion.mean(axis=0), (2, 1)))
    # Spread in depth too, the warp interpolates the control points' own motion.
    control = rng.uniform(-15, 15, size=(6, 3))
    np.testing.assert_allclose(control_point_warp(control, motion)(control), motion, atol=1e-8)
