"""Compiling the kernels a training needs while it runs its first phase, the run's side: a first
run (an empty numba cache) compiles the phase-1 kernel in the training process and, at the same
time, the closed-loop, phase-2 and symbol kernels in a helper process (`helper`) that calls each
on a tiny problem of the same types (the gating RNN of the run's sizes, which the run writes
to the helper's stdin: phase 2's kernel is compiled for them, `lanes.sizes`) and leaves them in
the cache. `moex.launch` starts the helper
before the command's imports (`moex.compile_helper`) and the run adopts it (`start`); a run
started otherwise starts its own. Exact reruns make this safe: a kernel loaded from the cache
gives the bits of one compiled in the process (tested). Imports no kernel module: they import
this one (`lanes.first_use`)."""

import logging
import pickle
import subprocess
import time
from pathlib import Path

from moex import compile_helper

_helper: subprocess.Popen | None = None
_dtype: str | None = None  # the precision of the run (and its helper)
_sizes = None  # the numba type of the gating RNN's `lanes.sizes` in the run
_COMPILES = ("gating_items", "closed_blocks", "_nearest")  # what the helper compiles
_SIZED = ("gating_items",)  # compiled for the run's sizes
_failure_told = False
logger = logging.getLogger("moex.kernels.cpu")


def _indexed(kernel, dtype: str | None = None, sizes=None) -> bool:
    """Whether `kernel` has a cache index on disk holding a signature of `dtype` (any, when None;
    float32 arrays in the signature mean a float32 run) and, for the kernels compiled for the
    run's sizes, with `sizes` (the numba type of `lanes.sizes`) among its argument types: types
    compared as types (a string match had compared two spellings of them and never matched).
    numba's internals; False when unsure."""
    try:
        if dtype is None:
            return Path(kernel._cache._cache_file._index_path).exists()
        sized = sizes is not None and kernel.__name__ in _SIZED
        return any(("float32" in str(key[0])) == (dtype == "float32")
                   and (not sized or sizes in key[0])
                   for key in kernel._cache._cache_file._load_index())
    except (AttributeError, OSError, EOFError, pickle.UnpicklingError):
        return False


def cached(dtype: str, kernels: tuple, sizes=None) -> bool:
    """Whether `kernels` (the helper's two large ones: closed loop, phase 2) are cached for
    `dtype` (phase 2 for `sizes`, the numba type of its `lanes.sizes`)."""
    return all(_indexed(kernel, dtype, sizes) for kernel in kernels)


def start(dtype: str, later: tuple, gating: tuple[int, int, int],
          sizes) -> subprocess.Popen | None:
    """Adopt the helper the `moex` command started for `dtype` (stopping one of another
    precision), or start one when the kernels `later` are not cached for `dtype` and the gating
    RNN's units, inputs and outputs `gating` (`sizes`: the numba type of their `lanes.sizes`);
    tell the helper those sizes. None when no helper is needed."""
    global _helper, _dtype, _sizes
    _dtype, _sizes = dtype, sizes
    _helper = compile_helper.adopt(dtype)
    if _helper is None and cached(dtype, later, _sizes):
        compile_helper.mark_cached(dtype)  # the next command starts no helper
        return None
    _helper = _helper or compile_helper.spawn(dtype)
    compile_helper.tell(_helper, gating)
    return _helper


def wait_for(kernel) -> bool:
    """While the helper runs and has not cached `kernel` yet, wait for it rather than compile the
    same kernel beside it (on 2 cores that doubles the wait). Whether it waited. A helper that
    failed is said once in the log (the run then compiles the kernel itself)."""
    global _failure_told
    waited = False
    if kernel.__name__ not in _COMPILES:
        return waited
    while _helper is not None and _helper.poll() is None and not _indexed(kernel, _dtype,
                                                                            _sizes):
        time.sleep(0.05)
        waited = True
    if _helper is not None and _helper.poll() and not _failure_told:
        _failure_told = True
        logger.warning("the compile helper (python -m moex.precompile %s) failed with exit code "
                       "%d; the run compiles its kernels itself", _dtype, _helper.returncode)
    return waited
