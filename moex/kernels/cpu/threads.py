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

The first call on more than one thread sets PyTorch's intra-op threads to 1 for the process: the
training loop's tensor operations are small, and after each one PyTorch's OpenMP threads spin
for a while on the cores the kernel threads need (a 2-run training on 2 threads ran its phase 1
at half speed beside them; BENCHMARKS.md's history).
"""

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np
import torch
from numba import get_num_threads, types
from numba.extending import intrinsic
from numba.np.ufunc import parallel

logger = logging.getLogger("moex.kernels.cpu")

_pool: ThreadPoolExecutor | None = None
_workers = 0
_read = None  # the threading layer's own count, once numba has loaded it


def _forget_pool() -> None:
    """In a child of fork(), which has none of the pool's threads: a new pool at the first call
    on more than one thread (the old one would queue the calls for threads that do not exist)."""
    global _pool, _workers
    _pool, _workers = None, 0


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
# handoff costs 40-60 µs (55-61 on the AMD EPYC VM, 12-07), a pass over 2^16 entries ~30-60 µs
# (phase 1's (R, P) buffers at R = 30: 6 · 10^5)


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
    taking the first (alone, without the pool, where there is one)."""
    global _pool, _workers
    threads = len(ranges)
    if threads <= 1:
        for lo, hi in ranges:
            kernel(lo, hi, *args)
        return
    if _workers < threads - 1:
        _pool, _workers = ThreadPoolExecutor(threads - 1, "moex-kernel"), threads - 1
        if torch.get_num_threads() > 1:
            torch.set_num_threads(1)
            logger.info("PyTorch's intra-op threads set to 1: the compiled kernels' %d threads "
                        "use the cores", threads)
    futures = [_pool.submit(kernel, *ranges[t], *args) for t in range(1, threads)]
    try:
        kernel(*ranges[0], *args)
    finally:  # never return (or raise) while another thread still writes the arrays
        for future in futures:
            future.exception()
    for future in futures:
        future.result()
