"""The demo faces: scans of the shipped ICT FaceKit extract, and their truth."""
import ast
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

import tpscore
from tpscore import load_scan
from tpscore.face.image import sample_image
from tpscore.showcase import demo_faces
from tpscore.spatial import MeshSurface


@pytest.fixture(scope="module")
def neutral():
    return demo_faces.make_demo_scan(0, None, noise_mm=0.0, pose_deg=4.0, seed=5)


def test_the_extract_is_small_and_carries_its_licence():
    data = resources.files("tpscore").joinpath("data")
    size = len(data.joinpath("ict_demo_faces.npz").read_bytes())
    assert size < 1_200_000
    licence = data.joinpath("ict_facekit_LICENSE.txt").read_text()
    assert "MIT License" in licence and "USC Institute for Creative Technologies" in licence
    model = demo_faces.load_demo_model()
    assert model.n_people >= 2 and len(model.faces) > 10_000
    assert sorted(model.au_shapes, key=int) == sorted(demo_faces.DEMO_AUS, key=int)
    # quantised to 0.01 mm, so a person's face is within that of a smooth model face:
    # the inner eye corners of everyone lie 30 to 45 mm apart
    for person in range(model.n_people):
        face = model.person(person)
        inner = face[model.bosphorus_index[[7, 8]]]
        assert 30.0 < np.linalg.norm(inner[0] - inner[1]) < 45.0


def test_depth_is_the_mesh_seen_from_the_front(neutral):
    # without noise, every valid point is where a ray down -z first meets the posed mesh
    scan = neutral.scan
    points = scan.points[scan.valid]
    pick = np.random.default_rng(0).choice(len(points), 400, replace=False)
    origins = points[pick] + [0.0, 0.0, 500.0]
    hits = MeshSurface(neutral.vertices, neutral.faces).intersect_rays(
        origins, np.tile([0.0, 0.0, -1.0], (len(pick), 1)))
    assert hits.hit.all()
    assert np.abs(hits.points[:, 2] - points[pick, 2]).max() < 1e-6
    # a real face: 30k to 50k points at 0.7 mm, with the eyes open (holes inside the face)
    assert 30_000 < scan.n_valid < 50_000


def test_written_scan_reads_back_with_its_image_and_landmarks(neutral, tmp_path):
    with pytest.raises(ValueError, match="stem"):
        neutral.write(tmp_path, "personne à droite")
    assert not list(tmp_path.iterdir())
    path = neutral.write(tmp_path, "person0")
    assert {p.name for p in tmp_path.iterdir()} == {"person0.bnt", "person0.lm3", "person0.png"}
    grid = load_scan(path)
    assert grid.image is not None and grid.image.shape == neutral.image.shape
    # landmarks are the mesh's landmark vertices plus 0.5 mm annotation noise, snapped
    # to the 150 x 150 grid (about 1.2 mm apart)
    model = demo_faces.load_demo_model()
    exact = neutral.vertices[model.bosphorus_index]
    assert np.linalg.norm(grid.landmarks - exact, axis=1).max() < 4.0
    # skin is lit skin colour; the background is dark grey
    colours = grid.colours[grid.mask]
    assert colours.mean() > 0.3
    assert (colours[:, 0] > colours[:, 2]).mean() > 0.95   # skin is redder than blue


def test_the_skin_pattern_moves_with_the_skin(neutral):
    # the colour at a vertex's place in the smiling scan matches its colour in the
    # neutral scan (the pattern is glued to the skin), better than the colour that
    # was at that place before the smile
    smile = demo_faces.make_demo_scan(0, {"12": 1.0}, noise_mm=0.0, pose_deg=4.0, seed=5)
    moved = np.linalg.norm(smile.vertices - neutral.vertices, axis=1)
    cheek = np.flatnonzero(moved > 3.0)
    assert len(cheek) > 100

    def colour_at(scan, points):
        # the image's pixel (R, C) sees x0 - s/2 + (C + 0.5) s / k (see make_demo_scan)
        valid = scan.scan.points[scan.scan.valid]
        uv = scan.scan.uv[scan.scan.valid]
        # u,v are affine in x, y on a depth grid: fit the map from the points
        design = np.column_stack([valid[:, :2], np.ones(len(valid))])
        affine, *_ = np.linalg.lstsq(design, uv, rcond=None)
        return sample_image(scan.image, np.column_stack([points[:, :2], np.ones(len(points))]) @ affine)

    before = colour_at(neutral, neutral.vertices[cheek])
    after = colour_at(smile, smile.vertices[cheek])
    stayed = colour_at(smile, neutral.vertices[cheek])

    def correlation(a, b):
        a, b = a.mean(axis=1), b.mean(axis=1)
        return np.corrcoef(a - a.mean(), b - b.mean())[0, 1]

    assert correlation(before, after) > 0.8
    assert correlation(before, after) > correlation(before, stayed) + 0.2


def test_true_positions_follow_the_expression(neutral):
    smile = demo_faces.make_demo_scan(0, {"12": 1.0}, noise_mm=0.0, pose_deg=4.0, seed=5)
    # same person, same seed and pose stream only when the expression is the same, so
    # compare against the expression applied in the neutral scan's pose instead
    model = demo_faces.load_demo_model()
    expected = neutral.vertices + model.expression_delta({"12": 1.0}) @ neutral.pose[:3, :3].T
    some = np.random.default_rng(1).choice(len(neutral.vertices), 300, replace=False)
    np.testing.assert_allclose(neutral.true_positions(neutral.vertices[some], {"12": 1.0}), expected[some],
                               atol=1e-6)
    assert np.linalg.norm(expected - neutral.vertices, axis=1).max() > 5.0   # a smile moves mm
    assert smile.expression == {"12": 1.0}


def test_one_sided_aus_move_one_side():
    model = demo_faces.load_demo_model()
    left = model.expression_delta({"12L": 1.0})
    both = model.expression_delta({"12": 1.0})
    x = model.neutral[:, 0]
    # the subject's left is +x; a few lip vertices across the midline follow a little
    size = np.linalg.norm(left, axis=1)
    assert size[x < -10].sum() < 0.05 * size[x > 10].sum()
    np.testing.assert_allclose(model.expression_delta({"12L": 1.0, "12R": 1.0}), both)


def test_scans_are_deterministic():
    a = demo_faces.make_demo_scan(1, "4", seed=3, holes=1)
    b = demo_faces.make_demo_scan(1, "4", seed=3, holes=1)
    np.testing.assert_array_equal(a.scan.points, b.scan.points)
    np.testing.assert_array_equal(a.image, b.image)
    assert repr(a).startswith("DemoScan(person 1, AU4, ")


@pytest.mark.parametrize("kwargs, message", [
    (dict(person=9), "person"),
    (dict(person=0, expression={"99": 1.0}), "unknown AU"),
    (dict(person=0, expression={"17L": 1.0}), "one-sided"),
    (dict(person=0, texture_scale=0), "texture_scale"),
    (dict(person=0, spacing_mm=-1), "spacing_mm"),
    (dict(person=0, holes=-1), "holes"),
])
def test_bad_input_names_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        demo_faces.make_demo_scan(**kwargs)


def test_the_method_never_reads_the_demo_faces():
    # the extract is for the demo only: nothing but the demo's own modules imports it
    package = Path(tpscore.__file__).parent
    allowed = {"demo_faces.py", "demo.py"}
    for source in package.rglob("*.py"):
        if source.name in allowed:
            continue
        tree = ast.parse(source.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [alias.name for alias in node.names]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            assert not any("demo_faces" in name for name in names), source
        assert "ict_demo_faces" not in source.read_text(), source
