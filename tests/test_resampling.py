"""Resampling scans onto face grids: accuracy against analytic surfaces and griddata,
the validity mask, gap bridging, landmark snapping and the grid's triangles."""
from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy.interpolate import griddata

from tpscore import (
    BntScan,
    FaceGrid,
    LandmarkSnapWarning,
    LandmarksDetectedWarning,
    load_scan,
    load_scans,
    read_bnt,
    read_lm3,
    resample_scan,
    write_bnt,
    write_landmarks,
    write_lm3,
    write_mesh,
)
from tpscore.face.resampling import DEFAULT_MAX_GAP_MM

ZMIN = -1.0e9
SPACING = 0.7                      # source grid spacing, mm (as make_scans.py)
X0, Y_TOP, NROWS, NCOLS = -55.0, 50.0, 145, 158
BIG_HOLE, BIG_RADIUS = np.array([10.3, 4.1]), 6.0
SMALL_HOLE = np.array([X0 + 50 * SPACING, Y_TOP - 86 * SPACING])   # on a source node
SMALL_RADIUS = 0.75                # removes the node and its 4 neighbours: a 2.8 mm span

AMPLITUDE, WAVELENGTH = 10.0, 15.0
# |Hessian| of AMPLITUDE sin(x/L) cos(y/L) is at most 2 AMPLITUDE / L^2 (its entries are
# bounded by AMPLITUDE / L^2 and its eigenvalues are f_xx +- f_xy).
CURVATURE = 2 * AMPLITUDE / WAVELENGTH**2


def face_height(x, y):
    return 20.0 + 0.1 * x - 0.05 * y + AMPLITUDE * np.sin(x / WAVELENGTH) * np.cos(y / WAVELENGTH)


def plane_height(x, y):
    return 3.0 + 0.2 * x - 0.1 * y


def synthetic_scan(height=face_height) -> BntScan:
    """A .bnt-like depth grid: an elliptical face region, background, a 12 mm hole and
    a small dropout of 5 pixels."""
    rows, cols = np.mgrid[0:NROWS, 0:NCOLS]
    x, y = X0 + SPACING * cols, Y_TOP - SPACING * rows
    valid = (x / 50.0) ** 2 + (y / 45.0) ** 2 <= 1.0
    valid &= np.hypot(x - BIG_HOLE[0], y - BIG_HOLE[1]) > BIG_RADIUS
    valid &= np.hypot(x - SMALL_HOLE[0], y - SMALL_HOLE[1]) > SMALL_RADIUS
    points = np.stack([x, y, height(x, y)], axis=-1)
    points[~valid] = np.nan
    uv = np.stack([(cols + 0.5) / NCOLS, (rows + 0.5) / NROWS], axis=-1).astype(np.float64)
    return BntScan(NROWS, NCOLS, ZMIN, "synthetic.png", points, uv, valid)


def nearest_vertex(x, y, point):
    """(row, column) of the grid vertex nearest to `point` in x, y."""
    return np.unravel_index(np.argmin(np.hypot(x - point[0], y - point[1])), x.shape)


@pytest.fixture(scope="module")
def scan():
    return synthetic_scan()


@pytest.fixture(scope="module")
def strict(scan):
    return resample_scan(scan, max_gap_mm=0)


def grid_axes(scan: BntScan, shape=(150, 150)):
    inside = scan.points[scan.valid]
    xs = np.linspace(inside[:, 0].min(), inside[:, 0].max(), shape[1])
    ys = np.linspace(inside[:, 1].max(), inside[:, 1].min(), shape[0])
    return np.meshgrid(xs, ys)


# --------------------------------------------------------------------------- accuracy

def test_grid_spans_the_valid_data(scan, strict):
    x, y = grid_axes(scan)
    assert strict.shape == (150, 150)
    assert np.array_equal(strict.points[strict.mask][:, :2], np.stack([x, y], -1)[strict.mask])
    assert y[0, 0] > y[-1, 0] and x[0, 0] < x[0, -1]  # row 0 on top, column 0 at smallest x


def test_structured_path_matches_the_analytic_surface(strict):
    x, y = strict.points[..., 0][strict.mask], strict.points[..., 1][strict.mask]
    error = np.abs(strict.points[..., 2][strict.mask] - face_height(x, y))
    # Linear interpolation on a triangle of longest edge h errs by at most
    # CURVATURE h^2 / 2; the cells' triangles have h = sqrt(2) SPACING.
    bound = CURVATURE * SPACING**2
    assert error.max() <= bound
    assert error.max() > bound / 100  # the comparison is not trivially exact


