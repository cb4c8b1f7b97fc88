"""Compiling the kernels a training needs while it runs its first phase: a first run (an empty
numba cache) compiles the phase-1 kernel in the training process and, at the same time, the
closed-loop, phase-2 and symbol kernels in a helper process that calls each on a tiny problem of
the same types and leaves them in the cache. `moex.launch` starts the helper before the command's
imports (`moex.compile_helper`) and the run adopts it (`start`); a run started otherwise starts
its own. Exact reruns make this safe: a kernel loaded from the cache gives the bits of one
compiled in the process (tested)."""

import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from moex import compile_helper
from moex.kernels.cpu import phases

_helper: subprocess.Popen | None = None
_dtype: str | None = None  # the precision of the run (and its helper)
_COMPILES = ("_gating_items", "_closed_blocks", "_nearest")  # what compile_later_phases calls


def _indexed(kernel, dtype: str | None = None) -> bool:
    """Whether `kernel` has a cache index on disk holding a signature of `dtype` (any, when None;
    float32 arrays in the signature mean a float32 run). numba's internals; False when unsure."""
    try:
        if dtype is None:
            return Path(kernel._cache._cache_file._index_path).exists()
        return any(("float32" in str(key[0])) == (dtype == "float32")
                   for key in kernel._cache._cache_file._load_index())
    except (AttributeError, OSError, EOFError, pickle.UnpicklingError):
        return False


def cached(dtype: str) -> bool:
    """Whether the helper's two large kernels (closed loop, phase 2) are cached for `dtype`."""
    from moex.kernels.cpu.closed_loop import _closed_blocks

    return _indexed(_closed_blocks, dtype) and _indexed(phases._gating_items, dtype)


def start(dtype: str) -> subprocess.Popen | None:
    """Adopt the helper the `moex` command started for `dtype` (stopping one of another
    precision), or start one when the later kernels are not cached for `dtype`; None when none
    is needed."""
    global _helper, _dtype
    _dtype = dtype
    _helper = compile_helper.adopt(dtype)
    if _helper is not None:
        return _helper
    if cached(dtype):
        return None
    _helper = compile_helper.spawn(dtype)
    return _helper


def wait_for(kernel) -> bool:
    """While the helper runs and has not cached `kernel` yet, wait for it rather than compile the
    same kernel beside it (on 2 cores that doubles the wait). Whether it waited."""
    waited = False
    if kernel.__name__ not in _COMPILES:
        return waited
    while _helper is not None and _helper.poll() is None and not _indexed(kernel, _dtype):
        time.sleep(0.05)
        waited = True
    return waited


def compile_later_phases(dtype: str) -> None:
    """Call the phase-2, closed-loop and symbol kernels once on tiny inputs of `dtype`."""
    from moex.closed_loop import random_state
    from moex.kernels.cpu.closed_loop import closed_loop
    from moex.kernels.cpu.symbols import nearest_symbols
    from moex.model import ModelConfig, init_experts, init_gating
    from moex.train import GatingPhaseConfig

    torch_dtype = getattr(torch, dtype)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 2, 3
    generators = [torch.Generator().manual_seed(0)]
    gating = init_gating(model, 1, 2, generators, torch_dtype)
    experts = init_experts(model, 1, 2, generators, torch_dtype)
    # the closed loop first (about 12 s of an idle 2-core VM's core, the largest), then phase 2,
    # whose RNN passes (`rnn._forward`, `_backward`) the run's phase-1 kernel has cached by then,
    # so only its own functions are left (about 5 s): the run's phase 1 (compiling, then
    # training) ends about when they are ready
    state = random_state(experts, gating, 1, 2, 1, generators[0])
    tangents = torch.zeros(state.flat().shape + (1,), dtype=torch_dtype)
    tangents[..., 0, 0] = 1.0
    closed_loop(experts, gating, state, 2, None, tangents, True)
    ghat = torch.full((1, 1, 4, 2), 0.5, dtype=torch_dtype).numpy()
    problem = phases.GatingProblem(ghat, np.zeros((1, 4, 2), dtype), model, GatingPhaseConfig(),
                                   [0])
    grads = {k: torch.zeros_like(v) for k, v in gating.items()}
    problem.value_and_grad(gating, grads, torch.ones(1, dtype=torch.bool))
    nearest_symbols(np.zeros((1, 2, 2)), np.zeros((2, 2)), np.arange(2))


if __name__ == "__main__" and not cached(sys.argv[1]):
    compile_later_phases(sys.argv[1])
