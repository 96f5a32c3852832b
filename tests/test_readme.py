"""The README's kernel and transfer examples run as printed."""
import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks():
    if not README.is_file():
        pytest.skip("README.md is not beside the tests (installed package)")
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_the_kernel_example_runs():
    blocks = [b for b in _python_blocks() if "tpscore.TPS(" in b]
    assert blocks, "the README has no kernel example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    moved = namespace["moved"]
    assert moved.shape == (22500, 3)
    # the warp interpolates its centres
    warp, source, target = namespace["warp"], namespace["source"], namespace["target"]
    assert abs(warp(source) - target).max() < 1e-8


def test_the_transfer_example_runs_on_the_demo_scans(tmp_path, monkeypatch):
    # The example reads the scans `make demo` writes; the same scans are written here.
    from tpscore.cli.demo import write_demo_scans

    blocks = [b for b in _python_blocks() if "tpscore.transfer(" in b]
    assert blocks, "the README has no transfer example"
    write_demo_scans(tmp_path / "demo-output" / "scans")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    surprise, brows, smile = namespace["surprise"], namespace["brows"], namespace["smile"]
    assert surprise.vertices.shape == (150, 150, 3) and surprise.colours.shape == (150, 150, 3)
    assert (tmp_path / "surprise.html").stat().st_size > 10_000
    # The opened mouth: the surprise moves the chin down by millimetres, and the half
    # brows move less than the whole expression's brows.
    motion = np.linalg.norm(surprise.vertices - surprise.neutral, axis=-1)
    assert np.nanmax(motion[surprise.mask]) > 3.0
    assert "AU12L" in smile.animation.labels
    assert np.nanmax(np.linalg.norm(brows.vertices - brows.neutral, axis=-1)) < np.nanmax(motion)
