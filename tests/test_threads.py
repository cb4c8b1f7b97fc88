"""The kernels' thread pool (`moex.kernels.cpu.threads.over`): contiguous ranges that cover every
item once, the calling thread taking the first; errors reach the caller after every thread ends.
`share`: every thread claims items from one counter, each item taken exactly once. The pool:
none of its threads carried into a forked child, two callers at once each served whole. A
`Crew`: its calls as `share` and `over` make them, its worker out of its loop when idle or
released, a failing call said, and none of its state carried into a forked child."""

import os
import threading
import time
import warnings

import numba
import numpy as np
import pytest

from moex.kernels.cpu import threads


@pytest.fixture
def two_threads():
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs 2 numba threads")
    before = numba.get_num_threads()
    numba.set_num_threads(2)
    yield
    numba.set_num_threads(before)


@pytest.mark.parametrize("items", [1, 2, 5, 37])
def test_ranges_cover_every_item_once(two_threads, items):
    calls = []
    threads.over(lambda lo, hi, tag: calls.append((lo, hi, tag, threading.get_ident())), items,
                 "x")
    covered = sorted(i for lo, hi, _, _ in calls for i in range(lo, hi))
    assert covered == list(range(items))
    assert all(tag == "x" and hi > lo for lo, hi, tag, _ in calls)
    assert len(calls) == min(2, items)
    first = min(calls)
    assert first[0] == 0 and first[3] == threading.get_ident()  # the caller takes the first


def test_no_items_no_call(two_threads):
    calls = []
    threads.over(lambda lo, hi: calls.append((lo, hi)), 0)
    assert calls == []


def test_an_error_in_another_thread_reaches_the_caller_after_every_thread_ends(two_threads):
    finished = []

    def kernel(lo, hi):
        if lo > 0:
            raise ValueError("in the other thread")
        time.sleep(0.2)
        finished.append(lo)

    with pytest.raises(ValueError, match="other thread"):
        threads.over(kernel, 2)
    assert finished == [0]


def test_the_count_follows_numbas_setting(two_threads):
    """`threads.count` reads numba's threading layer directly (no process lock per call): what
    `numba.set_num_threads` set, in this thread, before and after a change."""
    assert threads.count() == numba.get_num_threads() == 2
    numba.set_num_threads(1)
    assert threads.count() == 1
    numba.set_num_threads(2)
    assert threads.count() == 2


@numba.njit(nogil=True)
def _claiming(lo, hi, queue, taken, spin):
    """Claims items until none is left, counting each item's takings, with `spin` iterations of
    work per item (so that both threads are inside at once)."""
    item = lo + threads.claim(queue)
    while item < hi:
        x = 0.0
        for k in range(spin):
            x += k * 1e-9
        taken[item] += 1 if x >= 0 else 2
        item = lo + threads.claim(queue)


@pytest.mark.parametrize("items", [1, 2, 7, 75, 1000])
def test_shared_items_are_each_taken_exactly_once(two_threads, items):
    """On two threads and on one, again with the counter left as the last call left it (`share`
    resets it): every item taken once, none past the end."""
    queue = np.zeros(1, np.int64)
    for count in (2, 1, 2):
        numba.set_num_threads(count)
        taken = np.zeros(items + 1, np.int64)
        threads.share(_claiming, items, queue, queue, taken, 20_000)
        assert (taken[:items] == 1).all() and taken[items] == 0
        assert queue[0] >= items  # (each thread's last claim went past the end)


def _cover(items: int) -> list[int]:
    """Every item `over` hands out on the threads, sorted."""
    calls = []
    threads.over(lambda lo, hi: calls.append((lo, hi)), items)
    return sorted(i for lo, hi in calls for i in range(lo, hi))


def test_a_forked_child_starts_a_pool_of_its_own(two_threads):
    """A child of fork() has none of the parent's threads: its first call on two threads must
    not wait on one (it would hang)."""
    assert _cover(4) == list(range(4))  # (the parent's pool running)
    with warnings.catch_warnings():  # (Python 3.12 warns of a fork beside threads)
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        os._exit(0 if _cover(4) == list(range(4)) else 1)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            assert os.waitstatus_to_exitcode(status) == 0
            return
        time.sleep(0.05)
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    pytest.fail("the forked child's call on two threads never returned")


def test_two_callers_at_once_each_get_every_item(two_threads):
    results, errors = {}, []

    def caller(name: str, items: int) -> None:
        try:
            for _ in range(200):
                results[name] = _cover(items)
                assert results[name] == list(range(items))
        except BaseException as error:  # noqa: BLE001
            errors.append(error)

    callers = [threading.Thread(target=caller, args=(n, k)) for n, k in (("a", 5), ("b", 8))]
    for t in callers:
        t.start()
    for t in callers:
        t.join(60)
    assert not errors and results == {"a": list(range(5)), "b": list(range(8))}


