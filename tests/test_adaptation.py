"""Template adaptation on procedural surfaces (no external data)."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

import tpscore
from tpscore import cli
from tpscore.adaptation import AdaptationWarning, AdaptOptions, adapt
from tpscore.adaptation.calibration import axes_calibration, calibrate, rotation_angles
from tpscore.adaptation.correspondence import curvature_features, self_occluded, triangulate_features
from tpscore.geometry import spread_vertices
from tpscore.adaptation.fill import fill_unseen_offsets
from tpscore.adaptation.setup import find_outlier_landmarks
from tpscore.adaptation.surface import SurfaceOffset, fit_surface_offset
from tpscore.face import io
from tpscore.face.grid import FaceGrid
from tpscore.face.landmarks import landmark_index
from tpscore.showcase import datasets
from tpscore.spatial import MeshSurface


def _face(identity=0, **kwargs):
    scan = datasets.make_face(identity, spacing_mm=2.0, **kwargs)
    grid = FaceGrid.from_points(scan.points, None, scan.landmarks)
    return scan, grid


def _template_from(grid):
    """(vertices, faces, landmark vertex indices) of a FaceGrid's mesh."""
    mesh = grid.mesh()
    remap = {int(g): i for i, g in enumerate(mesh.grid_index)}
    index = np.array([remap.get(int(v), -1) for v in grid.landmark_vertices])
    return mesh.vertices, mesh.faces, index


def _rotation(ax, ay, az):
    ax, ay, az = np.radians([ax, ay, az])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


# --------------------------------------------------------------------------- calibration

def test_rotation_angles_round_trip():
    angles = np.array([7.0, -12.0, 25.0])
    # exact up to rounding: arcsin/arctan2 of entries of a product of three rotations
    assert np.allclose(rotation_angles(_rotation(*angles)), angles, atol=1e-9)


@pytest.mark.parametrize("method", ["axes", "similarity"])
def test_calibration_undoes_a_similarity(method):
    _, grid = _face(1)
    landmarks = grid.landmarks
    rotation = _rotation(5.0, -8.0, 3.0)
    moved = 1.1 * landmarks @ rotation.T + np.array([10.0, -4.0, 30.0])
    transform = calibrate(moved, landmarks, method)
    # the same face moved rigidly and scaled: both calibrations recover it (the axes
    # are built from the same landmarks on both sides), to rounding
    assert np.allclose(transform.apply(moved), landmarks, atol=1e-6)


def test_axes_calibration_parts():
    _, grid = _face(2)
    landmarks = grid.landmarks
    rotation = _rotation(0.0, 10.0, 0.0)
    calib = axes_calibration(landmarks @ rotation.T, landmarks)
    # a pure 10 degree yaw of the scan is undone by a -10 degree y angle
    assert np.allclose(calib.angles_deg, [0.0, -10.0, 0.0], atol=1e-6)
    assert calib.scale == pytest.approx(1.0, abs=1e-9)


def test_calibration_errors():
    _, grid = _face(0)
    empty = np.full((22, 3), np.nan)
    with pytest.raises(ValueError, match="x axis"):
        axes_calibration(empty, grid.landmarks)
    with pytest.raises(ValueError, match="calibration must be"):
        calibrate(grid.landmarks, grid.landmarks, "bogus")


# --------------------------------------------------------------------------- correspondences

def test_curvature_search_finds_nose_tip_and_lips():
    _, grid = _face(3)
    vertices, faces, _ = _template_from(grid)
    found = curvature_features(vertices, faces, 80, spacing=4.0, sign="absolute")
    points = vertices[found]
    landmarks = grid.landmarks
    # 80 features at least 4 mm apart on a 2 mm grid. The nose tip and the mouth
    # corners are curvature maxima themselves (a grid step away at most); on the lips
    # the largest curvature runs along the vermilion ridges, a few mm from the midline
    # landmarks. Flat regions (cheeks, forehead) lie tens of mm from all of these.
    limits = {"Nose tip": 2.5, "Left mouth corner": 2.5, "Upper lip outer middle": 8.0,
              "Lower lip outer middle": 8.0}
    for name, limit in limits.items():
        distance = np.linalg.norm(points - landmarks[landmark_index(name)], axis=1).min()
        assert distance < limit, (name, distance)
    assert len(np.unique(found)) == len(found)
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1) + np.eye(len(points)) * 1e9
    assert gaps.min() >= 4.0