def test_structured_path_agrees_with_griddata(scan, strict):
    x, y = grid_axes(scan)
    inside = scan.points[scan.valid]
    reference = griddata(inside[:, :2], inside[:, 2], (x, y), method="linear")
    # Our surface never leaves the convex hull griddata interpolates over.
    assert np.isfinite(reference[strict.mask]).all()
    ours = strict.points[..., 2][strict.mask]
    # Both are linear interpolants over triangles of the same cells, which may differ
    # in the diagonal (cocircular corners make Delaunay's choice arbitrary): each is
    # within CURVATURE SPACING^2 of the surface, so within twice that of each other.
    assert np.abs(ours - reference[strict.mask]).max() <= 2 * CURVATURE * SPACING**2
    # griddata also fills the holes, which the mask excludes.
    assert np.isfinite(reference).sum() > strict.mask.sum()


def test_plane_is_reproduced_exactly_including_bridged_gaps():
    plane_scan = synthetic_scan(plane_height)
    for grid in (resample_scan(plane_scan), resample_scan(plane_scan, max_gap_mm=20.0)):
        x, y = grid.points[..., 0][grid.mask], grid.points[..., 1][grid.mask]
        # linear interpolation of a plane is exact up to rounding of ~1e-14 relative
        assert np.abs(grid.points[..., 2][grid.mask] - plane_height(x, y)).max() < 1e-9


def test_uv_map_is_interpolated_from_the_scan(scan, strict):
    x, y = grid_axes(scan)
    expected_u = ((x - X0) / SPACING + 0.5) / NCOLS
    expected_v = ((Y_TOP - y) / SPACING + 0.5) / NROWS
    assert np.allclose(strict.uv[..., 0], expected_u, atol=1e-12)  # u,v are affine in the pixel
    assert np.allclose(strict.uv[..., 1], expected_v, atol=1e-12)


# --------------------------------------------------------------------------- mask and gaps

def ellipse(x, y):
    return (x / 50.0) ** 2 + (y / 45.0) ** 2


def test_mask_excludes_holes_and_outside(scan, strict):
    x, y = grid_axes(scan)
    to_big = np.hypot(x - BIG_HOLE[0], y - BIG_HOLE[1])
    to_small = np.hypot(x - SMALL_HOLE[0], y - SMALL_HOLE[1])
    diagonal = SPACING * np.sqrt(2)
    # A vertex more than a cell diagonal inside a hole has no valid cell corner.
    assert not strict.mask[to_big < BIG_RADIUS - diagonal].any()
    assert not strict.mask[ellipse(x, y) > 1.1].any()       # outside the face region
    clear = (ellipse(x, y) < 0.9) & (to_big > BIG_RADIUS + diagonal) & (to_small > SMALL_RADIUS + diagonal)
    assert strict.mask[clear].all()
    r, c = nearest_vertex(x, y, SMALL_HOLE)
    assert not strict.mask[r, c]                              # the dropout is a hole here


def test_small_gaps_are_bridged_by_default(scan):
    assert DEFAULT_MAX_GAP_MM >= 2.8  # the dropout spans 2.8 mm between valid neighbours
    grid = resample_scan(scan)
    gx, gy = grid_axes(scan)
    r, c = nearest_vertex(gx, gy, SMALL_HOLE)
    assert grid.mask[r, c]
    x, y, z = grid.points[r, c]
    # 1D linear interpolation over a 2.8 mm span errs by at most CURVATURE 2.8^2 / 8,
    # plus the cell interpolation error of the bridged grid.
    assert abs(z - face_height(x, y)) <= CURVATURE * (2.8**2 / 8 + SPACING**2)
    r, c = nearest_vertex(gx, gy, BIG_HOLE)
    assert not grid.mask[r, c]                                # 12 mm wide: stays a hole
    wide = resample_scan(scan, max_gap_mm=20.0)
    assert wide.mask[r, c]
    x, y, z = wide.points[r, c]
    assert abs(z - face_height(x, y)) <= CURVATURE * ((2 * BIG_RADIUS + 2 * SPACING) ** 2 / 8 + SPACING**2)
    # Bridging never reaches outside the (convex) face region.
    assert not wide.mask[ellipse(gx, gy) > 1.1].any()


