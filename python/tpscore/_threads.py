"""The thread count of the compiled kernels, helper threads kept between calls, two
calls run side by side, and BLAS kept to one thread while a transfer runs."""
from __future__ import annotations

import functools
import numbers
import os
import queue
import threading
import warnings
from concurrent.futures import Future
from contextlib import contextmanager

from threadpoolctl import ThreadpoolController

from . import _core

__all__ = ["num_threads", "set_num_threads", "max_threads", "as_workers", "helper_thread", "side_by_side",
           "single_threaded_blas", "blas_on_one_thread"]


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


def as_workers(workers) -> int:
    """A kernel call's ``workers`` argument as the core takes it: -1 (all threads)
    becomes 0, the core's default; counts above :func:`max_threads` mean that many, as
    for :func:`set_num_threads` (the core takes a C int and caps it there anyway).

    Raises
    ------
    ValueError
        Naming ``workers``: not an integer, or 0 or below -1.
    """
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral):
        raise ValueError(f"workers must be an integer (-1 for all threads), got {workers!r}")
    workers = int(workers)
    if workers == -1:
        return 0
    if workers < 1:
        raise ValueError(f"workers must be -1 (all threads) or >= 1, got {workers}")
    return min(workers, _core.max_threads())


class _KeptThread:
    """A daemon thread that runs the calls handed to it, in order, and waits for more.

    Starting a thread costs 0.1 ms on an idle machine, and far more on a busy one:
    ``Thread.start`` waits until the new thread has run, which under a GIL held by
    another thread can take a switch interval (5 ms). A transfer starts ten of them, and
    they cost it 2-18 ms on its critical path (30 ms for closing eyes), so threads are
    kept between uses instead.
    """

    def __init__(self):
        self._calls = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._serve, name="tpscore-helper", daemon=True)
        self.thread.start()

    def run(self, call) -> Future:
        future = Future()
        self._calls.put((call, future))
        return future

    def stop(self) -> None:
        self._calls.put(None)

    def _serve(self) -> None:
        while (item := self._calls.get()) is not None:
            call, future = item
            del item
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(call())
                except BaseException as exc:  # handed to the caller, as an executor does
                    future.set_exception(exc)
            # an idle thread holds nothing: a kept result would outlive its users (and
            # the interpreter's exit, which does not end a daemon thread)
            del call, future


#: Idle kept threads beyond this many stop (calls nested several deep on several user
#: threads may lease many at once; they are not all kept).
_MAX_IDLE = 8
_idle: list[_KeptThread] = []
_idle_lock = threading.Lock()


def _forget_threads_after_fork() -> None:
    # a forked child has only the thread that forked; the parent's idle threads (and
    # the state of the lock guarding them) do not exist there
    global _idle_lock
    _idle.clear()
    _idle_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_threads_after_fork)


class HelperThread:
    """One thread leased for a block (see :func:`helper_thread`)."""

    def __init__(self, kept: _KeptThread):
        self._kept = kept
        self._pending: list[Future] = []

    def submit(self, function, *args, **kwargs) -> Future:
        """Run ``function(*args, **kwargs)`` on the thread after the calls submitted
        before it; the future holds its result or its exception."""
        future = self._kept.run(functools.partial(function, *args, **kwargs))
        self._pending.append(future)
        return future

    def _wait(self) -> None:
        for future in self._pending:
            future.exception()  # waits; an exception nobody asked for stays unraised, as in an executor
        self._pending.clear()


@contextmanager
def helper_thread(name: str = "tpscore-helper"):
    """A thread of tpscore's own for the block: an idle one kept from earlier blocks, or
    a new one. Calls given to its ``submit`` run in order; the block's end waits for
    them all (as a one-worker ``ThreadPoolExecutor``'s does), then keeps the thread
    for the next block. A block never waits for another block's thread, so helper
    blocks nested in helper threads cannot deadlock."""
    with _idle_lock:
        kept = _idle.pop() if _idle else None
    if kept is None:
        kept = _KeptThread()
    kept.thread.name = name
    lease = HelperThread(kept)
    try:
        yield lease
    finally:
        lease._wait()
        kept.thread.name = "tpscore-helper"
        with _idle_lock:
            if len(_idle) < _MAX_IDLE:
                _idle.append(kept)
                kept = None
        if kept is not None:
            kept.stop()


def side_by_side(first, second):
    """``(first(), second())``, the second called on a helper thread while this one calls
    the first: for two independent calls that release the GIL (compiled kernels,
    OpenCV). Their exceptions are raised here, the first call's before the second's."""
    with helper_thread("tpscore-side") as other_thread:
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
