"""The lane layout of the GPU backend's training kernels (as `moex.kernels.cpu.lanes` is the CPU
backend's): every independent recurrence is a lane, network n owns the lanes n·LPN + j, and a
program runs one network's lanes in chunks (`moex.kernels.gpu.rnn`). `Net` holds one leaky RNN's
lanes, buffers and its launches; `launch` is every training kernel's launch.

Four knobs for the GPU session's sweep, read once: MOEX_GPU_LANE_BUDGET (entries of the lanes'
(BL, H) tiles per program, default 1024: 64 lanes at H = 16, 16 at H = 64), MOEX_GPU_WARPS
(warps per program, default Triton's 4), MOEX_GPU_TRIALS (candidate steps of the adaptive rate
per launch, default 1; the result is the same for any value) and MOEX_GPU_CLOSED_LOOP_BUDGET
(the closed loop's lanes per program, `moex.kernels.gpu.closed_loop`).
"""

import os

import numpy as np
import torch
import triton

from moex.errors import check
from moex.kernels.gpu.rnn import rnn_backward, rnn_forward, rnn_weight_gradients


def _knob(name: str, default: str) -> int:
    """A whole number >= 1 from the environment (a `ConfigError` naming it otherwise)."""
    value = os.environ.get(name, default)
    check(value.isdigit() and int(value) >= 1, f"{name}={value} must be a whole number >= 1")
    return int(value)


LANE_BUDGET = _knob("MOEX_GPU_LANE_BUDGET", "1024")
NUM_WARPS = _knob("MOEX_GPU_WARPS", "4")
# the closed loop's lanes per program: entries of a lane's largest tile (its experts' W_in x_m,
# K × M × D padded) per program, over 8 warps; a sweep knob as the two above
CLOSED_LOOP_BUDGET = _knob("MOEX_GPU_CLOSED_LOOP_BUDGET", "256")
# k candidates are one call of k·R networks' forward passes, k times the work in one launch: on an
# H200 at 90 networks k = 1 took 0.12 ms per network-epoch in phase 1 (adaptive), k = 4 0.16 and
# k = 8 0.22 (BENCHMARKS.md, "First contact with an H200"); in Triton's interpreter k times the time
TRIALS = _knob("MOEX_GPU_TRIALS", "1")
COMPILED: dict[str, object] = {}  # kernel name -> the last compiled kernel launched (CUDA only)
PARAMS = ("w_in", "w_rec", "w_out", "b_c", "b_o", "tau", "u0")  # what the RNN kernels read
# every launch's compile options beside its warps: a multiply and an add fused into one FMA, as
# Triton 3.9 does by default and 3.10 will not (pinned, so that its bits do not change with it)
OPTIONS = {"enable_fp_fusion": True}


def gradient_launch(HG: int) -> dict:
    """`rnn_weight_gradients`' rows per matrix product (BR: the order of summation, and so the
    bits, depend on it), warps and pipeline stages, by its padded width HG: the largest that
    compile for an H200 without spilling in Triton 3.6 and 3.9 (`benchmarks/gpu_aot.py`; at
    HG = 64 four warps spilled 372 B; two stages spilled 4-40 B in 3.6 where 3.9 did not)."""
    wide = HG >= 64
    return dict(BR=32 if HG <= 16 else 16, num_warps=8 if wide else NUM_WARPS, num_stages=1)


def launched(name: str, kernel) -> None:
    """Keep a launch's compiled kernel (None in Triton's interpreter) for `kernel_report`."""
    if kernel is not None:
        COMPILED[name] = kernel


def launch(kernel, programs: int, *args, **meta) -> None:
    """One launch of a training kernel on `programs` programs."""
    launched(kernel.fn.__name__, kernel[(programs,)](*args, **{"num_warps": NUM_WARPS,
                                                               **OPTIONS, **meta}))


def kernel_report() -> list[dict]:
    """Registers, spills and warps of every kernel compiled in this process (empty when the
    kernels ran in Triton's interpreter)."""
    return [{"kernel": name, "registers": getattr(k, "n_regs", None),
             "spills": getattr(k, "n_spills", None),
             "num_warps": getattr(getattr(k, "metadata", None), "num_warps", None)}
            for name, k in sorted(COMPILED.items())]


def pow2(n: int) -> int:
    return triton.next_power_of_2(max(n, 1))


