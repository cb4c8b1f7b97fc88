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

The threads beyond the calling one are a pool's; a training step's calls go instead to a `Crew`
(where its loop is compiled), whose workers wait between the calls inside compiled code and
start each one without the GIL.

The first call on more than one thread sets PyTorch's intra-op threads to 1 for the process: the
training loop's tensor operations are small, and after each one PyTorch's OpenMP threads spin
for a while on the cores the kernel threads need (a 2-run training on 2 threads ran its phase 1
at half speed beside them; BENCHMARKS.md's history).
"""

import logging
import os
import platform
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np
import torch
from llvmlite import ir
from numba import config, get_num_threads, njit, typeof, types
from numba.core import cgutils
from numba.core.typing.typeof import Purpose
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
    for crew in Crew.live:  # (their workers were the parent's)
        crew.control[:, 6] = Crew._OUT


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
    threads = len(ranges)
    if threads <= 1:
        for lo, hi in ranges:
            kernel(lo, hi, *args)
        return
    for crew in Crew.live:  # (its workers out of their loops: the pool's threads free)
        crew.release()
    _grow(threads - 1)
    futures = [_pool.submit(kernel, *ranges[t], *args) for t in range(1, threads)]
    try:
        kernel(*ranges[0], *args)
    finally:  # never return (or raise) while another thread still writes the arrays
        for future in futures:
            future.exception()
    for future in futures:
        future.result()


def _grow(workers: int) -> None:
    """The pool, with at least `workers` threads."""
    global _pool, _workers
    if _workers < workers:
        _pool, _workers = ThreadPoolExecutor(workers, "moex-kernel"), workers
        if torch.get_num_threads() > 1:
            torch.set_num_threads(1)
            logger.info("PyTorch's intra-op threads set to 1: the compiled kernels' %d threads "
                        "use the cores", workers + 1)


class Crew:
    """The pool's threads held inside a compiled loop (`_serve`) from a bound call's first use
    on (a stepper's: `moex.kernels.cpu.step`), running the calls bound here as the calling thread
    posts them (`share`, `over`; one calling thread per crew) without
    the GIL: a worker that waits watches a counter (an atomic load and the CPU's spin-wait hint)
    and calls the bound kernel through its compiled entry point, so that neither its start nor
    the caller's wait for its end takes the GIL or wakes a thread. Through the pool each call's
    worker started 80-100 µs after the caller (woken by the host, then waiting for the GIL) and
    the caller returned 70 µs after the worker's end (the 2-vCPU AMD EPYC VM; BENCHMARKS.md).
    A worker leaves its loop after `PATIENCE` seconds without a call (the training loop's work
    between steps is shorter) or as soon as a call through the pool needs the threads (`_run`
    releases every crew first); while it waits it keeps its core busy.

    The loop is compiled for the bound calls' types, and its wrapper, which unboxes their nested
    tuples of arrays, takes numba 3.2-3.6 s to compile (a phase's stepper; the AMD EPYC VM)
    against 1-2.7 % of a step it saves at 30 networks on two threads: so a crew works only where
    the loop is compiled already or loads from numba's cache (`ready`), or once `compile` was
    called (the stepper calls it for a phase long enough to gain more than it costs,
    `moex.kernels.cpu.step.LONG`); until then its calls go through the pool, as they do while a
    kernel is not compiled yet (no worker watches while the calling thread compiles).

    Args:
        calls: (kernel, rest) pairs: a call runs kernel(lo, hi, *rest) on each thread, `rest`
            bound here (the worker reads these very arrays).
    """

    PATIENCE = 2e-3
    FIELDS = 8  # per worker: posted, job, lo, hi, ended, status, state (a cache line of int64)
    _OUT, _SERVING, _HELD = range(3)  # a worker's state: out of its loop, waiting, held for a call
    live: weakref.WeakSet = weakref.WeakSet()  # the crews made (`_run` releases them)

    def __init__(self, calls: list):
        self.kernels = [kernel for kernel, _ in calls]
        self.calls = tuple(tuple(rest) for _, rest in calls)
        self.addresses = np.zeros(len(calls), np.int64)  # entry points, once compiled
        self.control = np.zeros((max(config.NUMBA_NUM_THREADS, 2), self.FIELDS), np.int64)
        self.futures: list = [None] * len(self.control)
        self.ready = False  # whether `_serve` is compiled for the calls (`compile`, `_loaded`)
        self.looked = False  # whether the cache was looked in
        Crew.live.add(self)
        # a crew let go of (its stepper's training over) lets its workers go at once, rather
        # than have the next crew's first call wait for them to leave
        weakref.finalize(self, _release, self.control)

    def compile(self) -> None:
        """`_serve` compiled (or loaded) for the calls now."""
        if not self.ready:
            control = np.zeros(self.FIELDS, np.int64)
            _post(control, -1, 0, 0)  # (it leaves at once)
            _serve(control, 0, self.addresses, self.calls, 1)
            self.ready = True

    def share(self, job: int, kernel, items: int, queue: np.ndarray, *rest) -> None:
        """`threads.share` of call `job` (kernel and rest: the bound ones, as the caller's own
        part takes them)."""
        workers = self._workers(job)
        if not workers:
            share(kernel, items, queue, *rest)
            return
        queue[0] = 0
        self._call(job, [(0, items)] * (workers + 1), rest)

    def over(self, job: int, items: int) -> None:
        """`threads.over` of call `job` over 0..items-1."""
        workers = min(self._workers(job), items - 1)
        if workers < 1:
            over(self.kernels[job], items, *self.calls[job])
            return
        bounds = [items * t // (workers + 1) for t in range(workers + 2)]
        self._call(job, list(pairwise(bounds)), self.calls[job])

    def release(self) -> None:
        """Every worker out of its loop (a call through the pool comes)."""
        _release(self.control)

    def _workers(self, job: int) -> int:
        """The workers a call takes: none (the pool instead, or the calling thread alone) on
        one thread, and until the kernel is compiled for its call (its entry point known) and
        `_serve` for the crew's calls."""
        workers = count() - 1
        if workers < 1:
            return 0
        if not self.addresses[job]:
            self.addresses[job] = _entry(self.kernels[job], (0, 0, *self.calls[job]))
            if not self.addresses[job]:
                return 0
        if not self.ready and not self.looked:
            self.looked = True
            self.ready = _loaded(_serve, (self.control[0], 0, self.addresses, self.calls, 0))
        return workers if self.ready else 0

    def _call(self, job: int, ranges: list, rest: tuple) -> None:
        for other in Crew.live:
            if other is not self:
                other.release()
        posted = [self._post(w, job, lo, hi) for w, (lo, hi) in enumerate(ranges[1:])]
        try:
            self.kernels[job](*ranges[0], *rest)
        finally:  # never return (or raise) while another thread still writes the arrays
            for w, count_ in enumerate(posted):
                self._await(w, count_)

    def _post(self, w: int, job: int, lo: int, hi: int) -> int:
        """The call posted to worker w, its loop entered first where it had left it."""
        control = self.control[w]
        if not _hold(control):  # (out of its loop, or leaving it: a new one, which sees the post)
            control[6] = self._HELD
            _grow(w + 1)
            self.futures[w] = _pool.submit(_serve, control, control[0], self.addresses,
                                           self.calls, _patience(self.PATIENCE))
        return _post(control, job, lo, hi)

    def _await(self, w: int, posted: int) -> None:
        control = self.control[w]
        while not _await(control, posted, 1 << 14):
            future = self.futures[w]
            # out of its loop with the call not ended (it raised; the end looked at again: it
            # may have ended the call and left, idle, after the look above)
            if future is not None and future.done() and not _await(control, posted, 1):
                control[6] = self._OUT
                future.result()
                raise RuntimeError("a kernel thread left its loop before it ended a call")
        if control[5]:
            status, control[5] = control[5], 0
            raise RuntimeError(f"a kernel call on a worker thread failed (status {status})")


def _release(control: np.ndarray) -> None:
    """A crew's workers out of their loops (each row of `control`; a worker waiting in its loop
    ends the call to leave at once): `Crew.release`, and a crew's finaliser once it is gone."""
    for row in control:
        if _hold(row):
            posted = _post(row, -1, 0, 0)
            while not _await(row, posted, 1 << 14):
                pass


_spins_per_second = 0.0


def _patience(seconds: float) -> int:
    """The spin-wait rounds (`_await`) in `seconds`, measured once."""
    global _spins_per_second
    if not _spins_per_second:
        control, rounds = np.zeros(Crew.FIELDS, np.int64), 1 << 14
        _await(control, 1, rounds)  # (compiled or loaded first)
        start = time.perf_counter()
        _await(control, 1, rounds)
        _spins_per_second = rounds / max(time.perf_counter() - start, 1e-9)
    return int(seconds * _spins_per_second)


def _loaded(dispatcher, args: tuple) -> bool:
    """Whether `dispatcher` is compiled for these arguments' types in this process, or now
    loaded from numba's cache, without compiling it (numba's internals, as `Dispatcher.compile`
    loads an overload: False where they differ)."""
    signature = tuple(typeof(a, Purpose.argument) for a in args)
    if signature in dispatcher.overloads:
        return True
    try:
        result = dispatcher._cache.load_overload(signature, dispatcher.targetctx)
        if result is None:
            return False
        dispatcher.targetctx.insert_user_function(result.entry_point, result.fndesc,
                                                  [result.library])
        dispatcher.add_overload(result)
    except Exception:  # noqa: BLE001 (another numba: compiled where a long phase asks)
        return False
    return signature in dispatcher.overloads


def _entry(kernel, args: tuple) -> int:
    """The address of kernel's compiled function (numba's calling convention) for these
    arguments' types, or 0 where it is not compiled for them or is no numba dispatcher (a
    Python function: a benchmark's wrapper, say)."""
    overloads = getattr(kernel, "overloads", None)
    if overloads is None:
        return 0
    result = overloads.get(tuple(typeof(a, Purpose.argument) for a in args))
    if result is None:
        return 0
    return result.library.get_pointer_to_function(result.fndesc.llvm_func_name)


@intrinsic
def _load(typingctx, control, index):
    """control[index], an atomic load with acquire ordering (never hoisted out of a loop;
    control: a C-contiguous int64 array)."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        return builder.load_atomic(builder.gep(array.data, [arguments[1]]), "acquire", 8)

    return types.int64(control, index), codegen


@intrinsic
def _store(typingctx, control, index, value):
    """control[index] = value, an atomic store with release ordering."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        builder.store_atomic(arguments[2], builder.gep(array.data, [arguments[1]]), "release", 8)
        return context.get_dummy_value()

    return types.none(control, index, types.int64), codegen


@intrinsic
def _swap(typingctx, control, index, old, new):
    """control[index] = new where it was old, atomically (sequentially consistent); whether
    it was."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        pointer = builder.gep(array.data, [arguments[1]])
        pair = builder.cmpxchg(pointer, arguments[2], arguments[3], "seq_cst", "seq_cst")
        return builder.extract_value(pair, 1)

    return types.boolean(control, index, types.int64, types.int64), codegen


_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")


@intrinsic
def _pause(typingctx):
    """The CPU's spin-wait hint (x86's `pause`; nothing elsewhere)."""
    def codegen(context, builder, signature, arguments):
        if _X86:
            hint = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), []), "llvm.x86.sse2.pause")
            builder.call(hint, [])
        return context.get_dummy_value()

    return types.none(), codegen


@intrinsic
def _invoke(typingctx, addresses, job, lo, hi, calls):
    """kernel(lo, hi, *calls[job]) through its entry point addresses[job] (`_entry`), in numba's
    calling convention; its status (0: returned, else numba's error code)."""
    def codegen(context, builder, signature, arguments):
        array = context.make_array(signature.args[0])(context, builder, arguments[0])
        status = cgutils.alloca_once_value(builder, ir.Constant(ir.IntType(32), 0))
        for j, rest in enumerate(calls):
            with builder.if_then(builder.icmp_signed("==", arguments[1],
                                                     ir.Constant(arguments[1].type, j))):
                argtys = [types.int64, types.int64, *rest]
                function = context.call_conv.get_function_type(types.none, argtys)
                address = builder.load(builder.gep(array.data, [ir.Constant(ir.IntType(64), j)]))
                values = builder.extract_value(arguments[4], j)
                code, _ = context.call_conv.call_function(
                    builder, builder.inttoptr(address, function.as_pointer()), types.none, argtys,
                    [arguments[2], arguments[3],
                     *(builder.extract_value(values, k) for k in range(len(rest)))])
                builder.store(builder.select(code.is_error, code.code, status.type.pointee(0)),
                              status)
        return builder.load(status)

    return types.int32(addresses, job, lo, hi, calls), codegen


@njit(nogil=True, cache=True)
def _post(control, job, lo, hi):  # pragma: no cover
    """A call posted to a worker (`_serve`): its job and range, then its count (release: the
    worker that sees the count sees the rest); the count."""
    control[1], control[2], control[3] = job, lo, hi
    posted = control[0] + 1
    _store(control, 0, posted)
    return posted


@njit(nogil=True, cache=True)
def _await(control, posted, spins):  # pragma: no cover
    """Waits, without the GIL, up to `spins` loads for the worker to end call `posted`;
    whether it did."""
    for _ in range(spins):
        if _load(control, 4) == posted:
            return True
        _pause()
    return False


@njit(nogil=True, cache=True)
def _serve(control, seen, addresses, calls, patience):  # pragma: no cover
    """A worker's loop (`Crew`): each call posted after `seen` run, its end counted; it leaves
    on a call to leave (job -1) or after `patience` rounds without a call, where no caller
    holds it (state from waiting to out, atomically: a caller that holds it first posts)."""
    rounds = 0
    while True:
        posted = _load(control, 0)
        if posted == seen:
            rounds += 1
            if rounds >= patience and _swap(control, 6, 1, 0):
                return
            _pause()
            continue
        rounds, seen = 0, posted
        job = control[1]
        if job < 0:
            _store(control, 6, 0)
            _store(control, 4, posted)
            return
        status = _invoke(addresses, job, control[2], control[3], calls)
        if status != 0:
            control[5] = status
        _store(control, 6, 1)
        _store(control, 4, posted)


@njit(nogil=True, cache=True)
def _hold(control):  # pragma: no cover
    """Whether the worker was waiting in its loop, now held for a call (it will not leave)."""
    return _swap(control, 6, 1, 2)
