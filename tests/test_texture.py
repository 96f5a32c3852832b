"""Texture tracking: colour images of two scans of one skin, slid along a smooth surface
by a known amount, are matched back to that slide, which the geometry cannot see."""
from __future__ import annotations

import pickle
import warnings

import numpy as np
import pytest

from tpscore.expression import registration
from tpscore.expression.registration import MotionOptions, register_surfaces
from tpscore.face.grid import FaceGrid
from tpscore.spatial import MeshSurface
from tpscore.expression.texture import TextureOptions, TextureWarning, track_texture

SIZE = 120                  # grid 120 x 120 over [-48, 48] mm: 0.8 mm spacing
EXTENT = 48.0
SLIDE_MM = 2.0              # peak slide of the skin along x
SLIDE_SIGMA_MM = 14.0


def height(x, y):
    """A gentle dome: no feature tells where the skin went."""
    return 30.0 - (x ** 2 + y ** 2) / 250.0


def pattern(x, y, seed=3):
    """A skin-like pattern: random-phase cosines of 1 to 4 mm wavelength."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, 96)
    wavelength = rng.uniform(1.0, 4.0, 96)
    phase = rng.uniform(0, 2 * np.pi, 96)
    k = 2 * np.pi / wavelength
    value = sum(np.cos(k[i] * (np.cos(angle[i]) * x + np.sin(angle[i]) * y) + phase[i]) for i in range(96))
    return value / np.sqrt(48.0)


def slide(x, y):
    return SLIDE_MM * np.exp(-(x ** 2 + y ** 2) / (2 * SLIDE_SIGMA_MM ** 2))


def textured_pair(*, seed=3, contrast=40.0, exposure=1.0, slide=slide):
    """Neutral and expressive grids of one dome; the skin of the expressive one slid by
    ``slide`` along x (and the surface). Images at twice the grid's resolution."""
    xs = np.linspace(-EXTENT, EXTENT, SIZE)
    x, y = np.meshgrid(xs, xs[::-1])
    points = np.dstack([x, y, height(x, y)])
    # image pixel (r, c) shows the grid position of u = (c + 0.5) / 2 SIZE
    c = (np.arange(2 * SIZE) + 0.5) / 2 - 0.5
    px = -EXTENT + c * (2 * EXTENT / (SIZE - 1))
    ix, iy = np.meshgrid(px, px[::-1])
    rest_x = ix.copy()
    for _ in range(20):                     # the skin seen at ix came from rest_x
        rest_x = ix - slide(rest_x, iy)

    def image(of_x):
        grey = 128.0 + contrast * pattern(of_x, iy, seed)
        return np.clip(np.round(exposure * grey), 0, 255).astype(np.uint8)[..., None].repeat(3, axis=2)

    neutral = FaceGrid.from_points(points)
    neutral.image = image(ix)
    expressive = FaceGrid.from_points(points)
    expressive.image = image(rest_x)
    return neutral, expressive


def true_motion(points, slide=slide):
    """Where each neutral point's skin went: x + slide, back on the dome."""
    x, y = points[..., 0], points[..., 1]
    moved_x = x + slide(x, y)
    return np.stack([moved_x, y, height(moved_x, y)], axis=-1) - points


def test_matches_follow_the_slide():
    neutral, expressive = textured_pair()
    matches = track_texture(neutral, expressive)
    assert matches is not None
    assert matches.matched_fraction > 0.8
    used = matches.confidence > 0
    error = np.linalg.norm(matches.targets[used] - neutral.points[used] - true_motion(neutral.points[used]), axis=1)
    # the flow's error on a clear pattern is a small fraction of the 2 mm slide
    assert np.median(error) < 0.1, np.median(error)
    assert np.percentile(error, 95) < 0.3


def test_exposure_change_does_not_matter():
    # the same pair photographed with 30 % more light on the neutral scan
    neutral, expressive = textured_pair()
    brighter, _ = textured_pair(exposure=1.3)
    a = track_texture(neutral, expressive)
    b = track_texture(brighter, expressive)
    used = (a.confidence > 0) & (b.confidence > 0)
    assert used.mean() > 0.7
    assert np.median(np.linalg.norm(a.targets[used] - b.targets[used], axis=1)) < 0.05


