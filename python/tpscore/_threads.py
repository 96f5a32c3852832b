"""The thread count of the compiled kernels, two calls run side by side, and BLAS kept
to one thread while a transfer runs."""
from __future__ import annotations

import functools
import numbers
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

from threadpoolctl import ThreadpoolController

from . import _core

__all__ = ["num_threads", "set_num_threads", "max_threads", "side_by_side", "single_threaded_blas",
           "blas_on_one_thread"]


def num_threads() -> int:
    """Threads a kernel may use.

    ``set_num_threads(n)`` if called with n > 0, else the environment variable
    ``TPSCORE_NUM_THREADS``, else the number of hardware threads; never more than
    :func:`max_threads`.
    """
    return _core.num_threads()


def max_threads() -> int:
    """The cap on the thread count: four times the number of hardware threads.

    More threads than that would only share the cores; larger requests (from
    :func:`set_num_threads` or ``TPSCORE_NUM_THREADS``) are reduced to it.
    """
    return _core.max_threads()


def set_num_threads(n: int) -> None:
    """Set the number of threads the compiled kernels use from now on.

    Parameters
    ----------
    n : int
        The thread count; 0 or less restores the default (see :func:`num_threads`),
        and values above :func:`max_threads` are capped to it, with a
        ``RuntimeWarning`` that says so (a count of 2**40 is a slip, not a request).
        Results do not depend on the thread count.

    Raises
    ------
    ValueError
        If n is not an integer (a string, None, a float such as 2.5, a bool).

    Warns
    -----
    RuntimeWarning
        If n is above :func:`max_threads`: the kernels then use max_threads().
    """
    if isinstance(n, bool) or not isinstance(n, numbers.Integral):
        raise ValueError(f"n (the thread count) must be an integer, got {n!r}")
    count = int(n)
    cap = _core.max_threads()
    if count > cap:
        warnings.warn(f"set_num_threads: n = {count} is more than max_threads() = {cap}; the kernels "
                      f"use {cap} threads", RuntimeWarning, stacklevel=2)
    # The core takes a C int; anything beyond the cap means the cap.
    _core.set_num_threads(max(0, min(count, cap)))


def side_by_side(first, second):
    """``(first(), second())``, the second called on another thread while this one calls
    the first: for two independent calls that release the GIL (compiled kernels,
    OpenCV). Their exceptions are raised here, the first call's before the second's."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tpscore-side") as other_thread:
        later = other_thread.submit(second)
        return first(), later.result()


_blas_lock = threading.Lock()
_blas_users = 0
_blas_limit = None
_blas_controller = None


@contextmanager
def single_threaded_blas():
    """BLAS (the OpenBLAS under NumPy and SciPy) on one thread while the block runs.

    A transfer makes many small matrix products, which gain nothing from more threads,
    while OpenBLAS's idle threads spin for a while after each and take a core from
    tpscore's own threads (a transfer's registration took 20 % longer on two cores).
    Blocks that overlap, in one thread or several, share one limit: the thread counts
    in force before the first are restored after the last.
    """
    global _blas_users, _blas_limit, _blas_controller
    with _blas_lock:
        if _blas_users == 0:
            if _blas_controller is None:
                # found once (a millisecond); the BLAS libraries are loaded by then
                _blas_controller = ThreadpoolController()
            _blas_limit = _blas_controller.limit(limits=1, user_api="blas")
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0:
                _blas_limit.restore_original_limits()
                _blas_limit = None


def blas_on_one_thread(function):
    """Decorate a function to run within :func:`single_threaded_blas`."""
    @functools.wraps(function)
    def on_one_thread(*args, **kwargs):
        with single_threaded_blas():
            return function(*args, **kwargs)
    return on_one_thread