def test_triangles_cover_only_valid_vertices(strict):
    triangles = strict.triangles()
    flat_mask = strict.mask.reshape(-1)
    assert flat_mask[triangles].all()
    quads = (strict.mask[:-1, :-1].astype(int) + strict.mask[:-1, 1:] + strict.mask[1:, :-1] + strict.mask[1:, 1:])
    assert len(triangles) == 2 * (quads == 4).sum() + (quads == 3).sum()
    points = strict.vertices
    a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    normal_z = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert (normal_z > 0).all()  # counter-clockwise seen from +z
    mesh = strict.mesh()
    assert len(mesh.vertices) == strict.n_valid and np.isfinite(mesh.vertices).all()
    assert np.array_equal(mesh.vertices, strict.vertices[mesh.grid_index])
    assert np.array_equal(mesh.grid_index[mesh.faces], triangles)
    assert np.array_equal(mesh.uv, strict.uv.reshape(-1, 2)[mesh.grid_index])


# --------------------------------------------------------------------------- other inputs

def scattered_cloud(n=6000, seed=0, height=face_height):
    rng = np.random.default_rng(seed)
    radius, angle = 40.0 * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    x, y = radius * np.cos(angle), radius * np.sin(angle)
    keep = np.hypot(x - 10.0, y) > 7.0  # a hole
    return np.column_stack([x, y, height(x, y)])[keep]


def test_unstructured_cloud_matches_griddata():
    cloud = scattered_cloud()
    grid = resample_scan(cloud, max_gap_mm=0)
    x, y = grid_axes_of_cloud(cloud)
    reference = griddata(cloud[:, :2], cloud[:, 2], (x, y), method="linear")
    assert np.isfinite(reference[grid.mask]).all()
    # The same Delaunay triangulation (random points: unique) and barycentric weights;
    # only the arithmetic order differs (values ~30 mm: rounding ~1e-14).
    assert np.abs(grid.points[..., 2][grid.mask] - reference[grid.mask]).max() < 1e-9
    hole = np.hypot(x - 10.0, y) < 5.0
    assert hole.any() and not grid.mask[hole].any()
    assert np.isfinite(reference[hole]).any()          # griddata bridges it, we do not
    assert not grid.mask[np.hypot(x, y) > 40.5].any()   # outside the disc
    # Random (Poisson) points leave about 1% of Delaunay triangles with an edge longer
    # than 3 median edges; those are dropped as gaps.
    assert grid.mask[(np.hypot(x, y) < 38.0) & (np.hypot(x - 10.0, y) > 9.0)].mean() > 0.97


def grid_axes_of_cloud(cloud, shape=(150, 150)):
    xs = np.linspace(cloud[:, 0].min(), cloud[:, 0].max(), shape[1])
    ys = np.linspace(cloud[:, 1].max(), cloud[:, 1].min(), shape[0])
    return np.meshgrid(xs, ys)


def test_unstructured_plane_is_exact():
    grid = resample_scan(scattered_cloud(height=plane_height, seed=4))
    x, y = grid.points[..., 0][grid.mask], grid.points[..., 1][grid.mask]
    assert np.abs(grid.points[..., 2][grid.mask] - plane_height(x, y)).max() < 1e-9


def test_flat_lattice_cloud_takes_the_structured_path(scan, strict):
    order = np.random.default_rng(2).permutation(scan.n_valid)
    cloud = scan.points[scan.valid][order]
    uv = scan.uv[scan.valid][order]
    grid = resample_scan(cloud, max_gap_mm=0, uv=uv)
    assert np.array_equal(grid.mask, strict.mask)
    # same cells and weights; only the lattice fit's rounding differs
    assert np.nanmax(np.abs(grid.points - strict.points)) < 1e-9
    assert np.abs(grid.uv - strict.uv)[grid.mask].max() < 1e-12


def test_irregular_grid_falls_back_to_delaunay(scan):
    jittered = scan.points.copy()
    jittered[..., :2] += np.random.default_rng(3).normal(0.0, 0.05, jittered[..., :2].shape)
    grid = resample_scan(jittered, max_gap_mm=0)
    inside = jittered[scan.valid]
    x, y = grid_axes_of_cloud(inside)
    reference = griddata(inside[:, :2], inside[:, 2], (x, y), method="linear")
    assert np.isfinite(reference[grid.mask]).all()
    assert np.abs(grid.points[..., 2][grid.mask] - reference[grid.mask]).max() < 1e-9  # same triangles
    r, c = nearest_vertex(x, y, BIG_HOLE)
    assert not grid.mask[r, c]


# --------------------------------------------------------------------------- landmarks

