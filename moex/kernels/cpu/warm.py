"""Compiling the kernels a training needs while it runs its first phase: a first run (an empty
numba cache) compiles the phase-1 kernel in the training process and, at the same time, the
phase-2, closed-loop and symbol kernels in a helper process that calls each on a tiny problem of
the same types and leaves them in the cache. Exact reruns make this safe: a kernel loaded from the
cache gives the bits of one compiled in the process (tested)."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from moex.kernels.cpu import phases

_helper: subprocess.Popen | None = None
_COMPILES = ("_gating_items", "_closed_blocks", "_nearest")  # what compile_later_phases calls


def _indexed(kernel) -> bool:
    """Whether `kernel` has a cache index on disk (numba's internals; False when unsure)."""
    try:
        return Path(kernel._cache._cache_file._index_path).exists()
    except AttributeError:
        return False


def cached() -> bool:
    """Whether the helper's last kernel (the closed loop) is in the cache."""
    from moex.kernels.cpu.closed_loop import _closed_blocks

    return _indexed(_closed_blocks)


def start(dtype: str) -> subprocess.Popen | None:
    """Start the helper when the later phases' kernels are not cached yet; None otherwise."""
    global _helper
    if cached():
        return None
    _helper = subprocess.Popen([sys.executable, "-m", "moex.kernels.cpu.warm", dtype],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return _helper


def wait_for(kernel) -> bool:
    """While the helper runs and has not cached `kernel` yet, wait for it rather than compile the
    same kernel beside it (on 2 cores that doubles the wait). Whether it waited."""
    waited = False
    if kernel.__name__ not in _COMPILES:
        return waited
    while _helper is not None and _helper.poll() is None and not _indexed(kernel):
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
    # in the order the run needs them (the run waits for the one it needs next): phase 2 (7 s on
    # an idle 2-core VM), ready before the run's phase 1 ends, then the closed loop (11 s)
    ghat = torch.full((1, 1, 4, 2), 0.5, dtype=torch_dtype).numpy()
    problem = phases.GatingProblem(ghat, np.zeros((1, 4, 2), dtype), model, GatingPhaseConfig(),
                                   [0])
    grads = {k: torch.zeros_like(v) for k, v in gating.items()}
    problem.value_and_grad(gating, grads, torch.ones(1, dtype=torch.bool))
    state = random_state(experts, gating, 1, 2, 1, generators[0])
    tangents = torch.zeros(state.flat().shape + (1,), dtype=torch_dtype)
    tangents[..., 0, 0] = 1.0
    closed_loop(experts, gating, state, 2, None, tangents, True)
    nearest_symbols(np.zeros((1, 2, 2)), np.zeros((2, 2)), np.arange(2))


if __name__ == "__main__":
    compile_later_phases(sys.argv[1])