def test_registration_follows_the_texture_where_geometry_sees_nothing():
    neutral, expressive = textured_pair()
    mesh = expressive.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    landmarks = np.full((22, 3), np.nan)
    truth = true_motion(neutral.points)
    moving = np.linalg.norm(truth, axis=-1) > 0.5

    def error(texture):
        field = register_surfaces(neutral.points, neutral.mask, landmarks, surface, landmarks,
                                  MotionOptions(), texture=texture)
        got = field(neutral.points.reshape(-1, 3)).reshape(truth.shape)
        return np.sqrt(np.mean(np.sum((got - truth)[moving] ** 2, axis=-1)) / np.mean(np.sum(truth[moving] ** 2, axis=-1)))

    geometry_only = error(None)
    with_texture = error(track_texture(neutral, expressive))
    # the dome is the same surface before and after: geometry alone finds no slide
    assert geometry_only > 0.9
    assert with_texture < 0.2, with_texture


def test_the_first_iteration_follows_a_block_of_skin_that_slides_far(monkeypatch):
    # a disc of skin 24 mm across slides 2.5 mm as a block, the rest of the face keeps
    # still: the still skin sets the matches' robust scale to its lower bound, and a
    # bound as tight at the first iteration as at the last (0.3 mm: a 0.9 mm cut-off)
    # drops every match of the block while the field has not moved yet
    def block(x, y):
        return 2.5 / (1.0 + np.exp((np.hypot(x, y) - 12.0) / 1.5))

    neutral, expressive = textured_pair(slide=block)
    mesh = expressive.mesh()
    surface = MeshSurface(mesh.vertices, mesh.faces)
    landmarks = np.full((22, 3), np.nan)
    matches = track_texture(neutral, expressive)
    centre = neutral.points[SIZE // 2, SIZE // 2]
    truth = true_motion(centre, block)[0]

    def followed(start_floor):
        monkeypatch.setattr(registration, "TEXTURE_SCALE_FLOOR_START_MM", start_floor)
        field = register_surfaces(neutral.points, neutral.mask, landmarks, surface, landmarks,
                                  MotionOptions(iterations=1), texture=matches)
        return field(centre[None])[0, 0] / truth

    assert followed(registration.TEXTURE_SCALE_FLOOR_START_MM) > 0.8
    assert followed(registration.TEXTURE_SCALE_FLOOR_END_MM) < 0.5


def test_no_image_or_a_flat_one_falls_back_with_a_warning():
    neutral, expressive = textured_pair()
    bare = FaceGrid.from_points(expressive.points)
    with pytest.warns(TextureWarning, match="expressive scan has no colour image"):
        assert track_texture(neutral, bare) is None
    dark = FaceGrid.from_points(expressive.points)
    dark.image = np.full_like(expressive.image, 3)
    with pytest.warns(TextureWarning, match="too dark"):
        assert track_texture(neutral, dark) is None
    flat = FaceGrid.from_points(expressive.points)
    flat.image = np.full_like(expressive.image, 128)
    with pytest.warns(TextureWarning, match="no texture"):
        assert track_texture(neutral, flat) is None


def test_unrelated_texture_fails_the_consistency_check():
    neutral, _ = textured_pair()
    _, stranger = textured_pair(seed=11)
    with pytest.warns(TextureWarning, match="matched less than"):
        assert track_texture(neutral, stranger) is None


@pytest.mark.parametrize("kwargs, name", [
    (dict(shading_sigma_mm=0.0), "shading_sigma_mm"),
    (dict(consistency_px=np.nan), "consistency_px"),
    (dict(rim_px=1.5), "rim_px"),
    (dict(min_matched_fraction=1.0), "min_matched_fraction"),
])
def test_bad_options_are_rejected(kwargs, name):
    with pytest.raises(ValueError, match=name):
        TextureOptions(**kwargs)


def test_no_match_lands_in_a_hole_of_the_expressive_scan():
    # a hole in the expressive depth scan where its image still shows skin: matches must
    # not land in it (nothing there to lift them to), and the rest still match
    neutral, expressive = textured_pair()
    x, y = expressive.points[..., 0], expressive.points[..., 1]
    hole = np.hypot(x - 10.0, y - 5.0) < 6.0
    holed = FaceGrid.from_points(np.where(hole[..., None], np.nan, expressive.points))
    holed.image = expressive.image
    matches = track_texture(neutral, holed)
    targets = matches.targets[matches.confidence > 0]
    assert np.hypot(targets[:, 0] - 10.0, targets[:, 1] - 5.0).min() > 6.0
    assert matches.matched_fraction > 0.7


@pytest.fixture(scope="module")
def scans_with_images(shared, tmp_path_factory):
    """Two subjects of make_scans.py: neutral and smile, with their colour images."""
    import subprocess
    import sys

    folder = tmp_path_factory.mktemp("scans")
    subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(folder), "--subjects", "0", "1",
                    "--expressions", "N_N_0", "LFAU_12_0"], check=True, capture_output=True)
    return folder


