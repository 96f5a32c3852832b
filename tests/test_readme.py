"""The README's kernel example runs as printed."""
import re
from pathlib import Path

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