def test_landmarks_snap_to_the_nearest_valid_vertex(scan):
    rng = np.random.default_rng(5)
    xy = rng.uniform(-30.0, 30.0, (22, 2))
    landmarks = np.column_stack([xy, face_height(xy[:, 0], xy[:, 1]) + rng.normal(0, 1.0, 22)])
    landmarks[3] = np.nan
    landmarks[7] = [BIG_HOLE[0], BIG_HOLE[1], face_height(*BIG_HOLE)]  # over the hole, 6 mm from data
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        grid = resample_scan(scan, landmarks)
    valid = np.flatnonzero(grid.mask.reshape(-1))
    for k in range(22):
        if k == 3:
            assert grid.landmark_vertices[k] == -1 and np.isnan(grid.landmarks[k]).all()
            continue
        distances = np.linalg.norm(grid.vertices[valid] - landmarks[k], axis=1)
        chosen = grid.landmark_vertices[k]
        assert grid.mask.reshape(-1)[chosen]
        # the chosen vertex is a nearest one (ties only up to rounding)
        assert np.linalg.norm(grid.vertices[chosen] - landmarks[k]) <= distances.min() + 1e-9
        assert np.array_equal(grid.landmarks[k], grid.vertices[chosen])
    assert np.linalg.norm(grid.landmarks[7] - landmarks[7]) > BIG_RADIUS - 2 * SPACING


def test_far_landmark_warns_but_snaps(scan):
    landmarks = np.full((22, 3), np.nan)
    landmarks[13] = [0.0, 0.0, face_height(0.0, 0.0) + 15.0]
    with pytest.warns(LandmarkSnapWarning, match="Nose tip"):
        grid = resample_scan(scan, landmarks)
    assert grid.landmark_vertices[13] >= 0
    assert np.isfinite(grid.landmarks[13]).all()


def test_face_grid_methods(strict):
    landmarks = np.full((22, 3), np.nan)
    landmarks[0] = [5.0, 5.0, face_height(5.0, 5.0)]
    grid = strict.with_landmarks(landmarks)
    assert grid.landmark_vertices[0] >= 0 and (grid.landmark_vertices[1:] == -1).all()
    copy = grid.copy()
    copy.points[grid.mask] += 1.0
    assert not np.array_equal(copy.points, grid.points, equal_nan=True)
    moved = grid.with_points(grid.vertices + np.array([1.0, 2.0, 3.0]))
    assert np.array_equal(moved.landmarks[0], grid.landmarks[0] + [1.0, 2.0, 3.0])
    assert np.array_equal(moved.mask, grid.mask) and np.isnan(moved.points[~moved.mask]).all()
    filled = np.where(grid.mask[..., None], grid.points, 0.0)
    assert np.array_equal(grid.with_points(filled).points, grid.points, equal_nan=True)
    broken = grid.points.copy()
    broken[grid.mask] = np.nan
    with pytest.raises(ValueError, match="new_points has NaN"):
        grid.with_points(broken)
    with pytest.raises(ValueError, match="new_points must have shape"):
        grid.with_points(np.zeros((10, 3)))


# --------------------------------------------------------------------------- bad input

def test_bad_input_raises(scan):
    empty = synthetic_scan()
    empty.valid[:] = False
    empty.points[:] = np.nan
    with pytest.raises(ValueError, match="0 valid point"):
        resample_scan(empty)
    with pytest.raises(ValueError, match="2 valid point"):
        resample_scan([[0, 0, 0], [1, 1, 1], [np.nan, 0, 0]])
    with pytest.raises(ValueError, match="cannot be triangulated"):
        resample_scan(np.column_stack([np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)]))
    with pytest.raises(ValueError, match="no extent"):
        resample_scan(np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)]))
    with pytest.raises(ValueError, match=r"shape \(22, 3\)"):
        resample_scan(scan, np.zeros((21, 3)))
    partial = np.full((22, 3), np.nan)
    partial[2, 0] = 1.0
    with pytest.raises(ValueError, match="row 2"):
        resample_scan(scan, partial)
    with pytest.raises(ValueError, match="shape must be"):
        resample_scan(scan, shape=(1, 150))
    with pytest.raises(ValueError, match="shape must be"):
        resample_scan(scan, shape=(150.5, 150))
    with pytest.raises(ValueError, match="max_gap_mm"):
        resample_scan(scan, max_gap_mm=-1)
    with pytest.raises(ValueError, match="scan_or_points must be"):
        resample_scan(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="uv"):
        resample_scan(scan, uv=np.zeros((NROWS, NCOLS, 2)))
    # all-NaN landmarks are fine: every landmark missing
    grid = resample_scan(scan, np.full((22, 3), np.nan))
    assert (grid.landmark_vertices == -1).all()


