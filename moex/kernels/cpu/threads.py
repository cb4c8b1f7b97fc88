"""The kernels' threads: every compiled kernel is a serial `nogil` function over a range of
independent items (blocks of lanes, runs, chunks of series), and `over` runs one call per thread on
contiguous ranges, the calling thread taking the first.

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
from concurrent.futures import ThreadPoolExecutor

import torch
from numba import get_num_threads
from numba.np.ufunc import parallel

logger = logging.getLogger("moex.kernels.cpu")

_pool: ThreadPoolExecutor | None = None
_workers = 0
_read = None  # the threading layer's own count, once numba has loaded it


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


def over(kernel, items: int | range, *args) -> None:
    """kernel(lo, hi, *args) for contiguous ranges that cover 0..items-1 (or the range `items`),
    one per thread."""
    global _pool, _workers
    first, items = (items.start, len(items)) if isinstance(items, range) else (0, items)
    threads = min(count(), items)
    if threads <= 1:
        if items > 0:
            kernel(first, first + items, *args)
        return
    if _workers < threads - 1:
        _pool, _workers = ThreadPoolExecutor(threads - 1, "moex-kernel"), threads - 1
        if torch.get_num_threads() > 1:
            torch.set_num_threads(1)
            logger.info("PyTorch's intra-op threads set to 1: the compiled kernels' %d threads "
                        "use the cores", threads)
    bounds = [first + items * t // threads for t in range(threads + 1)]
    futures = [_pool.submit(kernel, bounds[t], bounds[t + 1], *args) for t in range(1, threads)]
    try:
        kernel(bounds[0], bounds[1], *args)
    finally:  # never return (or raise) while another thread still writes the arrays
        for future in futures:
            future.exception()
    for future in futures:
        future.result()
