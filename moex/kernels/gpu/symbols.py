"""The symbol of each generated point (nearest prototype, `moex.metrics.symbols.symbolize_nearest`)
as one Triton kernel."""

import torch
import triton
import triton.language as tl

from moex.kernels.gpu.lanes import OPTIONS, pow2

PB = 16  # prototypes per tile of the kernel's loop


@triton.jit
def nearest_kernel(X, PROTO, SYM, OUT, n, P: tl.constexpr, D: tl.constexpr, DP: tl.constexpr,
                   PB: tl.constexpr, BLOCK: tl.constexpr):
    """OUT[i] = SYM[argmin_p ‖X[i] - PROTO[p]‖²] for a block of points X (n, D), the prototypes
    PB at a time (a running minimum: a (BLOCK, P) tile of all of them spilled 31 KB per thread
    with 288 prototypes); ties go to the first prototype, as on the CPU (within a tile by
    argmin, across tiles since a later tile must be strictly nearer)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = i < n
    d = tl.arange(0, DP)
    x = tl.load(X + i[:, None].to(tl.int64) * D + d[None, :], mask=ok[:, None] & (d < D)[None, :],
                other=0.0)
    best_d = tl.full((BLOCK,), float("inf"), x.dtype)
    best_p = tl.zeros((BLOCK,), tl.int32)
    for first in range(0, P, PB):
        p = first + tl.arange(0, PB)
        proto = tl.load(PROTO + p[:, None] * D + d[None, :],
                        mask=(p < P)[:, None] & (d < D)[None, :], other=0.0)
        diff = x[:, None, :] - proto[None, :, :]
        dist = tl.where((p < P)[None, :], tl.sum(diff * diff, axis=2), float("inf"))
        nearest = tl.min(dist, axis=1)
        nearer = nearest < best_d
        best_p = tl.where(nearer, first + tl.argmin(dist, axis=1, tie_break_left=True), best_p)
        best_d = tl.where(nearer, nearest, best_d)
    tl.store(OUT + i, tl.load(SYM + best_p, mask=ok, other=0), mask=ok)


def nearest_symbols(points: torch.Tensor, prototypes: torch.Tensor,
                    prototype_symbols: torch.Tensor, device: str = "cpu") -> torch.Tensor:
    """`moex.metrics.symbols.symbolize_nearest` as one kernel: (..., T, D) -> (..., T) int64,
    on `device`."""
    device = torch.device(device)
    points = torch.as_tensor(points)
    D = points.shape[-1]
    flat = points.to(device, torch.float64).reshape(-1, D).contiguous()
    proto = torch.as_tensor(prototypes).to(device, torch.float64).contiguous()
    symbols = torch.as_tensor(prototype_symbols).to(device, torch.int64).contiguous()
    out = torch.empty(len(flat), dtype=torch.int64, device=device)
    P, block = len(proto), 128
    nearest_kernel[(triton.cdiv(len(flat), block),)](flat, proto, symbols, out, len(flat), P=P,
                                                     D=D, DP=pow2(D), PB=PB, BLOCK=block,
                                                     **OPTIONS)
    return out.reshape(points.shape[:-1])