def test_small_grids_and_float32_input(scan):
    grid = resample_scan(scan.points.astype(np.float32), shape=(20, 30), max_gap_mm=0)
    exact = resample_scan(scan.points, shape=(20, 30), max_gap_mm=0)
    assert grid.shape == (20, 30) and grid.points.dtype == np.float64
    assert np.array_equal(grid.mask, exact.mask)
    # float32 rounds coordinates of up to ~60 mm by ~4e-6 mm
    assert np.nanmax(np.abs(grid.points - exact.points)) < 1e-4


# --------------------------------------------------------------------------- load_scan

def test_load_scan_bnt_and_mesh(tmp_path, scan):
    landmarks = np.full((22, 3), np.nan)
    landmarks[13] = [1.0, 2.0, face_height(1.0, 2.0)]
    write_bnt(tmp_path / "face.bnt", scan)
    write_lm3(tmp_path / "face.lm3", landmarks)
    loaded = load_scan(tmp_path / "face.bnt", shape=(80, 90))
    direct = resample_scan(read_bnt(tmp_path / "face.bnt"), read_lm3(tmp_path / "face.lm3"), (80, 90))
    assert np.array_equal(loaded.points, direct.points, equal_nan=True)
    assert np.array_equal(loaded.landmark_vertices, direct.landmark_vertices)

    cloud = scattered_cloud(seed=6)
    write_mesh(tmp_path / "cloud.ply", cloud, np.empty((0, 3), dtype=int))
    write_landmarks(tmp_path / "marks.json", landmarks)
    loaded = load_scan(tmp_path / "cloud.ply", tmp_path / "marks.json")
    direct = resample_scan(cloud, landmarks)
    assert np.array_equal(loaded.points, direct.points, equal_nan=True)
    assert loaded.landmark_vertices[13] == direct.landmark_vertices[13] >= 0

    write_mesh(tmp_path / "alone.obj", cloud, [])
    # without a landmark file they are detected from the scan, and a warning says so
    with pytest.warns(LandmarksDetectedWarning, match="no landmark file.*detected"):
        alone = load_scan(tmp_path / "alone.obj")
    assert np.isfinite(alone.landmarks).any()
    # detect=False keeps them all missing, as before detection existed
    with pytest.warns(LandmarkSnapWarning, match="no landmark file"):
        alone = load_scan(tmp_path / "alone.obj", detect=False)
    assert (alone.landmark_vertices == -1).all()


def test_load_scans_reads_several_at_once_in_order(tmp_path):
    landmarks = np.full((22, 3), np.nan)
    landmarks[13] = [1.0, 2.0, face_height(1.0, 2.0)]
    paths = []
    for k in range(3):
        # three scans that differ, so that a mix-up of their order shows
        write_bnt(tmp_path / f"face{k}.bnt", synthetic_scan(lambda x, y: face_height(x, y) + k))
        write_lm3(tmp_path / f"face{k}.lm3", landmarks)
        paths.append(tmp_path / f"face{k}.bnt")
    together = load_scans(paths, shape=(60, 70))
    for path, grid in zip(paths, together):
        alone = load_scan(path, shape=(60, 70))
        assert np.array_equal(grid.points, alone.points, equal_nan=True)
        assert np.array_equal(grid.landmark_vertices, alone.landmark_vertices)
    assert [np.nanmean(grid.points[..., 2]) for grid in together] == sorted(
        np.nanmean(grid.points[..., 2]) for grid in together)
    # the first path in order that fails is the one reported, naming its file
    (tmp_path / "broken.bnt").write_bytes(b"\x00" * 10)
    with pytest.raises(ValueError, match="broken.bnt"):
        load_scans([paths[0], tmp_path / "broken.bnt", tmp_path / "missing.bnt"])
    with pytest.raises(ValueError, match="landmarks_paths has 1 entries for 3 paths"):
        load_scans(paths, [None])
    with pytest.raises(ValueError, match="paths must be a sequence of scan paths"):
        load_scans(paths[0])


