"""Compiled CPU kernels (numba) for the one time loop of the teacher-forced passes, `leaky_scan`
(Eqs. 1-2 and 5-6), with its hand-written BPTT, wrapped as a torch autograd Function.

Layout behind the boundary: the batch axes B... of distinct networks are flattened to one axis
b (run in parallel threads), the N rows sharing a network's weights are looped inside, and time
is the outer loop of each row. The reference is `moex.model.leaky_scan` in plain PyTorch.
"""

import numpy as np
import torch
from numba import njit, prange


@njit(inline="always", fastmath=True)
def _tanh(x):  # pragma: no cover - compiled; exp-based, 3x faster than libm tanh, exact to 1e-15
    return 1.0 - 2.0 / (np.exp(2.0 * x) + 1.0)


@njit(parallel=True, cache=True, fastmath=True)
def _scan_forward(drive, w_rec, eps, bias, u0, out, contexts):  # pragma: no cover - compiled
    B, T, N, M = drive.shape
    for b in prange(B):  # time outer, rows inner: every step reads one contiguous (N, M) block
        c = np.empty((N, M), drive.dtype)
        u = np.empty((N, M), drive.dtype)
        for n in range(N):
            for i in range(M):
                u[n, i] = u0[b, n, i]
                c[n, i] = _tanh(u[n, i] + bias[b, i])
        for t in range(T):
            for n in range(N):
                for i in range(M):
                    acc = drive[b, t, n, i]
                    for j in range(M):
                        acc += w_rec[b, i, j] * c[n, j]
                    u[n, i] = (1.0 - eps[b, i]) * u[n, i] + eps[b, i] * acc
                    out[b, t, n, i] = u[n, i]
            for n in range(N):
                for i in range(M):
                    c[n, i] = _tanh(u[n, i] + bias[b, i])
                    contexts[b, t, n, i] = c[n, i]


@njit(parallel=True, cache=True, fastmath=True)
def _scan_backward(has_grad_u, grad_u, has_grad_c, grad_c, drive, w_rec, eps, bias, u0, u,
                   contexts, g_drive, g_w, g_eps, g_bias, g_u0):  # pragma: no cover - compiled
    B, T, N, M = drive.shape
    for b in prange(B):
        a = np.zeros((N, M), drive.dtype)  # dL/du_t
        back = np.zeros((N, M), drive.dtype)  # W^T (ε ⊙ a_{t+1})
        prev_c = np.empty(M, drive.dtype)
        ea = np.empty(M, drive.dtype)
        w_t = np.ascontiguousarray(w_rec[b].T)  # rows of W^T are contiguous
        g_wb = np.zeros((M, M), drive.dtype)  # local accumulators, written once
        g_eb = np.zeros(M, drive.dtype)
        g_bb = np.zeros(M, drive.dtype)
        for t in range(T - 1, -1, -1):
            for n in range(N):
                # a_t = ∂L/∂u_t + (1 - c_t²) ∂L/∂c_t + (1-ε) a_{t+1} + (1 - c_t²) W^T(ε a_{t+1})
                for i in range(M):
                    c_t = contexts[b, t, n, i]
                    direct = grad_u[b, t, n, i] if has_grad_u else 0.0
                    through = 0.0
                    if has_grad_c:  # c_t = tanh(u_t + v_1)
                        through = (1.0 - c_t * c_t) * grad_c[b, t, n, i]
                        g_bb[i] += through
                    a[n, i] = direct + through + (1.0 - eps[b, i]) * a[n, i] \
                        + (1.0 - c_t * c_t) * back[n, i]
                    prev_c[i] = contexts[b, t - 1, n, i] if t > 0 else _tanh(u0[b, n, i]
                                                                             + bias[b, i])
                for i in range(M):
                    ea[i] = eps[b, i] * a[n, i]
                    g_drive[b, t, n, i] = ea[i]
                    rec = 0.0
                    for j in range(M):
                        rec += w_rec[b, i, j] * prev_c[j]
                        g_wb[i, j] += ea[i] * prev_c[j]
                    u_prev = u[b, t - 1, n, i] if t > 0 else u0[b, n, i]
                    g_eb[i] += a[n, i] * (drive[b, t, n, i] + rec - u_prev)
                for j in range(M):
                    acc = 0.0
                    for i in range(M):
                        acc += w_t[j, i] * ea[i]
                    back[n, j] = acc
                    g_bb[j] += (1.0 - prev_c[j] * prev_c[j]) * acc
                if t == 0:
                    for i in range(M):
                        g_u0[b, n, i] = (1.0 - eps[b, i]) * a[n, i] \
                            + (1.0 - prev_c[i] * prev_c[i]) * back[n, i]
        g_w[b] = g_wb
        g_eps[b] = g_eb
        g_bias[b] = g_bb


def _flat(x: torch.Tensor, tail: int) -> np.ndarray:
    """(B..., *tail dims) -> a contiguous (B, *tail dims) array; (B..., 1, M) -> (B, M)."""
    return np.ascontiguousarray(x.detach().reshape((-1,) + tuple(x.shape[-tail:])).numpy())


class _LeakyScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, drive, w_rec, eps, bias, u0):
        arrays = [_flat(x, k) for x, k in ((drive, 3), (w_rec, 2), (eps, 1), (bias, 1), (u0, 2))]
        out, contexts = np.empty_like(arrays[0]), np.empty_like(arrays[0])
        _scan_forward(*arrays, out, contexts)
        ctx.save_for_backward(drive, w_rec, eps, bias, u0)
        ctx.arrays = (out, contexts)  # kept as numpy: no copies for the backward pass
        return (torch.from_numpy(out).reshape(drive.shape),
                torch.from_numpy(contexts).reshape(drive.shape))

    @staticmethod
    def backward(ctx, grad_u, grad_c):
        drive, w_rec, eps, bias, u0 = ctx.saved_tensors
        d, w, e, v, z = (_flat(x, k) for x, k in ((drive, 3), (w_rec, 2), (eps, 1), (bias, 1),
                                                   (u0, 2)))
        unused = np.zeros((1, 1, 1, 1), d.dtype)  # an output nobody used has no gradient
        g_u = unused if grad_u is None else _flat(grad_u, 3)
        g_c = unused if grad_c is None else _flat(grad_c, 3)
        grads = [np.empty_like(d), np.zeros_like(w), np.zeros_like(e), np.zeros_like(v),
                 np.empty_like(z)]
        _scan_backward(grad_u is not None, g_u, grad_c is not None, g_c, d, w, e, v, z,
                       *ctx.arrays, *grads)
        shapes = (drive.shape, w_rec.shape, eps.shape, bias.shape, u0.shape)
        return tuple(torch.from_numpy(x).reshape(s) for x, s in zip(grads, shapes, strict=True))


def leaky_scan_compiled(drive, w_rec, eps, bias, u0):
    """`moex.model.leaky_scan` as one compiled forward and one compiled BPTT pass (CPU).

    Same arguments and results (u and c); eps and bias must have the shape (B..., 1, M) and
    every batch axis must be explicit (no broadcasting), as in `expert_forward` and
    `gating_forward`.
    """
    return _LeakyScan.apply(drive, w_rec, eps, bias, u0)
