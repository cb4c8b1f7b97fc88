"""Backends: where the time loops of training and evaluation run.

Three backends, each a module with the same names (the `Problem` protocol below and two
functions):

- `ExpertProblem(inputs, targets, model, phase, num_runs, device)`: phase 1 (Eqs. 9-13);
- `GatingProblem(gate_targets, inputs, model, phase, seeds, device)`: phase 2 (Eqs. 14-16);
- `closed_loop(experts, gating, state, steps, noise, tangents, count)`: the autonomous mixture
  (Sec. 2.2) with Lyapunov tangent vectors;
- `nearest_symbols(points, prototypes, prototype_symbols)`: the symbol of each generated point.

`reference` is the model's equations in PyTorch with autograd (any device); it is the oracle the
tests hold the others to. `cpu` is the compiled numba implementation; `gpu` runs both training
phases as Triton kernels (CUDA, or Triton's interpreter on a CPU). The training loop
(`moex.train`) keeps parameters, gradients and momentum on the problem's `device` and is the
same for all three. The choice is made once, by `get_backend`, and passed down.
"""

from dataclasses import dataclass
from types import ModuleType
from typing import Protocol

import numpy as np
import torch

from moex.errors import check

BACKENDS = ("auto", "reference", "cpu", "gpu", "compiled")
ALIASES = {"compiled": "cpu"}  # the cpu backend's name before the GPU backend existed


class Problem(Protocol):
    """One training phase of R runs as a backend computes it.

    `params` and `grads` are dicts of (R, ...) tensors on `device` (views of the training loop's
    flat buffers); `active` is an (R,) bool tensor. Statistics are per run: objective (ln L) and
    the phase's terms and errors (`STATS`)."""

    STATS: tuple[str, ...]
    device: torch.device

    def resample(self, step: int) -> None:
        """Draw what the objective of training step `step` needs (phase-2 input noise)."""

    def value_and_grad(self, params: dict, grads: dict, active) -> dict[str, torch.Tensor]:
        """Statistics per run; ∂ ln L of every active run written into `grads`."""

    def value(self, params: dict, active) -> dict[str, torch.Tensor]:
        """The same statistics without gradients (the adaptive-rate retry)."""


@dataclass(frozen=True)
class Backend:
    """A backend module bound to a device; `name` is `reference`, `cpu` or `gpu`."""

    name: str
    device: str
    module: ModuleType

    def expert_problem(self, inputs, targets, model, phase, num_runs) -> Problem:
        return self.module.ExpertProblem(inputs, targets, model, phase, num_runs, self.device)

    def gating_problem(self, gate_targets, inputs, model, phase, seeds) -> Problem:
        return self.module.GatingProblem(gate_targets, inputs, model, phase, seeds, self.device)

    def closed_loop(self, *args, **kwargs):
        return self.module.closed_loop(*args, **kwargs)

    def nearest_symbols(self, points, prototypes, prototype_symbols):
        return self.module.nearest_symbols(points, prototypes, prototype_symbols)


def _gpu_module():
    try:
        from moex.kernels import gpu
    except ImportError as error:  # triton missing
        return None, str(error)
    return gpu, ""


def get_backend(name: str = "auto", device: str = "cpu") -> Backend:
    """`reference` (PyTorch), `cpu` (numba), `gpu` (Triton; device=cuda), or `auto`: cpu on the
    CPU, gpu with device=cuda when Triton is installed (else reference)."""
    check(name in BACKENDS, f"backend={name!r}; choose one of {', '.join(BACKENDS[:4])}")
    name = ALIASES.get(name, name)
    check(name != "cpu" or device == "cpu",
          "backend=cpu runs on the CPU only; use backend=gpu (or auto) with device=cuda")
    if name == "auto":
        name = "cpu" if device == "cpu" else "gpu" if _gpu_module()[0] else "reference"
    if name == "reference":
        from moex.kernels import reference

        return Backend("reference", device, reference)
    if name == "gpu":
        gpu, why = _gpu_module()
        check(gpu is not None, f"backend=gpu needs Triton ({why}); pip install triton")
        check(gpu.available(device), f"backend=gpu needs device=cuda (device={device}); "
              f"Triton's interpreter runs it on the CPU when TRITON_INTERPRET=1")
        return Backend("gpu", device, gpu)
    from moex.kernels import cpu

    return Backend("cpu", device, cpu)


def input_noise(seeds: list[int], step: int, shape: tuple, variance: float, dtype) -> np.ndarray:
    """(R, *shape) Gaussian noise of `variance` for training step `step`, run r drawn from
    (seeds[r], step) alone: a run sees the same noise batched or alone, fresh or resumed."""
    return np.stack([np.random.default_rng([seed, step]).standard_normal(shape)
                     for seed in seeds]).astype(dtype) * np.sqrt(variance)
