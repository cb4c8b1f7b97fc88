"""The symbol of each generated point (nearest prototype, `moex.metrics.symbols.symbolize_nearest`)
as one Triton kernel."""

import torch
import triton
import triton.language as tl

from moex.kernels.gpu.lanes import pow2


@triton.jit
def nearest_kernel(X, PROTO, SYM, OUT, n, P: tl.constexpr, D: tl.constexpr, PP: tl.constexpr,
                   DP: tl.constexpr, BLOCK: tl.constexpr):
    """OUT[i] = SYM[argmin_p ‖X[i] - PROTO[p]‖²] for a block of points X (n, D); ties go to the
    first prototype, as on the CPU."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = i < n
    p, d = tl.arange(0, PP), tl.arange(0, DP)
    x = tl.load(X + i[:, None].to(tl.int64) * D + d[None, :], mask=ok[:, None] & (d < D)[None, :],
                other=0.0)
    proto = tl.load(PROTO + p[:, None] * D + d[None, :], mask=(p < P)[:, None] & (d < D)[None, :],
                    other=0.0)
    diff = x[:, None, :] - proto[None, :, :]
    dist = tl.where((p < P)[None, :], tl.sum(diff * diff, axis=2), float("inf"))
    best = tl.argmin(dist, axis=1, tie_break_left=True)
    tl.store(OUT + i, tl.load(SYM + best, mask=ok, other=0), mask=ok)



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
                                                     D=D, PP=pow2(P), DP=pow2(D), BLOCK=block)
    return out.reshape(points.shape[:-1])
