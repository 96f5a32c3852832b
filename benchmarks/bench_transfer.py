"""Speed of expression transfer: whole transfers from files, and animation frames.

A transfer from files is the user's job: three scans with their colour images
(tpscore's demo scans: Bosphorus .bnt + .lm3 + .png) given to tpscore.transfer as
paths, which reads the target while it measures the source's motion; reading them
first with tpscore.load_scans is timed beside it. The default follows the skin's
texture in two passes, and one pass is timed beside it; geometry alone (the same scans without their images) and the method as
published are timed too, and so is a transfer from neutral grids given again (what was
computed of each face is kept with it) against fresh copies of them. A frame is a
scaled add of precomputed displacement fields; it is compared with re-fitting the warps
for every frame (what a frame would cost without precomputing).
"""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

import tpscore
from tpscore.expression import animate
from tpscore.face import io
from tpscore.showcase.demo_faces import make_demo_scan


GROUP = "transfer: 3 scans (with colour images) from files to the animated target"


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    """The demo's source (neutral, smiling) and target scans, with and without images."""
    folder = tmp_path_factory.mktemp("scans")
    options = dict(noise_mm=0.1, holes=1, pose_deg=4.0, landmark_noise_mm=0.5)
    scans = {"source_neutral": make_demo_scan(0, None, seed=11, **options),
             "source_au12": make_demo_scan(0, {"12": 1.0}, seed=12, **options),
             "target_neutral": make_demo_scan(1, None, seed=13, **options)}
    with_images = [scan.write(folder, stem) for stem, scan in scans.items()]
    without = []
    for path in with_images:
        bare = folder / f"{path.stem}_bare.bnt"
        io.write_bnt(bare, dataclasses.replace(io.read_bnt(path), image_name=""))
        shutil.copy(path.with_suffix(".lm3"), bare.with_suffix(".lm3"))
        without.append(bare)
    return with_images, without


# A transfer's time moves by a tenth from one round to the next on a shared machine:
# fifteen rounds (about 3.5 s) instead of pytest-benchmark's five give a steadier
# minimum and median.
ROUNDS = 15


def _transfer_from_files(paths, options=tpscore.TransferOptions()):
    return tpscore.transfer(*paths, "12", options=options)


def _timed(benchmark, function, *args):
    return benchmark.pedantic(function, args=args, rounds=ROUNDS, warmup_rounds=1)


@pytest.mark.benchmark(group=GROUP)
def test_tpscore_transfer_default(benchmark, scan_files):
    result = _timed(benchmark, _transfer_from_files, scan_files[0])
    assert result.model.texture is not None      # the texture was followed
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.mark.benchmark(group=GROUP)
def test_transfer_after_load_scans(benchmark, scan_files):
    result = _timed(benchmark, lambda: tpscore.transfer(*tpscore.load_scans(scan_files[0]), "12"))
    assert result.model.texture is not None
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.mark.benchmark(group=GROUP)
def test_transfer_one_texture_pass(benchmark, scan_files):
    # the default matches the texture twice (MotionOptions.texture_refine_after=4); once
    # is the quicker choice (--texture-passes 1)
    one_pass = tpscore.TransferOptions(motion=tpscore.MotionOptions(texture_refine_after=0))
    result = _timed(benchmark, _transfer_from_files, scan_files[0], one_pass)
    assert result.model.texture is not None
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.mark.benchmark(group=GROUP)
def test_transfer_geometry_only(benchmark, scan_files):
    result = _timed(benchmark, _transfer_from_files, scan_files[1])
    assert result.model.texture is None
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


@pytest.mark.benchmark(group=GROUP)
def test_transfer_published_method(benchmark, scan_files):
    result = _timed(benchmark, _transfer_from_files, scan_files[0], tpscore.TransferOptions.published())
    assert np.nanmax(np.linalg.norm(result.vertices - result.neutral, axis=2)) > 1.0


REUSE_GROUP = "transfer from grids: the same neutral grids again, against fresh copies of them"


@pytest.fixture(scope="module")
def scan_grids(scan_files):
    return tpscore.load_scans(scan_files[0])


@pytest.mark.benchmark(group=REUSE_GROUP)
def test_tpscore_transfer_from_grids_given_again(benchmark, scan_grids):
    # a rig's or a batch's case: what was computed of each neutral face is kept with its
    # grid (kept_normalisation), so every round after the first starts from it
    neutral, expressive, target = scan_grids
    first = tpscore.transfer(neutral, expressive, target, "12")
    result = _timed(benchmark, lambda: tpscore.transfer(neutral, expressive, target, "12"))
    assert result.target is first.target
    assert np.array_equal(result.vertices, first.vertices, equal_nan=True)


@pytest.mark.benchmark(group=REUSE_GROUP)
def test_transfer_from_fresh_grids(benchmark, scan_grids):
    def fresh_transfer():
        return tpscore.transfer(*[dataclasses.replace(grid) for grid in scan_grids], "12")
    result = _timed(benchmark, fresh_transfer)
    assert result.target is not fresh_transfer().target


@pytest.fixture(scope="module")
def transfer_result(scan_files):
    return _transfer_from_files(scan_files[0])


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