def test_transfer_tracks_texture_when_the_scans_have_images(scans_with_images):
    import tpscore

    def load(subject, code):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", tpscore.LandmarkSnapWarning)
            return tpscore.load_scan(scans_with_images / f"bs{subject:03d}" / f"bs{subject:03d}_{code}.bnt")

    neutral, smile, target = load(0, "N_N_0"), load(0, "LFAU_12_0"), load(1, "N_N_0")
    result = tpscore.transfer(neutral, smile, target, "12")
    assert result.model.texture is not None and result.model.texture.matched_fraction > 0.5
    assert result.timings["texture"] > 0
    # without the expressive scan's image the geometry alone says how the skin moved
    bare = FaceGrid.from_points(smile.points, smile.mask, smile.landmarks)
    with pytest.warns(TextureWarning, match="expressive scan has no colour image"):
        plain = tpscore.transfer(neutral, bare, target, "12")
    assert plain.model.texture is None and "texture" not in plain.timings
    # the two fields differ: the texture moved the skin along the surface
    moved = np.linalg.norm(result.vertices - plain.vertices, axis=-1)[result.mask]
    assert np.percentile(moved, 99) > 0.3


def test_a_neutral_view_seen_before_gives_the_same_matches():
    neutral, expressive = textured_pair()
    first = track_texture(neutral, expressive)
    view = first.neutral_view
    assert view is not None and view.look.pattern is not None
    # another expressive scan of the same skin, tracked from the view kept of the neutral one
    _, other = textured_pair(exposure=0.8)
    again = track_texture(neutral, other, neutral_view=view)
    anew = track_texture(neutral, other)
    assert again.neutral_view is view
    assert np.array_equal(again.targets, anew.targets, equal_nan=True)
    assert np.array_equal(again.confidence, anew.confidence)
    # the view is not pickled with the matches (nor are the tracker's images)
    assert pickle.loads(pickle.dumps(first)).neutral_view is None
    with pytest.raises(ValueError, match="neutral_view must be a NeutralView"):
        track_texture(neutral, other, neutral_view={"plane": view.plane})


def test_refined_matches_follow_a_warp_and_still_find_the_slide():
    neutral, expressive = textured_pair()
    first = track_texture(neutral, expressive)
    # a guess of the motion half way to the truth: the refined flow finds the rest
    guess = 0.5 * true_motion(neutral.points)
    refined = first.refined(guess)
    used = refined.confidence > 0
    assert used.mean() > 0.7
    error = np.linalg.norm(refined.targets[used] - neutral.points[used] - true_motion(neutral.points[used]), axis=1)
    assert np.median(error) < 0.1, np.median(error)
    # the registration can match again half way through its iterations
    mesh = expressive.mesh()
    landmarks = np.full((22, 3), np.nan)
    field = register_surfaces(neutral.points, neutral.mask, landmarks, MeshSurface(mesh.vertices, mesh.faces),
                              landmarks, MotionOptions(texture_refine_after=5), texture=first)
    assert field.texture is not first
    got = field(neutral.points.reshape(-1, 3)).reshape(neutral.points.shape)
    moving = np.linalg.norm(true_motion(neutral.points), axis=-1) > 0.5
    assert np.sqrt(np.mean(np.sum((got - true_motion(neutral.points))[moving] ** 2, axis=-1))) < 0.3