def test_load_scan_on_make_scans_output(shared, tmp_path):
    subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(tmp_path),
                    "--subjects", "0", "--expressions", "N_N_0"], check=True, capture_output=True)
    base = tmp_path / "bs000" / "bs000_N_N_0"
    grid = load_scan(base.with_suffix(".bnt"))
    truth = np.load(str(base) + "_gt.npz")
    assert grid.n_valid > 0.6 * grid.mask.size
    present = grid.landmark_vertices >= 0
    assert np.array_equal(present, truth["landmarks_written"])
    distance = np.linalg.norm(grid.landmarks[present] - truth["landmarks_true"][present], axis=1)
    # The written landmarks carry 0.8 mm noise per axis; snapping adds at most half a
    # grid-cell diagonal (about 0.5 mm) on this ~1 mm grid.
    assert np.median(distance) < 2.0 and distance.max() < 6.0
    # the colour image the .bnt names is read with it, and the grid's colours are the
    # image at the vertices' u,v
    assert grid.image is not None and grid.image.shape[2] == 3
    colours = grid.colours
    assert np.isfinite(colours[grid.mask]).all() and np.isnan(colours[~grid.mask]).all()
    # skin, not the dark background: the generator draws the background at 12 % grey
    assert np.median(colours[grid.mask]) > 0.2


# --------------------------------------------------------------------------- colour images

def checkerboard(height, width, cell=4):
    rows, cols = np.mgrid[0:height, 0:width]
    grey = np.where(((rows // cell) + (cols // cell)) % 2 == 0, 40, 220).astype(np.uint8)
    return np.dstack([grey, grey // 2, 255 - grey])


def test_load_scan_reads_the_named_image_beside_the_scan(tmp_path, scan):
    from PIL import Image

    write_bnt(tmp_path / "face.bnt", scan)           # names synthetic.png
    image = checkerboard(2 * NROWS, 2 * NCOLS)
    Image.fromarray(image).save(tmp_path / "synthetic.png")
    with pytest.warns(LandmarksDetectedWarning):
        grid = load_scan(tmp_path / "face.bnt", shape=(60, 70))
    np.testing.assert_array_equal(grid.image, image)
    assert not grid.image.flags.writeable
    # a vertex's colour is the image at its u,v: compare with a direct bilinear lookup
    r, c = 30, 35
    u, v = grid.uv[r, c]
    x, y = u * image.shape[1] - 0.5, v * image.shape[0] - 0.5
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    patch = image[y0:y0 + 2, x0:x0 + 2].astype(float)
    expected = ((1 - fy) * ((1 - fx) * patch[0, 0] + fx * patch[0, 1])
                + fy * ((1 - fx) * patch[1, 0] + fx * patch[1, 1])) / 255
    np.testing.assert_allclose(grid.colours[r, c], expected, atol=1e-5)
    # copies and moved grids keep the image
    assert grid.copy().image is grid.image
    assert grid.with_points(grid.points + 1.0).image is grid.image


def test_missing_image_leaves_a_geometry_only_scan(tmp_path, scan):
    write_bnt(tmp_path / "face.bnt", scan)
    with pytest.warns(LandmarksDetectedWarning):
        grid = load_scan(tmp_path / "face.bnt", shape=(60, 70))
    assert grid.image is None and grid.colours is None


@pytest.mark.parametrize("make, problem", [
    (lambda path: path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40), "corrupt|not an image"),
    (lambda path: path.write_bytes(b"this is no picture"), "not an image"),
    (lambda path: path.mkdir(), "folder"),
    # half as wide as the u,v were made for: the pixels would be stretched two to one
    (lambda path: __import__("PIL.Image").Image.fromarray(checkerboard(2 * NROWS, NCOLS)).save(path, "PNG"),
     "does not fit"),
])
def test_bad_image_is_refused_naming_the_file(tmp_path, scan, make, problem):
    write_bnt(tmp_path / "face.bnt", scan)
    make(tmp_path / "synthetic.png")
    with pytest.raises(ValueError, match=problem) as error:
        load_scan(tmp_path / "face.bnt", shape=(60, 70))
    assert "synthetic.png" in str(error.value)


def test_truncated_image_is_refused(tmp_path, scan):
    from PIL import Image

    write_bnt(tmp_path / "face.bnt", scan)
    Image.fromarray(checkerboard(2 * NROWS, 2 * NCOLS)).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "synthetic.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="synthetic.png.*(truncated|corrupt)"):
        load_scan(tmp_path / "face.bnt", shape=(60, 70))


def test_explicit_image_path_must_exist(tmp_path, scan):
    write_bnt(tmp_path / "face.bnt", scan)
    with pytest.raises(ValueError, match="nowhere.png.*not found"):
        load_scan(tmp_path / "face.bnt", shape=(60, 70), image_path=tmp_path / "nowhere.png")
