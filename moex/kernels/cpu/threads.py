"""The kernels' threads: every compiled kernel is a serial `nogil` function over a range of
independent items (blocks of lanes, runs, chunks of series), and `over` runs one call per thread on
contiguous ranges, the calling thread taking the first; `share` runs one call per thread on all of
them, each thread taking the next item from a counter it adds to atomically (`claim`) until none
is left: a training step's main call, whose many items (a block of lanes each) balance out a
thread held up (1.02-1.08x over equal halves at 30 networks, BENCHMARKS.md).

Why not numba's `prange`: each `prange` loop compiles into a function of its own that links and
re-optimises everything it calls, and the function around it does so again; the phase-1 kernel's
seven loops made a first run spend about 35 s compiling it (BENCHMARKS.md's history). The items
and their arithmetic are the same whichever thread runs them, so results do not depend on the
number of threads: `numba.get_num_threads()` (`NUMBA_NUM_THREADS`, `numba.set_num_threads`) sets it.

The other threads are the pool's workers (`_Pool`), each handed one range of a call. A thread that
waits (a worker for its next range, the caller for a worker to end) first watches a counter
without the GIL for up to a millisecond, then sleeps: a handoff through a blocking queue had cost
55-100 µs per call on the 2-vCPU AMD EPYC VM (a vCPU that slept is woken by the host), against
20-25 µs so. While it watches, a worker keeps its core busy: between a training step's calls (a
few hundred µs of Python) it always does, as a kernel's threads do while it computes.

The first call on more than one thread sets PyTorch's intra-op threads to 1 for the process: the
training loop's tensor operations are small, and after each one PyTorch's OpenMP threads spin
for a while on the cores the kernel threads need (a 2-run training on 2 threads ran its phase 1
at half speed beside them; BENCHMARKS.md's history).
"""

import logging
import os
import threading
import time
from itertools import pairwise

import numpy as np
import torch
from numba import config, get_num_threads, njit, types
from numba.extending import intrinsic
from numba.np.ufunc import parallel

logger = logging.getLogger("moex.kernels.cpu")

_pool = None  # the `_Pool`, made at the first call on more than one thread
_read = None  # the threading layer's own count, once numba has loaded it


def _forget_pool() -> None:
    """In a child of fork(), which has none of the pool's threads: a new pool at the first call
    on more than one thread (the old one would hand the calls to threads that do not exist)."""
    global _pool
    _pool = None


os.register_at_fork(after_in_child=_forget_pool)


def count() -> int:
    """The number of threads a kernel call uses: what `numba.get_num_threads` returns, read from
    numba's threading layer directly once `get_num_threads` has loaded it. `get_num_threads`
    itself takes a process-wide lock on every call (to load the layer once), letting go of the
    GIL: in the training loop 9-12 µs a call, in a bad minute 220 µs (15 % of a phase-1 epoch at
    one network), against 2-4 µs (numba's internals: `get_num_threads` where they moved)."""
    global _read
    if _read is None:
        get_num_threads()  # loads the layer (and checks it)
        _read = getattr(parallel, "_get_num_threads", get_num_threads)
    return _read()


SPLIT = 1 << 16  # numbers a call passes over from which it goes to the threads (`by_size`): a
# handoff costs 20-25 µs (the AMD EPYC VM, 12-07; 55-100 µs before `_Pool`), a pass over 2^16
# entries ~30-60 µs (phase 1's (R, P) buffers at R = 30: 6 · 10^5)


def by_size(entries: int):
    """How to run a call that passes over `entries` numbers: `over` the threads from `SPLIT` on,
    else `one` (a handoff would cost more than the pass)."""
    return over if entries >= SPLIT else one


def one(kernel, items: int, *args) -> None:
    """kernel(0, items, *args) on the calling thread."""
    kernel(0, items, *args)


