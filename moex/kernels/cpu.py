"""Compiled CPU backend (numba): the functions of `moex.kernels.reference`, each training step one
compiled call for all R runs.

Layout. Every independent recurrence is a *lane*: an (expert, series) pair of one run in phase 1
(lane (r·K + k)·S + s), a series of one run in phase 2 (lane r·S + s), a (run, sample) trajectory
of the closed loop. Lanes are the last axis of every work array, padded to whole blocks of `LB`;
each lane carries its own copy of its network's weights, so a block of lanes is one SIMD vector
whichever networks its lanes belong to. A block runs its whole time loop with the lane loop
innermost; blocks run in parallel threads. The per-lane weight gradients are summed over the
lanes of each network at the end.

Shapes inside: T steps, H units, NI inputs, NO outputs, NL lanes. The leaky RNN is Eqs. 1-3 / 5-8:
u_t = (1-ε) u_{t-1} + ε (W_in x_t + W_rec c_{t-1}), c_t = tanh(u_t + b_c), o_t = W_out c_t + b_o,
with c_{-1} = tanh(u_0 + b_c).
"""

import contextlib
import logging
import math
import time

import numpy as np
import torch
from numba import get_num_threads, njit, prange

from moex.kernels import input_noise
from moex.kernels.simd import JIT, LB, exp, fma, lanes, log, padded, stack, tanh
from moex.model import ClosedLoopRun

# ---------------------------------------------------------------------------------------------
# the leaky RNN over one block of lanes: forward and backward (BPTT)


@njit(**JIT)
def _forward(X, wi, wr, wo, bc, bo, eps, u0, squash, C0, C, Y, U, S1, S2):  # pragma: no cover
    """One block of lanes (every array is that block's (..., LB) part): Y (T, NO, LB) = tanh(o_t)
    if `squash` else o_t; C (T, H, LB), U (T, H, LB) and the sums S1, S2 (H, LB) of u and u²
    over {u_0..u_T} are filled where their arrays are not empty."""
    T, NI = X.shape[0], X.shape[1]
    H, NO = wr.shape[0], wo.shape[0]
    keep_c, keep_u, keep_sums = C.shape[0] > 0, U.shape[0] > 0, S1.shape[0] > 0
    u, c = stack(X, H), stack(X, H)
    s1, s2 = stack(S1, H), stack(S1, H)  # float64 sums: the variance is taken by difference
    acc = lanes(X)
    for i in range(H):
        for v in range(LB):
            u[i, v] = u0[i, v]
            c[i, v] = tanh(u[i, v] + bc[i, v])
            s1[i, v] = u[i, v]
            s2[i, v] = u[i, v] * u[i, v]
        for v in range(LB):
            C0[i, v] = c[i, v]
    for t in range(T):
        for i in range(H):
            for v in range(LB):
                acc[v] = 0.0
            for d in range(NI):
                for v in range(LB):
                    acc[v] = fma(wi[i, d, v], X[t, d, v], acc[v])
            for j in range(H):
                for v in range(LB):
                    acc[v] = fma(wr[i, j, v], c[j, v], acc[v])
            for v in range(LB):
                u[i, v] = fma(eps[i, v], acc[v] - u[i, v], u[i, v])  # (1 - ε) u + ε acc
        for i in range(H):
            for v in range(LB):
                c[i, v] = tanh(u[i, v] + bc[i, v])
                s1[i, v] += u[i, v]
                s2[i, v] = fma(u[i, v], u[i, v], s2[i, v])
        if keep_c:
            for i in range(H):
                for v in range(LB):
                    C[t, i, v] = c[i, v]
        if keep_u:
            for i in range(H):
                for v in range(LB):
                    U[t, i, v] = u[i, v]
        for o in range(NO):
            for v in range(LB):
                acc[v] = bo[o, v]
            for i in range(H):
                for v in range(LB):
                    acc[v] = fma(wo[o, i, v], c[i, v], acc[v])
            if squash:
                for v in range(LB):
                    Y[t, o, v] = tanh(acc[v])
            else:
                for v in range(LB):
                    Y[t, o, v] = acc[v]
    if keep_sums:
        for i in range(H):
            for v in range(LB):
                S1[i, v] = s1[i, v]
                S2[i, v] = s2[i, v]


