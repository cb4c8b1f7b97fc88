"""Compiling the kernels a training needs while it runs its first phase: a first run (an empty
numba cache) compiles the phase-1 kernel in the training process and, at the same time, the
phase-2, closed-loop and symbol kernels in a helper process that calls each on a tiny problem of
the same types and leaves them in the cache. Exact reruns make this safe: a kernel loaded from the
cache gives the bits of one compiled in the process (tested)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from moex.kernels.cpu import phases


def cached() -> bool:
    """Whether the closed-loop kernel has a cache index (numba's internals; False when
    unsure)."""
    from moex.kernels.cpu.closed_loop import _closed_loop

    try:
        return Path(_closed_loop._cache._cache_file._index_path).exists()
    except AttributeError:
        return False


def start(dtype: str) -> subprocess.Popen | None:
    """Start the helper when the later phases' kernels are not cached yet; None otherwise."""
    if cached():
        return None
    return subprocess.Popen([sys.executable, "-m", "moex.kernels.cpu.warm", dtype],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


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
    # the longest compilation first (the closed loop, 15-23 s on a 2-core VM): of the three it
    # saves the run the most when the helper does not finish before the run needs them all
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


if __name__ == "__main__":
    compile_later_phases(sys.argv[1])