def over(kernel, items: int | range, *args) -> None:
    """kernel(lo, hi, *args) for contiguous ranges that cover 0..items-1 (or the range `items`),
    one per thread."""
    first, items = (items.start, len(items)) if isinstance(items, range) else (0, items)
    threads = min(count(), items)
    bounds = [first + items * t // threads for t in range(threads + 1)] if threads else []
    _run(kernel, list(pairwise(bounds)), args)


def share(kernel, items: int, queue: np.ndarray, *args) -> None:
    """kernel(0, items, *args) on every thread at once, the threads taking the items one at a
    time from `queue` (`claim`; reset here), which `args` hand the kernel: a thread held up
    (this VM's vCPUs stall for milliseconds now and then) takes fewer, instead of the others
    waiting for its equal share. Which thread computes an item changes no bit."""
    queue[0] = 0
    _run(kernel, [(0, items)] * min(count(), items), args)


@intrinsic
def claim(typingctx, queue):
    """The next item of a `share` call: queue[0] before adding 1 to it, atomically (queue: a
    C-contiguous int64 array)."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw("add", array.data, one, "monotonic")

    return types.int64(queue), codegen


@intrinsic
def done(typingctx, counts, index):
    """counts[index] before subtracting 1 from it, atomically, with acquire-release ordering:
    the thread that takes a count from 1 to 0 sees every write the others made before theirs
    (counts: a C-contiguous int64 array)."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        pointer = builder.gep(array.data, [arguments[1]])
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw("sub", pointer, one, "acq_rel")

    return types.int64(counts, index), codegen


def _run(kernel, ranges: list, args: tuple) -> None:
    """kernel(lo, hi, *args) for each (lo, hi) of `ranges`, one per thread, the calling thread
    taking the first (alone, without the pool, where there is one; all of them in turn where
    another caller holds the pool)."""
    if len(ranges) <= 1 or not _ensure_pool(len(ranges) - 1).busy.acquire(blocking=False):
        for lo, hi in ranges:
            kernel(lo, hi, *args)
        return
    try:
        _pool.run(kernel, ranges, args)
    finally:
        _pool.busy.release()


def _ensure_pool(workers: int):
    global _pool
    if _pool is None:
        _pool = _Pool()
        if torch.get_num_threads() > 1:
            torch.set_num_threads(1)
            logger.info("PyTorch's intra-op threads set to 1: the compiled kernels' %d threads "
                        "use the cores", workers + 1)
    _pool.grow(workers)
    return _pool


@intrinsic
def _load(typingctx, flags, index):
    """flags[index], an atomic load with acquire ordering (never hoisted out of a loop; flags: a
    C-contiguous int64 array)."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        pointer = builder.gep(array.data, [arguments[1]])
        return builder.load_atomic(pointer, "acquire", 8)

    return types.int64(flags, index), codegen


@intrinsic
def _store(typingctx, flags, index, value):
    """flags[index] = value, an atomic store with release ordering."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        pointer = builder.gep(array.data, [arguments[1]])
        builder.store_atomic(arguments[2], pointer, "release", 8)
        return context.get_dummy_value()

    return types.none(flags, index, types.int64), codegen


@njit(nogil=True, cache=True)
def _await(flags, index, old, spins):  # pragma: no cover
    """Waits, without the GIL, up to `spins` loads, for flags[index] to differ from `old`;
    whether it did."""
    for _ in range(spins):
        if _load(flags, index) != old:
            return True
    return False


@njit(nogil=True, cache=True)
def _end_and_await(ended, posted, w, count, spins, grace):  # pragma: no cover
    """A worker's side, without the GIL: `count` ranges ended (the caller, watching `ended`
    without the GIL too, then takes the GIL uncontended), then up to `spins` loads for a range
    more to be posted, and `grace` loads more once it is (the caller drops the GIL as it enters
    its own range: a worker that asked for it before would sleep on it, as long to wake as the
    handoff it saved); whether it was."""
    _store(ended, w, count)
    for _ in range(spins):
        if _load(posted, w) != count:
            for _ in range(grace):
                _load(posted, w)
            return True
    return False


class _Pool:
    """The kernels' worker threads, each handed one range of a call at a time (`run`): its task,
    a count of ranges posted and its `go` semaphore released. The thread that waits (a worker for
    its next range, the caller for a worker's end) first watches the other's count without the
    GIL for up to `SPIN` seconds (`_end_and_await`, `_await`), then sleeps on the semaphore (a
    worker's `go`, the caller's `done`), which is released as well: a wait that saw the count
    takes it without sleeping. In a training on two threads a worker that slept started its
    range 70-100 µs after the caller and the caller returned 70 µs after the worker ended (the
    2-vCPU AMD EPYC VM: a vCPU that slept is woken by the host)."""

    SPIN, GRACE = 1e-3, 2e-5

    def __init__(self):
        size = max(config.NUMBA_NUM_THREADS, 2)
        self.posted, self.ended = np.zeros((2, size), np.int64)  # ranges handed, ended: counts
        self.tasks, self.errors = [None] * size, [None] * size
        self.go = [threading.Semaphore(0) for _ in range(size)]
        self.done = [threading.Semaphore(0) for _ in range(size)]
        self.busy, self.workers = threading.Lock(), 0
        loads = 1 << 16
        _await(self.posted, 0, 0, loads)  # (compiled or loaded, then timed)
        start = time.perf_counter()
        _await(self.posted, 0, 0, loads)
        per_second = loads / max(time.perf_counter() - start, 1e-9)
        self.spins, self.grace = int(per_second * self.SPIN), int(per_second * self.GRACE)

    def grow(self, workers: int) -> None:
        for w in range(self.workers, workers):
            threading.Thread(target=self._work, args=(w,), name=f"moex-kernel-{w}",
                             daemon=True).start()
        self.workers = max(self.workers, workers)

    def _work(self, w: int) -> None:
        ended = 0
        while True:
            _end_and_await(self.ended, self.posted, w, ended, self.spins, self.grace)
            self.go[w].acquire()
            kernel, lo, hi, args = self.tasks[w]
            self.tasks[w] = None
            try:
                kernel(lo, hi, *args)
            except BaseException as error:  # noqa: BLE001 (raised in the caller)
                self.errors[w] = error
            ended += 1
            self.done[w].release()

    def run(self, kernel, ranges: list, args: tuple) -> None:
        workers = range(len(ranges) - 1)
        for w in workers:
            self.tasks[w] = (kernel, *ranges[w + 1], args)
            self.go[w].release()
            self.posted[w] += 1
        try:
            kernel(*ranges[0], *args)
        finally:  # never return (or raise) while another thread still writes the arrays
            for w in workers:
                _await(self.ended, w, self.posted[w] - 1, self.spins)
                self.done[w].acquire()
        errors = [self.errors[w] for w in workers if self.errors[w] is not None]
        for w in workers:
            self.errors[w] = None
        if errors:
            raise errors[0]
