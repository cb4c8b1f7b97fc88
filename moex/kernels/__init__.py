"""Backends: where the time loops of training and evaluation run.

Three backends (`REGISTRY`), each a module with the same names (`BackendModule`): the two training
problems (`Problem`), a closed loop and a symbol readout, torch tensors in and out (data given on
another device is moved; the cpu backend's kernels read numpy views of it), each honouring the
device the `Backend` binds it to:

- `ExpertProblem(inputs, targets, model, phase, *, num_runs, device)`: phase 1 (Eqs. 9-13);
- `GatingProblem(gate_targets, inputs, model, phase, *, seeds, device)`: phase 2 (Eqs. 14-16);
- `closed_loop(experts, gating, state, steps, *, noise, tangents, count, ..., device)`: the
  autonomous mixture (Sec. 2.2) with Lyapunov tangent vectors;
- `nearest_symbols(points, prototypes, prototype_symbols, device)`: the symbol of each point;
- `momentum_step(...)`, `apply_step(...)`: the training loop's update of its (R, P) buffers
  (Eqs. 17-18), the reference's PyTorch operators as one compiled call (cpu) or launch (gpu);
- `adaptive_trial(...)`: one trial of the adaptive rate (Sec. 2.1.4), one compiled call (cpu);
- `warm_up(precision, gating)`: before a first training, start compiling what comes later (cpu
  only; `gating`: the gating RNN's units, inputs and outputs).

The problems take data shared by all runs, (S, T, D), or data of each run's own, (R, S, T, D):
jobs packed into one batch (`moex.jobs`).

`reference` is the model's equations in PyTorch with autograd (any device); it is the oracle the
tests hold the others to. `cpu` (package `cpu/`) is the compiled numba implementation; `gpu`
(package `gpu/`, module for module the same) runs as Triton kernels (CUDA, or Triton's
interpreter on a CPU). Each declares its `Capabilities`. The training loop (`moex.train`) keeps
parameters, gradients and momentum on the problem's `device` and is the same for all three. The
choice is made once, by `get_backend`, and passed down; `available(name)` says whether and where
a backend runs here (the tests' one `backend` fixture is built from it). A new backend is a package
of `BackendModule`'s names and one entry in `LOADERS`; its module is checked for those names when
it is first chosen.
"""

from dataclasses import dataclass
from typing import Protocol

import torch

from moex.errors import check
from moex.model import ClosedLoopRun, ClosedLoopState

ALIASES = {"compiled": "cpu"}  # the cpu backend's name before the GPU backend existed


class Problem(Protocol):
    """One training phase of R runs as a backend computes it.

    `params` and `grads` are dicts of (R, ...) tensors on `device` (views of the training loop's
    flat buffers); `active` is an (R,) bool tensor. Statistics are per run: objective (ln L) and
    the phase's terms and errors (`STATS`)."""

    STATS: tuple[str, ...]
    device: torch.device
    trials: int  # adaptive-rate candidate steps evaluated per call (>1: `value_of_candidates`)

    def resample(self, step: int) -> None:
        """Draw what the objective of training step `step` needs (phase-2 input noise)."""

    def value_and_grad(self, params: dict, grads: dict, active) -> dict[str, torch.Tensor]:
        """Statistics per run; ∂ ln L of every active run written into `grads`."""

    def value(self, params: dict, active) -> dict[str, torch.Tensor]:
        """The same statistics without gradients (the adaptive-rate retry). A backend may keep
        its forward pass: the next `value_and_grad` at the same parameters (the accepted trial's
        point) may take it instead of running it again (the cpu backend does, bit for bit)."""

    def stepper(self, buffers: dict, columns: dict, fixed: dict, **settings):
        """A callable that runs a whole training step on the training loop's buffers in one call,
        whose `statistics()` returns that step's statistics at θ (cpu: `moex.kernels.cpu.step`),
        or None where the loop makes its calls (`moex.train._ascend`: the arguments)."""

    def value_of_candidates(self, params: dict) -> dict[str, torch.Tensor]:
        """Where `trials` > 1 (gpu): statistics (k·R,) of k = `trials` parameter sets per run in
        one call; params are (k·R, ...) groups, candidate j of run r in row j·R + r."""


