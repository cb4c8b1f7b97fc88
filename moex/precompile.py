"""The helper process of a first run (`python -m moex.precompile <precision>`, started by
`moex.compile_helper`, adopted by `warm.start`): it calls the phase-2, closed-loop, noise and symbol
kernels once on tiny inputs, so that numba compiles them into its cache while the run trains
phase 1; phase 2 with the gating RNN's units, inputs and outputs that the run writes to its stdin
(`compile_helper.tell`; phase 2's kernel is compiled for them, `lanes.sizes`). Nothing imports
this module; it imports what it calls."""

import sys

import torch

from moex import compile_helper
from moex.config.model import ModelConfig
from moex.config.train import GatingPhaseConfig
from moex.kernels.cpu import phases
from moex.kernels.cpu.closed_loop import closed_loop
from moex.kernels.cpu.symbols import nearest_symbols
from moex.model import init_experts, init_gating, random_state


def compile_later_phases(dtype: str, sizes=None) -> None:
    """Call the phase-2, closed-loop, noise and symbol kernels once on tiny inputs of `dtype`;
    phase 2 for the gating RNN's units, inputs and outputs that `sizes` returns (a callable,
    called once the closed loop is compiled), or where it returns None 3 units, 2 experts and 2
    features."""
    torch_dtype = getattr(torch, dtype)
    model = ModelConfig()
    model.experts.context_size, model.gating.context_size = 2, 3
    generators = [torch.Generator().manual_seed(0)]
    gating = init_gating(model, 1, 2, generators, torch_dtype)
    experts = init_experts(model, 1, 2, generators, torch_dtype)
    # the closed loop first (about 11 s of an idle 2-core VM's core, the largest), then phase 2
    # for the run's gating RNN (its RNN passes compiled for its sizes): ready before the run's
    # phase 1 (compiling, then training) ends
    state = random_state(experts, gating, 1, num_features=2, delay=1, generator=generators[0])
    tangents = torch.zeros(state.flat().shape + (1,), dtype=torch_dtype)
    tangents[..., 0, 0] = 1.0
    closed_loop(experts, gating, state, 2, tangents=tangents, count=True)
    H, NI, K = (sizes and sizes()) or (3, 4, 2)
    model.gating.context_size, model.num_experts = H, K
    gating = init_gating(model, 1, NI - K, generators, torch_dtype)
    ghat = torch.full((1, 1, 4, K), 1.0 / K, dtype=torch_dtype)
    problem = phases.GatingProblem(ghat, torch.zeros((1, 4, NI - K), dtype=torch_dtype), model,
                                   GatingPhaseConfig(input_noise_var=1e-3), seeds=[0])
    problem.resample(0)  # phase 2's input noise, where a run has some
    grads = {k: torch.zeros_like(v) for k, v in gating.items()}
    active = torch.ones(1, dtype=torch.bool)
    problem.value_and_grad(gating, grads, active)
    nearest_symbols(torch.zeros((1, 2, 2)), torch.zeros((2, 2)), torch.arange(2))


def _told() -> tuple[int, ...] | None:
    """The gating RNN's sizes as the run writes them (`compile_helper.tell`); None at the end of
    the input (a run that ended or wrote nothing)."""
    line = sys.stdin.readline().split()
    return tuple(map(int, line)) if len(line) == 3 else None


if __name__ == "__main__":
    compile_later_phases(sys.argv[1], _told)
    compile_helper.mark_cached(sys.argv[1])