def test_spread_vertices_are_spread():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 100, size=(5000, 3))
    chosen = spread_vertices(points, 10.0)
    # one per occupied 10 mm cube: about 1000 cubes in 100^3, nearly all occupied
    assert 900 <= len(chosen) <= 1000
    assert len(np.unique(np.floor(points[chosen] / 10), axis=0)) == len(chosen)


def test_triangulate_features_orientation():
    _, grid = _face(0)
    lm = grid.landmarks[np.isfinite(grid.landmarks).all(axis=1)]
    triangles = triangulate_features(lm)
    a, b, c = (lm[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert (normals[:, 2] > 0).all()


def test_outlier_landmark_found():
    _, grid = _face(4)
    lm = grid.landmarks.copy()
    moved = lm.copy()
    moved[landmark_index("Left mouth corner")] += [30.0, 0.0, 0.0]
    assert find_outlier_landmarks(lm, moved, threshold=15.0) == [landmark_index("Left mouth corner")]
    assert find_outlier_landmarks(lm, lm, threshold=15.0) == []


# --------------------------------------------------------------------------- adaptation

def test_affine_copy_is_near_exact():
    _, grid = _face(5)
    vertices, faces, index = _template_from(grid)
    matrix = np.array([[1.05, 0.03, 0.0], [-0.02, 0.97, 0.04], [0.01, 0.0, 1.02]])
    moved = vertices @ matrix.T + np.array([3.0, -2.0, 5.0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AdaptationWarning)
        options = AdaptOptions(calibration="none", levels=4)
        result = adapt((vertices, faces), (moved, faces), index, moved[index],
                       options=replace(options, fill_unseen=False))
        filled = adapt((vertices, faces), (moved, faces), index, moved[index], options=options)
        interpolated = adapt((vertices, faces), (moved, faces), index, moved[index],
                             options=AdaptOptions.published(calibration="none", levels=4))
    # an affine map is in the span of the RBF's affine part: level 0 reproduces it
    # whatever rho, and the refinement levels then see zero residuals (solver rounding)
    for fit in (result, interpolated):
        error = np.linalg.norm(fit.vertices - moved, axis=1)
        assert error.max() < 0.05, error.max()
    assert result.vertices.shape == vertices.shape
    # the mesh fill of unpaired vertices does not reproduce a linear field on a curved
    # surface exactly; for this 5% shear it moves them by a fraction of a millimetre
    # (about 0.33 mm at most with the harmonic fill)
    error = np.linalg.norm(filled.vertices - moved, axis=1)
    assert error.max() < 0.4, error.max()
    assert np.sqrt(np.mean(error**2)) < 0.05


def _sphere(radius=50.0, n=40):
    theta = np.linspace(0.15, np.pi / 2, n)
    phi = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    points = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    faces = []
    m = 2 * n
    for i in range(n - 1):
        for j in range(m):
            a, b, c, d = i * m + j, i * m + (j + 1) % m, (i + 1) * m + j, (i + 1) * m + (j + 1) % m
            faces += [[a, c, b], [b, c, d]]
    return radius * points, np.array(faces)


def test_sphere_adapts_to_ellipsoid():
    sphere, faces = _sphere()
    axes = np.array([60.0, 45.0, 55.0]) / 50.0
    ellipsoid = sphere * axes
    rng = np.random.default_rng(1)
    features = rng.choice(len(sphere), 30, replace=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AdaptationWarning)
        result = adapt((sphere, faces), (ellipsoid, faces), features, ellipsoid[features] + 0.0,
                       options=AdaptOptions(calibration="none", levels=5, scan_view=None, feature_box=None))
    # distance of each fitted vertex to the ellipsoid surface, |x/a|^2 + ... = 1
    level = np.sqrt(np.sum((result.vertices / (50.0 * axes)) ** 2, axis=1))
    off_surface = np.abs(level - 1.0) * 50.0
    # the axes differ by up to 10 mm from the sphere; the fit lands within 0.5 mm
    assert np.percentile(off_surface, 95) < 0.5, np.percentile(off_surface, 95)
    assert len(result.levels) >= 2


def _adapt_faces(scan_kwargs=None, landmarks=None, **options):
    _, template_grid = _face(10)
    scan, scan_grid = _face(11, **(scan_kwargs or {}))
    vertices, faces, index = _template_from(template_grid)
    lm = scan.landmarks if landmarks is None else landmarks
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = adapt((vertices, faces), scan_grid, index, lm, options=AdaptOptions(**options))
    return result, [str(w.message) for w in caught if issubclass(w.category, AdaptationWarning)], scan


def _scan_distance(result):
    """Median distance (mm) of the fitted vertices to the scan of :func:`_adapt_faces`."""
    _, scan_grid = _face(11)
    scan = scan_grid.mesh()
    return float(np.median(MeshSurface(scan.vertices, scan.faces).closest_point(result.vertices).distances))


def test_adapt_faces_improves_on_landmark_rbf():
    result, _, _ = _adapt_faces(levels=5, stop_at_minimum=False)
    errors = [lv.distance_error for lv in result.levels]
    # the refinement levels bring the template onto the scan's surface (the two
    # procedural identities differ by a few mm; Ed falls by about half)
    assert min(errors[1:]) < 0.7 * errors[0]
    assert result.levels[result.best_level].error == min(lv.error for lv in result.levels)
    assert set(result.correspondences.source) == {"surface"}
    interpolated, _, _ = _adapt_faces(levels=5, stop_at_minimum=False, refinement="interpolate",
                                      calibration="axes")
    errors = [lv.distance_error for lv in interpolated.levels]
    # the published pairs (feature mesh and curvature vertices) cover less of the face than
    # the surface levels' visible vertices: Ed falls by about 30 % (1.52 -> 1.07 mm^2)
    assert min(errors[1:]) < 0.75 * errors[0]
    assert set(interpolated.correspondences.source) >= {"landmark", "feature-mesh"}
    # the snap (default) lands the visible vertices on the scan's tangent planes: the fit
    # ends closer to the scan than without it
    unsnapped, _, _ = _adapt_faces(levels=5, stop_at_minimum=False, snap=False)
    assert _scan_distance(result) < 0.8 * _scan_distance(unsnapped), (_scan_distance(result),
                                                                     _scan_distance(unsnapped))


def test_defective_noise_warns():
    result, messages, _ = _adapt_faces({"noise_mm": 1.5, "seed": 3})
    assert any("noisy" in m for m in messages)
    assert np.isfinite(result.vertices).all()


def test_defective_missing_landmarks_warns():
    _, _, scan = _adapt_faces()
    lm = scan.landmarks.copy()
    lm[[landmark_index("Nose tip"), landmark_index("Left mouth corner")]] = np.nan
    result, messages, _ = _adapt_faces(landmarks=lm)
    assert any("missing" in m and "Nose tip" in m for m in messages)
    assert np.isfinite(result.vertices).all()


def test_defective_holes_warn():
    result, messages, _ = _adapt_faces({"holes": 60, "seed": 5})
    assert any("scan data" in m for m in messages)
    assert np.isfinite(result.vertices).all()


def test_defective_wrong_landmark_warns_and_is_left_out():
    _, _, scan = _adapt_faces()
    lm = scan.landmarks.copy()
    lm[landmark_index("Left mouth corner")] += [30.0, 10.0, 0.0]
    result, messages, _ = _adapt_faces(landmarks=lm)
    assert landmark_index("Left mouth corner") in result.outlier_landmarks
    assert any("Left mouth corner" in m for m in messages)


def test_held_out_markers_give_marker_error():
    result, _, _ = _adapt_faces(held_out_landmarks=("Nose saddle left", "Nose saddle right"), levels=3)
    assert all(np.isfinite(lv.marker_error) for lv in result.levels)
    without, _, _ = _adapt_faces(levels=2)
    assert all(np.isnan(lv.marker_error) for lv in without.levels)


def test_rigid_part_moves_rigidly():
    _, template_grid = _face(10)
    vertices, faces, index = _template_from(template_grid)
    eye = index[landmark_index("Outer left eye corner")]
    part = np.flatnonzero(np.linalg.norm(vertices - vertices[eye], axis=1) < 8.0)
    result, _, _ = _adapt_faces(rigid_parts=[part])
    before = vertices[part]
    after = result.template_frame_vertices[part]
    # pairwise distances scale uniformly under a similarity
    d0 = np.linalg.norm(before[:, None] - before[None], axis=-1)
    d1 = np.linalg.norm(after[:, None] - after[None], axis=-1)
    ratio = d1[d0 > 1] / d0[d0 > 1]
    assert np.ptp(ratio) < 1e-9


def test_bad_arguments():
    _, grid = _face(0)
    vertices, faces, index = _template_from(grid)
    with pytest.raises(ValueError, match="scan_landmarks must have shape"):
        adapt((vertices, faces), (vertices, faces), index, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="options must be an AdaptOptions"):
        adapt((vertices, faces), (vertices, faces), index, vertices[index], options={"levels": 3})
    with pytest.raises(ValueError, match="template must be"):
        adapt(42, (vertices, faces), index, vertices[index])
    with pytest.raises(ValueError, match="at least 5"):
        lm = np.full((22, 3), np.nan)
        lm[:3] = vertices[index[:3]]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AdaptationWarning)
            adapt((vertices, faces), (vertices, faces), index, lm, options=AdaptOptions(calibration="none"))


def test_cli_adapt_end_to_end(tmp_path):
    _, template_grid = _face(10)
    scan, scan_grid = _face(11)
    mesh = template_grid.mesh()
    io.write_mesh(tmp_path / "template.obj", mesh.vertices, mesh.faces)
    remap = {int(g): i for i, g in enumerate(mesh.grid_index)}
    io.write_lm3(tmp_path / "template.lm3", template_grid.landmarks)
    io.write_bnt(tmp_path / "scan.bnt", io.BntScan.from_points(scan.points))
    io.write_lm3(tmp_path / "scan.lm3", scan.landmarks)
    out = tmp_path / "fitted.obj"
    status = cli.main(["adapt", str(tmp_path / "template.obj"), str(tmp_path / "scan.bnt"),
                       "--template-landmarks", str(tmp_path / "template.lm3"),
                       "--scan-landmarks", str(tmp_path / "scan.lm3"), "--out", str(out),
                       "--png", str(tmp_path / "fit.png"), "--levels", "3"])
    assert status == 0
    fitted, fitted_faces = io.read_mesh(out)
    assert fitted.shape == mesh.vertices.shape
    assert np.array_equal(fitted_faces, mesh.faces)
    assert (tmp_path / "fit.png").stat().st_size > 0
    assert remap  # the template's landmarks were snapped to its own vertices
    status = cli.main(["adapt", str(tmp_path / "missing.obj"), str(tmp_path / "scan.bnt"),
                       "--template-landmarks", str(tmp_path / "template.lm3"),
                       "--scan-landmarks", str(tmp_path / "scan.lm3"), "--out", str(out)])
    assert status == 2


# --------------------------------------------------------------------------- surface refinement

def _grid_mesh(height, half=40.0, spacing=1.0):
    """A height field z = height(x, y) over a square, as (vertices, faces) facing +z."""
    axis = np.arange(-half, half + spacing / 2, spacing)
    x, y = np.meshgrid(axis, axis, indexing="xy")
    vertices = np.stack([x, y, height(x, y)], axis=-1).reshape(-1, 3)
    n = len(axis)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return vertices, np.array(faces, dtype=np.int64)


def _bump(shift):
    return lambda x, y: 8.0 * np.exp(-((x - shift) ** 2 + y**2) / (2 * 6.0**2))


def test_surface_refinement_lands_on_the_scan_and_keeps_the_feature_points():
    template, faces = _grid_mesh(_bump(0.0))
    scan, _ = _grid_mesh(_bump(3.0))
    # feature points on the flat border (where template and scan agree) and the apexes
    apex = int(np.argmax(template[:, 2]))
    corners = np.array([np.argmin(np.linalg.norm(template - p, axis=1)) for p in
                        ([-35, -35, 0], [35, -35, 0], [-35, 35, 0], [35, 35, 0], [0, -35, 0], [0, 35, 0])]
                       + [apex])
    scan_landmarks = scan[corners]
    scan_landmarks[-1] = scan[int(np.argmax(scan[:, 2]))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AdaptationWarning)
        result = adapt((template, faces), (scan, faces), corners, scan_landmarks,
                       options=AdaptOptions(calibration="none", rho=0.0))
    inner = np.abs(template[:, :2]).max(axis=1) < 30.0
    distance = MeshSurface(scan, faces).closest_point(result.vertices[inner]).distances
    # the 3 mm shift of the bump puts its flanks up to about 2 mm off the scan; level 0
    # (the feature points' RBF) cannot follow that, the point-to-plane levels bring
    # every vertex within 0.1 mm
    assert distance.max() < 0.1, distance.max()
    assert result.best_level >= 1
    # the feature points stay where they were put (the surface agrees with them here)
    assert np.linalg.norm(result.vertices[apex] - scan_landmarks[-1]) < 0.3


def test_fit_surface_offset_moves_along_the_normal_only_on_a_plane():
    template, faces = _grid_mesh(lambda x, y: 0.0 * x, half=20.0, spacing=2.0)
    centres = template[spread_vertices(template, 5.0)]
    field = SurfaceOffset(centres, np.zeros((len(centres), 3)), 15.0)
    targets = template + np.array([0.7, -0.4, 2.0])  # a plane 2 mm up, paired with a slide
    normals = np.tile([0.0, 0.0, 1.0], (len(template), 1))
    coefficients = fit_surface_offset(field, template, template, targets, normals, regularisation=0.1)
    offsets = field.plus(coefficients)(template)
    inner = np.abs(template[:, :2]).max(axis=1) < 10.0
    # the z shift is asked for everywhere and met inside (the border lacks support) up
    # to a ripple: sums of Wendland functions do not reproduce a constant exactly and
    # the regulariser pulls toward 0 between the centres (measured about 0.1 mm)
    assert np.allclose(offsets[inner, 2], 2.0, atol=0.15), offsets[inner, 2].min()
    assert abs(offsets[inner, 2].mean() - 2.0) < 0.05
    assert np.abs(offsets[:, :2]).max() < 1e-6


def test_self_occluded_finds_what_an_overhang_hides():
    lower, lower_faces = _grid_mesh(lambda x, y: 0.0 * x, half=10.0, spacing=1.0)
    upper = lower[lower[:, 0] <= 0] + np.array([0.0, 0.0, 5.0])
    upper_index = np.full(len(lower), -1)
    upper_index[lower[:, 0] <= 0] = np.arange(len(upper)) + len(lower)
    upper_faces = upper_index[lower_faces]
    upper_faces = upper_faces[(upper_faces >= 0).all(axis=1)]
    vertices = np.vstack([lower, upper])
    faces = np.vstack([lower_faces, upper_faces])
    hidden = self_occluded(vertices, faces, (0.0, 0.0, 1.0))
    # lower vertices with x < 0 lie under the overhang; x > 0 and the overhang are open
    # (x = 0 sits under its edge, which counts as inside: either answer is right)
    assert hidden[: len(lower)][lower[:, 0] < -0.5].all()
    assert not hidden[: len(lower)][lower[:, 0] > 0.5].any()
    assert not hidden[len(lower):].any()


def test_fill_unseen_offsets_reproduces_a_linear_field_on_a_flat_mesh():
    vertices, faces = _grid_mesh(lambda x, y: 0.0 * x, half=10.0, spacing=1.0)
    linear = vertices @ np.array([[0.1, 0.0, 0.02], [0.0, -0.05, 0.03], [0.0, 0.0, 0.0]]) + 1.0
    anchored = np.linalg.norm(vertices[:, :2], axis=1) > 4.0  # a hole in the middle
    start = np.where(anchored[:, None], linear, 0.0)
    filled = fill_unseen_offsets(vertices, faces, start, anchored)
    # cotangent Laplacian of a linear function vanishes on a flat mesh: the harmonic
    # fill is exact up to the solver's rounding (and the 1e-9 regularising diagonal)
    assert np.allclose(filled, linear, atol=1e-6)
    assert np.array_equal(filled[anchored], linear[anchored])


def test_fill_unseen_offsets_harmonic_stays_within_the_rim_values():
    # a bumpy rim: the harmonic fill obeys the maximum principle (a biharmonic one may
    # overshoot, which is why adapt fills harmonically)
    vertices, faces = _grid_mesh(lambda x, y: 0.0 * x, half=10.0, spacing=1.0)
    angle = np.arctan2(vertices[:, 1], vertices[:, 0])
    values = np.stack([np.sin(3 * angle), np.cos(2 * angle), 0.5 * np.sin(angle)], axis=1)
    anchored = np.linalg.norm(vertices[:, :2], axis=1) > 5.0
    start = np.where(anchored[:, None], values, 0.0)
    filled = fill_unseen_offsets(vertices, faces, start, anchored)
    rim = values[anchored]
    # 1e-9: the regularising diagonal and the solver's rounding
    assert np.all(filled[~anchored] <= rim.max(axis=0) + 1e-9)
    assert np.all(filled[~anchored] >= rim.min(axis=0) - 1e-9)


@pytest.mark.parametrize("field, value", [
    ("levels", 0), ("levels", 2.5), ("refinement", "nearest"), ("calibration", "bogus"), ("rho", -1.0),
    ("regularisation", 0.0), ("landmark_weight", -1.0), ("surface_iterations", 0), ("centre_spacing", np.nan),
    ("snap_rings", -1), ("snap", "yes"), ("fill_unseen", 1), ("curvature_count", -5), ("outlier_threshold", 0.0),
    ("alpha", np.inf), ("min_support", -2.0), ("scan_view", (0.0, 0.0, 0.0)), ("feature_box", ("Nose tip", "Ear")),
    ("held_out_landmarks", ("Nose tip", -1)), ("markers", np.zeros((3, 3))), ("vertex_weights", [1.0, -1.0]),
    ("rigid_parts", [[0.5, 1.5]]),
])
def test_options_refuse_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"AdaptOptions\.{field}\b"):
        AdaptOptions(**{field: value})
    with pytest.raises(ValueError, match=field):
        replace(AdaptOptions(), **{field: value})


def test_options_published_is_the_interpolated_scheme_with_the_axes_calibration():
    published = AdaptOptions.published()
    assert (published.refinement, published.calibration) == ("interpolate", "axes")
    assert AdaptOptions.published(calibration="none").calibration == "none"
    assert AdaptOptions() == AdaptOptions()


def test_options_data_fields_fit_the_template():
    _, grid = _face(0)
    vertices, faces, index = _template_from(grid)
    for bad in (dict(vertex_weights=np.ones(3)), dict(rigid_parts=[[len(vertices)]]),
                dict(held_out_landmarks=(40,))):
        name = next(iter(bad))
        with pytest.raises(ValueError, match=name):
            adapt((vertices, faces), (vertices, faces), index, vertices[index], options=AdaptOptions(**bad))