@dataclass(frozen=True)
class Capabilities:
    """What a backend can do, so that callers and tests size themselves from it."""

    float32: bool = True  # computes in float32 as well as float64
    interpreted: bool = False  # runs slowly here (Triton's interpreter): tests shrink their sizes
    threads: bool = False  # parallel over numba's threads (`moex.kernels.cpu.threads`)


class BackendModule(Protocol):
    """What each backend module (`reference`, `cpu`, `gpu`) defines, with the same names."""

    ExpertProblem: type  # (inputs, targets, model, phase, *, num_runs, device) -> Problem
    GatingProblem: type  # (gate_targets, inputs, model, phase, *, seeds, device) -> Problem

    def closed_loop(self, experts: dict, gating: dict, state: ClosedLoopState, steps: int, *,
                    noise: torch.Tensor | None = None, tangents: torch.Tensor | None = None,
                    count: bool = False, uniform_gates: bool = False, potentials: bool = True,
                    device: str = "cpu") -> ClosedLoopRun: ...

    def nearest_symbols(self, points: torch.Tensor, prototypes: torch.Tensor,
                        prototype_symbols: torch.Tensor, device: str = "cpu") -> torch.Tensor: ...

    def warm_up(self, precision: str, gating: tuple[int, int, int]) -> None:
        """Before a first training: start compiling what the run needs later (or nothing);
        `gating`: the gating RNN's units, inputs and outputs."""

    def momentum_step(self, theta, grad, velocity, delta, *, rate, lr_scale, objective, failed,
                      momentum: float, paper_form: bool, apply: bool, tau=None) -> None: ...

    def apply_step(self, theta, delta, velocity, frozen, *, paper_form: bool,
                   tau=None) -> None: ...

    def adaptive_trial(self, delta, values, base, pending, lr_scale, *, retries,
                       decrease: float, increase: float, max_ratio: float) -> bool: ...


@dataclass(frozen=True)
class Backend:
    """A backend module bound to a device; `name` is `reference`, `cpu` or `gpu`."""

    name: str
    device: str
    module: BackendModule
    caps: Capabilities = Capabilities()

    def expert_problem(self, inputs, targets, model, phase, num_runs) -> Problem:
        return self.module.ExpertProblem(inputs, targets, model, phase, num_runs=num_runs,
                                         device=self.device)

    def gating_problem(self, gate_targets, inputs, model, phase, seeds) -> Problem:
        return self.module.GatingProblem(gate_targets, inputs, model, phase, seeds=seeds,
                                         device=self.device)

    def closed_loop(self, experts: dict, gating: dict, state: ClosedLoopState, steps: int, *,
                    noise: torch.Tensor | None = None, tangents: torch.Tensor | None = None,
                    count: bool = False, uniform_gates: bool = False,
                    potentials: bool = True) -> ClosedLoopRun:
        """`steps` closed-loop steps on this backend's device (results where `state` is)."""
        return self.module.closed_loop(experts, gating, state, steps, noise=noise,
                                       tangents=tangents, count=count,
                                       uniform_gates=uniform_gates, potentials=potentials,
                                       device=self.device)

    def nearest_symbols(self, points: torch.Tensor, prototypes: torch.Tensor,
                        prototype_symbols: torch.Tensor) -> torch.Tensor:
        """The symbol (int64) of each point's nearest prototype, on this backend's device."""
        return self.module.nearest_symbols(points, prototypes, prototype_symbols,
                                           device=self.device)

    def warm_up(self, precision: str, gating: tuple[int, int, int]) -> None:
        """Start compiling the kernels a first training needs after its first phase."""
        self.module.warm_up(precision, gating)

    def momentum_step(self, theta, grad, velocity, delta, **kwargs) -> None:
        """The ascent's step Δθ on the training loop's buffers, and with `apply` the step taken
        (`moex.kernels.reference.momentum_step`: the arguments and the bits)."""
        self.module.momentum_step(theta, grad, velocity, delta, **kwargs)

    def apply_step(self, theta, delta, velocity, frozen, **kwargs) -> None:
        """θ += Δθ for the runs not frozen (`moex.kernels.reference.apply_step`)."""
        self.module.apply_step(theta, delta, velocity, frozen, **kwargs)

    def adaptive_trial(self, delta, values, base, pending, lr_scale, **kwargs) -> bool:
        """One trial of the adaptive rate (`moex.kernels.reference.adaptive_trial`): whether a
        run is still pending."""
        return self.module.adaptive_trial(delta, values, base, pending, lr_scale, **kwargs)


