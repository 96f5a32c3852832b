"""Mesh operators: compiled core against the NumPy reference, and analytic truths
(sphere curvature 1/R, flat meshes, symmetry and null space of the Laplacian)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import tpscore
from tpscore import mesh
from tpscore.reference import mesh as reference


def grid_mesh(rows, cols, *, spacing=1.0):
    """A flat rows x cols grid in the plane z = 0, two triangles per quad, +z normals."""
    x, y = np.meshgrid(np.arange(cols) * spacing, np.arange(rows) * spacing)
    vertices = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3).astype(float)
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return vertices, faces


def grid_border(rows, cols):
    border = np.zeros((rows, cols), dtype=bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    return border.reshape(-1)


def perturbed_grid(rows, cols, seed, jitter, height):
    """A grid with jittered x, y (keeps triangles oriented: jitter < half the spacing)
    and a random height field; some triangles become obtuse."""
    rng = np.random.default_rng(seed)
    vertices, faces = grid_mesh(rows, cols, spacing=2.0)
    vertices[:, :2] += rng.uniform(-jitter, jitter, size=(len(vertices), 2))
    vertices[:, 2] = rng.uniform(-height, height, size=len(vertices))
    return vertices, faces


def face_like_grid(rows, cols):
    x, y = np.meshgrid(np.linspace(-75, 75, cols), np.linspace(-90, 90, rows))
    z = 60 * np.exp(-(x**2 / (2 * 55**2) + y**2 / (2 * 70**2))) + 18 * np.exp(
        -(x**2 / (2 * 9**2) + (y + 5) ** 2 / (2 * 16**2)))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    _, faces = grid_mesh(rows, cols)
    return vertices, faces


def assert_all_match_reference(vertices, faces):
    n = len(vertices)
    scale = max(1.0, float(np.abs(vertices).max()))
    # Same formulas, different summation order: agreement to a few ulps of the
    # largest term; 1e-10 relative leaves room for the cancellation in L_ii.
    np.testing.assert_allclose(mesh.face_normals(vertices, faces),
                               reference.face_normals(vertices, faces), rtol=0, atol=1e-12)
    for weighting in ("area", "angle", "uniform"):
        # a normal amplifies rounding by its total weight over its sum's length (large at a
        # fold of a jittered grid, where its faces' normals nearly cancel)
        total, total_weight = reference.vertex_normal_sums(vertices, faces, weighting)
        with np.errstate(divide="ignore", invalid="ignore"):
            amplification = np.nan_to_num(total_weight / np.linalg.norm(total, axis=1), nan=1.0, posinf=1.0)
        error = np.abs(mesh.vertex_normals(vertices, faces, weighting=weighting)
                       - reference.vertex_normals(vertices, faces, weighting))
        assert (error <= 1e-10 + 1e-13 * amplification[:, None]).all(), weighting
    laplacian = mesh.cotan_laplacian(vertices, faces)
    expected = reference.cotan_laplacian(vertices, faces)
    assert laplacian.shape == (n, n)
    weight_scale = max(1.0, float(np.abs(expected).max()))
    assert abs(laplacian - expected).max() <= 1e-10 * weight_scale
    np.testing.assert_allclose(mesh.voronoi_areas(vertices, faces),
                               reference.voronoi_areas(vertices, faces), rtol=1e-10,
                               atol=1e-10 * scale**2)
    np.testing.assert_array_equal(mesh.boundary_vertices(faces, n),
                                  reference.boundary_vertices(faces, n))
    result = mesh.mean_curvature(vertices, faces)
    h, k, boundary = reference.mean_curvature(vertices, faces)
    np.testing.assert_array_equal(result.boundary, boundary)
    np.testing.assert_array_equal(np.isnan(result.values), np.isnan(h))
    # H = |K| / 2 with K = -(L x) / A: the same 1e-10 relative budget, scaled by |K|.
    h_scale = np.nanmax(np.abs(h), initial=1)
    np.testing.assert_allclose(np.abs(result.values), np.abs(h), rtol=1e-9, atol=1e-9 * h_scale)
    # The sign of H is that of K . n: compare it only where K is not (nearly) tangent,
    # since rounding decides the sign of a dot product of orthogonal vectors (it
    # happens in triangle soups, whose normals can cancel).
    unit_normal = reference.vertex_normals(vertices, faces, "area")
    with np.errstate(invalid="ignore"):
        clear_sign = np.abs(np.einsum("ij,ij->i", k, unit_normal)) > 1e-6 * np.linalg.norm(k, axis=1)
    np.testing.assert_allclose(result.values[clear_sign], h[clear_sign], rtol=1e-9, atol=1e-9 * h_scale)
    np.testing.assert_allclose(result.normals, k, rtol=1e-9, atol=1e-9 * np.nanmax(np.abs(k), initial=1))


# --- agreement with the reference ------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 9), cols=st.integers(2, 9), seed=st.integers(0, 2**32 - 1),
       jitter=st.floats(0, 0.9), height=st.floats(0, 5))
def test_matches_reference_on_perturbed_grids(rows, cols, seed, jitter, height):
    vertices, faces = perturbed_grid(rows, cols, seed, jitter, height)
    assert_all_match_reference(vertices, faces)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(2, 12), cols=st.integers(2, 12), seed=st.integers(0, 2**32 - 1),
       density=st.floats(0, 1))
def test_grid_triangles_match_reference(rows, cols, seed, density):
    # random masks hold every quad case: four, three (each corner missing), two or
    # fewer valid corners
    valid = np.random.default_rng(seed).random((rows, cols)) < density
    grid = tpscore.FaceGrid.from_points(np.zeros((rows, cols, 3)), mask=valid)
    triangles = grid.triangles()
    assert triangles.dtype == np.int64 and triangles.shape[1] == 3
    np.testing.assert_array_equal(triangles, reference.grid_triangles(valid))
    assert valid.reshape(-1)[triangles].all()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_faces=st.integers(1, 60), n_vertices=st.integers(3, 25))
def test_matches_reference_on_random_triangle_soups(seed, n_faces, n_vertices):
    # Arbitrary index triples: non-manifold edges, collapsed faces (repeated indices),
    # unreferenced vertices, inconsistent orientation, and coincident positions.
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(n_vertices, 3))
    vertices[rng.integers(0, n_vertices, size=n_vertices // 4)] = vertices[0]
    faces = rng.integers(0, n_vertices, size=(n_faces, 3))
    assert_all_match_reference(vertices, faces)
    for array in (mesh.cotan_laplacian(vertices, faces).data, mesh.voronoi_areas(vertices, faces),
                  mesh.vertex_normals(vertices, faces)):
        assert np.isfinite(array).all()


def test_matches_reference_on_face_like_height_field():
    vertices, faces = face_like_grid(40, 30)
    assert_all_match_reference(vertices, faces)


def test_sphere_matches_reference():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=7.0)
    assert_all_match_reference(np.asarray(sphere.vertices), np.asarray(sphere.faces))


# --- analytic truths ------------------------------------------------------------

@pytest.mark.parametrize("subdivisions, tolerance", [(2, 5e-4), (3, 1e-4), (4, 3e-5)])
def test_icosphere_mean_curvature_is_one_over_radius(subdivisions, tolerance):
    # Vertices lie exactly on the sphere; the measured relative error of Meyer's
    # operator is 1.4e-4, 3.5e-5, 8.7e-6 at subdivisions 2, 3, 4 (about 4x smaller per
    # level, second order): each tolerance is ~3.5x the measured error.
    radius = 25.0
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    result = mesh.mean_curvature(sphere.vertices, sphere.faces)
    assert not result.boundary.any()
    np.testing.assert_allclose(result.values, 1 / radius, rtol=tolerance)
    # K = 2 H n points outward along the radius: 1 - cos(angle to the radius) measures
    # 1.4e-4, 3.5e-5, 8.7e-6 (the angle itself is ~1 degree at subdivision 2).
    radial = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    cosine = np.einsum("ij,ij->i", result.normals, radial) / np.linalg.norm(result.normals, axis=1)
    assert (1 - cosine).max() < tolerance


def test_inward_oriented_sphere_has_negative_curvature():
    radius = 4.0
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    flipped = np.asarray(sphere.faces)[:, ::-1]
    result = mesh.mean_curvature(sphere.vertices, flipped)
    np.testing.assert_allclose(result.values, -1 / radius, rtol=1e-4)  # as above


def test_uv_sphere_mean_curvature_including_poles():
    # Long thin triangles near the poles; the measured worst relative error is 2.7e-4.
    radius = 25.0
    sphere = trimesh.creation.uv_sphere(radius=radius, count=[64, 64])
    result = mesh.mean_curvature(sphere.vertices, sphere.faces)
    assert not result.boundary.any()
    np.testing.assert_allclose(result.values, 1 / radius, rtol=1e-3)


def test_open_sphere_cap_interior_curvature_and_boundary_nan():
    radius = 10.0
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    cap = faces[(vertices[faces][:, :, 2] > 0.3 * radius).all(axis=1)]
    used = np.zeros(len(vertices), dtype=bool)
    used[cap.reshape(-1)] = True
    result = mesh.mean_curvature(vertices, cap)
    rim = result.boundary
    assert rim.any() and (rim <= used).all()
    # The rim is where z is smallest among the cap's vertices (it is a loop at the cut).
    assert vertices[rim, 2].max() < vertices[used & ~rim, 2].min() + 1.0
    assert np.isnan(result.values[rim]).all() and np.isnan(result.normals[rim]).all()
    interior = used & ~rim
    np.testing.assert_allclose(result.values[interior], 1 / radius, rtol=1e-4)  # as the icosphere
    # Unused vertices have no area: NaN, not boundary.
    assert np.isnan(result.values[~used]).all() and not rim[~used].any()


def test_vertex_normals_of_sphere_point_radially():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=3.0)
    radial = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    for weighting in ("area", "angle", "uniform"):
        normals = mesh.vertex_normals(sphere.vertices, sphere.faces, weighting=weighting)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-12)
        # Measured worst 0.99993 at subdivision 3 (faces are not all alike).
        assert np.einsum("ij,ij->i", normals, radial).min() > 0.9995


def test_face_normals_of_sphere_point_outward_and_are_unit():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    normals = mesh.face_normals(sphere.vertices, sphere.faces)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-12)
    centroids = sphere.vertices[sphere.faces].mean(axis=1)
    assert (np.einsum("ij,ij->i", normals, centroids) > 0).all()


@pytest.mark.parametrize("jitter", [0.0, 0.8])
def test_plane_has_zero_curvature_and_laplacian_kills_linear_functions(jitter):
    rows, cols = 9, 12
    vertices, faces = perturbed_grid(rows, cols, seed=3, jitter=jitter, height=0)
    # Tilt the plane: the operators are rotation invariant.
    rotation = trimesh.transformations.rotation_matrix(0.7, [1, 2, 0.5])[:3, :3]
    vertices = vertices @ rotation.T + [4.0, -2.0, 9.0]
    border = grid_border(rows, cols)
    result = mesh.mean_curvature(vertices, faces)
    np.testing.assert_array_equal(result.boundary, border)
    # Linear precision of the cotangent weights: exactly 0 up to rounding of
    # coordinates ~20 mm with weights ~1 (1e-12 is ~5000 ulps of slack).
    np.testing.assert_allclose(result.values[~border], 0, atol=1e-12)
    np.testing.assert_allclose(result.normals[~border], 0, atol=1e-12)
    laplacian = mesh.cotan_laplacian(vertices, faces)
    linear = vertices @ [0.3, -1.2, 2.0] + 5.0
    np.testing.assert_allclose((laplacian @ linear)[~border], 0, atol=1e-11)
    assert np.abs(laplacian @ linear)[border].max() > 1e-3  # the boundary does not satisfy it


def test_laplacian_structure():
    vertices, faces = face_like_grid(30, 25)
    laplacian = mesh.cotan_laplacian(vertices, faces)
    assert isinstance(laplacian, sp.csr_matrix)
    assert laplacian.has_sorted_indices
    # Symmetric and zero row sums up to rounding of weights ~1.
    assert abs(laplacian - laplacian.T).max() < 1e-14
    np.testing.assert_allclose(laplacian @ np.ones(len(vertices)), 0, atol=1e-12)
    # Negative semi-definite on this well-shaped mesh: x^T L x <= 0.
    rng = np.random.default_rng(0)
    probe = rng.normal(size=(len(vertices), 5))
    assert (np.einsum("ij,ij->j", probe, laplacian @ probe) <= 0).all()
    # Every diagonal entry is stored; an interior grid vertex has 6 neighbours.
    assert (laplacian.diagonal() < 0).all()
    row_lengths = np.diff(laplacian.indptr)
    assert row_lengths.max() == 7


def test_laplacian_of_regular_grid_is_the_five_point_stencil():
    # On a right-angled grid the diagonals of the quads get cot(90) = 0 and the axis
    # edges 1/2 + 1/2: the classic 5-point stencil (with zero stored diagonals).
    vertices, faces = grid_mesh(5, 5)
    laplacian = mesh.cotan_laplacian(vertices, faces).toarray()
    centre = 2 * 5 + 2
    expected = np.zeros(25)
    expected[[centre - 1, centre + 1, centre - 5, centre + 5]] = 1.0
    expected[centre] = -4.0
    np.testing.assert_allclose(laplacian[centre], expected, atol=1e-15)


def test_voronoi_areas_and_mass_matrix():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    areas = mesh.voronoi_areas(sphere.vertices, sphere.faces)
    assert (areas > 0).all()
    np.testing.assert_allclose(areas.sum(), sphere.area, rtol=1e-12)  # exact partition
    mass = mesh.mass_matrix(sphere.vertices, sphere.faces)
    assert isinstance(mass, sp.csr_matrix) and mass.shape == (len(areas),) * 2
    np.testing.assert_array_equal(mass.diagonal(), areas)
    assert mass.nnz == len(areas)
    # A unit right triangle is not obtuse, so every corner gets its Voronoi region
    # (|e1|^2 cot + |e2|^2 cot) / 8: (1 * 1 + 1 * 1) / 8 = 1/4 at the right angle,
    # (2 * cot 90 + 1 * cot 45) / 8 = 1/8 at the others; they sum to the area 1/2.
    right = mesh.voronoi_areas([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    np.testing.assert_allclose(right, [0.25, 0.125, 0.125], atol=1e-16)
    # An obtuse triangle: half the area to the obtuse corner, a quarter to the others.
    obtuse = mesh.voronoi_areas([[0, 0, 0], [4, 0, 0], [2, 0.5, 0]], [[0, 1, 2]])
    np.testing.assert_allclose(obtuse, [0.25, 0.25, 0.5], atol=1e-15)


def test_boundary_vertices_of_grid_and_closed_mesh():
    _, faces = grid_mesh(6, 7)
    np.testing.assert_array_equal(mesh.boundary_vertices(faces), grid_border(6, 7))
    sphere = trimesh.creation.icosphere(subdivisions=1)
    assert not mesh.boundary_vertices(sphere.faces).any()
    # Padding with unused vertices: they are not boundary vertices.
    padded = mesh.boundary_vertices(faces, n_vertices=50)
    assert padded.shape == (50,) and not padded[42:].any()


def test_non_manifold_edge_marks_boundary_and_does_not_crash():
    # Three triangles share edge (0, 1).
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1.0]])
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    boundary = mesh.boundary_vertices(faces)
    assert boundary.all()
    result = mesh.mean_curvature(vertices, faces)
    assert np.isnan(result.values).all()
    assert np.isfinite(mesh.cotan_laplacian(vertices, faces).data).all()
    assert_all_match_reference(vertices, faces)


def test_degenerate_faces_give_finite_results():
    # Collinear triangle, a triangle with two coincident vertices, a collapsed face
    # (repeated index), next to a well-formed one.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 1, 0], [1, 1, 0.5]], float)
    faces = np.array([[0, 1, 2], [0, 3, 4], [1, 1, 5], [0, 1, 5]])
    laplacian = mesh.cotan_laplacian(vertices, faces)
    assert np.isfinite(laplacian.data).all()
    assert np.abs(laplacian.data).max() <= 2 * reference.MAX_COTANGENT  # the clamp bounds every weight
    assert np.isfinite(mesh.voronoi_areas(vertices, faces)).all()
    assert np.isfinite(mesh.vertex_normals(vertices, faces)).all()
    normals = mesh.face_normals(vertices, faces)
    np.testing.assert_array_equal(normals[:3], 0)  # zero-area faces: zero normal
    result = mesh.mean_curvature(vertices, faces)
    assert not np.isinf(result.values).any()
    assert_all_match_reference(vertices, faces)


def test_collapsed_faces_change_nothing():
    vertices, faces = face_like_grid(12, 10)
    with_collapsed = np.concatenate([faces, [[3, 3, 7], [5, 9, 5], [8, 8, 8]]])
    for function in (mesh.vertex_normals, mesh.voronoi_areas):
        np.testing.assert_array_equal(function(vertices, with_collapsed), function(vertices, faces))
    assert (mesh.cotan_laplacian(vertices, with_collapsed) != mesh.cotan_laplacian(vertices, faces)).nnz == 0
    np.testing.assert_array_equal(mesh.boundary_vertices(with_collapsed), mesh.boundary_vertices(faces))


def test_isolated_vertices():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5.0]])
    faces = [[0, 1, 2]]
    np.testing.assert_array_equal(mesh.vertex_normals(vertices, faces)[3], 0)
    np.testing.assert_array_equal(mesh.vertex_normals(vertices, faces)[0], [0, 0, 1])
    laplacian = mesh.cotan_laplacian(vertices, faces)
    assert laplacian[3, 3] == 0 and laplacian.getrow(3).nnz == 1
    assert mesh.voronoi_areas(vertices, faces)[3] == 0
    assert np.isnan(mesh.mean_curvature(vertices, faces).values[3])


def test_results_do_not_depend_on_thread_count():
    vertices, faces = face_like_grid(120, 110)  # large enough to be split across threads
    tpscore.set_num_threads(1)
    try:
        serial = (mesh.cotan_laplacian(vertices, faces), mesh.mean_curvature(vertices, faces),
                  mesh.vertex_normals(vertices, faces), mesh.voronoi_areas(vertices, faces))
    finally:
        tpscore.set_num_threads(0)
    tpscore.set_num_threads(2)
    try:
        threaded = (mesh.cotan_laplacian(vertices, faces), mesh.mean_curvature(vertices, faces),
                    mesh.vertex_normals(vertices, faces), mesh.voronoi_areas(vertices, faces))
    finally:
        tpscore.set_num_threads(0)
    np.testing.assert_array_equal(serial[0].data, threaded[0].data)
    np.testing.assert_array_equal(serial[0].indices, threaded[0].indices)
    np.testing.assert_array_equal(serial[1].values, threaded[1].values)
    np.testing.assert_array_equal(serial[2], threaded[2])
    np.testing.assert_array_equal(serial[3], threaded[3])


def test_accepts_array_likes():
    vertices, faces = perturbed_grid(4, 5, seed=1, jitter=0.5, height=1.0)
    expected = mesh.mean_curvature(vertices, faces).values
    as_lists = mesh.mean_curvature(vertices.tolist(), faces.tolist()).values
    np.testing.assert_array_equal(as_lists, expected)
    strided = np.asfortranarray(vertices)
    np.testing.assert_array_equal(mesh.mean_curvature(strided, faces.astype(np.int32)).values, expected)
    float32 = mesh.voronoi_areas(vertices.astype(np.float32), faces)
    np.testing.assert_allclose(float32, mesh.voronoi_areas(vertices, faces), rtol=1e-5)


def test_empty_mesh():
    empty_vertices, empty_faces = np.zeros((0, 3)), np.zeros((0, 3), dtype=int)
    assert mesh.face_normals(empty_vertices, empty_faces).shape == (0, 3)
    assert mesh.vertex_normals(empty_vertices, empty_faces).shape == (0, 3)
    assert mesh.cotan_laplacian(empty_vertices, empty_faces).shape == (0, 0)
    assert mesh.mean_curvature(empty_vertices, empty_faces).values.shape == (0,)
    assert mesh.boundary_vertices(empty_faces).shape == (0,)


def test_outputs_own_their_memory():
    vertices, faces = grid_mesh(4, 4)
    normals = mesh.vertex_normals(vertices, faces)
    normals[:] = 7  # must not affect anything else
    np.testing.assert_array_equal(mesh.vertex_normals(vertices, faces)[:, 2], 1)
    assert normals.flags.writeable and normals.flags.c_contiguous


# --- bad input --------------------------------------------------------------------

@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "faces refers to vertex indices outside"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, -1]], "faces refers to vertex indices outside"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1]], r"faces must have shape \(m, 3\)"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2.5]], "faces must hold integer"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], r"vertices must have shape \(n, 3\)"),
        ([[0, 0, 0], [1, np.nan, 0], [0, 1, 0]], [[0, 1, 2]], "vertices contains NaN"),
    ],
)
def test_bad_input_raises_value_error(vertices, faces, message):
    for function in (mesh.face_normals, mesh.vertex_normals, mesh.cotan_laplacian,
                     mesh.voronoi_areas, mesh.mass_matrix, mesh.mean_curvature):
        with pytest.raises(ValueError, match=message):
            function(vertices, faces)


def test_bad_options_raise_value_error():
    vertices, faces = grid_mesh(3, 3)
    with pytest.raises(ValueError, match="weighting must be one of"):
        mesh.vertex_normals(vertices, faces, weighting="volume")
    with pytest.raises(ValueError, match="n_vertices must be a non-negative integer"):
        mesh.boundary_vertices(faces, n_vertices=-1)
    with pytest.raises(ValueError, match="faces refers to vertex indices outside"):
        mesh.boundary_vertices(faces, n_vertices=4)
    with pytest.raises(ValueError, match=r"faces must have shape \(m, 3\)"):
        mesh.boundary_vertices([0, 1, 2])


def test_public_names_are_exported():
    for name in ("face_normals", "vertex_normals", "cotan_laplacian", "voronoi_areas",
                 "mass_matrix", "mean_curvature", "boundary_vertices", "MeanCurvature"):
        assert getattr(tpscore, name) is getattr(mesh, name)
        assert name in tpscore.__all__


def test_height_field_remesh_resamples_the_front_surface():
    # a hemisphere of radius 40 seen from +z: every grid vertex lies on it, and the
    # source triangle + barycentric weights give back the same point
    from tpscore.mesh import height_field_remesh

    theta, phi = np.meshgrid(np.linspace(0, np.pi / 2, 30), np.linspace(0, 2 * np.pi, 60, endpoint=False))
    points = 40.0 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    vertices = points.reshape(-1, 3)
    index = np.arange(vertices.shape[0]).reshape(60, 30)
    a, b = index[:, :-1], np.roll(index, -1, axis=0)[:, :-1]
    c, d = index[:, 1:], np.roll(index, -1, axis=0)[:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    remeshed = height_field_remesh(vertices, faces, [0.0, 0.0, 40.0], shape=(40, 40), crop_mm=200.0)
    assert len(remeshed.faces) > 1000
    radius = np.linalg.norm(remeshed.vertices, axis=1)
    # flat facets of a 3 x 6 degree tessellation sit inside the sphere by < 0.3 mm
    assert np.abs(radius - 40.0).max() < 0.3
    rebuilt = np.einsum("ki,kij->kj", remeshed.barycentric, vertices[remeshed.source_corners])
    assert np.abs(rebuilt - remeshed.vertices).max() < 1e-9
    with pytest.raises(ValueError, match="crop_mm"):
        height_field_remesh(vertices, faces, [500.0, 0.0, 0.0], crop_mm=1.0)
