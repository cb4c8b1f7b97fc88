"""The helper process of a first run (`python -m moex.precompile <precision>`, started by
`moex.compile_helper`, adopted by `warm.start`): it calls the phase-2, closed-loop and symbol
kernels once on tiny inputs, so that numba compiles them into its cache while the run trains
phase 1. Nothing imports this module; it imports what it calls."""

import sys

import torch

from moex import compile_helper
from moex.config.model import ModelConfig
from moex.config.train import GatingPhaseConfig
from moex.kernels.cpu import LATER, phases, warm
from moex.kernels.cpu.closed_loop import closed_loop
from moex.kernels.cpu.symbols import nearest_symbols
from moex.model import init_experts, init_gating, random_state


def compile_later_phases(dtype: str) -> None:
    """Call the phase-2, closed-loop and symbol kernels once on tiny inputs of `dtype`."""
    torch_dtype = getattr(torch, dtype)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 2, 3
    generators = [torch.Generator().manual_seed(0)]
    gating = init_gating(model, 1, 2, generators, torch_dtype)
    experts = init_experts(model, 1, 2, generators, torch_dtype)
    # the closed loop first (about 11 s of an idle 2-core VM's core, the largest), then phase 2,
    # whose RNN passes (`rnn.forward_pass`, `backward_pass`) the run's phase-1 kernel has cached
    # by then, so only its own functions are left (about 5 s): ready a few seconds before the
    # run's phase 1 (compiling, then training) ends
    state = random_state(experts, gating, 1, num_features=2, delay=1, generator=generators[0])
    tangents = torch.zeros(state.flat().shape + (1,), dtype=torch_dtype)
    tangents[..., 0, 0] = 1.0
    closed_loop(experts, gating, state, 2, tangents=tangents, count=True)
    ghat = torch.full((1, 1, 4, 2), 0.5, dtype=torch_dtype)
    problem = phases.GatingProblem(ghat, torch.zeros((1, 4, 2), dtype=torch_dtype), model,
                                   GatingPhaseConfig(), seeds=[0])
    grads = {k: torch.zeros_like(v) for k, v in gating.items()}
    active = torch.ones(1, dtype=torch.bool)
    problem.value_and_grad(gating, grads, active)
    problem.value(gating, active)  # an adaptive trial: the record of the lanes' forward pass
    problem.value_and_grad(gating, grads, active)  # and its reuse (`lanes.Forwarded`)
    nearest_symbols(torch.zeros((1, 2, 2)), torch.zeros((2, 2)), torch.arange(2))


if __name__ == "__main__":
    if not warm.cached(sys.argv[1], LATER):
        compile_later_phases(sys.argv[1])
    compile_helper.mark_cached(sys.argv[1])
