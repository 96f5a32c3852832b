"""Mesh operators on face-like height fields: tpscore against the NumPy reference.

Grid meshes of 150 x 150 and 300 x 300 vertices, two triangles per quad, with a
face-like height field (a broad dome and a nose-like bump), as produced by the
preprocessing stage.
"""
from __future__ import annotations

import numpy as np
import pytest

from tpscore import mesh
from tpscore.reference import mesh as reference

SIZES = [150, 300]


def face_like_grid(rows, cols):
    x, y = np.meshgrid(np.linspace(-75, 75, cols), np.linspace(-90, 90, rows))
    z = 60 * np.exp(-(x**2 / (2 * 55**2) + y**2 / (2 * 70**2))) + 18 * np.exp(
        -(x**2 / (2 * 9**2) + (y + 5) ** 2 / (2 * 16**2)))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return vertices, faces


_MESHES = {size: face_like_grid(size, size) for size in SIZES}


@pytest.mark.parametrize("size", SIZES)
def test_mean_curvature_tpscore(benchmark, size):
    benchmark.group = f"mean_curvature {size}x{size}"
    vertices, faces = _MESHES[size]
    result = benchmark(mesh.mean_curvature, vertices, faces)
    expected, _, _ = reference.mean_curvature(vertices, faces)
    np.testing.assert_allclose(result.values, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("size", SIZES)
def test_mean_curvature_numpy_reference(benchmark, size):
    benchmark.group = f"mean_curvature {size}x{size}"
    vertices, faces = _MESHES[size]
    values, _, boundary = benchmark(reference.mean_curvature, vertices, faces)
    assert np.isfinite(values[~boundary]).all()


@pytest.mark.parametrize("size", SIZES)
def test_cotan_laplacian_tpscore(benchmark, size):
    benchmark.group = f"cotan_laplacian {size}x{size}"
    vertices, faces = _MESHES[size]
    laplacian = benchmark(mesh.cotan_laplacian, vertices, faces)
    assert abs(laplacian - reference.cotan_laplacian(vertices, faces)).max() < 1e-12


@pytest.mark.parametrize("size", SIZES)
def test_cotan_laplacian_numpy_reference(benchmark, size):
    benchmark.group = f"cotan_laplacian {size}x{size}"
    vertices, faces = _MESHES[size]
    laplacian = benchmark(reference.cotan_laplacian, vertices, faces)
    assert laplacian.shape == (len(vertices), len(vertices))
