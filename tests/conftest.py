"""Test configuration: locate ../shared (data for tests that need it) if present."""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def shared_dir() -> Path | None:
    """The shared data folder: $TPSCORE_SHARED, else ../shared beside the repository."""
    env = os.environ.get("TPSCORE_SHARED")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared")
    for path in candidates:
        if (path / "data" / "ict-facekit" / "face_model.npz").is_file():
            return path
    return None


@pytest.fixture(scope="session")
def shared():
    path = shared_dir()
    if path is None:
        pytest.skip("needs ../shared (the ICT face model and scan tools); set TPSCORE_SHARED")
    return path


@pytest.fixture(scope="session")
def coloured_smile_files(tmp_path_factory):
    """The demo's smile as three scan files with their colour images (the people and
    seeds `make demo` uses): the source's neutral and smiling scans, the target's
    neutral scan."""
    from tpscore.showcase.demo_faces import make_demo_scan

    folder = tmp_path_factory.mktemp("coloured_smile")
    return [make_demo_scan(person, expression, seed=seed).write(folder, name)
            for person, expression, seed, name in ((0, None, 11, "a"), (0, {"12": 1.0}, 12, "b"), (1, None, 13, "c"))]


@pytest.fixture(scope="session")
def chromium():
    """The path of a headless-capable Chromium: Debian's `chromium`, installed with
    apt-get on first use when it is missing and this runs as root (set
    TPSCORE_NO_BROWSER_INSTALL to forbid that); the test skips where none can be had."""
    from headless_browser import find_chromium, install_chromium

    path = find_chromium() or install_chromium()
    if path is None:
        pytest.skip("needs a headless Chromium (Debian package 'chromium'): not installed, and apt-get "
                    "could not install it here (not root, no apt-get, no network to the Debian "
                    "mirrors, or TPSCORE_NO_BROWSER_INSTALL set)")
    return path


@pytest.fixture(scope="session")
def blender():
    """The environment in which a subprocess imports Blender's ``bpy`` (run scripts with
    ``headless_blender.run_blender``): installed with pip on first use into a folder of
    its own (set TPSCORE_NO_BLENDER_INSTALL to forbid that); the test skips where bpy
    cannot be had, e.g. no wheel for this Python."""
    from headless_blender import blender_environment

    environment, why = blender_environment()
    if environment is None:
        pytest.skip(f"needs Blender's bpy module: {why}")
    return environment