def strides(tensors: dict, names) -> list[int]:
    """Each group's run stride; the kernels need every run's entries contiguous (as in the
    training loop's flat buffer, or a contiguous tensor)."""
    out = []
    for name in names:
        x = tensors[name]
        inner = x.shape[1:]
        want = [int(np.prod(inner[d + 1:])) for d in range(len(inner))]
        if [s for s, n in zip(x.stride()[1:], inner, strict=True) if n > 1] != [
                s for s, n in zip(want, inner, strict=True) if n > 1]:
            raise ValueError(f"parameter {name}: each run's entries must be contiguous")
        out.append(x.stride(0))
    return out


class Net:
    """One leaky RNN per network (`networks` of them, `per_run` per run) and its lanes
    (`lanes_per_net` each): which input row and u_0 row each lane reads, and the buffers the
    two kernels fill.

    Args:
        xrow, u0j: (L,) each lane's row of X and its row of its run's u_0.
        learn_eps: ε learned (keep u_t, write ∂τ); sums: keep Σu, Σu² (the attraction).
        keep: buffers for gradients (else values only)."""

    def __init__(self, networks, per_run, lanes_per_net, *, T, NI, H, NO, xrow, u0j, learn_eps,
                 sums, dtype, device, keep=True):
        L = networks * lanes_per_net
        self.networks, self.learn_eps, self.attract = networks, learn_eps, sums

        def index(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.int64, device=device)

        self.xrow, self.u0j = index(xrow), index(u0j)
        HP = pow2(H)
        block = max(1, min(pow2(lanes_per_net), LANE_BUDGET // HP))
        self.meta = dict(T=T, NI=NI, H=H, NO=NO, HP=HP, NOP=pow2(NO), BL=block,
                         LPN=lanes_per_net, NPR=per_run,
                         CHUNKS=triton.cdiv(lanes_per_net, block))
        wide = {name: max(16, pow2(size)) for name, size in (("IG", NI), ("HG", H), ("OG", NO))}
        self.gradient_meta = dict(T=T, NI=NI, H=H, NO=NO, LPN=lanes_per_net, NPR=per_run,
                                  **wide, **gradient_launch(wide["HG"]))

        def empty(*shape):
            return torch.zeros(shape, dtype=dtype, device=device)

        self.O = empty(L, T, NO)
        self.DO, self.C = (empty(L, T, NO), empty(L, T, H)) if keep else (empty(1), empty(1))
        self.EA = empty(L, T, H) if keep else empty(1)  # ε a_t, from the backward recurrence
        # a forward without histories passes c_t through these rows; the backward leaves each
        # lane's c_{-1} in its first row for the weight gradients
        self.passing = empty(L, 2, H)
        self.U = empty(L, T, H) if learn_eps and keep else empty(1)
        self.S = torch.zeros(L, 2, H, dtype=torch.float64, device=device) if sums else empty(1)

    def forward(self, X, params, keep):
        """O (L, T, NO); with `keep` also the histories the backward pass reads."""
        p = [params[k] for k in PARAMS]
        launch(rnn_forward, self.networks, X, self.xrow, self.u0j, *p, self.O,
               self.C if keep else self.passing, self.U, self.S, *strides(params, PARAMS),
               KEEP_C=keep, KEEP_U=keep and self.learn_eps,
               KEEP_SUMS=self.attract, **self.meta)
        return self.O

    def backward(self, X, params, grads, active, *, attract, floor):
        """The networks' gradients for ∂L/∂O = self.DO, written into `grads` where `active`;
        `floor` (a device tensor, its first entry read): the attraction's variance floor σ̄².
        Two launches: the backward recurrence, then the weight matrices' sums over lanes."""
        learn = "tau" in grads
        g = {k: grads[k] if k in grads else grads["b_c"] for k in PARAMS}  # (τ: not written)
        read = ("w_rec", "w_out", "b_c", "tau", "u0")
        meta = {k: self.meta[k] for k in ("T", "H", "NO", "HP", "BL", "LPN", "NPR", "CHUNKS")}
        launch(rnn_backward, self.networks, self.DO, self.xrow, self.u0j,
               *(params[k] for k in read), self.C, self.U, self.S, active, floor, self.EA,
               self.passing,
               g["b_c"], g["tau"], g["u0"], *strides(params, read),
               *strides(g, ("b_c", "tau", "u0")), LEARN_EPS=learn, ATTRACT=attract, **meta)
        weights = ("w_in", "w_rec", "w_out", "b_o")
        launch(rnn_weight_gradients, self.networks, self.EA, self.DO, self.C, self.passing, X,
               self.xrow, active, *(g[k] for k in weights), *strides(g, weights),
               **self.gradient_meta)
