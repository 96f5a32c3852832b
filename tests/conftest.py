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
