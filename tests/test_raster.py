"""The z-buffer rasteriser: compiled core against the NumPy reference, and pictures
whose answer is known (coverage of a square, the nearer of two planes, interpolation)."""
from __future__ import annotations

import numpy as np
import pytest

import tpscore
from tpscore import raster
from tpscore.face.image import bilinear
from tpscore.reference import raster as reference


def random_mesh(seed, n_vertices=400, n_faces=600, size=64):
    rng = np.random.default_rng(seed)
    pixels = rng.uniform(-5, size + 5, size=(n_vertices, 2))
    depth = rng.normal(size=n_vertices)
    faces = rng.integers(0, n_vertices, size=(n_faces, 3))
    return pixels, depth, faces


@pytest.mark.parametrize("seed", range(4))
def test_core_agrees_with_reference(seed):
    pixels, depth, faces = random_mesh(seed)
    triangle, barycentric = raster.rasterise(pixels, depth, faces, 64, 48)
    expected_triangle, expected_barycentric = reference.rasterise(pixels, depth, faces, 64, 48)
    np.testing.assert_array_equal(triangle, expected_triangle)
    # the weights come from the same formula; rounding differs only in the last bits
    np.testing.assert_allclose(barycentric, expected_barycentric, atol=1e-12)


def test_result_does_not_depend_on_thread_count():
    pixels, depth, faces = random_mesh(7, n_vertices=3000, n_faces=6000, size=400)
    try:
        tpscore.set_num_threads(1)
        one = raster.rasterise(pixels, depth, faces, 400, 300)
        tpscore.set_num_threads(3)
        three = raster.rasterise(pixels, depth, faces, 400, 300)
    finally:
        tpscore.set_num_threads(0)
    np.testing.assert_array_equal(one[0], three[0])
    np.testing.assert_array_equal(one[1], three[1])


def test_reference_does_not_depend_on_its_chunking(monkeypatch):
    # triangles covering the whole picture exceed a tiny chunk budget
    pixels = np.array([[0, 0], [64, 0], [64, 64], [0, 64], [32, 32]], dtype=float)
    depth = np.array([0, 0, 0, 0, 1.0])
    faces = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]
    expected = reference.rasterise(pixels, depth, faces, 64, 64)
    monkeypatch.setattr(reference, "CHUNK_CANDIDATES", 100)
    result = reference.rasterise(pixels, depth, faces, 64, 64)
    np.testing.assert_array_equal(result[0], expected[0])
    np.testing.assert_array_equal(result[1], expected[1])


def test_square_covers_exactly_its_pixel_centres():
    # a square from (2, 3) to (10, 7): centres (c + 0.5, r + 0.5) inside are columns
    # 2..9 and rows 3..6
    pixels = np.array([[2, 3], [10, 3], [10, 7], [2, 7]], dtype=float)
    triangle, _ = raster.rasterise(pixels, np.zeros(4), [[0, 1, 2], [0, 2, 3]], 16, 12)
    covered = triangle >= 0
    expected = np.zeros((12, 16), dtype=bool)
    expected[3:7, 2:10] = True
    np.testing.assert_array_equal(covered, expected)


def test_nearer_plane_wins_and_weights_interpolate():
    # two overlapping triangles; the second is nearer (larger depth) everywhere
    pixels = np.array([[0, 0], [20, 0], [0, 20], [0, 0], [20, 0], [0, 20]], dtype=float)
    depth = np.array([0, 0, 0, 1, 1, 1.0])
    triangle, barycentric = raster.rasterise(pixels, depth, [[0, 1, 2], [3, 4, 5]], 20, 20)
    assert set(np.unique(triangle[triangle >= 0])) == {1}
    # the weights reproduce the pixel centre
    r, c = np.nonzero(triangle >= 0)
    centre = np.einsum("nk,kd->nd", barycentric[r, c], pixels[3:])
    np.testing.assert_allclose(centre, np.column_stack([c + 0.5, r + 0.5]), atol=1e-12)


