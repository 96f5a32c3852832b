import os
import subprocess
import sys
import textwrap
import threading

import numpy as np
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


def test_blas_runs_on_one_thread_while_a_transfer_runs_and_is_restored_after():
    from threadpoolctl import threadpool_info, threadpool_limits
    from tpscore._threads import blas_on_one_thread, single_threaded_blas

    def blas_threads():
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        assert before and max(before) == 2
        seen = []

        @blas_on_one_thread
        def inside():
            seen.append(blas_threads())
            with single_threaded_blas():      # nested
                seen.append(blas_threads())
            seen.append(blas_threads())      # still limited: the outer block runs on
            raise KeyError("leaves by an exception")

        with pytest.raises(KeyError):
            inside()
        assert seen == [[1] * len(before)] * 3
        assert blas_threads() == before


def test_side_by_side_runs_the_second_call_on_another_thread_and_returns_both():
    import threading

    from tpscore._threads import side_by_side

    caller = threading.get_ident()
    assert side_by_side(lambda: "a", lambda: "b") == ("a", "b")
    first, second = side_by_side(threading.get_ident, threading.get_ident)
    assert first == caller and second != caller
    # an exception of either call reaches the caller, the first call's before the second's
    with pytest.raises(KeyError):
        side_by_side(lambda: {}["first"], lambda: 2)
    with pytest.raises(IndexError):
        side_by_side(lambda: 1, lambda: [][0])
    with pytest.raises(KeyError):
        side_by_side(lambda: {}["first"], lambda: [][0])


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


# --- the thread count: bad values are refused, large ones capped, failures survived ----

@pytest.mark.parametrize("bad", ["a", None, 2.5, True, [2]])
def test_set_num_threads_refuses_non_integers(bad):
    before = tpscore.num_threads()
    with pytest.raises(ValueError, match=r"n \(the thread count\) must be an integer"):
        tpscore.set_num_threads(bad)
    assert tpscore.num_threads() == before


def _kernel_results():
    rng = np.random.default_rng(0)
    source = rng.uniform(-50.0, 50.0, size=(60, 3))
    warp = tpscore.TPS(source, source + rng.normal(size=source.shape))
    queries = rng.uniform(-80.0, 80.0, size=(100_000, 3))
    tree = tpscore.KDTree(queries[:20_000])
    distances, indices = tree.query(queries, k=4)
    return warp(queries), distances, indices


def test_a_huge_thread_count_is_capped_and_gives_the_serial_results():
    try:
        tpscore.set_num_threads(1)
        serial = _kernel_results()
        tpscore.set_num_threads(600)
        assert tpscore.num_threads() == tpscore.max_threads() == 4 * (os.cpu_count() or 1)
        capped = _kernel_results()
        tpscore.set_num_threads(2**80)  # a Python int no C int holds
        assert tpscore.num_threads() == tpscore.max_threads()
    finally:
        tpscore.set_num_threads(0)
    for a, b in zip(serial, capped):
        assert np.array_equal(a, b)


def _run_python(code, **env):
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=120, env={**os.environ, **env})


def test_a_huge_thread_count_from_the_environment_is_capped():
    result = _run_python("""
        import tpscore
        print(tpscore.num_threads(), tpscore.max_threads())
        """, TPSCORE_NUM_THREADS="600")
    assert result.returncode == 0, result.stderr
    count, cap = map(int, result.stdout.split())
    assert count == cap


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and RLIMIT_AS")
def test_threads_that_cannot_start_do_not_abort_the_interpreter():
    # With the address space capped a few MiB above what the process already uses,
    # at most one 8 MiB thread stack fits: the other starts fail, and their rows must
    # run on the calling thread instead of aborting (std::terminate).
    result = _run_python("""
        import resource
        import numpy as np
        import tpscore
        rng = np.random.default_rng(0)
        source = rng.uniform(-50.0, 50.0, size=(60, 3))
        warp = tpscore.TPS(source, source + rng.normal(size=source.shape))
        queries = rng.uniform(-80.0, 80.0, size=(200_000, 3))
        tpscore.set_num_threads(1)
        serial = warp(queries)
        tpscore.set_num_threads(600)
        out = np.empty_like(serial)
        status = open("/proc/self/status").read().split("VmSize:")[1]
        used = int(status.split()[0]) * 1024
        resource.setrlimit(resource.RLIMIT_AS, (used + (16 << 20), resource.RLIM_INFINITY))
        warp._model.evaluate_into(queries, out)
        print(np.array_equal(out, serial))
        """)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork()")
def test_kernels_run_in_a_forked_child_after_the_parent_used_threads():
    # The kernels keep a pool of threads between calls; a child of fork() has none of
    # them and must start its own rather than wait for threads that do not exist.
    warp, queries = _threaded_warp()
    expected = warp(queries)  # the parent's pool is running now
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: evaluate, report, and leave without running pytest's exit
        try:
            ok = np.array_equal(warp(queries), expected)
            os.write(write, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(write)
    _, status = os.waitpid(pid, 0)
    answer = os.read(read, 1)
    os.close(read)
    assert status == 0 and answer == b"1"


def _threaded_warp():
    rng = np.random.default_rng(3)
    source = rng.uniform(-50.0, 50.0, size=(80, 3))
    return tpscore.TPS(source, source + rng.normal(size=source.shape)), rng.uniform(-80.0, 80.0, (100_000, 3))