def test_refined_matches_in_regions_are_made_there_only_and_at_full_resolution():
    neutral, expressive = textured_pair()
    first = track_texture(neutral, expressive)
    guess = 0.5 * true_motion(neutral.points)
    x, y = neutral.points[..., 0], neutral.points[..., 1]
    regions = [np.hypot(x + 15.0, y) < 10.0, np.hypot(x - 15.0, y - 5.0) < 8.0]
    refined = first.refined(guess, regions)
    used = refined.confidence > 0
    within = regions[0] | regions[1]
    assert not used[~within].any()
    assert np.isnan(refined.targets[~within]).all()
    assert used[within].mean() > 0.7
    error = np.linalg.norm(refined.targets[used] - neutral.points[used] - true_motion(neutral.points[used]), axis=1)
    assert np.median(error) < 0.1, np.median(error)
    # the whole face's refined flow, at half the resolution, is further off there
    whole = first.refined(guess)
    both = used & (whole.confidence > 0)
    whole_error = np.linalg.norm(whole.targets[both] - neutral.points[both] - true_motion(neutral.points[both]),
                                 axis=1)
    region_error = np.linalg.norm(refined.targets[both] - neutral.points[both] - true_motion(neutral.points[both]),
                                  axis=1)
    assert np.median(region_error) < 0.75 * np.median(whole_error), (np.median(region_error), np.median(whole_error))
    # a region with no vertex matches nothing: the matches come back unchanged
    assert first.refined(guess, [np.zeros(x.shape, dtype=bool)]) is first
    with pytest.raises(ValueError, match="regions"):
        first.refined(guess, [np.ones((3, 3), dtype=bool)])


def _pair_with_an_eye():
    """The textured pair, a disc of its neutral grid standing for an eye, and a function
    that returns the disc as the fine regions and notes each call in ``asked``."""
    neutral, expressive = textured_pair()
    x, y = neutral.points[..., 0], neutral.points[..., 1]
    eye = np.hypot(x + 15.0, y) < 10.0
    asked = []

    def regions():
        asked.append(True)
        return [eye]

    return neutral, expressive, eye, regions, asked


def test_fine_regions_are_matched_at_full_resolution_and_nothing_else_changes():
    neutral, expressive, eye, _, _ = _pair_with_an_eye()
    plain = track_texture(neutral, expressive)
    fine = track_texture(neutral, expressive, fine_regions=[eye])
    # outside the region the matches are the plain ones, bit for bit
    assert np.array_equal(plain.targets[~eye], fine.targets[~eye], equal_nan=True)
    assert np.array_equal(plain.confidence[~eye], fine.confidence[~eye])
    both = eye & (plain.confidence > 0) & (fine.confidence > 0)
    assert both.sum() > 0.7 * eye.sum()

    def error(matches):
        return np.median(np.linalg.norm(matches.targets[both] - neutral.points[both]
                                        - true_motion(neutral.points[both]), axis=1))

    assert error(fine) < 0.75 * error(plain), (error(fine), error(plain))
    # refined over the whole face, the region is matched at full resolution again
    guess = 0.5 * true_motion(neutral.points)
    assert np.array_equal(fine.refined(guess).targets[eye], fine.refined(guess, [eye]).targets[eye],
                          equal_nan=True)
    with pytest.raises(ValueError, match="fine_regions"):
        track_texture(neutral, expressive, fine_regions=[np.ones((4, 4), dtype=bool)])