def test_equal_depths_go_to_the_lower_index():
    pixels = np.array([[0, 0], [8, 0], [0, 8]], dtype=float)
    triangle, _ = raster.rasterise(np.vstack([pixels, pixels]), np.zeros(6), [[3, 4, 5], [0, 1, 2]], 8, 8)
    assert set(np.unique(triangle[triangle >= 0])) == {0}


@pytest.mark.parametrize("kwargs, name", [
    (dict(pixels=[[0, 0], [1, 0]], depth=[0, 0]), "faces"),
    (dict(pixels=[[0, 0, 0], [1, 0, 0], [0, 1, 0]]), "pixels"),
    (dict(depth=[0, np.nan, 0]), "depth"),
    (dict(depth=[0, 0]), "depth"),
    (dict(width=0), "width"),
    (dict(height=2.5), "height"),
    (dict(width=100_000, height=100_000), "exceeds"),
])
def test_bad_input_is_rejected(kwargs, name):
    arguments = dict(pixels=[[0, 0], [1, 0], [0, 1]], depth=[0, 0, 0], faces=[[0, 1, 2]], width=4, height=4)
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=name):
        raster.rasterise(**arguments)


@pytest.mark.parametrize("channels", [None, 1, 4])
def test_interpolation_agrees_with_reference_and_reproduces_linear_values(channels):
    pixels, depth, faces = random_mesh(5, size=40)
    triangle, barycentric = raster.rasterise(pixels, depth, faces, 40, 40)
    rng = np.random.default_rng(1)
    values = rng.normal(size=(len(pixels),) if channels is None else (len(pixels), channels))
    got = raster.interpolate_pixels(values, faces, triangle, barycentric)
    np.testing.assert_allclose(got, reference.interpolate_pixels(values, faces, triangle, barycentric),
                               atol=1e-12, equal_nan=True)
    # a linear function of the pixel position is reproduced exactly at the centres
    linear = 2.0 + 0.5 * pixels[:, 0] - 0.25 * pixels[:, 1]
    at = raster.interpolate_pixels(linear, faces, triangle, barycentric)
    r, c = np.nonzero(triangle >= 0)
    np.testing.assert_allclose(at[r, c], 2.0 + 0.5 * (c + 0.5) - 0.25 * (r + 0.5), atol=1e-9)
    assert np.isnan(at[triangle < 0]).all()


def test_interpolation_rejects_a_foreign_raster():
    pixels, depth, faces = random_mesh(5, size=40)
    triangle, barycentric = raster.rasterise(pixels, depth, faces, 40, 40)
    with pytest.raises(ValueError, match="triangle refers"):
        raster.interpolate_pixels(np.zeros(len(pixels)), faces[:10], triangle, barycentric)
    with pytest.raises(ValueError, match="barycentric"):
        raster.interpolate_pixels(np.zeros(len(pixels)), faces, triangle, barycentric[..., :2])


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8])
@pytest.mark.parametrize("channels", [None, 1, 2, 3])
def test_bilinear_sampling_matches_the_reference_to_the_bit(dtype, channels):
    rng = np.random.default_rng(7)
    shape = (37, 53) if channels is None else (37, 53, channels)
    image = (rng.uniform(0, 255, shape) if dtype == np.uint8 else rng.normal(size=shape)).astype(dtype)
    # inside, on the last row and column, and beyond every border (clamped)
    x = np.concatenate([rng.uniform(-3, 56, 4000), [0.0, 52.0, 51.999999, 60.0, -1.0]])
    y = np.concatenate([rng.uniform(-3, 40, 4000), [0.0, 36.0, 35.5, -2.0, 50.0]])
    got = bilinear(image, x, y)
    expected = reference.bilinear(image, x, y)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert np.array_equal(got, expected)
    # (m,) coordinates given as a (k, l) grid keep their shape
    assert bilinear(image, x[:20].reshape(4, 5), y[:20].reshape(4, 5)).shape == (4, 5) + shape[2:]


def test_bilinear_sampling_refuses_what_it_cannot_read():
    image = np.zeros((4, 5), dtype=np.float32)
    with pytest.raises(ValueError, match="x and y must be finite"):
        bilinear(image, [1.0, np.nan], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"h, w >= 2, got \(1, 5\)"):
        bilinear(np.zeros((1, 5)), [0.0], [0.0])
