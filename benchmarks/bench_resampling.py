"""Scan resampling (resample_scan) against scipy.interpolate.griddata, and read_bnt.

Each resampling group puts tpscore's cell-by-cell interpolation of a regular depth
grid (the baseline) beside griddata(..., method="linear") on the same valid points
and the same 150 x 150 target grid: the Delaunay-based interpolation the method
prescribes. Two scans: a synthetic ~35k-point depth grid that always runs, and a
make_scans.py scan when ../shared is present.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import griddata

from tpscore import BntScan, read_bnt, resample_scan, write_bnt
from shared_data import shared_dir

SHAPE = (150, 150)
SPACING = 0.7
AMPLITUDE, WAVELENGTH = 10.0, 15.0
CURVATURE = 2 * AMPLITUDE / WAVELENGTH**2   # bound on the Hessian of the height field


def height(x, y):
    return 20.0 + 0.1 * x - 0.05 * y + AMPLITUDE * np.sin(x / WAVELENGTH) * np.cos(y / WAVELENGTH)


def synthetic_scan() -> BntScan:
    """A face-sized depth grid at 0.7 mm with ~34k valid points, background and holes."""
    nrows, ncols = 258, 190
    rows, cols = np.mgrid[0:nrows, 0:ncols]
    x, y = -66.0 + SPACING * cols, 90.0 - SPACING * rows
    valid = (x / 62.0) ** 2 + (y / 85.0) ** 2 <= 1.0
    for cx, cy, radius in ((20.0, 30.0, 7.0), (-25.0, 30.0, 7.0), (0.0, -40.0, 4.0), (10.0, 0.0, 1.0)):
        valid &= np.hypot(x - cx, y - cy) > radius
    points = np.stack([x, y, height(x, y)], axis=-1)
    points[~valid] = np.nan
    uv = np.stack([(cols + 0.5) / ncols, (rows + 0.5) / nrows], axis=-1).astype(np.float64)
    return BntScan(nrows, ncols, -1.0e9, "synthetic.png", points, uv, valid)


def target_grid(scan: BntScan):
    inside = scan.points[scan.valid]
    xs = np.linspace(inside[:, 0].min(), inside[:, 0].max(), SHAPE[1])
    ys = np.linspace(inside[:, 1].max(), inside[:, 1].min(), SHAPE[0])
    return np.meshgrid(xs, ys)


def griddata_resample(scan: BntScan):
    inside = scan.points[scan.valid]
    x, y = target_grid(scan)
    return griddata(inside[:, :2], inside[:, 2], (x, y), method="linear")


@pytest.fixture(scope="module")
def synthetic():
    scan = synthetic_scan()
    assert 30_000 < scan.n_valid < 40_000
    return scan


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    shared = shared_dir()
    if shared is None:
        pytest.skip("needs ../shared (make_scans.py); set TPSCORE_SHARED")
    out = tmp_path_factory.mktemp("scans")
    subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(out),
                    "--subjects", "0", "--expressions", "N_N_0"], check=True, capture_output=True)
    return out / "bs000" / "bs000_N_N_0.bnt"


@pytest.fixture(scope="module")
def generated_scan(generated):
    return read_bnt(generated)


def check_against_griddata(grid, reference):
    # Wherever tpscore has surface, griddata has too (tpscore never leaves the data's
    # convex hull), and both are linear interpolants of the same points.
    assert np.isfinite(reference[grid.mask]).all()
    difference = np.abs(grid.points[..., 2] - reference)[grid.mask]
    return difference


# --------------------------------------------------------------------------- synthetic

@pytest.mark.benchmark(group="resample 150x150 synthetic (34k points)")
def test_resample_tpscore_synthetic(benchmark, synthetic):
    grid = benchmark(resample_scan, synthetic)
    x, y = grid.points[..., 0][grid.mask], grid.points[..., 1][grid.mask]
    error = np.abs(grid.points[..., 2][grid.mask] - height(x, y))
    # Linear interpolation on cells of diagonal sqrt(2) s errs by at most CURVATURE s^2;
    # the 2 mm hole is bridged (max_gap_mm=3) with a 1D error of CURVATURE 2.8^2 / 8 more.
    assert error.max() <= CURVATURE * (SPACING**2 + 2.8**2 / 8)
    strict = resample_scan(synthetic, max_gap_mm=0)
    difference = check_against_griddata(strict, griddata_resample(synthetic))
    # Only the diagonal chosen inside a cell may differ (both within CURVATURE s^2).
    assert difference.max() <= 2 * CURVATURE * SPACING**2


@pytest.mark.benchmark(group="resample 150x150 synthetic (34k points)")
def test_resample_griddata_synthetic(benchmark, synthetic):
    reference = benchmark.pedantic(griddata_resample, args=(synthetic,), rounds=3, iterations=1)
    assert np.isfinite(reference).sum() > 0.5 * reference.size


# --------------------------------------------------------------------------- make_scans

@pytest.mark.benchmark(group="resample 150x150 make_scans bs000 N_N_0")
def test_resample_tpscore_make_scans(benchmark, generated_scan):
    grid = benchmark(resample_scan, generated_scan)
    strict = resample_scan(generated_scan, max_gap_mm=0)
    difference = check_against_griddata(strict, griddata_resample(generated_scan))
    # Same triangles except for the diagonal Delaunay picks among cocircular cell
    # corners; with 0.15 mm depth noise the two diagonals differ by up to a few noise
    # sigmas at most vertices, and more only at depth discontinuities (nose sides).
    assert np.median(difference) < 1e-9
    assert np.percentile(difference, 99) < 1.0
    assert grid.n_valid >= strict.n_valid


@pytest.mark.benchmark(group="resample 150x150 make_scans bs000 N_N_0")
def test_resample_griddata_make_scans(benchmark, generated_scan):
    reference = benchmark.pedantic(griddata_resample, args=(generated_scan,), rounds=3, iterations=1)
    assert np.isfinite(reference).sum() > 0.5 * reference.size


# --------------------------------------------------------------------------- read_bnt

@pytest.mark.benchmark(group="read_bnt")
def test_read_bnt_tpscore_synthetic(benchmark, synthetic, tmp_path):
    path = tmp_path / "synthetic.bnt"
    write_bnt(path, synthetic)
    scan = benchmark(read_bnt, path)
    assert np.array_equal(scan.points, synthetic.points, equal_nan=True)


@pytest.mark.benchmark(group="read_bnt make_scans")
def test_read_bnt_tpscore_make_scans(benchmark, generated):
    scan = benchmark(read_bnt, generated)
    assert 30_000 < scan.n_valid < 45_000
