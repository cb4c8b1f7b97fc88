"""The lane layout of the GPU backend's training kernels (as `moex.kernels.cpu.lanes` is the CPU
backend's): every independent recurrence is a lane, a program runs a block of lanes, and `_Net`
holds one leaky RNN's lanes, buffers and the two launches of `moex.kernels.gpu.rnn`.

Two knobs for the GPU session's sweep, read once: MOEX_GPU_LANE_BUDGET (weight-tile entries per
program, default 2048) and MOEX_GPU_WARPS (warps per program, default Triton's 4).
"""

import os

import numpy as np
import torch
import triton

from moex.kernels.gpu.rnn import rnn_backward, rnn_forward

# weight-tile entries per program (BL · HP², the registers a tile may take) and warps per program
LANE_BUDGET = int(os.environ.get("MOEX_GPU_LANE_BUDGET", "2048"))
NUM_WARPS = int(os.environ.get("MOEX_GPU_WARPS", "4"))
COMPILED: dict[str, object] = {}  # kernel name -> the last compiled kernel launched (CUDA only)


def launched(name: str, kernel) -> None:
    """Keep a launch's compiled kernel (None in Triton's interpreter) for `kernel_report`."""
    if kernel is not None:
        COMPILED[name] = kernel


def kernel_report() -> list[dict]:
    """Registers, spills and warps of every kernel compiled in this process (empty when the
    kernels ran in Triton's interpreter)."""
    return [{"kernel": name, "registers": getattr(k, "n_regs", None),
             "spills": getattr(k, "n_spills", None),
             "num_warps": getattr(getattr(k, "metadata", None), "num_warps", None)}
            for name, k in sorted(COMPILED.items())]


def pow2(n: int) -> int:
    return triton.next_power_of_2(max(n, 1))


class Net:
    """One leaky RNN per network (B networks) and its lanes: which network, input row and u_0 row
    each lane reads, and the buffers the two kernels fill."""

    def __init__(self, num_lanes, T, NI, H, NO, net, xrow, u0row, learn_eps, sums, dtype, device):
        self.L, self.T, self.NI, self.H, self.NO = num_lanes, T, NI, H, NO
        self.learn_eps, self.sums = learn_eps, sums

        def index(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.int64, device=device)

        self.net, self.xrow, self.u0row = index(net), index(xrow), index(u0row)
        self.pad = dict(NIP=pow2(NI), HP=pow2(H), NOP=pow2(NO))
        self.block = max(1, min(32, LANE_BUDGET // self.pad["HP"] ** 2))

        def empty(*shape):
            return torch.zeros(shape, dtype=dtype, device=device)

        self.O, self.C = empty(num_lanes, T, NO), empty(num_lanes, T, H)
        self.U = empty(num_lanes, T, H) if learn_eps else empty(1)
        self.S = empty(num_lanes, 2, H) if sums else empty(1)
        self.grads = (empty(num_lanes, H, NI), empty(num_lanes, H, H), empty(num_lanes, NO, H),
                      empty(num_lanes, H), empty(num_lanes, NO), empty(num_lanes, H),
                      empty(num_lanes, H))

    def _launch(self, kernel, *args, **flags):
        grid = (triton.cdiv(self.L, self.block),)
        launched(kernel.fn.__name__, kernel[grid](
            *args, self.L, T=self.T, NI=self.NI, H=self.H, NO=self.NO, BL=self.block,
            num_warps=NUM_WARPS, **self.pad, **flags))

    def forward(self, X, w, u0, keep):
        """O (L, T, NO); with `keep` also the histories the backward pass reads."""
        self._launch(rnn_forward, X, self.xrow, self.net, self.u0row, w["w_in"], w["w_rec"],
                     w["w_out"], w["b_c"], w["b_o"], w["eps"], u0, self.O, self.C, self.U,
                     self.S, KEEP_C=keep, KEEP_U=keep and self.learn_eps, KEEP_SUMS=self.sums)
        return self.O

    def backward(self, dO, X, w, u0):
        """Per-lane gradients (w_in, w_rec, w_out, b_c, b_o, ε, u_0) for ∂L/∂O = dO."""
        self._launch(rnn_backward, dO.contiguous(), X, self.xrow, self.net, self.u0row,
                     w["w_in"], w["w_rec"], w["w_out"], w["b_c"], w["eps"], u0, self.C, self.U,
                     *self.grads, LEARN_EPS=self.learn_eps)
        return self.grads


def weights(params: dict, lead: int) -> dict:
    """Contiguous weights (B, ...) and ε = 1/τ of the B networks in the first `lead` axes."""
    out = {k: params[k].flatten(0, lead - 1).contiguous()
           for k in ("w_in", "w_rec", "w_out", "b_c", "b_o")}
    out["eps"] = (1 / params["tau"]).flatten(0, lead - 1).contiguous()
    return out