@njit(**JIT)
def _backward(DY, X, C0, C, U, u0, wr, wo, eps, g_wi, g_wr, g_wo, g_bc, g_bo, g_eps,
              g_u0):  # pragma: no cover
    """One block of lanes, given DY (T, NO, LB) = ∂L/∂o_t: every per-lane gradient (BPTT). g_eps
    is filled when U holds the potentials (learned time constants). Gradients are summed in
    stack arrays (they cannot alias the histories they read) and written once."""
    T, NI = X.shape[0], X.shape[1]
    H, NO = wr.shape[0], wo.shape[0]
    learn_eps = U.shape[0] > 0
    a, ea, back = stack(X, H), stack(X, H), stack(X, H)  # ∂L/∂u_t, ε ⊙ a_t, W_recᵀ(ε ⊙ a_{t+1})
    gbc, geps = stack(X, H), stack(X, H)
    gwr, gwi, gwo = stack(X, H * H), stack(X, H * NI), stack(X, NO * H)
    gbo = stack(X, NO)
    acc = lanes(X)
    for i in range(H):
        for v in range(LB):
            a[i, v] = back[i, v] = gbc[i, v] = geps[i, v] = 0.0
    for q in range(H * H):
        for v in range(LB):
            gwr[q, v] = 0.0
    for q in range(H * NI):
        for v in range(LB):
            gwi[q, v] = 0.0
    for q in range(NO * H):
        for v in range(LB):
            gwo[q, v] = 0.0
    for o in range(NO):
        for v in range(LB):
            gbo[o, v] = 0.0
    for t in range(T - 1, -1, -1):
        prev = C[t - 1] if t > 0 else C0
        for i in range(H):  # a_t = (1 - c_t²)(W_outᵀ δo_t + back) + (1 - ε) a_{t+1}
            for v in range(LB):
                acc[v] = back[i, v]
            for o in range(NO):
                for v in range(LB):
                    acc[v] = fma(wo[o, i, v], DY[t, o, v], acc[v])
            for v in range(LB):
                dq = fma(-C[t, i, v], C[t, i, v], 1.0) * acc[v]
                gbc[i, v] += dq
                a[i, v] = fma(1.0 - eps[i, v], a[i, v], dq)
                ea[i, v] = eps[i, v] * a[i, v]
        for o in range(NO):
            for v in range(LB):
                gbo[o, v] += DY[t, o, v]
            for i in range(H):
                for v in range(LB):
                    gwo[o * H + i, v] = fma(DY[t, o, v], C[t, i, v], gwo[o * H + i, v])
        for i in range(H):
            for d in range(NI):
                for v in range(LB):
                    gwi[i * NI + d, v] = fma(ea[i, v], X[t, d, v], gwi[i * NI + d, v])
            for j in range(H):
                for v in range(LB):
                    gwr[i * H + j, v] = fma(ea[i, v], prev[j, v], gwr[i * H + j, v])
        if learn_eps:  # ∂u_t/∂ε = s_t - u_{t-1} = (u_t - u_{t-1}) / ε
            u_prev = U[t - 1] if t > 0 else u0
            for i in range(H):
                for v in range(LB):
                    geps[i, v] += a[i, v] * (U[t, i, v] - u_prev[i, v]) \
                        / eps[i, v]
        for j in range(H):
            for v in range(LB):
                acc[v] = 0.0
            for i in range(H):
                for v in range(LB):
                    acc[v] = fma(wr[i, j, v], ea[i, v], acc[v])
            for v in range(LB):
                back[j, v] = acc[v]
    for i in range(H):  # c_{-1} = tanh(u_0 + b_c) feeds step 0
        for v in range(LB):
            dq = (1.0 - C0[i, v] * C0[i, v]) * back[i, v]
            g_bc[i, v] = gbc[i, v] + dq
            g_u0[i, v] = (1.0 - eps[i, v]) * a[i, v] + dq
            g_eps[i, v] = geps[i, v]
        for d in range(NI):
            for v in range(LB):
                g_wi[i, d, v] = gwi[i * NI + d, v]
        for j in range(H):
            for v in range(LB):
                g_wr[i, j, v] = gwr[i * H + j, v]
    for o in range(NO):
        for v in range(LB):
            g_bo[o, v] = gbo[o, v]
        for i in range(H):
            for v in range(LB):
                g_wo[o, i, v] = gwo[o * H + i, v]


# ---------------------------------------------------------------------------------------------
# parameters <-> lanes. Lane l is entry l % LB of block l // LB; network g (an expert of a run, or
# a run's gating RNN) owns lanes g·S .. g·S + S - 1, one per series. Lanes past the last network
# are padding: zero weights, no data.


