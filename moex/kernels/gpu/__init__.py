"""GPU backend (Triton), module for module the CPU backend's (`moex.kernels.cpu`):

- `rnn`: the leaky RNN's teacher-forced forward and BPTT kernels (derivation inside);
- `lanes`: the lane layout, the kernels' launches and their compiled registers and spills;
- `phases`: `ExpertProblem` (phase 1) and `GatingProblem` (phase 2) around those kernels;
- `closed_loop`: the autonomous mixture with its Lyapunov tangents, one launch per chunk;
- `symbols`: the nearest-prototype symbol of generated points, one launch;
- `update`: the training loop's momentum step, one launch.

With `TRITON_INTERPRET=1` (set before this package is imported) Triton runs every kernel on the
CPU, slowly: that is how the tests check them without a GPU.
"""

import torch

from moex.kernels.gpu.closed_loop import closed_loop
from moex.kernels.gpu.lanes import kernel_report
from moex.kernels.gpu.phases import ExpertProblem, GatingProblem
from moex.kernels.gpu.rnn import INTERPRET
from moex.kernels.gpu.symbols import nearest_symbols
from moex.kernels.gpu.update import apply_step, momentum_step
from moex.kernels.reference import adaptive_trial  # (a few operators on (R,) tensors)

__all__ = ["ExpertProblem", "GatingProblem", "adaptive_trial", "apply_step", "available",
           "closed_loop", "kernel_report", "momentum_step", "nearest_symbols", "warm_up"]


def warm_up(precision: str, gating: tuple[int, int, int]) -> None:
    """Nothing: Triton compiles each kernel at its first launch (and caches it on disk)."""


def available(device: str) -> bool:
    """The kernels run on CUDA, or anywhere in Triton's interpreter."""
    return INTERPRET or (device.startswith("cuda") and torch.cuda.is_available())
