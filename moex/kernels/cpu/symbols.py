"""The symbol of each generated point: the symbol of its nearest prototype, compiled."""

import numpy as np
import torch
from numba import njit

from moex.kernels.cpu import threads
from moex.kernels.cpu.lanes import first_use
from moex.kernels.cpu.simd import JIT, fma, lanes, padded, width


@njit(nogil=True, **JIT)
def _nearest(lo, hi, points, prototypes, symbols, out):  # pragma: no cover
    """out[n] = symbols[argmin_p ‖points[:, n] - prototypes[p]‖²] for points (D, n), LB points
    at a time (blocks lo..hi-1 of them)."""
    (P, D), LB = prototypes.shape, width(points)
    for b in range(lo, hi):
        best, index, dist = lanes(points), lanes(points), lanes(points)
        for v in range(LB):
            best[v] = np.inf
            index[v] = 0.0
        for p in range(P):
            for v in range(LB):
                dist[v] = 0.0
            for d in range(D):
                for v in range(LB):
                    diff = points[d, b * LB + v] - prototypes[p, d]
                    dist[v] = fma(diff, diff, dist[v])
            for v in range(LB):
                closer = dist[v] < best[v]
                best[v] = dist[v] if closer else best[v]
                index[v] = p if closer else index[v]
        for v in range(LB):
            out[b * LB + v] = symbols[int(index[v])]


def nearest_symbols(points: torch.Tensor, prototypes: torch.Tensor,
                    prototype_symbols: torch.Tensor, device: str = "cpu") -> torch.Tensor:
    """`moex.metrics.symbols.symbolize_nearest` compiled: (..., T, D) -> (..., T) int64 symbols."""
    points = torch.as_tensor(points).detach().cpu().numpy()
    D = points.shape[-1]
    flat = np.asarray(points, np.float64).reshape(-1, D)
    by_coordinate = np.zeros((D, padded(len(flat), np.float64)))
    by_coordinate[:, :len(flat)] = flat.T
    out = np.empty(by_coordinate.shape[1], np.int64)
    with first_use(_nearest, "symbol kernel"):
        threads.over(_nearest, by_coordinate.shape[1] // width(by_coordinate), by_coordinate,
                     np.ascontiguousarray(torch.as_tensor(prototypes).cpu().numpy(), np.float64),
                     np.ascontiguousarray(torch.as_tensor(prototype_symbols).cpu().numpy(),
                                          np.int64), out)
    return torch.from_numpy(out[:len(flat)].reshape(points.shape[:-1]))
