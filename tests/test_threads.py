"""tpscore's helper threads: kept between uses, ordered within a block, never deadlocked
by nesting, holding nothing once idle, and usable again in a forked child."""
import gc
import multiprocessing
import os
import sys
import threading
import weakref

import pytest

from tpscore import _threads
from tpscore._threads import helper_thread, side_by_side


def test_calls_run_in_order_on_one_thread_and_the_block_waits_for_them():
    order, threads = [], set()

    def step(k):
        threads.add(threading.get_ident())
        order.append(k)
        return k * k

    with helper_thread("tpscore-test") as other:
        futures = [other.submit(step, k) for k in range(20)]
    # the block's end waited: every call ran, in the order given, on one thread
    assert order == list(range(20))
    assert [future.result(timeout=0) for future in futures] == [k * k for k in range(20)]
    assert len(threads) == 1 and threading.get_ident() not in threads


def test_a_thread_is_kept_for_the_next_block():
    with helper_thread() as other:
        first = other.submit(threading.get_ident).result()
    with helper_thread() as other:
        second = other.submit(threading.get_ident).result()
    assert first == second


def test_an_exception_reaches_the_caller_and_the_thread_stays_usable():
    def fail():
        raise ValueError("from the helper")

    with helper_thread() as other:
        failed = other.submit(fail)
        after = other.submit(lambda: 42)
    with pytest.raises(ValueError, match="from the helper"):
        failed.result()
    assert after.result() == 42
    with pytest.raises(KeyError):
        side_by_side(lambda: 1, lambda: {}["missing"])


def test_nested_blocks_do_not_deadlock():
    # every call leases a helper of its own, three deep, from several user threads at
    # once: more blocks than idle threads are kept
    def nest(depth):
        if depth == 0:
            return 1
        left, right = side_by_side(lambda: nest(depth - 1), lambda: nest(depth - 1))
        return left + right

    results = []
    users = [threading.Thread(target=lambda: results.append(nest(3))) for _ in range(6)]
    for user in users:
        user.start()
    for user in users:
        user.join(timeout=30)
    assert not any(user.is_alive() for user in users)
    assert results == [8] * 6
    assert len(_threads._idle) <= _threads._MAX_IDLE


def test_an_idle_thread_holds_no_result():
    class Big:
        pass

    with helper_thread() as other:
        future = other.submit(Big)
    kept = weakref.ref(future.result())
    del future
    gc.collect()
    assert kept() is None


def _child_uses_helpers(queue):
    queue.put(side_by_side(lambda: os.getpid(), lambda: os.getpid()))


@pytest.mark.skipif(sys.platform != "linux", reason="fork is the default start method on Linux only")
def test_a_forked_child_starts_its_own_helpers():
    side_by_side(lambda: None, lambda: None)  # the parent keeps an idle thread
    assert _threads._idle
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_child_uses_helpers, args=(queue,))
    child.start()
    child.join(timeout=60)
    assert child.exitcode == 0
    first, second = queue.get(timeout=5)
    assert first == second == child.pid
