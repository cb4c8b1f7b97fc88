"""The cpu kernels the suite calls, compiled into numba's cache once before pytest's workers start
(`python -m tests.precompile <precision>`, from `conftest.pytest_sessionstart`): otherwise on a
fresh checkout every worker and every `moex` subprocess that starts before the cache holds a
kernel compiles it again beside the others (on a 2-core VM the suite took 12:22 from an empty
cache against 10:43 with a full one). Phase 1 at both rates here, then what a first run's helper
compiles (`moex.precompile`)."""

import sys

import torch

from moex.config.model import ModelConfig
from moex.config.train import ExpertPhaseConfig, TrainConfig
from moex.kernels import get_backend
from moex.model import init_experts
from moex.precompile import compile_later_phases
from moex.train import train_experts


def compile_kernels(precision: str) -> None:
    """Two phase-1 steps of one tiny network at a fixed and an adaptive rate, then phase 2, the
    closed loop and the symbols' kernels, all in `precision`."""
    dtype = getattr(torch, precision)
    model = ModelConfig()
    model.experts.context_size = 2
    series = torch.sin(torch.arange(12, dtype=dtype)).reshape(1, 6, 2)
    for adaptive in (False, True):
        experts = init_experts(model, 1, 2, [torch.Generator().manual_seed(0)], dtype)
        train_experts(experts, series, model, ExpertPhaseConfig(steps=2, adaptive_lr=adaptive),
                      TrainConfig(), backend=get_backend("cpu"))
    compile_later_phases(precision)


if __name__ == "__main__":
    compile_kernels(sys.argv[1])
