"""Where the benchmarks find the optional shared data (the ICT face model, make_scans.py
and score_transfer.py): $TPSCORE_SHARED, else ../shared beside the repository."""
from __future__ import annotations

import os
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]


def shared_dir() -> Path | None:
    """The shared folder, or None when it is absent (the benchmarks then skip)."""
    env = os.environ.get("TPSCORE_SHARED")
    candidates = [Path(env)] if env else []
    candidates.append(REPOSITORY.parent / "shared")
    for path in candidates:
        if (path / "data" / "ict-facekit" / "face_model.npz").is_file() and (path / "tools" / "make_scans.py").is_file():
            return path
    return None


def load_module(path: Path, name: str):
    """A shared tool (make_scans.py, score_transfer.py) imported from its file."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
