"""The thread count of the compiled kernels."""
from __future__ import annotations

import numbers

from . import _core

__all__ = ["num_threads", "set_num_threads", "max_threads"]


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
        and values above :func:`max_threads` are capped to it. Results do not depend
        on the thread count.

    Raises
    ------
    ValueError
        If n is not an integer (a string, None, a float such as 2.5, a bool).
    """
    if isinstance(n, bool) or not isinstance(n, numbers.Integral):
        raise ValueError(f"n (the thread count) must be an integer, got {n!r}")
    count = int(n)
    # The core takes a C int; anything beyond the cap means the cap.
    _core.set_num_threads(max(0, min(count, _core.max_threads())))