@numba.njit(nogil=True)
def _doubled(lo, hi, values, failing):
    """values[lo:hi] doubled; an error at the value `failing`."""
    for i in range(lo, hi):
        if values[i] == failing:
            raise ValueError("a failing item")
        values[i] *= 2


def _bound(items: int):
    """A crew of `_claiming` (shared) and `_doubled` (over), the kernels compiled first."""
    queue, taken = np.zeros(1, np.int64), np.zeros(items + 1, np.int64)
    values = np.arange(items, dtype=np.float64)
    _claiming(0, 0, queue, taken, 1)
    _doubled(0, 0, values, -1.0)
    crew = threads.Crew([(_claiming, (queue, taken, 20_000)), (_doubled, (values, -1.0))])
    return crew, queue, taken, values


def _shared(crew, queue, taken, items: int) -> None:
    taken[:] = 0
    crew.share(0, _claiming, items, queue, queue, taken, 20_000)


@pytest.mark.parametrize("items", [1, 7, 75])
def test_a_crew_makes_the_calls_of_share_and_over(two_threads, monkeypatch, items):
    """Through the pool while its loop is neither compiled nor in the cache; then on its worker
    (its count of calls ended), on two threads and one: every item taken once, every value
    doubled once."""
    crew, queue, taken, values = _bound(items)
    with monkeypatch.context() as patch:
        patch.setattr(threads, "_loaded", lambda *args: False)
        _shared(crew, queue, taken, items)
    assert (taken[:items] == 1).all() and crew.futures[0] is None and not crew.ready
    crew.compile()
    for count in (2, 1, 2):
        numba.set_num_threads(count)
        _shared(crew, queue, taken, items)
        assert (taken[:items] == 1).all() and taken[items] == 0
    crew.over(1, items)
    assert (values == 2 * np.arange(items)).all()
    assert crew.control[0, 4] == crew.control[0, 0] == 2 + (items > 1)  # (2 shared, 1 over)


def test_a_crews_worker_leaves_when_idle_or_released_and_comes_back(two_threads):
    crew, queue, taken, _ = _bound(20)
    crew.compile()
    crew.PATIENCE = 60.0  # (however slow this minute: in its loop until released)
    _shared(crew, queue, taken, 20)
    assert crew.control[0, 6] == crew._SERVING and (taken[:20] == 1).all()
    assert _cover(4) == list(range(4))  # (a call through the pool releases it)
    assert crew.control[0, 6] == crew._OUT
    crew.PATIENCE = 1e-3
    _shared(crew, queue, taken, 20)
    assert (taken[:20] == 1).all()
    deadline = time.monotonic() + 30
    while crew.control[0, 6] != crew._OUT and time.monotonic() < deadline:
        time.sleep(0.01)  # (idle: it leaves)
    assert crew.control[0, 6] == crew._OUT
    crew.futures[0].result(30)
    assert crew.control[0, 4] == 3  # (its calls ended: 2 shared, 1 to leave)
    _shared(crew, queue, taken, 20)
    assert (taken[:20] == 1).all() and crew.control[0, 4] == 4


def test_a_failing_call_on_a_crews_worker_reaches_the_caller(two_threads):
    crew, _, _, values = _bound(8)
    crew.compile()
    values[6] = -1.0  # (the bound failing value; the worker's range is 4..7)
    with pytest.raises(RuntimeError, match="worker thread failed"):
        crew.over(1, 8)
    assert (values[:4] == 2 * np.arange(4)).all()  # the caller's range done, then the error
    values[6] = 6.0
    crew.over(1, 8)  # (the crew works on)
    assert values[7] == 14.0


def test_a_forked_child_starts_a_crew_worker_of_its_own(two_threads):
    crew, queue, taken, _ = _bound(30)
    crew.compile()
    crew.PATIENCE = 60.0
    _shared(crew, queue, taken, 30)
    assert crew.control[0, 6] == crew._SERVING  # (the parent's worker in its loop)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        _shared(crew, queue, taken, 30)
        os._exit(0 if (taken[:30] == 1).all() and crew.control[0, 4] == 2 else 1)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            crew.release()
            assert os.waitstatus_to_exitcode(status) == 0
            return
        time.sleep(0.05)
    crew.release()
    os.kill(pid, 9)
    os.waitpid(pid, 0)
    pytest.fail("the forked child's crew call never returned")


def test_a_crew_of_a_python_function_goes_through_the_pool(two_threads):
    """A bound kernel that is no numba dispatcher (a benchmark's timing wrapper) has no compiled
    entry point: its calls go through the pool, every item once."""
    crew, _, _, values = _bound(6)
    crew.compile()
    seen = []
    crew.kernels[1] = lambda lo, hi, *rest: (seen.append((lo, hi)), _doubled(lo, hi, *rest))
    crew.over(1, 6)
    assert sorted(seen) == [(0, 3), (3, 6)] and (values == 2 * np.arange(6)).all()
    assert crew.control[0, 0] == 0  # (nothing posted to a worker)
