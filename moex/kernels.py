"""Compiled CPU kernels (numba), each with its time loop inside:

- `leaky_scan_compiled`: the one time loop of the teacher-forced passes, `leaky_scan`
  (Eqs. 1-2 and 5-6), with its hand-written BPTT, wrapped as a torch autograd Function.
  The batch axes B... of distinct networks are flattened to one axis b (run in parallel
  threads), the N rows sharing a network's weights are looped inside, and time is the outer
  loop of each row. The reference is `moex.model.leaky_scan`.
- `closed_loop_compiled`: the autonomous mixture (Sec. 2.2) with k tangent vectors re-
  orthonormalised every step (spec §5), one thread per trajectory (run × sample). The
  reference is `moex.model.closed_loop_step` followed by a QR step.
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


@njit(parallel=True, cache=True, fastmath=True)
def _closed_loop(eu, gu, xs, gs, tang, e_win, e_wrec, e_eps, e_bc, e_wout, e_bo, g_win, g_wrec,
                 g_eps, g_bc, g_wout, g_bo, noise, count, out_y, out_g, out_u,
                 log_growth):  # pragma: no cover - compiled
    B, KE, M = eu.shape
    H, TAU, D, K = gu.shape[1], xs.shape[1], xs.shape[2], gs.shape[2]
    C, NV, N = out_y.shape[1], tang.shape[1], B // g_wrec.shape[0]
    og = KE * M  # tangent layout of ClosedLoopState.flat: experts_u, gating_u, inputs, gates
    ox = og + H
    ot = ox + TAU * D
    has_noise = noise.shape[1] > 0
    for b in prange(B):
        r = b // N
        ue, ug = eu[b].copy(), gu[b].copy()
        x_line, g_line, V = xs[b].copy(), gs[b].copy(), tang[b].copy()
        ce, ce_prev = np.empty((KE, M), eu.dtype), np.empty((KE, M), eu.dtype)
        cg, cg_prev = np.empty(H, eu.dtype), np.empty(H, eu.dtype)
        outs = np.empty((KE, D), eu.dtype)
        x, y, dy = np.empty(D, eu.dtype), np.empty(D, eu.dtype), np.empty(D, eu.dtype)
        g, ng, dl = np.empty(K, eu.dtype), np.empty(K, eu.dtype), np.empty(K, eu.dtype)
        nv = np.empty(ot + TAU * K, eu.dtype)
        for e in range(KE):
            for i in range(M):
                ce[e, i] = _tanh(ue[e, i] + e_bc[r, e, i])
        for h in range(H):
            cg[h] = _tanh(ug[h] + g_bc[r, h])
        for t in range(C):
            for d in range(D):
                x[d] = x_line[0, d] + (noise[b, t, d] if has_noise else 0.0)
            for k in range(K):
                g[k] = g_line[0, k]
            # experts, Eqs. 1-3, all on the same input x_m
            for e in range(KE):
                for i in range(M):
                    acc = 0.0
                    for d in range(D):
                        acc += e_win[r, e, i, d] * x[d]
                    for j in range(M):
                        acc += e_wrec[r, e, i, j] * ce[e, j]
                    ue[e, i] = (1.0 - e_eps[r, e, i]) * ue[e, i] + e_eps[r, e, i] * acc
                for i in range(M):
                    ce_prev[e, i] = ce[e, i]
                    ce[e, i] = _tanh(ue[e, i] + e_bc[r, e, i])
                for d in range(D):
                    acc = e_bo[r, e, d]
                    for i in range(M):
                        acc += e_wout[r, e, d, i] * ce[e, i]
                    outs[e, d] = _tanh(acc)
            for d in range(D):  # Eq. 4; without experts (symbolic tasks) y = x, D = 0
                y[d] = x[d] if KE == 0 else 0.0
                for e in range(KE):
                    y[d] += g[e] * outs[e, d]
            # gating RNN, Eqs. 5-8: reads (g_m, x_m), emits g_{m+τ}
            for h in range(H):
                acc = 0.0
                for k in range(K):
                    acc += g_win[r, h, k] * g[k]
                for d in range(D):
                    acc += g_win[r, h, K + d] * x[d]
                for j in range(H):
                    acc += g_wrec[r, h, j] * cg[j]
                ug[h] = (1.0 - g_eps[r, h]) * ug[h] + g_eps[r, h] * acc
            for h in range(H):
                cg_prev[h] = cg[h]
                cg[h] = _tanh(ug[h] + g_bc[r, h])
            top = -np.inf
            for k in range(K):
                acc = g_bo[r, k]
                for h in range(H):
                    acc += g_wout[r, k, h] * cg[h]
                ng[k] = acc
                top = max(top, acc)
            total = 0.0
            for k in range(K):
                ng[k] = np.exp(ng[k] - top)
                total += ng[k]
            for k in range(K):
                ng[k] /= total
            # tangents: the same steps differentiated (the Jacobian of the whole closed loop)
            for v in range(NV):
                for e in range(KE):
                    for i in range(M):
                        acc = 0.0
                        for d in range(D):
                            acc += e_win[r, e, i, d] * V[v, ox + d]
                        for j in range(M):
                            acc += e_wrec[r, e, i, j] * (1.0 - ce_prev[e, j] ** 2) \
                                * V[v, e * M + j]
                        nv[e * M + i] = (1.0 - e_eps[r, e, i]) * V[v, e * M + i] \
                            + e_eps[r, e, i] * acc
                for d in range(D):
                    dy[d] = V[v, ox + d] if KE == 0 else 0.0
                    for e in range(KE):
                        acc = 0.0
                        for i in range(M):
                            acc += e_wout[r, e, d, i] * (1.0 - ce[e, i] ** 2) * nv[e * M + i]
                        dy[d] += V[v, ot + e] * outs[e, d] + g[e] * (1.0 - outs[e, d] ** 2) * acc
                for h in range(H):
                    acc = 0.0
                    for k in range(K):
                        acc += g_win[r, h, k] * V[v, ot + k]
                    for d in range(D):
                        acc += g_win[r, h, K + d] * V[v, ox + d]
                    for j in range(H):
                        acc += g_wrec[r, h, j] * (1.0 - cg_prev[j] ** 2) * V[v, og + j]
                    nv[og + h] = (1.0 - g_eps[r, h]) * V[v, og + h] + g_eps[r, h] * acc
                mean = 0.0
                for k in range(K):
                    dl[k] = 0.0
                    for h in range(H):
                        dl[k] += g_wout[r, k, h] * (1.0 - cg[h] ** 2) * nv[og + h]
                    mean += ng[k] * dl[k]
                for s in range(TAU - 1):  # the delay lines shift by one
                    for d in range(D):
                        nv[ox + s * D + d] = V[v, ox + (s + 1) * D + d]
                    for k in range(K):
                        nv[ot + s * K + k] = V[v, ot + (s + 1) * K + k]
                for d in range(D):
                    nv[ox + (TAU - 1) * D + d] = dy[d]
                for k in range(K):
                    nv[ot + (TAU - 1) * K + k] = ng[k] * (dl[k] - mean)
                for i in range(nv.shape[0]):
                    V[v, i] = nv[i]
            for v in range(NV):  # modified Gram-Schmidt = QR; |R_vv| is the growth
                for w in range(v):
                    dot = 0.0
                    for i in range(nv.shape[0]):
                        dot += V[w, i] * V[v, i]
                    for i in range(nv.shape[0]):
                        V[v, i] -= dot * V[w, i]
                norm = 0.0
                for i in range(nv.shape[0]):
                    norm += V[v, i] * V[v, i]
                norm = np.sqrt(norm)
                for i in range(nv.shape[0]):
                    V[v, i] /= norm
                if count:
                    log_growth[b, v] += np.log(norm)
            for s in range(TAU - 1):
                for d in range(D):
                    x_line[s, d] = x_line[s + 1, d]
                for k in range(K):
                    g_line[s, k] = g_line[s + 1, k]
            for d in range(D):
                x_line[TAU - 1, d] = y[d]
                out_y[b, t, d] = y[d]
            for k in range(K):
                g_line[TAU - 1, k] = ng[k]
                out_g[b, t, k] = g[k]
            for h in range(H):
                out_u[b, t, h] = ug[h]
        eu[b], gu[b], xs[b], gs[b], tang[b] = ue, ug, x_line, g_line, V


_RNN_KEYS = ("w_in", "w_rec", "tau", "b_c", "w_out", "b_o")  # the kernel's order; tau -> ε = 1/τ


def closed_loop_compiled(experts, gating, state, steps: int, noise=None, tangents=None,
                         count: bool = False):
    """Advance the closed loop `steps` steps in one compiled call (CPU).

    Args:
        experts, gating: parameters (R leading; experts empty for symbolic tasks).
        state: a `moex.model.ClosedLoopState` (R, N, ...).
        noise: (R, N, steps, D) noise added to x_m at each step, or None.
        tangents: (R, N, dim, k) tangent vectors in the layout of `state.flat()`, or None;
            they are re-orthonormalised after every step, as a QR step would.
        count: add ln |R_vv| of each re-orthonormalisation to the returned growth.

    Returns:
        the next state, (y (R, N, steps, D), g (R, N, steps, K), u^g (R, N, steps, H)) as
        `closed_loop_step` returns them step by step, the new tangents (R, N, dim, k) or None,
        and the summed log growth (R, N, k).
    """
    R, N, K = state.gates.shape[0], state.gates.shape[1], state.gates.shape[-1]
    D, H = state.inputs.shape[-1], state.gating_u.shape[-1]
    B = R * N
    as_np = np.dtype(str(state.gates.dtype).removeprefix("torch."))

    def arr(x):  # a private C-contiguous copy: the kernel updates the state in place
        return np.array(x.detach().cpu().numpy(), order="C", copy=True)

    def weights(params):
        return [arr(1 / params[k] if k == "tau" else params[k]) for k in _RNN_KEYS]

    if experts:
        ev = weights(experts)
    else:  # symbolic tasks: no experts, y = x with D = 0
        ev = [np.zeros((R, 0, 0) + (0,) * (k in ("w_in", "w_rec", "w_out")), as_np)
              for k in _RNN_KEYS]
    gv = weights(gating)
    eu = arr(state.experts_u.reshape(B, *state.experts_u.shape[2:]))
    gu, xs, gs = (arr(x.reshape(B, *x.shape[2:])) for x in (state.gating_u, state.inputs,
                                                            state.gates))
    tang = (np.zeros((B, 0, 0), as_np) if tangents is None
            else arr(tangents.reshape(B, *tangents.shape[2:]).transpose(1, 2)))
    noise_arr = np.zeros((B, 0, 0), as_np) if noise is None else arr(noise.reshape(B, steps, D))
    out_y, out_g = np.empty((B, steps, D), as_np), np.empty((B, steps, K), as_np)
    out_u, growth = np.empty((B, steps, H), as_np), np.zeros((B, tang.shape[1]), as_np)
    _closed_loop(eu, gu, xs, gs, tang, *ev, *gv, noise_arr, count, out_y, out_g, out_u, growth)

    def back(x, like):
        return torch.from_numpy(x).reshape(like.shape)

    nxt = type(state)(back(eu, state.experts_u), back(gu, state.gating_u),
                      back(xs, state.inputs), back(gs, state.gates))
    aux = tuple(torch.from_numpy(x).reshape(R, N, steps, x.shape[-1])
                for x in (out_y, out_g, out_u))
    new_tangents = (None if tangents is None
                    else torch.from_numpy(tang).transpose(1, 2).reshape(tangents.shape))
    return nxt, aux, new_tangents, torch.from_numpy(growth).reshape(R, N, -1)
