"""Backends: where the time loops of training and evaluation run.

Each backend module exposes the same three names:

- `ExpertProblem(inputs, targets, model, phase, num_runs, device)`: phase 1 (Eqs. 9-13) with
  `value_and_grad(params, grads, active)` and `value(params, active)`;
- `GatingProblem(gate_targets, inputs, model, phase, seeds, device)`: phase 2 (Eqs. 14-16),
  the same two methods;
- `closed_loop(experts, gating, state, steps, noise, tangents, count)`: the autonomous mixture
  (Sec. 2.2) with Lyapunov tangent vectors;
- `nearest_symbols(points, prototypes, prototype_symbols)`: the symbol of each generated point.

Both problems also have `resample(step)`, called before each training step: it draws the
phase's input noise (`input_noise`), if it has any.

`reference` is the model's equations in PyTorch with autograd (any device); it is the oracle the
tests hold the others to. `cpu` is the compiled numba implementation. A GPU implementation would
be a third module with the same names. The choice is made once, by `get_backend`, and passed down.
"""

from dataclasses import dataclass
from types import ModuleType

import numpy as np

from moex.errors import check

BACKENDS = ("auto", "reference", "compiled")


@dataclass(frozen=True)
class Backend:
    """A backend module bound to a device; `name` is `reference` or `compiled`."""

    name: str
    device: str
    module: ModuleType

    def expert_problem(self, inputs, targets, model, phase, num_runs):
        return self.module.ExpertProblem(inputs, targets, model, phase, num_runs, self.device)

    def gating_problem(self, gate_targets, inputs, model, phase, seeds):
        return self.module.GatingProblem(gate_targets, inputs, model, phase, seeds, self.device)

    def closed_loop(self, *args, **kwargs):
        return self.module.closed_loop(*args, **kwargs)

    def nearest_symbols(self, points, prototypes, prototype_symbols):
        return self.module.nearest_symbols(points, prototypes, prototype_symbols)


def get_backend(name: str = "auto", device: str = "cpu") -> Backend:
    """`reference` (PyTorch), `compiled` (numba, CPU only), or `auto`: compiled on the CPU."""
    check(name in BACKENDS, f"backend={name!r}; choose one of {', '.join(BACKENDS)}")
    check(name != "compiled" or device == "cpu",
          "backend=compiled runs on the CPU only; use backend=reference with device=cuda")
    if name == "reference" or device != "cpu":
        from moex.kernels import reference

        return Backend("reference", device, reference)
    from moex.kernels import cpu

    return Backend("compiled", device, cpu)


def input_noise(seeds: list[int], step: int, shape: tuple, variance: float, dtype) -> np.ndarray:
    """(R, *shape) Gaussian noise of `variance` for training step `step`, run r drawn from
    (seeds[r], step) alone: a run sees the same noise batched or alone, fresh or resumed."""
    return np.stack([np.random.default_rng([seed, step]).standard_normal(shape)
                     for seed in seeds]).astype(dtype) * np.sqrt(variance)
