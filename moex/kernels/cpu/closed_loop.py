"""The closed loop (Sec. 2.2) with Lyapunov tangent vectors, compiled: one lane per (run, sample)
trajectory, the same results as `moex.kernels.reference.closed_loop`."""

import numpy as np
import torch
from numba import njit

from moex.kernels.cpu import threads
from moex.kernels.cpu.lanes import NET, first_use, in_lanes
from moex.kernels.cpu.simd import JIT, exp, fma, lanes, log, stack, tanh, width, zeros
from moex.model import ClosedLoopRun


@njit(inline="always", **JIT)
def _spread_run(lane, N, params, lane_params):  # pragma: no cover
    """Copy the weights of run lane // N into `lane`: params (R, K', ...) -> (NB, K', ..., LB),
    1/τ for the last entry; padding lanes copy the last run (they are discarded)."""
    w_in, w_rec, w_out, b_c, b_o, tau = params
    lane_w_in, lane_w_rec, lane_w_out, lane_b_c, lane_b_o, eps = lane_params
    LB = width(lane_b_c)
    b, v = lane // LB, lane % LB
    r = min(lane // N, params[0].shape[0] - 1)
    for k in range(w_in.shape[1]):
        for i in range(w_rec.shape[2]):
            lane_b_c[b, k, i, v] = b_c[r, k, i]
            eps[b, k, i, v] = 1.0 / tau[r, k, i]
            for d in range(w_in.shape[3]):
                lane_w_in[b, k, i, d, v] = w_in[r, k, i, d]
            for j in range(w_rec.shape[3]):
                lane_w_rec[b, k, i, j, v] = w_rec[r, k, i, j]
        for o in range(w_out.shape[2]):
            lane_b_o[b, k, o, v] = b_o[r, k, o]
            for i in range(w_out.shape[3]):
                lane_w_out[b, k, o, i, v] = w_out[r, k, o, i]


@njit(nogil=True, **JIT)
def closed_blocks(lo, hi, N, experts, gating, E_all, G_all, state_all, V_all, noise_all, count,
                  uniform_gates, out_y_all, out_g_all, out_u_all, growth_all):  # pragma: no cover
    """Blocks lo..hi-1 of trajectories for out_y_all.shape[1] steps; each block first gets its
    lanes' weights from experts / gating (`_spread_run`), then, with every array below its part
    of the block-major *_all array:

    E: expert weights (w_in (KE, M, D), w_rec (KE, M, M), w_out (KE, D, M), b_c, b_o, ε) per
    lane; G: gating weights (w_in (H, K + D), w_rec, w_out (K, H), b_c, b_o, ε) per lane;
    state: u of the experts (KE·M), u^g (H), the delay lines x (τ·D) and g (τ·K), updated in
    place; V (k, dim): tangent vectors in the layout of `ClosedLoopState.flat`, propagated by the
    exact Jacobian and re-orthonormalised (modified Gram-Schmidt) every step; growth (k) += ln of
    the norms when `count`. Records y, the gates that mixed it and u^g (if out_u is not empty)."""
    # one compiled function for the whole loop: a callee per block would be compiled twice
    # (alone, then again inside its caller; BENCHMARKS.md's history)
    E_w_in, E_w_rec, E_w_out, E_b_c, E_b_o, E_eps = E_all
    G_w_in, G_w_rec, G_w_out, G_b_c, G_b_o, G_eps = G_all
    EU, GU, XL, GL = state_all
    LB = width(EU)
    KE, M = E_w_in.shape[1], E_w_in.shape[2]
    H, K = G_w_rec.shape[2], G_w_out.shape[2]
    TAU = GL.shape[1] // K
    D = XL.shape[1] // TAU
    NV, steps = V_all.shape[1], out_y_all.shape[1]
    og, ox = KE * M, KE * M + H
    ot = ox + TAU * D
    dim = ot + TAU * K
    has_noise, keep_u = noise_all.shape[1] > 0, out_u_all.shape[1] > 0
    ue, ce, dce_prev, dce = stack(EU, KE * M), stack(EU, KE * M), stack(EU, KE * M), \
        stack(EU, KE * M)
    outs = stack(EU, KE * D)
    dc = stack(EU, KE * M)  # a tangent's ∂c of the experts (and dcgv of the gating RNN)
    ug, cg, dcg_prev, dcg = stack(EU, H), stack(EU, H), stack(EU, H), stack(EU, H)
    dcgv = stack(EU, H)
    x, y, dy = stack(EU, D), stack(EU, D), stack(EU, D)
    g, ng, dl = stack(EU, K), stack(EU, K), stack(EU, K)
    nv = stack(EU, dim)
    acc, top, total = lanes(EU), lanes(EU), lanes(EU)
    for b in range(lo, hi):
        for lane in range(b * LB, (b + 1) * LB):
            _spread_run(lane, N, experts, E_all)
            _spread_run(lane, N, gating, G_all)
        e_w_in, e_w_rec, e_w_out = E_w_in[b], E_w_rec[b], E_w_out[b]
        e_b_c, e_b_o, e_eps = E_b_c[b], E_b_o[b], E_eps[b]
        g_w_in, g_w_rec, g_w_out = G_w_in[b, 0], G_w_rec[b, 0], G_w_out[b, 0]
        g_b_c, g_b_o, g_eps = G_b_c[b, 0], G_b_o[b, 0], G_eps[b, 0]
        eu, gu, xl, gl = EU[b], GU[b], XL[b], GL[b]
        V, noise, out_y, out_g = V_all[b], noise_all[b], out_y_all[b], out_g_all[b]
        out_u, growth = out_u_all[b], growth_all[b]
        for q in range(KE * M):
            for v in range(LB):
                ue[q, v] = eu[q, v]
                ce[q, v] = tanh(ue[q, v] + e_b_c[q // M, q % M, v])
        for h in range(H):
            for v in range(LB):
                ug[h, v] = gu[h, v]
                cg[h, v] = tanh(ug[h, v] + g_b_c[h, v])
        for t in range(steps):
            for d in range(D):
                for v in range(LB):
                    x[d, v] = xl[d, v] + (noise[t, d, v] if has_noise else 0.0)
            for k in range(K):
                for v in range(LB):
                    g[k, v] = gl[k, v]
            # experts, Eqs. 1-3, all on the same input x_m
            for e in range(KE):
                for i in range(M):
                    for v in range(LB):
                        dce_prev[e * M + i, v] = 1.0 - ce[e * M + i, v] * ce[e * M + i, v]
                for i in range(M):
                    for v in range(LB):
                        acc[v] = 0.0
                    for d in range(D):
                        for v in range(LB):
                            acc[v] = fma(e_w_in[e, i, d, v], x[d, v], acc[v])
                    for j in range(M):
                        for v in range(LB):
                            acc[v] = fma(e_w_rec[e, i, j, v], ce[e * M + j, v], acc[v])
                    for v in range(LB):
                        ue[e * M + i, v] = (1.0 - e_eps[e, i, v]) * ue[e * M + i, v] \
                            + e_eps[e, i, v] * acc[v]
                for i in range(M):
                    for v in range(LB):
                        ce[e * M + i, v] = tanh(ue[e * M + i, v] + e_b_c[e, i, v])
                        dce[e * M + i, v] = 1.0 - ce[e * M + i, v] * ce[e * M + i, v]
                for d in range(D):
                    for v in range(LB):
                        acc[v] = e_b_o[e, d, v]
                    for i in range(M):
                        for v in range(LB):
                            acc[v] = fma(e_w_out[e, d, i, v], ce[e * M + i, v], acc[v])
                    for v in range(LB):
                        outs[e * D + d, v] = tanh(acc[v])
            for d in range(D):  # Eq. 4; without experts (symbolic tasks) D = 0
                for v in range(LB):
                    y[d, v] = 0.0
                for e in range(KE):
                    for v in range(LB):
                        y[d, v] = fma(g[e, v], outs[e * D + d, v], y[d, v])
            # gating RNN, Eqs. 5-8: reads (g_m, x_m), emits g_{m+τ}
            for h in range(H):
                for v in range(LB):
                    dcg_prev[h, v] = 1.0 - cg[h, v] * cg[h, v]
            for h in range(H):
                for v in range(LB):
                    acc[v] = 0.0
                for k in range(K):
                    for v in range(LB):
                        acc[v] = fma(g_w_in[h, k, v], g[k, v], acc[v])
                for d in range(D):
                    for v in range(LB):
                        acc[v] = fma(g_w_in[h, K + d, v], x[d, v], acc[v])
                for j in range(H):
                    for v in range(LB):
                        acc[v] = fma(g_w_rec[h, j, v], cg[j, v], acc[v])
                for v in range(LB):
                    ug[h, v] = (1.0 - g_eps[h, v]) * ug[h, v] + g_eps[h, v] * acc[v]
            for h in range(H):
                for v in range(LB):
                    cg[h, v] = tanh(ug[h, v] + g_b_c[h, v])
                    dcg[h, v] = 1.0 - cg[h, v] * cg[h, v]
            for k in range(K):
                for v in range(LB):
                    acc[v] = g_b_o[k, v]
                for h in range(H):
                    for v in range(LB):
                        acc[v] = fma(g_w_out[k, h, v], cg[h, v], acc[v])
                for v in range(LB):
                    ng[k, v] = acc[v]
            for v in range(LB):
                top[v] = ng[0, v]
                total[v] = 0.0
            for k in range(1, K):
                for v in range(LB):
                    top[v] = ng[k, v] if ng[k, v] > top[v] else top[v]
            for k in range(K):
                for v in range(LB):
                    ng[k, v] = exp(ng[k, v] - top[v])
                    total[v] += ng[k, v]
            for k in range(K):
                for v in range(LB):
                    ng[k, v] /= total[v]
            # tangents: the same step differentiated (the Jacobian of the whole closed loop)
            for n in range(NV):
                for q in range(KE * M):  # ∂c_{m-1} = (1 - c_{m-1}²) ∂u_{m-1}
                    for v in range(LB):
                        dc[q, v] = dce_prev[q, v] * V[n, q, v]
                for e in range(KE):
                    for i in range(M):
                        for v in range(LB):
                            acc[v] = 0.0
                        for d in range(D):
                            for v in range(LB):
                                acc[v] = fma(e_w_in[e, i, d, v], V[n, ox + d, v], acc[v])
                        for j in range(M):
                            for v in range(LB):
                                acc[v] = fma(e_w_rec[e, i, j, v], dc[e * M + j, v], acc[v])
                        for v in range(LB):
                            nv[e * M + i, v] = (1.0 - e_eps[e, i, v]) * V[n, e * M + i, v] \
                                + e_eps[e, i, v] * acc[v]
                for q in range(KE * M):  # ∂c_m
                    for v in range(LB):
                        dc[q, v] = dce[q, v] * nv[q, v]
                for d in range(D):
                    for v in range(LB):
                        dy[d, v] = 0.0
                    for e in range(KE):
                        for v in range(LB):
                            acc[v] = 0.0
                        for i in range(M):
                            for v in range(LB):
                                acc[v] = fma(e_w_out[e, d, i, v], dc[e * M + i, v], acc[v])
                        for v in range(LB):
                            weight = 1.0 / KE if uniform_gates else g[e, v]
                            dy[d, v] += V[n, ot + e, v] * outs[e * D + d, v] + weight \
                                * (1.0 - outs[e * D + d, v] * outs[e * D + d, v]) * acc[v]
                for h in range(H):
                    for v in range(LB):
                        dcgv[h, v] = dcg_prev[h, v] * V[n, og + h, v]
                for h in range(H):
                    for v in range(LB):
                        acc[v] = 0.0
                    for k in range(K):
                        for v in range(LB):
                            acc[v] = fma(g_w_in[h, k, v], V[n, ot + k, v], acc[v])
                    for d in range(D):
                        for v in range(LB):
                            acc[v] = fma(g_w_in[h, K + d, v], V[n, ox + d, v], acc[v])
                    for j in range(H):
                        for v in range(LB):
                            acc[v] = fma(g_w_rec[h, j, v], dcgv[j, v], acc[v])
                    for v in range(LB):
                        nv[og + h, v] = (1.0 - g_eps[h, v]) * V[n, og + h, v] + g_eps[h, v] * acc[v]
                for h in range(H):
                    for v in range(LB):
                        dcgv[h, v] = dcg[h, v] * nv[og + h, v]
                for v in range(LB):
                    total[v] = 0.0
                for k in range(K):
                    for v in range(LB):
                        acc[v] = 0.0
                    for h in range(H):
                        for v in range(LB):
                            acc[v] = fma(g_w_out[k, h, v], dcgv[h, v], acc[v])
                    for v in range(LB):
                        dl[k, v] = acc[v]
                        total[v] = fma(ng[k, v], acc[v], total[v])
                for q in range(TAU - 1):  # the delay lines shift by one
                    for d in range(D):
                        for v in range(LB):
                            nv[ox + q * D + d, v] = V[n, ox + (q + 1) * D + d, v]
                    for k in range(K):
                        for v in range(LB):
                            nv[ot + q * K + k, v] = V[n, ot + (q + 1) * K + k, v]
                for d in range(D):
                    for v in range(LB):
                        nv[ox + (TAU - 1) * D + d, v] = dy[d, v]
                for k in range(K):
                    for v in range(LB):
                        nv[ot + (TAU - 1) * K + k, v] = ng[k, v] * (dl[k, v] - total[v])
                for q in range(dim):
                    for v in range(LB):
                        V[n, q, v] = nv[q, v]
            for n in range(NV):  # modified Gram-Schmidt = QR; the norms are |R_nn|
                for w in range(n):
                    for v in range(LB):
                        acc[v] = 0.0
                    for q in range(dim):
                        for v in range(LB):
                            acc[v] = fma(V[w, q, v], V[n, q, v], acc[v])
                    for q in range(dim):
                        for v in range(LB):
                            V[n, q, v] -= acc[v] * V[w, q, v]
                for v in range(LB):
                    acc[v] = 0.0
                for q in range(dim):
                    for v in range(LB):
                        acc[v] = fma(V[n, q, v], V[n, q, v], acc[v])
                for v in range(LB):
                    acc[v] = np.sqrt(acc[v])
                for q in range(dim):
                    for v in range(LB):
                        V[n, q, v] /= acc[v]
                if count:
                    for v in range(LB):
                        growth[n, v] += log(acc[v])
            for q in range(TAU - 1):
                for d in range(D):
                    for v in range(LB):
                        xl[q * D + d, v] = xl[(q + 1) * D + d, v]
                for k in range(K):
                    for v in range(LB):
                        gl[q * K + k, v] = gl[(q + 1) * K + k, v]
            for d in range(D):
                for v in range(LB):
                    xl[(TAU - 1) * D + d, v] = y[d, v]
                    out_y[t, d, v] = y[d, v]
            for k in range(K):
                for v in range(LB):
                    gl[(TAU - 1) * K + k, v] = ng[k, v]
                    out_g[t, k, v] = g[k, v]
            if keep_u:
                for h in range(H):
                    for v in range(LB):
                        out_u[t, h, v] = ug[h, v]
        for q in range(KE * M):
            for v in range(LB):
                eu[q, v] = ue[q, v]
        for h in range(H):
            for v in range(LB):
                gu[h, v] = ug[h, v]


def _check_shapes(experts, gating, state) -> None:
    """The kernel reads without bounds checks: refuse parameters that do not fit the state."""
    R, N, TAU, K = state.gates.shape
    D, H = state.inputs.shape[-1], state.gating_u.shape[-1]
    expected = {f"gating[{n!r}]": (tuple(gating[n].shape), shape) for n, shape in (
        ("w_in", (R, H, K + D)), ("w_rec", (R, H, H)), ("w_out", (R, K, H)), ("b_c", (R, H)),
        ("b_o", (R, K)), ("tau", (R, H)))}
    if experts:
        KE, M = state.experts_u.shape[2:]
        expected.update({f"experts[{n!r}]": (tuple(experts[n].shape), shape) for n, shape in (
            ("w_in", (R, KE, M, D)), ("w_rec", (R, KE, M, M)), ("w_out", (R, KE, D, M)),
            ("b_c", (R, KE, M)), ("b_o", (R, KE, D)), ("tau", (R, KE, M)))})
    for name, (shape, want) in expected.items():
        if shape != want:
            raise ValueError(f"{name} has shape {shape}; the closed-loop state needs {want}")


def closed_loop(experts, gating, state, steps: int, *, noise=None, tangents=None,
                count: bool = False, uniform_gates: bool = False,
                potentials: bool = True, device: str = "cpu") -> ClosedLoopRun:
    """`moex.kernels.reference.closed_loop` in one compiled call per thread: same arguments and
    results.

    Trajectory (r, n) is lane r·N + n; every lane carries its run's weights, so a block of
    lanes advances LB trajectories with vector instructions; blocks are shared out among the
    threads (`threads.over`).
    """
    R, N, K = state.gates.shape[0], state.gates.shape[1], state.gates.shape[-1]
    TAU, D, H = state.inputs.shape[2], state.inputs.shape[-1], state.gating_u.shape[-1]
    _check_shapes(experts, gating, state)
    B = R * N
    dtype = np.dtype(str(state.gates.dtype).removeprefix("torch."))
    LB = width(dtype)

    def lanes_of(x, per_trajectory_shape):  # (R, N, ...) -> (NB, ..., LB)
        flat = np.asarray(x.detach().cpu().numpy(), dtype).reshape((B,) + per_trajectory_shape)
        return in_lanes(np.moveaxis(flat, 0, -1))

    def params_of(net, per_run):
        if not net:  # symbolic tasks: no experts
            return tuple(np.zeros((R, 0, 1, 1), dtype) if n in ("w_in", "w_rec", "w_out") else
                         np.ones((R, 0, 1), dtype) for n in NET)
        arrays = tuple(np.ascontiguousarray(net[n].detach().cpu().numpy(), dtype) for n in NET)
        return arrays if per_run else tuple(a[:, None] for a in arrays)

    experts_p, gating_p = params_of(experts, True), params_of(gating, False)
    eu = lanes_of(state.experts_u, (-1,))
    NB = eu.shape[0]
    E = tuple(zeros((NB,) + a.shape[1:] + (LB,), dtype) for a in experts_p)
    G = tuple(zeros((NB,) + a.shape[1:] + (LB,), dtype) for a in gating_p)
    gu, xl, gl = (lanes_of(x, (-1,)) for x in (state.gating_u, state.inputs, state.gates))
    k = 0 if tangents is None else tangents.shape[-1]
    V = (zeros((NB, 0, 0, LB), dtype) if tangents is None else
         lanes_of(tangents.transpose(-1, -2), (k, -1)))
    noise_l = (zeros((NB, 0, 0, LB), dtype) if noise is None else
               lanes_of(noise, (steps, D)))
    out_y, out_g = zeros((NB, steps, D, LB), dtype), zeros((NB, steps, K, LB), dtype)
    out_u = zeros((NB, steps if potentials else 0, H, LB), dtype)
    growth = zeros((NB, k, LB), dtype)
    with first_use(closed_blocks, "closed-loop kernel"):
        threads.over(closed_blocks, NB, N, experts_p, gating_p, E, G, (eu, gu, xl, gl), V,
                     noise_l, count, uniform_gates, out_y, out_g, out_u, growth)

    def back(x, shape):  # (NB, ..., LB) -> (R, N, ...)
        flat = np.moveaxis(x, -1, 1).reshape((NB * LB,) + x.shape[1:-1])[:B]
        return torch.from_numpy(np.ascontiguousarray(flat.reshape((R, N) + shape)))

    nxt = type(state)(back(eu, state.experts_u.shape[2:]), back(gu, (H,)),
                      back(xl, (TAU, D)), back(gl, (TAU, K)))
    new_tangents = None if tangents is None else back(V, (k, -1)).transpose(-1, -2).contiguous()
    return ClosedLoopRun(nxt, back(out_y, (steps, D)), back(out_g, (steps, K)),
                         back(out_u, (steps, H)) if potentials else None, new_tangents,
                         back(growth, (k,)))
