"""Speed of expression transfer: whole transfers from files, and animation frames.

A frame is a scaled add of precomputed displacement fields; it is compared with
re-fitting the warps for every frame (what a frame would cost without precomputing).
"""
from __future__ import annotations

import numpy as np
import pytest

import tpscore
from tpscore import datasets
from tpscore.face import io
from tpscore.expression import animate


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans")
    paths = []
    for name, scan in zip(("a", "b", "c"), datasets.demo_triplet("12", noise_mm=0.1, holes=2, pose_deg=5.0)):
        io.write_bnt(folder / f"{name}.bnt", io.BntScan.from_points(scan.points))
        io.write_lm3(folder / f"{name}.lm3", scan.landmarks)
        paths.append(str(folder / f"{name}.bnt"))
    return paths


def _transfer_from_files(paths, options):
    grids = [tpscore.load_scan(p) for p in paths]
    return tpscore.transfer(*grids, "12", options=options)


@pytest.mark.benchmark(group="transfer: 3 scans from files to the animated target")
def test_tpscore_transfer_default(benchmark, scan_files):
    result = benchmark(_transfer_from_files, scan_files, tpscore.TransferOptions())
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.mark.benchmark(group="transfer: 3 scans from files to the animated target")
def test_transfer_published_method(benchmark, scan_files):
    result = benchmark(_transfer_from_files, scan_files, tpscore.TransferOptions.published())
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.fixture(scope="module")
def transfer_result(scan_files):
    return _transfer_from_files(scan_files, tpscore.TransferOptions())


@pytest.mark.benchmark(group="animation frame, 150 x 150")
def test_tpscore_frame_scaled_add(benchmark, transfer_result):
    animation = transfer_result.animation
    frame = benchmark(animation.frame, 0.6)
    expected = animation.frame(0.0) + 0.6 * animation.fields[0]
    assert np.allclose(frame, expected, equal_nan=True)


@pytest.mark.benchmark(group="animation frame, 150 x 150")
def test_refit_warps_per_frame(benchmark, transfer_result):
    def refit():
        return animate(transfer_result.model, transfer_result.target).frame(0.6)

    frame = benchmark(refit)
    assert np.allclose(frame, transfer_result.animation.frame(0.6), equal_nan=True, atol=1e-9)