def _gpu_module():
    try:
        from moex.kernels import gpu
    except ImportError as error:  # triton missing
        return None, str(error)
    return gpu, ""


def _checked(module) -> BackendModule:
    """A backend module that defines every name of `BackendModule` (a `TypeError` naming those it
    lacks otherwise: a new backend fails when it is first chosen, not halfway through a run)."""
    missing = [name for name in INTERFACE if not callable(getattr(module, name, None))]
    if missing:
        raise TypeError(f"backend module {module.__name__} lacks {', '.join(missing)}")
    return module


def _reference(device: str) -> Backend:
    from moex.kernels import reference

    return Backend("reference", device, _checked(reference))


def _cpu(device: str) -> Backend:
    check(device == "cpu",
          "backend=cpu runs on the CPU only; use backend=gpu (or auto) with device=cuda")
    from moex.kernels import cpu

    return Backend("cpu", device, _checked(cpu), Capabilities(threads=True))


def _gpu(device: str) -> Backend:
    gpu, why = _gpu_module()
    check(gpu is not None, f"backend=gpu needs Triton ({why}); pip install triton")
    check(gpu.available(device), f"backend=gpu needs device=cuda and a CUDA device "
          f"(device={device}); use backend=cpu (or auto) on this machine")
    return Backend("gpu", device, _checked(gpu),
                   Capabilities(interpreted=gpu.INTERPRET and not device.startswith("cuda")))


# every backend, by name: a function binding its module to a device (a `ConfigError` where it
# cannot run there). A new backend is a package of `BackendModule`'s names and one entry here.
LOADERS = {"reference": _reference, "cpu": _cpu, "gpu": _gpu}
REGISTRY = tuple(LOADERS)  # `available` says which run here
INTERFACE = ("ExpertProblem", "GatingProblem", "closed_loop", "nearest_symbols", "warm_up",
             "momentum_step", "apply_step", "adaptive_trial")  # `BackendModule`


def check_name(name: str) -> str:
    """The backend a user's `backend=` names (an alias resolved, `auto` kept); a `ConfigError`
    listing the choices for any other name."""
    check(name in ("auto", *LOADERS, *ALIASES),
          f"backend={name!r}; choose one of {', '.join(('auto', *LOADERS))}")
    return ALIASES.get(name, name)


def check_backend(name: str, device: str) -> None:
    """A config's `backend` and `device` before anything is written: a known name, and gpu only
    where its device and Triton are (refused before a run folder exists, not when training
    starts); on the cpu backend its MOEX_CPU_SIZES (`moex.kernels.cpu.lanes.size_choice`)."""
    name = check_name(name)
    if name == "gpu":
        get_backend(name, device)
    elif name == "cpu" or (name == "auto" and device == "cpu"):
        from moex.kernels.cpu.lanes import size_choice

        size_choice()


def get_backend(name: str = "auto", device: str = "cpu") -> Backend:
    """`reference` (PyTorch), `cpu` (numba), `gpu` (Triton; device=cuda), or `auto`: cpu on the
    CPU, gpu with device=cuda when Triton is installed (else reference)."""
    name = check_name(name)
    if name == "auto":
        name = "cpu" if device == "cpu" else "gpu" if _gpu_module()[0] else "reference"
    return LOADERS[name](device)


def available(name: str) -> tuple[Backend | None, str]:
    """Backend `name` on the device it runs on here (gpu: CUDA if present, else Triton's
    interpreter when TRITON_INTERPRET=1), or (None, why it cannot run here)."""
    device = "cuda" if name == "gpu" and torch.cuda.is_available() else "cpu"
    try:
        return get_backend(name, device), ""
    except ValueError as error:
        return None, str(error)
