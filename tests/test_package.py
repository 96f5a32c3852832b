import threading

import pytest

import tpscore
import tpscore._core as core


def test_thread_count_can_be_set_and_restored():
    default = tpscore.num_threads()
    assert default >= 1
    tpscore.set_num_threads(1)
    try:
        assert tpscore.num_threads() == 1
    finally:
        tpscore.set_num_threads(0)
    assert tpscore.num_threads() == default


def test_stub_file_ships_with_the_extension():
    from pathlib import Path

    stub = Path(core.__file__).with_name("_core.pyi")
    assert stub.is_file()
    assert "def set_num_threads" in stub.read_text()


def test_version_comes_from_the_installed_metadata():
    from importlib import metadata

    import tpscore

    try:
        installed = metadata.version("tpscore")
    except metadata.PackageNotFoundError:
        pytest.skip("tpscore is not installed (run from a source tree)")
    assert tpscore.__version__ == installed