def test_a_warp_moves_the_pixels_that_see_the_surface_and_only_those():
    # the warp a refinement flows against, over the whole plane and over a region's box,
    # against the same sums made over every pixel of the box
    from tpscore.raster import interpolate_pixels

    neutral, expressive, eye, _, _ = _pair_with_an_eye()
    tracker = track_texture(neutral, expressive)._tracker
    view, plane = tracker.views[0], tracker.plane
    guess = 0.5 * true_motion(neutral.points)
    for box in [(0, plane.height, 0, plane.width), tracker._box(eye)[1]]:
        row0, row1, col0, col1 = box
        moved = interpolate_pixels(np.nan_to_num(guess[neutral.mask]), neutral.mesh().faces,
                                   view.triangle[row0:row1, col0:col1], view.barycentric[row0:row1, col0:col1])
        columns, rows = np.meshgrid(np.arange(col0, col1), np.arange(row0, row1))
        expected = np.stack([columns, rows], axis=-1).astype(np.float32)
        seen = view.valid[row0:row1, col0:col1]
        assert seen.any() and (box[0] > 0 or not seen.all())  # the whole plane has pixels off the surface
        expected[seen] = plane.pixels(view.points[row0:row1, col0:col1][seen] + moved[seen]).astype(np.float32)
        warp = tracker._warp(guess, box)
        assert np.array_equal(warp, expected)
        # no motion: every pixel stays where it is (a surface point lies under its pixel)
        still = tracker._warp(0.0 * guess, box)
        identity = np.stack([columns, rows], axis=-1).astype(np.float32)
        assert np.array_equal(still[~seen], identity[~seen])
        assert np.allclose(still[seen], identity[seen], atol=1e-3)
        assert np.abs(warp[seen] - identity[seen]).max() > 1.0  # the guess moves the pixels


def test_fine_regions_later_are_matched_only_when_the_matches_are_refined():
    neutral, expressive, eye, regions, asked = _pair_with_an_eye()
    plain = track_texture(neutral, expressive)
    now = track_texture(neutral, expressive, fine_regions=[eye])
    later = track_texture(neutral, expressive, fine_regions=regions, fine_regions_later=True)
    # the first matches are the whole face's alone, and nobody asked for the regions
    assert not asked
    assert np.array_equal(later.targets, plain.targets, equal_nan=True)
    assert not np.array_equal(now.targets[eye], plain.targets[eye], equal_nan=True)
    # refined, the region is matched at full resolution, as when it was given up front
    guess = 0.5 * true_motion(neutral.points)
    assert np.array_equal(later.refined(guess).targets, now.refined(guess).targets, equal_nan=True)
    assert asked == [True]
    with pytest.raises(ValueError, match="fine_regions_later"):
        track_texture(neutral, expressive, fine_regions_later="yes")


def test_fine_regions_can_be_found_while_the_whole_face_is_matched():
    neutral, expressive, eye, regions, asked = _pair_with_an_eye()
    given = track_texture(neutral, expressive, fine_regions=[eye])
    found = track_texture(neutral, expressive, fine_regions=regions)
    assert np.array_equal(given.targets, found.targets, equal_nan=True)
    assert np.array_equal(given.confidence, found.confidence)
    guess = 0.5 * true_motion(neutral.points)
    assert np.array_equal(given.refined(guess).targets, found.refined(guess).targets, equal_nan=True)
    assert asked == [True]  # asked for once, and kept for the refinements
    with pytest.raises(ValueError, match="fine_regions"):
        track_texture(neutral, expressive, fine_regions=lambda: [np.ones((4, 4), dtype=bool)])


def test_a_transfer_that_refines_its_matches_has_the_eyes_matched_only_then(monkeypatch, coloured_smile_files):
    import tpscore
    from tpscore.expression import modelling

    scans = tpscore.load_scans(coloured_smile_files)
    asked = []
    track = modelling.track_texture

    def tracking(*args, **kwargs):
        asked.append(kwargs["fine_regions_later"])
        return track(*args, **kwargs)

    monkeypatch.setattr(modelling, "track_texture", tracking)
    one_pass = tpscore.TransferOptions(motion=tpscore.MotionOptions(texture_refine_after=0))
    once = tpscore.transfer(*scans, "12", options=one_pass)
    twice = tpscore.transfer(*scans, "12")  # the default refines after the fourth iteration
    # a refinement after the last iteration never happens: the eyes are matched up front
    late = tpscore.TransferOptions(motion=tpscore.MotionOptions(texture_refine_after=10))
    tpscore.transfer(*scans, "12", options=late)
    assert asked == [False, True, False]
    moved = [np.linalg.norm(result.vertices - result.neutral, axis=-1) for result in (once, twice)]
    assert np.nanmax(moved[1]) > 1.0
    # the second pass changes the carried motion, not what the transfer is
    assert np.nanmax(np.abs(moved[1] - moved[0])) < 0.5 * np.nanmax(moved[0])
