"""The physical skin's Python layer: the template head and its muscle set, regions, the
jaw, carrying the structure through a fit, and what is refused or clamped."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import tpscore
from tpscore import physics
from tpscore.cli import main
from tpscore.face import io
from tpscore.face.landmarks import landmark_index
from tpscore.physics import SimulationError, SimulationOptions, SkinMaterial, SkinModel, SkinWarning
from tpscore.physics.fitting import carry_head, deform_from_vertices
from tpscore.physics.head import REGIONS
from tpscore.reference.skin import bone_points
from tpscore.showcase import datasets
from tpscore.showcase.datasets import skin_template

from skin_helpers import flat_head, linear_muscle

REQUIRED_MUSCLES = ("frontalis_medial_left", "frontalis_lateral_left", "corrugator_left", "zygomaticus_major_left",
                    "buccinator_left", "depressor_anguli_oris_left", "mentalis", "risorius_left", "orbicularis_oris")


@pytest.fixture(scope="module")
def template():
    return physics.load_template()


@pytest.fixture(scope="module")
def coarse():
    """The template at 5 mm: the same head, a sixth of the particles, quick to simulate."""
    head = skin_template(5.0)
    return head, SkinModel(head)


def test_shipped_template_is_what_the_builder_makes(template):
    built = skin_template()
    # integer and boolean fields are the builder's exactly; the positions pass through
    # NumPy's floating-point paths, whose SIMD kernels round differently from one CPU to
    # another (an AVX2-only CPU moved 117 vertices by up to 7e-15 mm): they agree to a
    # micrometre's millionth (1e-9 mm), far below the 0.01 mm the template is given in
    for name in ("faces", "landmark_vertices", "regions", "mandible"):
        assert np.array_equal(getattr(template, name), getattr(built, name)), name
    for name in ("vertices", "skull_vertices", "jaw_pivot"):
        np.testing.assert_allclose(getattr(template, name), getattr(built, name), rtol=0, atol=1e-9, err_msg=name)
    assert template.region_names == REGIONS
    assert 2000 < len(template.vertices) < 4000


def test_template_has_the_muscle_set_and_a_skull_under_the_skin(template):
    for name in REQUIRED_MUSCLES:
        template.muscle(name)
    assert template.muscle("orbicularis_oris").kind == "sphincter"
    depth = template.tissue_depth()
    # published soft-tissue depths of the face run from about 3 (nasal bridge) to about
    # 20 mm (cheek, over the molars); the skull lies under the skin everywhere
    assert 3.0 < depth.min() and depth.max() < 25.0
    normals = tpscore.face_normals(template.vertices, template.faces)
    skull_normals = tpscore.face_normals(template.skull_vertices, template.faces)
    assert np.all(np.einsum("ij,ij->i", normals, skull_normals) > 0)
    # the lips have their own vertices along the mouth line, so the jaw can open it
    upper = template.landmark_vertices[landmark_index("Upper lip inner middle")]
    lower = template.landmark_vertices[landmark_index("Lower lip inner middle")]
    assert upper != lower and np.allclose(template.vertices[upper], template.vertices[lower])
    assert template.mandible[lower] and not template.mandible[upper]


def test_the_muscle_set_is_mirror_symmetric(template):
    # The template is symmetric about x = 0 (vertex for vertex), so each left muscle's
    # attachment and insertion must be the mirror images of the right one's, and a
    # midline muscle must lie on the midline: a symmetric AU then pulls both sides alike.
    mirror = np.array([-1.0, 1.0, 1.0])
    distance, _ = tpscore.KDTree(template.vertices).query(template.vertices * mirror)
    assert np.max(distance) < 1e-9
    for muscle in template.muscles:
        if muscle.name.endswith("_right"):
            continue
        other = template.muscle(muscle.name.replace("_left", "_right"))
        if muscle.kind == "linear":
            for a, b, surface in ((muscle.attachment, other.attachment, template.skull_vertices),
                                  (muscle.insertion, other.insertion, template.vertices)):
                assert np.allclose(a.position(surface, template.faces) * mirror,
                                   b.position(surface, template.faces), atol=1e-6), muscle.name
        else:
            assert np.allclose(muscle.epicentre * mirror, muscle.epicentre, atol=1e-6)


def test_contractions_for_action_units(template):
    smile = template.contractions_for({"12": 0.5})
    assert smile == {"zygomaticus_major_left": 0.5, "zygomaticus_major_right": 0.5}
    assert template.contractions_for("12L") == {"zygomaticus_major_left": 1.0}
    with pytest.raises(ValueError, match="unknown AU"):
        template.contractions_for({"99": 1.0})


def test_relaxed_template_stays_at_rest(coarse):
    _, model = coarse
    result = model.simulate(None, options=SimulationOptions(ramp_time=0.0))
    # At rest every force is zero up to the rounding of the rest lengths (~1e-10 of a
    # force that moves a particle ~1e-15 mm).
    assert result.settled and np.abs(result.layers - model.layers.rest).max() < 1e-9


def test_a_smile_lifts_the_mouth_corners_and_leaves_the_brows(coarse):
    head, model = coarse
    result = model.simulate(head.contractions_for({"12": 0.6}))
    assert result.settled
    moved = result.vertices - head.vertices
    corner = head.landmark_vertices[landmark_index("Left mouth corner")]
    brow = head.landmark_vertices[landmark_index("Middle left eyebrow")]
    assert moved[corner, 1] > 1.0  # up
    assert np.linalg.norm(moved[brow]) < 0.1 * np.linalg.norm(moved[corner])
    # the frames animate it from rest to the settled state
    assert np.array_equal(result.frames[0], head.vertices)
    assert np.allclose(result.frames[-1], result.vertices)
    assert np.all(np.diff(result.times) > 0)


def test_regions_keep_the_mentalis_off_the_upper_lip(coarse):
    head, model = coarse
    result = model.simulate({"mentalis": 0.25})
    moved = np.linalg.norm(result.vertices - head.vertices, axis=1)
    upper = head.region_mask(["upper_lip"])
    chin = head.region_mask(["chin"])
    assert moved[chin].max() > 1.0
    assert moved[upper].max() < 0.2 * moved[chin].max()
    # and its force never touches a particle outside its region
    arrays = model.layers.arrays
    row = model.muscle_names.index("mentalis")
    particles = arrays.muscle_particles[arrays.muscle_indptr[row]:arrays.muscle_indptr[row + 1]]
    assert np.all(head.regions[particles % len(head.vertices)] == REGIONS.index("chin"))


def test_the_jaw_opens_the_mouth_about_its_axis(coarse):
    head, model = coarse
    result = model.simulate(None, jaw=12.0)
    assert result.settled
    chin = head.landmark_vertices[landmark_index("Chin middle")]
    brow = head.landmark_vertices[landmark_index("Inner left eyebrow")]
    moved = result.vertices - head.vertices
    # the mandible turns about the x axis through the pivot, ~85 mm from the chin: its
    # bone under the chin moves ~17 mm, down and back; the soft tissue over it follows
    # much of that (the loose tissue over the bone and the stretched cheeks hold back
    # the rest), the brows stay
    arrays = model.layers.arrays
    bone = bone_points(arrays, head.skull_vertices[[chin]], [1], np.radians(12.0))[0] - head.skull_vertices[chin]
    assert bone[1] < -10.0
    assert moved[chin] @ bone > 0.4 * (bone @ bone)
    assert np.linalg.norm(moved[brow]) < 0.5
    upper = head.landmark_vertices[landmark_index("Upper lip inner middle")]
    lower = head.landmark_vertices[landmark_index("Lower lip inner middle")]
    assert result.vertices[upper, 1] - result.vertices[lower, 1] > 5.0  # the mouth is open
    # the muscles fixed to the mandible turn with it
    jaw = np.radians(12.0)
    moved_points = bone_points(arrays, arrays.muscle_point, arrays.muscle_bone, jaw)
    on_jaw = arrays.muscle_bone == 1
    assert on_jaw.any() and np.all(np.linalg.norm(moved_points[on_jaw] - arrays.muscle_point[on_jaw], axis=1) > 5)
    assert np.array_equal(moved_points[~on_jaw], arrays.muscle_point[~on_jaw])


def test_bad_input_names_the_argument(coarse):
    head, model = coarse
    with pytest.raises(ValueError, match="contractions"):
        model.simulate({"no_such_muscle": 0.5})
    with pytest.raises(ValueError, match="contractions"):
        model.simulate({"mentalis": 1.5})
    with pytest.raises(ValueError, match="contractions"):
        model.simulate({"mentalis": -0.1})
    with pytest.raises(ValueError, match="contractions"):
        model.simulate({"mentalis": float("nan")})
    with pytest.raises(ValueError, match="contractions"):
        model.simulate(np.zeros(3))
    with pytest.raises(ValueError, match="jaw"):
        model.simulate(None, jaw=-5)
    with pytest.raises(ValueError, match="jaw"):
        model.simulate(None, jaw=45)
    with pytest.raises(ValueError, match="SimulationOptions.integrator"):
        SimulationOptions(integrator="rk4")
    with pytest.raises(ValueError, match="SimulationOptions.dt"):
        SimulationOptions(dt=-1e-3)
    with pytest.raises(ValueError, match="SimulationOptions.frames"):
        SimulationOptions(frames=1)
    with pytest.raises(ValueError, match="SimulationOptions.max_time"):
        SimulationOptions(max_time=0.0)
    with pytest.raises(ValueError, match="options"):
        model.simulate(None, options={"dt": 1e-3})
    with pytest.raises(ValueError, match="head"):
        SkinModel("template")
    with pytest.raises(ValueError, match="SkinMaterial"):
        SkinMaterial(dermal_depth=0.9, hypodermal_depth=0.5)
    with pytest.raises(ValueError, match="SkinMaterial.drag"):
        SkinMaterial(drag=-1.0)
    for bad in (-1.0, float("nan"), 1j):
        with pytest.raises(ValueError, match="SkinMaterial.bulk_ratio"):
            SkinMaterial(bulk_ratio=bad)
    with pytest.raises(ValueError, match="skull_vertices"):
        head.with_changes(skull_vertices=head.skull_vertices[:-1])


def test_an_unstable_step_is_cut_into_stable_substeps_with_a_warning(coarse):
    head, model = coarse
    with pytest.warns(SkinWarning, match="stable step"):
        result = model.simulate(head.contractions_for({"12": 0.3}),
                                options=SimulationOptions(dt=10 * model.stable_step))
    assert result.dt <= model.stable_step and np.isfinite(result.vertices).all()


def test_contractions_that_invert_elements_are_scaled_down_with_a_warning():
    # A strong muscle that drags a small patch of skin 12 mm across the face folds it
    # over (the tissue's volume term and the skull's rounded rim hold a weaker pull
    # upright).
    base = flat_head(size=9)
    head = flat_head(size=9, muscles=[linear_muscle(base, attachment=(0.0, 8.0), insertion=(0.0, -4.0), force=25.0,
                                                    falloff_mm=5.0)])
    model = SkinModel(head)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        unclamped = model._settle(np.array([1.0]), 0.0, SimulationOptions(), model.stable_step)
    assert model.inverted(unclamped["positions"]) > 0
    with pytest.warns(SkinWarning, match="invert"):
        result = model.simulate(np.array([1.0]))
    assert 0 < result.scale < 1.0
    assert model.inverted(result.layers) == 0
    assert result.contractions["pull"] == pytest.approx(result.scale)


def test_a_diverging_run_is_repeated_at_a_smaller_step_and_never_returns_nan(coarse, monkeypatch):
    head, model = coarse
    original = model._run
    calls = []

    def diverge_twice(*args, **kwargs):
        calls.append(args[3])  # dt
        result = original(*args, **kwargs)
        result["settled"] = True  # (the short run need not settle)
        if len(calls) <= 2:
            result["diverged"] = True
            result["positions"] = np.full_like(result["positions"], np.nan)
        return result

    monkeypatch.setattr(model, "_run", diverge_twice)
    with pytest.warns(SkinWarning, match="diverged"):
        result = model.simulate(head.contractions_for({"12": 0.2}), options=SimulationOptions(ramp_time=0.005, max_time=0.01))
    assert calls[1] == pytest.approx(calls[0] / 2) and calls[2] == pytest.approx(calls[0] / 4)
    assert np.isfinite(result.layers).all()

    def always(*args, **kwargs):
        result = original(*args, **kwargs)
        result["diverged"] = True
        return result

    monkeypatch.setattr(model, "_run", always)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(SimulationError):
            model.simulate(head.contractions_for({"12": 0.2}), options=SimulationOptions(ramp_time=0.005, max_time=0.01))


def test_carrying_through_an_affine_fit_moves_everything_with_it(coarse):
    template, _ = coarse
    angle = np.radians(10.0)
    turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    scale = 1.1

    def deform(points):
        return scale * np.asarray(points) @ turn.T + np.array([5.0, -3.0, 20.0])

    fitted = carry_head(template, deform)
    assert np.allclose(fitted.vertices, deform(template.vertices))
    assert np.allclose(fitted.skull_vertices, deform(template.skull_vertices))
    assert np.allclose(fitted.jaw_pivot, deform(template.jaw_pivot[None])[0])
    assert np.allclose(fitted.jaw_axis, turn @ np.array([1.0, 0.0, 0.0]), atol=1e-9)
    for before, after in zip(template.muscles, fitted.muscles):
        if before.kind == "linear":
            assert after == before  # triangle and barycentric: the same muscle
        else:
            assert np.allclose(after.epicentre, deform(before.epicentre[None])[0])
            # turned with the fit, each semi-axis scaled by its landmarks' distance
            assert np.allclose(after.axes, scale * before.axes @ turn.T, atol=1e-6)
    # the fitted head simulates at once: the skin of a face 10 % larger, turned and
    # moved, smiles as the template does, turned likewise; with the same moduli and
    # muscle forces a larger body is stiffer in proportion (k = E V / L^2), so it moves
    # about 1 / 1.1 as far
    smile = {"zygomaticus_major_left": 0.3}
    before = (SkinModel(template).simulate(smile).vertices - template.vertices) @ turn.T
    after = SkinModel(fitted).simulate(smile).vertices - fitted.vertices
    ratio = np.sum(after * before) / np.sum(before * before)
    assert 0.8 < ratio < 1.0
    assert np.abs(after - ratio * before).max() < 0.05 * np.abs(after).max()


def test_fit_head_carries_the_template_onto_a_scan():
    scan = datasets.make_face(datasets.random_identity(11), spacing_mm=1.0)
    grid = tpscore.resample_scan(scan.points, scan.landmarks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        head, adaptation = physics.fit_head(grid, scan.landmarks, skin_template(5.0))
    assert np.allclose(head.vertices, adaptation.vertices)
    # the skull follows the smooth map and, where the fit's final snap pushed the skin
    # toward it, the snap too: no column is thinner than the smooth map made it
    template = skin_template(5.0)
    smooth_skin, smooth_skull = adaptation.deform(template.vertices), adaptation.deform(template.skull_vertices)
    assert np.abs(adaptation.vertices - smooth_skin).max() > 0.1  # the snap moved the skin
    moved = np.linalg.norm(head.skull_vertices - smooth_skull, axis=1) > 1e-9
    assert 0 < moved.sum() < len(moved)
    depth = np.linalg.norm(head.vertices - head.skull_vertices, axis=1)
    assert np.all(depth >= np.linalg.norm(smooth_skin - smooth_skull, axis=1) - 1e-9)
    # the fitted skin lies on the scan, and its landmarks near the scan's
    lm = head.landmarks
    assert np.nanmax(np.linalg.norm(lm[[landmark_index("Nose tip"), landmark_index("Chin middle")]]
                                    - scan.landmarks[[landmark_index("Nose tip"), landmark_index("Chin middle")]],
                                    axis=1)) < 4.0
    result = SkinModel(head).simulate(head.contractions_for({"4": 0.8}))
    brow = head.landmark_vertices[landmark_index("Inner left eyebrow")]
    assert result.settled and (result.vertices - head.vertices)[brow, 1] < -0.5  # the frown lowers the brow


def test_deform_from_vertices_reproduces_a_fitted_template(template):
    moved = template.vertices * 1.05 + np.array([1.0, 2.0, 3.0])
    mapping = deform_from_vertices(template, moved)
    assert np.abs(mapping(template.vertices) - moved).max() < 1e-3
    assert np.abs(mapping(template.skull_vertices) - (template.skull_vertices * 1.05 + [1, 2, 3])).max() < 1e-3


def test_simulate_command_fits_a_scan_and_writes_the_outputs(tmp_path, capsys):
    scan = datasets.make_face(datasets.random_identity(4), spacing_mm=1.0)
    io.write_bnt(tmp_path / "face.bnt", io.BntScan.from_points(scan.points, image_name="face.png"))
    io.write_lm3(tmp_path / "face.lm3", scan.landmarks)
    out, gif, png = tmp_path / "smile.npz", tmp_path / "smile.gif", tmp_path / "smile.png"
    coarse = tmp_path / "coarse_head.npz"  # the template at 5 mm: a quick test
    skin_template(5.0).save(coarse)
    assert main(["simulate", str(tmp_path / "face.bnt"), "--au", "12:0.4", "--jaw", "5", "--out", str(out),
                 "--gif", str(gif), "--png", str(png), "--mesh", str(tmp_path / "smile.obj"), "--quiet",
                 "--template", str(coarse)]) == 0
    data = np.load(out)
    assert data["vertices"].shape == data["neutral"].shape and np.isfinite(data["vertices"]).all()
    assert np.linalg.norm(data["vertices"] - data["neutral"], axis=1).max() > 1.0
    assert set(data["muscles"]) == {"zygomaticus_major_left", "zygomaticus_major_right"}
    assert data["frames"].shape[1:] == data["vertices"].shape and float(data["jaw_deg"]) == 5.0
    assert gif.stat().st_size > 1000 and png.stat().st_size > 1000
    # a fitted mesh works as well; errors are one line
    assert main(["simulate", "--fitted", str(tmp_path / "smile.obj"), "--contract", "mentalis=0.2", "--quiet",
                 "--out", str(tmp_path / "chin.npz"), "--template", str(coarse)]) == 0
    capsys.readouterr()
    assert main(["simulate", str(tmp_path / "face.bnt"), "--au", "12:2"]) == 2
    assert "contractions" in capsys.readouterr().err
    assert main(["simulate", "--au", "12"]) == 2
    assert "SCAN" in capsys.readouterr().err


def test_a_fit_keeps_the_tissue_as_deep_as_the_template_and_the_skin_settles():
    # rest, a full smile, a full frown and an open jaw on heads fitted to two generated faces
    # The fit's final snap once moved a chin's skin to 2 mm over the skull (9 mm on the
    # template) and the skin chattered without end: the skull now follows the snap
    # along each column, and only there (following it sideways folded skull triangles
    # over, and tissue caught behind one never came to rest).
    template = skin_template(5.0)
    shallowest = np.linalg.norm(template.vertices - template.skull_vertices, axis=1).min()

    def skull_face_normals(skull):
        corners = skull[template.faces]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        return cross / np.linalg.norm(cross, axis=1, keepdims=True)

    for identity in (7, 19):
        scan = datasets.make_face(datasets.random_identity(identity), noise_mm=0.1, seed=identity)
        grid = tpscore.resample_scan(scan.points, scan.landmarks)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            head, _ = physics.fit_head(grid, scan.landmarks, template)
        depth = np.linalg.norm(head.vertices - head.skull_vertices, axis=1)
        assert depth.min() > 0.8 * shallowest
        turn = np.einsum("ij,ij->i", skull_face_normals(head.skull_vertices),
                         skull_face_normals(template.skull_vertices))
        assert turn.min() > 0.5  # no skull triangle turned over (60 degrees at most)
        model = SkinModel(head)
        rest = model.simulate(None)
        assert rest.settled and np.abs(rest.vertices - head.vertices).max() < 0.5
        corner = head.landmark_vertices[landmark_index("Left mouth corner")]
        smile = model.simulate(head.contractions_for({"12": 1.0}))
        assert smile.settled and smile.scale == 1.0
        assert (smile.vertices - head.vertices)[corner, 1] > 3.0  # the corner rises
        brow = head.landmark_vertices[landmark_index("Inner left eyebrow")]
        frown = model.simulate(head.contractions_for({"4": 1.0}))
        assert frown.settled and (frown.vertices - head.vertices)[brow, 1] < -0.5  # the brow comes down
        chin = head.landmark_vertices[landmark_index("Chin middle")]
        jaw = model.simulate(None, jaw=10.0)
        assert jaw.settled and (jaw.vertices - head.vertices)[chin, 1] < -2.0  # the chin drops