@njit(inline="always", **JIT)
def _spread(lane, S, params, u0, net):  # pragma: no cover
    """Copy the weights of the network that owns `lane` into it (zeros for padding lanes).
    Network parameters are (R, K', ...) with K' experts per run (1 for the gating RNN); u0 is
    (R, S, K', H)."""
    w_in, w_rec, w_out, b_c, b_o, tau = params
    wi, wr, wo, bc, bo, eps, u0_lane = net
    R, KK = w_in.shape[0], w_in.shape[1]
    b, v = lane // LB, lane % LB
    g, s = lane // S, lane % S
    r, k = min(g // KK, R - 1), g % KK
    real = g < R * KK
    H, NI, NO = w_rec.shape[2], w_in.shape[3], w_out.shape[2]
    for i in range(H):
        bc[b, i, v] = b_c[r, k, i] if real else 0.0
        eps[b, i, v] = 1.0 / tau[r, k, i] if real else 1.0
        u0_lane[b, i, v] = u0[r, s, k, i] if real else 0.0
        for d in range(NI):
            wi[b, i, d, v] = w_in[r, k, i, d] if real else 0.0
        for j in range(H):
            wr[b, i, j, v] = w_rec[r, k, i, j] if real else 0.0
    for o in range(NO):
        bo[b, o, v] = b_o[r, k, o] if real else 0.0
        for i in range(H):
            wo[b, o, i, v] = w_out[r, k, o, i] if real else 0.0


@njit(inline="always", **JIT)
def _lane_sum(x, lo, hi):  # pragma: no cover
    """Σ over lanes lo..hi-1 of x (NB, LB)."""
    total = 0.0
    for lane in range(lo, hi):
        total += x[lane // LB, lane % LB]
    return total


@njit(inline="always", **JIT)
def _gather(g, S, tau, lane_grads, grads, learn_eps):  # pragma: no cover
    """Sum the per-lane gradients of network g's S lanes into its parameter gradients
    (∂/∂τ = -ε² ∂/∂ε); layouts as in `_spread`."""
    l_wi, l_wr, l_wo, l_bc, l_bo, l_eps = lane_grads
    g_w_in, g_w_rec, g_w_out, g_b_c, g_b_o, g_tau = grads
    KK = g_w_in.shape[1]
    r, k = g // KK, g % KK
    H, NI, NO = g_w_rec.shape[2], g_w_in.shape[3], g_w_out.shape[2]
    lo, hi = g * S, g * S + S
    for i in range(H):
        g_b_c[r, k, i] = _lane_sum(l_bc[:, i], lo, hi)
        if learn_eps:
            g_tau[r, k, i] = -_lane_sum(l_eps[:, i], lo, hi) / (tau[r, k, i] * tau[r, k, i])
        for d in range(NI):
            g_w_in[r, k, i, d] = _lane_sum(l_wi[:, i, d], lo, hi)
        for j in range(H):
            g_w_rec[r, k, i, j] = _lane_sum(l_wr[:, i, j], lo, hi)
    for o in range(NO):
        g_b_o[r, k, o] = _lane_sum(l_bo[:, o], lo, hi)
        for i in range(H):
            g_w_out[r, k, o, i] = _lane_sum(l_wo[:, o, i], lo, hi)


@njit(inline="always", **JIT)
def _run_lanes(r, S, T, u0_lane, S1, S2, floor, attraction, want_grad, l_u0,
               g_u0):  # pragma: no cover
    """After the backward pass, for the lanes of run r: the C code's attraction of u_0 to the
    mean μ of its own trajectory {u_0..u_T} (not in the paper; value returned, gradient
    (μ - u_0)/max(var, floor) added) and the u_0 gradients copied out to g_u0 (R, S, K', H)."""
    value = 0.0
    KK = g_u0.shape[2]
    for lane in range(r * KK * S, (r + 1) * KK * S):
        b, v = lane // LB, lane % LB
        k, s = (lane // S) % KK, lane % S
        for i in range(u0_lane.shape[1]):
            if attraction:
                mean = S1[b, i, v] / (T + 1)
                var = max(S2[b, i, v] / (T + 1) - mean * mean, floor)
                diff = u0_lane[b, i, v] - mean
                value -= diff * diff / (2.0 * var)
                l_u0[b, i, v] -= diff / var
            if want_grad:
                g_u0[r, s, k, i] = l_u0[b, i, v]
    return value


def _runs_of_blocks(num_blocks, lanes_per_run, num_runs):
    """(NB, 2): the first and last run each block of lanes touches."""
    starts = np.arange(num_blocks) * LB
    first = np.minimum(starts // lanes_per_run, num_runs - 1)
    last = np.minimum((starts + LB - 1) // lanes_per_run, num_runs - 1)
    return np.stack([first, last], 1)


@njit(inline="always", **JIT)
def _block_active(b, block_runs, active):  # pragma: no cover
    return active[block_runs[b, 0]:block_runs[b, 1] + 1].any()


# ---------------------------------------------------------------------------------------------
# phase 1: the experts and β (Eqs. 9-13)


@njit(**JIT)
def _mixture(r, s, Y, targets, beta, var, want_grad, DY, g_beta, partial):  # pragma: no cover
    """Series s of run r: ln p(y | X, β, γ) in log space (Eqs. 10-12), the Brownian prior on β
    (Eq. 13) and the E error; with want_grad ∂/∂o of every expert output and ∂/∂β (Eq. 19).
    partial[r·S + s] gets (ln p, ln φ(β), Σ‖ŷ - y‖², then per expert ∂ ln p/∂s of
    σ² = e^{2s} + σ̄² without its factor (σ² - σ̄²)/σ²). Every loop runs over time, innermost;
    the strided inputs are copied to contiguous arrays first."""
    S, T, D = targets.shape
    K = beta.shape[3]
    prior_std = var[r, K]
    y = np.empty((K, D, T))
    target = np.empty((D, T))
    log_ghat, z = np.empty((K, T)), np.empty((K, T))
    top, total = np.empty(T), np.empty(T)
    for k in range(K):
        lane = (r * K + k) * S + s
        for d in range(D):
            for t in range(T):
                y[k, d, t] = Y[lane // LB, t, d, lane % LB]
    for d in range(D):
        for t in range(T):
            target[d, t] = targets[s, t, d]
    # ln ĝ = β - ln Σ exp β (Eq. 9)
    for t in range(T):
        top[t] = beta[r, s, t, 0]
        total[t] = 0.0
    for k in range(1, K):
        for t in range(T):
            top[t] = max(top[t], beta[r, s, t, k])
    for k in range(K):
        for t in range(T):
            total[t] += exp(beta[r, s, t, k] - top[t])
    for t in range(T):
        top[t] += log(total[t])
    for k in range(K):
        for t in range(T):
            log_ghat[k, t] = beta[r, s, t, k] - top[t]
    # z_k = ln ĝ_k + ln N(y; y^k, σ_k² NI); ln p = ln Σ_k exp z_k
    for k in range(K):
        norm = -0.5 * D * log(2.0 * math.pi * var[r, k])
        for t in range(T):
            z[k, t] = 0.0
        for d in range(D):
            for t in range(T):
                diff = y[k, d, t] - target[d, t]
                z[k, t] = fma(diff, diff, z[k, t])
        for t in range(T):
            z[k, t] = log_ghat[k, t] + norm - z[k, t] / (2.0 * var[r, k])
    for t in range(T):
        top[t] = z[0, t]
        total[t] = 0.0
    for k in range(1, K):
        for t in range(T):
            top[t] = max(top[t], z[k, t])
    for k in range(K):
        for t in range(T):
            total[t] += exp(z[k, t] - top[t])
    log_lik = 0.0
    for t in range(T):
        top[t] += log(total[t])
        log_lik += top[t]
    error = 0.0  # E: the mixture Σ_k ĝ_k y^k against the target
    for d in range(D):
        for t in range(T):
            total[t] = -target[d, t]
        for k in range(K):
            for t in range(T):
                total[t] = fma(exp(log_ghat[k, t]), y[k, d, t], total[t])
        for t in range(T):
            error = fma(total[t], total[t], error)
    prior = 0.0
    inv = 1.0 / (prior_std * prior_std)
    log_norm = 0.5 * log(2.0 * math.pi * prior_std * prior_std)
    for k in range(K):
        for t in range(T - 1):
            diff = beta[r, s, t + 1, k] - beta[r, s, t, k]
            prior -= 0.5 * diff * diff * inv + log_norm
    partial[r * S + s, 0] = log_lik
    partial[r * S + s, 1] = prior
    partial[r * S + s, 2] = error
    if not want_grad:
        return
    resp, sq = total, np.empty(T)
    for k in range(K):
        lane = (r * K + k) * S + s
        for t in range(T):  # exp(z_k - ln p): the posterior responsibility of expert k
            resp[t] = exp(z[k, t] - top[t])
        for t in range(T):  # with G_n / ς² of Eq. 19
            g_beta[r, s, t, k] = resp[t] - exp(log_ghat[k, t]) + inv * (
                beta[r, s, min(t + 1, T - 1), k] - 2.0 * beta[r, s, t, k]
                + beta[r, s, max(t - 1, 0), k])
        for t in range(T):
            sq[t] = 0.0
        for d in range(D):
            for t in range(T):
                diff = y[k, d, t] - target[d, t]
                sq[t] = fma(diff, diff, sq[t])
        sigma_term = 0.0
        for t in range(T):
            sigma_term += resp[t] * (sq[t] / var[r, k] - D)
        partial[r * S + s, 3 + k] = sigma_term
        for d in range(D):
            for t in range(T):
                out = y[k, d, t]
                DY[lane // LB, t, d, lane % LB] = resp[t] * (target[d, t] - out) / var[r, k] \
                    * fma(-out, out, 1.0)


@njit(**JIT)
def _expert_runs(first, last, S, work, net, lane_grads, X, targets, beta, var, want_grad,
                 g_beta, active, block_runs):  # pragma: no cover
    """Runs first..last-1, whose lanes fill whole blocks: forward, mixture and backward."""
    C0, C, Y, U, S1, S2, DY, partial, _ = work
    wi, wr, wo, bc, bo, eps, u0_lane = net
    l_wi, l_wr, l_wo, l_bc, l_bo, l_eps, l_u0 = lane_grads
    K = beta.shape[3]
    lo, hi = first * K * S // LB, min(-(-last * K * S // LB), wi.shape[0])
    for b in range(lo, hi):
        if _block_active(b, block_runs, active):
            _forward(X[b], wi[b], wr[b], wo[b], bc[b], bo[b], eps[b], u0_lane[b], True, C0[b],
                     C[b], Y[b], U[b], S1[b], S2[b])
    for q in range(first * S, last * S):
        if active[q // S]:
            _mixture(q // S, q % S, Y, targets, beta, var, want_grad, DY, g_beta, partial)
    if want_grad:
        for b in range(lo, hi):
            if _block_active(b, block_runs, active):
                _backward(DY[b], X[b], C0[b], C[b], U[b], u0_lane[b], wr[b], wo[b], eps[b],
                          l_wi[b], l_wr[b], l_wo[b], l_bc[b], l_bo[b], l_eps[b], l_u0[b])


@njit(parallel=True, **JIT)
def _expert_step(params, u0, log_sigma, beta, net, work, lane_grads, grads, g_u0, g_log_sigma,
                 g_beta, X, targets, sigma_min, prior_std, attraction, want_grad, active,
                 block_runs, chunk, threads, out):  # pragma: no cover
    """Phase 1 of every active run in one call: forward, objective and every gradient.
    out (4, R): objective, ln p(Y | X, θ), ln φ(β), E.

    With at least as many chunks of `chunk` runs (whole blocks of lanes) as `threads`, each thread
    takes whole chunks through forward, mixture and backward while their histories are still in
    its cache; with fewer, each pass runs over all blocks, in parallel."""
    C0, C, Y, U, S1, S2, DY, partial, var = work
    R, S, T, K = beta.shape
    NB = net[0].shape[0]
    floor = sigma_min * sigma_min
    for r in range(R):  # σ_k² = e^{2 s_k} + σ̄², and ς beside them for _mixture
        for k in range(K):
            var[r, k] = exp(2.0 * log_sigma[r, k]) + floor
        var[r, K] = prior_std
    for lane in prange(NB * LB):
        _spread(lane, S, params, u0, net)
    chunks = -(-R // chunk)
    if chunks >= threads:
        for c in prange(chunks):
            _expert_runs(c * chunk, min((c + 1) * chunk, R), S, work, net, lane_grads, X,
                         targets, beta, var, want_grad, g_beta, active, block_runs)
    else:
        wi, wr, wo, bc, bo, eps, u0_lane = net
        l_wi, l_wr, l_wo, l_bc, l_bo, l_eps, l_u0 = lane_grads
        for b in prange(NB):
            if _block_active(b, block_runs, active):
                _forward(X[b], wi[b], wr[b], wo[b], bc[b], bo[b], eps[b], u0_lane[b], True,
                         C0[b], C[b], Y[b], U[b], S1[b], S2[b])
        for q in prange(R * S):
            if active[q // S]:
                _mixture(q // S, q % S, Y, targets, beta, var, want_grad, DY, g_beta, partial)
        if want_grad:
            for b in prange(NB):
                if _block_active(b, block_runs, active):
                    _backward(DY[b], X[b], C0[b], C[b], U[b], u0_lane[b], wr[b], wo[b],
                              eps[b], l_wi[b], l_wr[b], l_wo[b], l_bc[b], l_bo[b], l_eps[b],
                              l_u0[b])
    if want_grad:
        for g in prange(R * K):
            if active[g // K]:
                _gather(g, S, params[5], lane_grads[:6], grads, U.shape[1] > 0)
    for r in prange(R):
        if not active[r]:
            continue
        log_lik = partial[r * S:(r + 1) * S, 0].sum()
        prior = partial[r * S:(r + 1) * S, 1].sum()
        error = partial[r * S:(r + 1) * S, 2].sum()
        out[0, r] = log_lik + prior + _run_lanes(r, S, T, net[6], S1, S2, floor, attraction,
                                                 want_grad, lane_grads[6], g_u0)
        out[1, r], out[2, r] = log_lik, prior
        out[3, r] = 0.5 * error / (S * T * targets.shape[2])
        if want_grad:
            for k in range(K):
                g_log_sigma[r, k] = partial[r * S:(r + 1) * S, 3 + k].sum() \
                    * (var[r, k] - floor) / var[r, k]


# ---------------------------------------------------------------------------------------------
# phase 2: the gating RNN fitted to ĝ (Eqs. 14-16)


@njit(**JIT)
def _softmax_objective(Y, targets, want_grad, DY, log_lik):  # pragma: no cover
    """One block: log_lik (LB,) = Σ_t Σ_k ĝ_k ln softmax(o_t)_k (Eq. 15 without ln Z) and, with
    want_grad, DY (T, K, LB) = ∂/∂o_t = ĝ - g Σ_k ĝ_k."""
    T, K = Y.shape[0], Y.shape[1]
    total, top, norm, mass = lanes(Y), lanes(Y), lanes(Y), lanes(Y)
    for v in range(LB):
        total[v] = 0.0
    for t in range(T):
        for v in range(LB):
            top[v] = Y[t, 0, v]
            norm[v] = 0.0
            mass[v] = 0.0
        for k in range(1, K):
            for v in range(LB):
                top[v] = Y[t, k, v] if Y[t, k, v] > top[v] else top[v]
        for k in range(K):
            for v in range(LB):
                norm[v] += exp(Y[t, k, v] - top[v])
                mass[v] += targets[t, k, v]
        for v in range(LB):
            norm[v] = top[v] + log(norm[v])
        for k in range(K):
            for v in range(LB):
                total[v] += targets[t, k, v] * (Y[t, k, v] - norm[v])
        if want_grad:
            for k in range(K):
                for v in range(LB):
                    DY[t, k, v] = targets[t, k, v] - exp(Y[t, k, v] - norm[v]) * mass[v]
    for v in range(LB):
        log_lik[v] = total[v]


@njit(parallel=True, **JIT)
def _gating_step(params, u0, net, work, lane_grads, grads, g_u0, X, targets, entropy,
                 sigma_min, attraction, want_grad, active, block_runs, out):  # pragma: no cover
    """Phase 2 of every active run in one call. out (4, R): objective, Σ ĝ ln g, KL, E^g."""
    C0, C, Y, U, S1, S2, DY, log_lik = work
    wi, wr, wo, bc, bo, eps, u0_lane = net
    l_wi, l_wr, l_wo, l_bc, l_bo, l_eps, l_u0 = lane_grads
    R, S, NB = u0.shape[0], u0.shape[1], wi.shape[0]
    T, K = targets.shape[1], targets.shape[2]
    for lane in prange(NB * LB):
        _spread(lane, S, params, u0, net)
    for b in prange(NB):
        if _block_active(b, block_runs, active):
            _forward(X[b], wi[b], wr[b], wo[b], bc[b], bo[b], eps[b], u0_lane[b], False, C0[b],
                     C[b], Y[b], U[b], S1[b], S2[b])
            _softmax_objective(Y[b], targets[b], want_grad, DY[b], log_lik[b])
            if want_grad:
                _backward(DY[b], X[b], C0[b], C[b], U[b], u0_lane[b], wr[b], wo[b], eps[b],
                          l_wi[b], l_wr[b], l_wo[b], l_bc[b], l_bo[b], l_eps[b], l_u0[b])
    for r in prange(R):
        if not active[r]:
            continue
        total = _lane_sum(log_lik, r * S, (r + 1) * S)
        out[1, r] = total
        out[2, r] = entropy[r] - total
        out[3, r] = out[2, r] / (S * T * K)
        out[0, r] = total + _run_lanes(r, S, T, u0_lane, S1, S2, sigma_min * sigma_min,
                                       attraction, want_grad, l_u0, g_u0)
        if want_grad:
            _gather(r, S, params[5], lane_grads[:6], grads, U.shape[1] > 0)


# ---------------------------------------------------------------------------------------------
# the backend interface (the same classes as moex.kernels.reference)

logger = logging.getLogger(__name__)
_ready: set = set()


@contextlib.contextmanager
def _first_use(kernel, what: str):
    """Log lines around the first call of a kernel in this process: numba compiles it then
    (tens of seconds) or loads it from its cache on disk (about a second)."""
    if kernel in _ready:
        yield
        return
    logger.info("preparing the compiled %s (compiled on first use, then cached on disk) ...",
                what)
    start = time.perf_counter()
    yield
    _ready.add(kernel)
    logger.info("compiled %s ready in %.1f s", what, time.perf_counter() - start)


_NET = ("w_in", "w_rec", "w_out", "b_c", "b_o", "tau")


def _per_network(params: dict, experts: bool) -> tuple:
    """The network parameters as (R, K', ...) views (K' = 1 for the gating RNN), never copies:
    the kernels write gradients into them."""
    return tuple(params[n] if experts else params[n][:, None] for n in _NET)


def _in_lanes(per_lane: np.ndarray) -> np.ndarray:
    """(..., NL) -> (NB, ..., LB), lanes padded with zeros to whole blocks."""
    NL = per_lane.shape[-1]
    padded_lanes = np.zeros(per_lane.shape[:-1] + (padded(NL),), per_lane.dtype)
    padded_lanes[..., :NL] = per_lane
    blocks = padded_lanes.reshape(per_lane.shape[:-1] + (padded(NL) // LB, LB))
    return np.ascontiguousarray(np.moveaxis(blocks, -2, 0))


class _Lanes:
    """Work arrays of one phase, block-major (NB, ..., LB) so that a block's history is one
    contiguous piece of memory: per-lane weights, histories and per-lane gradients."""

    def __init__(self, T, H, NI, NO, num_lanes, lanes_per_run, num_runs, learn_tau, attraction,
                 dtype):
        NB = padded(num_lanes) // LB

        def zeros(*shape):
            return np.zeros((NB,) + shape + (LB,), dtype)

        self.net = (zeros(H, NI), zeros(H, H), zeros(NO, H), zeros(H), zeros(NO), zeros(H),
                    zeros(H))
        sums = (NB, H if attraction else 0, LB)
        self.work = [zeros(H), zeros(T, H), zeros(T, NO), zeros(*((T, H) if learn_tau else (0, 0))),
                     np.zeros(sums), np.zeros(sums), zeros(T, NO)]
        self.lane_grads = tuple(np.zeros_like(x) for x in self.net)
        self.block_runs = _runs_of_blocks(NB, lanes_per_run, num_runs)
        self.num_lanes = NB * LB
        self.out = np.zeros((4, num_runs), dtype)

    def stats(self, names) -> dict[str, np.ndarray]:
        return {n: self.out[i].copy() for i, n in enumerate(names)}


class _Staging:
    """C-contiguous copies of a phase's parameters and gradients. The training loop hands views
    of its (R, P) buffers, whose layout numba types differently for R = 1 and R > 1; copying
    into these (a few percent of a step) lets every kernel compile once per dtype."""

    def __init__(self, shapes: dict, dtype):
        self.params = {n: np.zeros(shape, dtype) for n, shape in shapes.items()}
        self.grads = {n: np.zeros(shape, dtype) for n, shape in shapes.items()}

    def load(self, params: dict) -> dict:
        for name, value in params.items():
            np.copyto(self.params[name], value)
        return self.params

    def store(self, grads: dict | None) -> None:
        for name, value in (grads or {}).items():
            np.copyto(value, self.grads[name])


class ExpertProblem:
    """Phase 1 of R runs (Sec. 2.1.2, Eqs. 9-13): `value_and_grad` and `value` of ln L(D, θ)
    for all runs, one compiled call each (`resample` has nothing to draw).

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}.
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`; num_runs: R.
    """

    STATS = ("objective", "log_likelihood", "log_prior", "E")

    def __init__(self, inputs, targets, model, phase, num_runs, device="cpu"):
        S, T, D = targets.shape
        R, K, M = num_runs, model.num_experts, model.experts.context_size
        dtype = np.dtype(inputs.dtype)
        self.shape, self.model, self.phase = (R, S, T, K), model, phase
        self.lanes = _Lanes(T, M, D, D, R * K * S, K * S, R, model.learn_time_constants,
                            phase.attraction, dtype)
        # lane (r·K + k)·S + s reads series s
        self.inputs = _in_lanes(np.tile(np.asarray(inputs).transpose(1, 2, 0), R * K))
        self.targets = np.ascontiguousarray(targets)
        self.lanes.work += [np.zeros((R * S, 3 + K), dtype), np.zeros((R, K + 1), dtype)]
        self.chunk = LB // math.gcd(K * S, LB)  # the fewest runs whose lanes fill whole blocks
        self.staging = _Staging({
            "w_in": (R, K, M, D), "w_rec": (R, K, M, M), "w_out": (R, K, D, M), "b_c": (R, K, M),
            "b_o": (R, K, D), "tau": (R, K, M), "log_sigma": (R, K), "u0": (R, S, K, M),
            "beta": (R, S, T, K)}, dtype)

    def _call(self, params, grads, active, want_grad):
        p, g, lanes = self.staging.load(params), self.staging.grads, self.lanes
        with _first_use(_expert_step, "phase-1 kernel"):
            self._step(p, g, lanes, active, want_grad)
        self.staging.store(grads)
        return lanes.stats(self.STATS)

    def _step(self, p, g, lanes, active, want_grad):
        _expert_step(_per_network(p, True), p["u0"], p["log_sigma"], p["beta"], lanes.net,
                     tuple(lanes.work), lanes.lane_grads, _per_network(g, True), g["u0"],
                     g["log_sigma"], g["beta"], self.inputs, self.targets,
                     float(self.model.sigma_min), float(self.phase.gate_prior_std),
                     bool(self.phase.attraction), want_grad, np.ascontiguousarray(active),
                     lanes.block_runs, self.chunk, get_num_threads(), lanes.out)

    def value_and_grad(self, params: dict, grads: dict, active: np.ndarray) -> dict:
        """Objective statistics per run (R,); every gradient is written into `grads`."""
        return self._call(params, grads, active, True)

    def value(self, params: dict, active: np.ndarray) -> dict:
        """The same statistics without gradients (the adaptive-rate retry)."""
        return self._call(params, None, active, False)

    def resample(self, step: int) -> None:
        pass


class GatingProblem:
    """Phase 2 of R runs (Sec. 2.1.2, Eqs. 14-16): ln L(D^g, θ^g) up to ln Z for all runs, one
    compiled call each.

    Args:
        gate_targets: (R, S, T, K) ĝ_n; inputs: (S, T, D) x_n aligned with ĝ_n (D may be 0).
        model: the `ModelConfig`; phase: the `GatingPhaseConfig`.
        seeds: one per run, for the input noise that `resample(step)` draws when
            `phase.input_noise_var` > 0 (`moex.kernels.input_noise`).
    """

    STATS = ("objective", "log_likelihood", "kl", "E_g")

    def __init__(self, gate_targets, inputs, model, phase, seeds, device="cpu"):
        R, S, T, K = gate_targets.shape
        D, H, delay = inputs.shape[-1], model.gating.context_size, model.delay
        T_g = T - delay
        dtype = np.dtype(gate_targets.dtype)
        self.shape, self.model, self.phase = (R, S, T_g, K), model, phase
        self.lanes = _Lanes(T_g, H, K + D, K, R * S, S, R, model.learn_time_constants,
                            phase.attraction, dtype)
        ghat = np.asarray(gate_targets)
        x = np.broadcast_to(np.asarray(inputs)[None], (R, S, T, D))
        # lane r·S + s reads [ĝ_n, x_n] of run r, series s and is fitted to ĝ_{n+τ} (Eq. 5)
        feed = np.concatenate([ghat[:, :, :T_g], x[:, :, :T_g]], -1)  # (R, S, T_g, K + D)
        self.inputs = _in_lanes(feed.transpose(2, 3, 0, 1).reshape(T_g, K + D, R * S))
        self.clean, self.seeds = self.inputs.copy(), seeds
        targets = ghat[:, :, delay:]
        self.targets = _in_lanes(targets.transpose(2, 3, 0, 1).reshape(T_g, K, R * S))
        with np.errstate(divide="ignore", invalid="ignore"):
            self.entropy = np.where(targets > 0, targets * np.log(targets), 0.0).sum((1, 2, 3))
        self.lanes.work.append(np.zeros((self.lanes.num_lanes // LB, LB), dtype))
        self.staging = _Staging({
            "w_in": (R, H, K + D), "w_rec": (R, H, H), "w_out": (R, K, H), "b_c": (R, H),
            "b_o": (R, K), "tau": (R, H), "u0": (R, S, H)}, dtype)

    def _call(self, params, grads, active, want_grad):
        p, g, lanes = self.staging.load(params), self.staging.grads, self.lanes
        with _first_use(_gating_step, "phase-2 kernel"):
            self._step(p, g, lanes, active, want_grad)
        self.staging.store(grads)
        return lanes.stats(self.STATS)

    def _step(self, p, g, lanes, active, want_grad):
        _gating_step(_per_network(p, False), p["u0"][:, :, None], lanes.net, tuple(lanes.work),
                     lanes.lane_grads, _per_network(g, False), g["u0"][:, :, None],
                     self.inputs, self.targets, self.entropy, float(self.model.sigma_min),
                     bool(self.phase.attraction), want_grad, np.ascontiguousarray(active),
                     lanes.block_runs, lanes.out)

    def value_and_grad(self, params: dict, grads: dict, active: np.ndarray) -> dict:
        """Objective statistics per run (R,); every gradient is written into `grads`."""
        return self._call(params, grads, active, True)

    def value(self, params: dict, active: np.ndarray) -> dict:
        """The same statistics without gradients (the adaptive-rate retry)."""
        return self._call(params, None, active, False)

    def resample(self, step: int) -> None:
        """Fresh input noise on x_n for this training step (nothing without noise)."""
        if self.phase.input_noise_var <= 0:
            return
        R, S, T_g, K = self.shape
        D = self.inputs.shape[2] - K
        noise = input_noise(self.seeds, step, (S, T_g + self.model.delay, D),  # all of x_n
                            self.phase.input_noise_var, self.inputs.dtype)[:, :, :T_g]
        self.inputs[:, :, K:] = self.clean[:, :, K:] + _in_lanes(
            noise.transpose(2, 3, 0, 1).reshape(T_g, D, R * S))


# ---------------------------------------------------------------------------------------------
# the closed loop (Sec. 2.2) with Lyapunov tangent vectors: one lane per (run, sample)


@njit(**JIT)
def _closed_block(E, G, state, V, noise, count, uniform_gates, out_y, out_g, out_u,
                  growth):  # pragma: no cover
    """One block of trajectories for out_y.shape[0] steps (every array is the block's part).

    E: expert weights (w_in (KE, M, D), w_rec (KE, M, M), w_out (KE, D, M), b_c, b_o, ε) per
    lane; G: gating weights (w_in (H, K + D), w_rec, w_out (K, H), b_c, b_o, ε) per lane;
    state: u of the experts (KE·M), u^g (H), the delay lines x (τ·D) and g (τ·K), updated in
    place; V (k, dim): tangent vectors in the layout of `ClosedLoopState.flat`, propagated by the
    exact Jacobian and re-orthonormalised (modified Gram-Schmidt) every step; growth (k) += ln of
    the norms when `count`. Records y, the gates that mixed it and u^g (if out_u is not empty)."""
    e_wi, e_wr, e_wo, e_bc, e_bo, e_eps = E
    g_wi, g_wr, g_wo, g_bc, g_bo, g_eps = G
    eu, gu, xl, gl = state
    KE, M = e_wi.shape[0], e_wi.shape[1]
    H, K = g_wr.shape[0], g_wo.shape[0]
    TAU = gl.shape[0] // K
    D = xl.shape[0] // TAU
    NV, steps = V.shape[0], out_y.shape[0]
    og, ox = KE * M, KE * M + H
    ot = ox + TAU * D
    dim = ot + TAU * K
    has_noise, keep_u = noise.shape[0] > 0, out_u.shape[0] > 0
    ue, ce, dce_prev, dce = stack(eu, KE * M), stack(eu, KE * M), stack(eu, KE * M), \
        stack(eu, KE * M)
    outs = stack(eu, KE * D)
    dc = stack(eu, KE * M)  # a tangent's ∂c of the experts (and dcgv of the gating RNN)
    ug, cg, dcg_prev, dcg = stack(eu, H), stack(eu, H), stack(eu, H), stack(eu, H)
    dcgv = stack(eu, H)
    x, y, dy = stack(eu, D), stack(eu, D), stack(eu, D)
    g, ng, dl = stack(eu, K), stack(eu, K), stack(eu, K)
    nv = stack(eu, dim)
    acc, top, total = lanes(eu), lanes(eu), lanes(eu)
    for q in range(KE * M):
        for v in range(LB):
            ue[q, v] = eu[q, v]
            ce[q, v] = tanh(ue[q, v] + e_bc[q // M, q % M, v])
    for h in range(H):
        for v in range(LB):
            ug[h, v] = gu[h, v]
            cg[h, v] = tanh(ug[h, v] + g_bc[h, v])
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
                        acc[v] = fma(e_wi[e, i, d, v], x[d, v], acc[v])
                for j in range(M):
                    for v in range(LB):
                        acc[v] = fma(e_wr[e, i, j, v], ce[e * M + j, v], acc[v])
                for v in range(LB):
                    ue[e * M + i, v] = (1.0 - e_eps[e, i, v]) * ue[e * M + i, v] \
                        + e_eps[e, i, v] * acc[v]
            for i in range(M):
                for v in range(LB):
                    ce[e * M + i, v] = tanh(ue[e * M + i, v] + e_bc[e, i, v])
                    dce[e * M + i, v] = 1.0 - ce[e * M + i, v] * ce[e * M + i, v]
            for d in range(D):
                for v in range(LB):
                    acc[v] = e_bo[e, d, v]
                for i in range(M):
                    for v in range(LB):
                        acc[v] = fma(e_wo[e, d, i, v], ce[e * M + i, v], acc[v])
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
                    acc[v] = fma(g_wi[h, k, v], g[k, v], acc[v])
            for d in range(D):
                for v in range(LB):
                    acc[v] = fma(g_wi[h, K + d, v], x[d, v], acc[v])
            for j in range(H):
                for v in range(LB):
                    acc[v] = fma(g_wr[h, j, v], cg[j, v], acc[v])
            for v in range(LB):
                ug[h, v] = (1.0 - g_eps[h, v]) * ug[h, v] + g_eps[h, v] * acc[v]
        for h in range(H):
            for v in range(LB):
                cg[h, v] = tanh(ug[h, v] + g_bc[h, v])
                dcg[h, v] = 1.0 - cg[h, v] * cg[h, v]
        for k in range(K):
            for v in range(LB):
                acc[v] = g_bo[k, v]
            for h in range(H):
                for v in range(LB):
                    acc[v] = fma(g_wo[k, h, v], cg[h, v], acc[v])
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
                            acc[v] = fma(e_wi[e, i, d, v], V[n, ox + d, v], acc[v])
                    for j in range(M):
                        for v in range(LB):
                            acc[v] = fma(e_wr[e, i, j, v], dc[e * M + j, v], acc[v])
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
                            acc[v] = fma(e_wo[e, d, i, v], dc[e * M + i, v], acc[v])
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
                        acc[v] = fma(g_wi[h, k, v], V[n, ot + k, v], acc[v])
                for d in range(D):
                    for v in range(LB):
                        acc[v] = fma(g_wi[h, K + d, v], V[n, ox + d, v], acc[v])
                for j in range(H):
                    for v in range(LB):
                        acc[v] = fma(g_wr[h, j, v], dcgv[j, v], acc[v])
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
                        acc[v] = fma(g_wo[k, h, v], dcgv[h, v], acc[v])
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


@njit(inline="always", **JIT)
def _spread_run(lane, N, params, lane_params):  # pragma: no cover
    """Copy the weights of run lane // N into `lane`: params (R, K', ...) -> (NB, K', ..., LB),
    1/τ for the last entry; padding lanes copy the last run (they are discarded)."""
    b, v = lane // LB, lane % LB
    r = min(lane // N, params[0].shape[0] - 1)
    w_in, w_rec, w_out, b_c, b_o, tau = params
    wi, wr, wo, bc, bo, eps = lane_params
    for k in range(w_in.shape[1]):
        for i in range(w_rec.shape[2]):
            bc[b, k, i, v] = b_c[r, k, i]
            eps[b, k, i, v] = 1.0 / tau[r, k, i]
            for d in range(w_in.shape[3]):
                wi[b, k, i, d, v] = w_in[r, k, i, d]
            for j in range(w_rec.shape[3]):
                wr[b, k, i, j, v] = w_rec[r, k, i, j]
        for o in range(w_out.shape[2]):
            bo[b, k, o, v] = b_o[r, k, o]
            for i in range(w_out.shape[3]):
                wo[b, k, o, i, v] = w_out[r, k, o, i]


@njit(parallel=True, **JIT)
def _closed_loop(N, experts, gating, E, G, state, V, noise, count, uniform_gates, out_y, out_g,
                 out_u, growth):  # pragma: no cover
    eu, gu, xl, gl = state
    NB = eu.shape[0]
    for lane in prange(NB * LB):
        _spread_run(lane, N, experts, E)
        _spread_run(lane, N, gating, G)
    e_wi, e_wr, e_wo, e_bc, e_bo, e_eps = E
    g_wi, g_wr, g_wo, g_bc, g_bo, g_eps = G
    for b in prange(NB):
        _closed_block((e_wi[b], e_wr[b], e_wo[b], e_bc[b], e_bo[b], e_eps[b]),
                      (g_wi[b, 0], g_wr[b, 0], g_wo[b, 0], g_bc[b, 0], g_bo[b, 0], g_eps[b, 0]),
                      (eu[b], gu[b], xl[b], gl[b]), V[b], noise[b], count, uniform_gates,
                      out_y[b], out_g[b], out_u[b], growth[b])


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


def closed_loop(experts, gating, state, steps: int, noise=None, tangents=None,
                count: bool = False, uniform_gates: bool = False,
                potentials: bool = True) -> ClosedLoopRun:
    """`moex.kernels.reference.closed_loop` in one compiled call: same arguments and results.

    Trajectory (r, n) is lane r·N + n; every lane carries its run's weights, so a block of
    lanes advances LB trajectories with vector instructions, one thread per block.
    """
    R, N, K = state.gates.shape[0], state.gates.shape[1], state.gates.shape[-1]
    TAU, D, H = state.inputs.shape[2], state.inputs.shape[-1], state.gating_u.shape[-1]
    _check_shapes(experts, gating, state)
    B = R * N
    dtype = np.dtype(str(state.gates.dtype).removeprefix("torch."))

    def lanes_of(x, per_trajectory_shape):  # (R, N, ...) -> (NB, ..., LB)
        flat = np.asarray(x.detach().cpu().numpy(), dtype).reshape((B,) + per_trajectory_shape)
        return _in_lanes(np.moveaxis(flat, 0, -1))

    def params_of(net, per_run):
        if not net:  # symbolic tasks: no experts
            return tuple(np.zeros((R, 0, 1, 1), dtype) if n in ("w_in", "w_rec", "w_out") else
                         np.ones((R, 0, 1), dtype) for n in _NET)
        arrays = tuple(np.ascontiguousarray(net[n].detach().cpu().numpy(), dtype) for n in _NET)
        return arrays if per_run else tuple(a[:, None] for a in arrays)

    experts_p, gating_p = params_of(experts, True), params_of(gating, False)
    eu = lanes_of(state.experts_u, (-1,))
    NB = eu.shape[0]
    E = tuple(np.zeros((NB,) + a.shape[1:] + (LB,), dtype) for a in experts_p)
    G = tuple(np.zeros((NB,) + a.shape[1:] + (LB,), dtype) for a in gating_p)
    gu, xl, gl = (lanes_of(x, (-1,)) for x in (state.gating_u, state.inputs, state.gates))
    k = 0 if tangents is None else tangents.shape[-1]
    V = (np.zeros((NB, 0, 0, LB), dtype) if tangents is None else
         lanes_of(tangents.transpose(-1, -2), (k, -1)))
    noise_l = (np.zeros((NB, 0, 0, LB), dtype) if noise is None else
               lanes_of(noise, (steps, D)))
    out_y, out_g = np.zeros((NB, steps, D, LB), dtype), np.zeros((NB, steps, K, LB), dtype)
    out_u = np.zeros((NB, steps if potentials else 0, H, LB), dtype)
    growth = np.zeros((NB, k, LB), dtype)
    with _first_use(_closed_loop, "closed-loop kernel"):
        _closed_loop(N, experts_p, gating_p, E, G, (eu, gu, xl, gl), V, noise_l, count,
                     uniform_gates, out_y, out_g, out_u, growth)

    def back(x, shape):  # (NB, ..., LB) -> (R, N, ...)
        flat = np.moveaxis(x, -1, 1).reshape((NB * LB,) + x.shape[1:-1])[:B]
        return torch.from_numpy(np.ascontiguousarray(flat.reshape((R, N) + shape)))

    nxt = type(state)(back(eu, state.experts_u.shape[2:]), back(gu, (H,)),
                      back(xl, (TAU, D)), back(gl, (TAU, K)))
    new_tangents = None if tangents is None else back(V, (k, -1)).transpose(-1, -2).contiguous()
    return ClosedLoopRun(nxt, back(out_y, (steps, D)), back(out_g, (steps, K)),
                         back(out_u, (steps, H)) if potentials else None, new_tangents,
                         back(growth, (k,)))


# ---------------------------------------------------------------------------------------------
# symbols of generated outputs


@njit(parallel=True, **JIT)
def _nearest(points, prototypes, symbols, out):  # pragma: no cover
    """out[n] = symbols[argmin_p ‖points[:, n] - prototypes[p]‖²] for points (D, n), LB points
    at a time."""
    P, D = prototypes.shape
    for b in prange(points.shape[1] // LB):
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


def nearest_symbols(points: np.ndarray, prototypes: np.ndarray,
                    prototype_symbols: np.ndarray) -> np.ndarray:
    """`moex.metrics.symbols.symbolize_nearest` compiled: (..., T, D) -> (..., T) symbols."""
    D = points.shape[-1]
    flat = np.asarray(points, np.float64).reshape(-1, D)
    by_coordinate = np.zeros((D, padded(len(flat))))
    by_coordinate[:, :len(flat)] = flat.T
    out = np.empty(by_coordinate.shape[1], np.int64)
    with _first_use(_nearest, "symbol kernel"):
        _nearest(by_coordinate, np.ascontiguousarray(prototypes, np.float64),
                 np.ascontiguousarray(prototype_symbols, np.int64), out)
    return out[:len(flat)].reshape(points.shape[:-1])
