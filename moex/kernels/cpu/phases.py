"""Both training phases, a training step of all R runs in one compiled call per thread: phase 1
(the experts and β, Eqs. 9-13) and phase 2 (the gating RNN fitted to ĝ, Eqs. 14-16), and the
problem classes the training loop calls (`moex.kernels.Problem`)."""

import math

import numpy as np
import torch
from numba import njit

from moex.kernels.cpu import threads
from moex.kernels.cpu.lanes import (
    NET,
    Forwarded,
    Lanes,
    Staging,
    block_active,
    first_use,
    gather,
    in_lanes,
    lane_sum,
    per_network,
    run_lanes,
    spread,
    to_host,
)
from moex.kernels.cpu.noise import noisy_inputs
from moex.kernels.cpu.rnn import backward_pass, forward_pass
from moex.kernels.cpu.simd import (
    JIT,
    exp,
    fma,
    lanes,
    line_rows,
    log,
    sums,
    transpose_tile,
    typed,
    width,
    zeros,
)
from moex.kernels.cpu.step import Stepper, idle
from moex.kernels.cpu.threads import claim, done
from moex.kernels.cpu.update import after_gradient

# phase 1: the experts and β (Eqs. 9-13)


@njit(inline="always", **JIT)
def _total(x, n):  # pragma: no cover
    """x[0] + ... + x[n-1] in float64 as 8 partial sums (x[t] into sum t mod 8, a vector's
    lanes) added in a fixed order: a sum over time that vectorises and rounds alike every run
    and on every CPU (float32 terms too: 8 of a block's 8 or 16 lanes)."""
    acc = sums(x, 1)[0]
    for v in range(8):
        acc[v] = 0.0
    for t0 in range(0, n - n % 8, 8):
        for v in range(8):
            acc[v] += x[t0 + v]
    for t in range(n - n % 8, n):
        acc[t % 8] += x[t]
    total = 0.0
    for v in range(8):
        total += acc[v]
    return total


@njit(no_cpython_wrapper=True, **JIT)
def _mixture(r, s, Y, targets, beta, var, want_grad, DY, g_beta, partial):  # pragma: no cover
    """Series s of run r: ln p(y | X, β, γ) in log space (Eqs. 10-12), the Brownian prior on β
    (Eq. 13) and the E error; with want_grad ∂/∂o of every expert output and ∂/∂β (Eq. 19).
    partial[r·S + s] gets (ln p, ln φ(β), Σ‖ŷ - y‖², then per expert ∂ ln p/∂s of
    σ² = e^{2s} + σ̄² without its factor (σ² - σ̄²)/σ²). The expert outputs y are read from,
    and ∂/∂o written to, rows by lane (Y, DY: (NB, D, LB, T'), `_by_lane` / `_by_step`); β and
    ∂/∂β are (rows, first column) pairs (`rows_of`), each run's (S, T, K) from that column on;
    the targets and β go through 1-D views of their column (one stride per step: 4-D indexing
    made each element's address anew, the mixture 4-19 % slower). Inputs are copied
    to contiguous rows of the run's precision first (float32 runs compute here in float32);
    every loop runs over time, innermost, element by element (LLVM vectorises them, exp and log
    included), and sums over time are `_total`'s, in float64."""
    S, T, D = targets.shape[1:]
    K, LB = var.shape[1] - 1, width(Y)
    (beta, at), (g_beta, g_at) = beta, g_beta
    half, one, two, dims = typed(Y, 0.5), typed(Y, 1.0), typed(Y, 2.0), typed(Y, D)
    prior_std = var[r, K]
    # every row of time steps (≥ T + 1 long) in one allocation, each starting on a cache line:
    # with numba's 16-byte alignment vector loads straddled two lines (the mixture 5-14 % slower)
    rows = line_rows(K * D + D + 5 * K + 3, T + 1, Y)
    y, target = rows[:K * D].reshape(K, D, rows.shape[1]), rows[K * D:K * D + D]
    q = K * D + D  # then K rows each of β (its column T lets β_{t+1} - β_t read within a row),
    # ln ĝ, z, ĝ and err = ‖y^k_t - y_t‖² (for z and again for ∂/∂s_k); then top, total, sq
    b, log_ghat = rows[q:q + K], rows[q + K:q + 2 * K]
    z, ghat, err = rows[q + 2 * K:q + 3 * K], rows[q + 3 * K:q + 4 * K], rows[q + 4 * K:q + 5 * K]
    top, total, sq = rows[q + 5 * K], rows[q + 5 * K + 1], rows[q + 5 * K + 2]
    for k in range(K):
        lane = (r * S + s) * K + k
        for d in range(D):
            column = Y[lane // LB, d, lane % LB]
            for t in range(T):
                y[k, d, t] = column[t]
    own = r if targets.shape[0] > 1 else 0  # (1, S, T, D): one data set for every run
    for d in range(D):
        column = targets[own, s, :, d]
        for t in range(T):
            target[d, t] = column[t]
    for k in range(K):
        column = beta[r, at + s * T * K + k:at + (s + 1) * T * K:K]
        for t in range(T):
            b[k, t] = column[t]
    for k in range(K):
        b[k, T] = b[k, T - 1]
    # ln ĝ = β - ln Σ exp β (Eq. 9)
    for t in range(T):
        top[t] = b[0, t]
        total[t] = 0.0
    for k in range(1, K):
        for t in range(T):
            top[t] = b[k, t] if b[k, t] > top[t] else top[t]
    for k in range(K):
        for t in range(T):
            total[t] += exp(b[k, t] - top[t])
    for t in range(T):
        top[t] += log(total[t])
    for k in range(K):
        for t in range(T):
            log_ghat[k, t] = b[k, t] - top[t]
            ghat[k, t] = exp(log_ghat[k, t])
    # z_k = ln ĝ_k + ln N(y; y^k, σ_k² NI); ln p = ln Σ_k exp z_k
    for k in range(K):
        norm = typed(Y, -0.5 * D * log(2.0 * math.pi * var[r, k]))
        scale = typed(Y, 2.0 * var[r, k])
        for t in range(T):
            err[k, t] = 0.0
        for d in range(D):
            for t in range(T):
                diff = y[k, d, t] - target[d, t]
                err[k, t] = fma(diff, diff, err[k, t])
        for t in range(T):
            z[k, t] = log_ghat[k, t] + norm - err[k, t] / scale
    for t in range(T):
        top[t] = z[0, t]
        total[t] = 0.0
    for k in range(1, K):
        for t in range(T):
            top[t] = z[k, t] if z[k, t] > top[t] else top[t]
    for k in range(K):
        for t in range(T):
            total[t] += exp(z[k, t] - top[t])
    for t in range(T):
        top[t] += log(total[t])  # ln p
    partial[r * S + s, 0] = _total(top, T)
    for t in range(T):  # E: the mixture Σ_k ĝ_k y^k against the target
        sq[t] = 0.0
    for d in range(D):
        for t in range(T):
            total[t] = -target[d, t]
        for k in range(K):
            for t in range(T):
                total[t] = fma(ghat[k, t], y[k, d, t], total[t])
        for t in range(T):
            sq[t] = fma(total[t], total[t], sq[t])
    partial[r * S + s, 2] = _total(sq, T)
    inv = typed(Y, 1.0 / (prior_std * prior_std))
    log_norm = typed(Y, 0.5 * log(2.0 * math.pi * prior_std * prior_std))
    for t in range(T):
        sq[t] = 0.0
    for k in range(K):  # the prior (Eq. 13): its terms per step t < T - 1
        for t in range(T):
            diff = b[k, t + 1] - b[k, t]
            sq[t] += half * diff * diff * inv + log_norm
    partial[r * S + s, 1] = -_total(sq, T - 1)
    if not want_grad:
        return
    resp, term = total, sq
    for k in range(K):
        lane = (r * S + s) * K + k
        var_k = var[r, k]
        for t in range(T):  # exp(z_k - ln p): the posterior responsibility of expert k
            resp[t] = exp(z[k, t] - top[t])
            term[t] = resp[t] * (err[k, t] / var_k - dims)
        partial[r * S + s, 3 + k] = _total(term, T)
        column = g_beta[r, g_at + s * T * K + k:g_at + (s + 1) * T * K:K]
        for t in range(T):  # with G_n / ς² of Eq. 19 (b[k, T] repeats β_{T-1})
            column[t] = resp[t] - ghat[k, t] + inv * (
                b[k, t + 1] - two * b[k, t] + b[k, max(t - 1, 0)])
        for d in range(D):
            for t in range(T):
                out = y[k, d, t]
                term[t] = resp[t] * (target[d, t] - out) / var_k * fma(-out, out, one)
            column = DY[lane // LB, d, lane % LB]
            for t in range(T):
                column[t] = term[t]


@njit(inline="always", **JIT)
def _by_lane(block, rows):  # pragma: no cover
    """A block's history (T, D, LB) as rows by lane (D, LB, T' ≥ T): whole LB × LB tiles by
    `transpose_tile`, the last T mod LB steps element by element."""
    T, D, LB = block.shape
    steps, whole = rows.shape[2], T - T % LB
    for d in range(D):
        for t0 in range(0, whole, LB):
            transpose_tile(block, (t0 * D + d) * LB, D * LB, rows, d * LB * steps + t0, steps)
        for t in range(whole, T):
            for v in range(LB):
                rows[d, v, t] = block[t, d, v]


@njit(inline="always", **JIT)
def _by_step(rows, block):  # pragma: no cover
    """`_by_lane`'s inverse: rows by lane (D, LB, T') into the block's (T, D, LB)."""
    T, D, LB = block.shape
    steps, whole = rows.shape[2], T - T % LB
    for d in range(D):
        for t0 in range(0, whole, LB):
            transpose_tile(rows, d * LB * steps + t0, steps, block, (t0 * D + d) * LB, D * LB)
        for t in range(whole, T):
            for v in range(LB):
                block[t, d, v] = rows[d, v, t]


@njit(**JIT)
def _variances(first, last, log_sigma, floor, prior_std, var):  # pragma: no cover
    """σ_k² = e^{2 s_k} + σ̄² of runs first..last-1, and ς beside them for `_mixture`."""
    K = log_sigma.shape[1]
    for r in range(first, last):
        for k in range(K):
            var[r, k] = exp(2.0 * log_sigma[r, k]) + floor
        var[r, K] = prior_std


@njit(no_cpython_wrapper=True, **JIT)
def _run_sums(r, S, T, targets, net, work, lane_grads, params, grads, g_u0, g_log_sigma, floor,
              attraction, want_grad, out):  # pragma: no cover
    """Run r after its backward pass: its K networks' gradients gathered from their lanes, and
    out[:, r], g_u0[r], g_log_sigma[r] from the per-series partial sums."""
    S1, S2, partial, var = work[4], work[5], work[7], work[8]
    K = g_log_sigma.shape[1]
    if want_grad:
        for g in range(r * K, (r + 1) * K):
            gather(g, S, params[5], lane_grads[:6], grads, work[3].shape[1] > 0)
    log_lik = partial[r * S:(r + 1) * S, 0].sum()
    prior = partial[r * S:(r + 1) * S, 1].sum()
    error = partial[r * S:(r + 1) * S, 2].sum()
    out[0, r] = log_lik + prior + run_lanes(r, S, T, net[6], S1, S2, floor, attraction,
                                            want_grad, lane_grads[6], g_u0)
    out[1, r], out[2, r] = log_lik, prior
    out[3, r] = 0.5 * error / (S * T * targets.shape[3])
    if want_grad:
        for k in range(K):
            g_log_sigma[r, k] = partial[r * S:(r + 1) * S, 3 + k].sum() \
                * (var[r, k] - floor) / var[r, k]


# the stages of a phase-1 step: whole chunks of series, or blocks / series / blocks / runs
_CHUNKS, _FORWARD, _MIXTURE, _BACKWARD, _RUNS = range(5)


@njit(nogil=True, **JIT)
def _expert_items(lo, hi, stage, params, u0, log_sigma, beta, net, work, lane_grads, grads,
                  g_u0, g_log_sigma, g_beta, X, targets, floor, prior_std, attraction, want_grad,
                  active, stale, reuse, block_runs, chunk, out, sizes, queue, left,
                  update):  # pragma: no cover
    """Items lo..hi-1 of one stage of a phase-1 step (the items of a stage are independent);
    the forward pass only in blocks that hold a `stale` run (`Forwarded`). With `reuse` (the
    stepper's record of the lanes covers every parameter the mixture reads, β and log σ too) a
    call without gradients (an adaptive trial) computes the mixture's gradients as well (∂L/∂o
    in the lanes, ∂L/∂β, the partial sums for ∂/∂ log σ), and a gradient call skips the mixture
    of the runs that are not stale: their lanes hold that trial's, at these very parameters.

    The stages, after `_variances` of every run: _FORWARD (blocks), _MIXTURE (series r·S + s),
    _BACKWARD (blocks), _RUNS (runs). _CHUNKS: chunks of `chunk` series (of any runs), the fewest
    whose lanes fill whole blocks, each taken through the first three stages in one thread while
    its histories are in that thread's cache, the threads claiming chunks lo.. below hi one at a
    time from `queue` (`threads.share`) (a series' mixture reads only its own K lanes, and
    a block's backward pass only the ∂L/∂o of its own series); _RUNS follows once every chunk is
    done, or, where `left` (R,) counts each run's chunks still to go (the stepper's calls), run
    by run in the thread that finishes the run's last chunk (`threads.done`): each run's sums,
    and in a gradient call then its `update.after_gradient` (`update`: its arguments after lo,
    hi): no pass over the (R, P) buffers after the call (memory-bound: a second thread gained
    little there), and a run's sums and update made while the other thread computes chunks.
    Each run's sums and update are the same arithmetic on the same numbers either way.

    The forward stage leaves each block's outputs also by lane (`Y_lane`), where the mixture reads
    them and writes ∂L/∂o (`DY_lane`), which the backward stage takes back into the block's layout
    by whole tiles of vectors (read along a lane in the block's layout, every element was a load
    of a line of its own: as slow in float32 as in float64)."""
    C0, C, Y, U, S1, S2, DY, partial, var, Y_lane, DY_lane = work
    w_in, w_rec, w_out, b_c, b_o, eps, u0_lane = net
    l_w_in, l_w_rec, l_w_out, l_b_c, l_b_o, l_eps, l_u0 = lane_grads
    (R, K), S, T = log_sigma.shape, targets.shape[1], targets.shape[2]
    NB, LB = w_in.shape[0], width(X)
    if stage == _CHUNKS:
        c = lo + claim(queue)
        while c < hi:
            first, last = c * chunk, min((c + 1) * chunk, R * S)  # series
            b0, b1 = first * K // LB, min(-(-last * K // LB), NB)
            for stage_of_chunk, i0, i1 in ((_FORWARD, b0, b1), (_MIXTURE, first, last),
                                           (_BACKWARD, b0, b1)):
                _expert_items(i0, i1, stage_of_chunk, params, u0, log_sigma, beta, net, work,
                              lane_grads, grads, g_u0, g_log_sigma, g_beta, X, targets, floor,
                              prior_std, attraction, want_grad, active, stale, reuse, block_runs,
                              chunk, out, sizes, queue, left, update)
            if left.shape[0] > 0:  # the runs whose last chunk this was: their sums and update
                for r in range(first // S, (last - 1) // S + 1):
                    if done(left, r) == 1:
                        if active[r]:
                            _run_sums(r, S, T, targets, net, work, lane_grads, params, grads,
                                      g_u0, g_log_sigma, floor, attraction, want_grad, out)
                        if want_grad:
                            after_gradient(r, r + 1, *update)
            c = lo + claim(queue)
        return
    for i in range(lo, hi):
        if stage == _FORWARD:
            for lane in range(i * LB, (i + 1) * LB):
                spread(lane, S, params, u0, net)
            if block_active(i, block_runs, stale):  # bool(True): a runtime flag, so that the
                # experts and the gating share one compiled forward_pass where its sizes are the
                # arrays' (MOEX_CPU_SIZES=runtime; a literal True or False compiled one each: 3-4
                # s more of a first run); compiled for their sizes, each phase has its own
                forward_pass(X[i], w_in[i], w_rec[i], w_out[i], b_c[i], b_o[i], eps[i],
                             u0_lane[i], bool(True),  # noqa: UP018
                             C0[i], C[i], Y[i], U[i], S1[i], S2[i], sizes)
                _by_lane(Y[i], Y_lane[i])
        elif stage == _MIXTURE:
            r = i // S
            if active[r] and not (reuse and want_grad and not stale[r]):
                _mixture(r, i % S, Y_lane, targets, beta, var, want_grad or reuse, DY_lane,
                         g_beta, partial)
        elif stage == _BACKWARD:
            if want_grad and block_active(i, block_runs, active):
                _by_step(DY_lane[i], DY[i])
                backward_pass(DY[i], X[i], C0[i], C[i], U[i], u0_lane[i], w_rec[i], w_out[i],
                              eps[i], l_w_in[i], l_w_rec[i], l_w_out[i], l_b_c[i], l_b_o[i],
                              l_eps[i], l_u0[i], sizes)
        elif active[i]:
            _run_sums(i, S, T, targets, net, work, lane_grads, params, grads, g_u0, g_log_sigma,
                      floor, attraction, want_grad, out)


def rows_of(x) -> tuple:
    """A group's values for the kernels as (rows, first column): a (rows, first) pair as it is
    (the stepper's: the (R, P) buffer and the group's first column), or an (R, ...)
    C-contiguous array as its (R, -1) view and column 0."""
    return x if isinstance(x, tuple) else (x.reshape(len(x), -1), 0)


# ---------------------------------------------------------------------------------------------
# phase 2: the gating RNN fitted to ĝ (Eqs. 14-16)


@njit(**JIT)
def _softmax_objective(Y, targets, want_grad, DY, log_lik):  # pragma: no cover
    """One block: log_lik (LB,) = Σ_t Σ_k ĝ_k ln softmax(o_t)_k (Eq. 15 without ln Z) and, with
    want_grad, DY (T, K, LB) = ∂/∂o_t = ĝ - g Σ_k ĝ_k."""
    T, K, LB = Y.shape[0], Y.shape[1], width(Y)
    total, top, norm, mass, grad = lanes(Y), lanes(Y), lanes(Y), lanes(Y), lanes(Y)
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
        if want_grad:  # into a stack array, then DY: stored straight into DY (which might
            # alias the next lane's loads) the exp ran lane by lane, 1.7-2.2x the time
            for k in range(K):
                for v in range(LB):
                    grad[v] = targets[t, k, v] - exp(Y[t, k, v] - norm[v]) * mass[v]
                for v in range(LB):
                    DY[t, k, v] = grad[v]
    for v in range(LB):
        log_lik[v] = total[v]


@njit(nogil=True, **JIT)
def gating_items(lo, hi, blocks, params, u0, net, work, lane_grads, grads, g_u0, X, targets,
                 entropy, sigma_min, attraction, want_grad, active, stale, reuse, block_runs,
                 out, sizes, queue, left, update):  # pragma: no cover
    """Items lo..hi-1 of one stage of a phase-2 step: with `blocks`, blocks of lanes (weights
    spread to the lanes, forward where a `stale` run is (`Forwarded`), objective, backward),
    claimed one at a time from `queue` (`threads.share`); otherwise runs, after every block
    (`_gating_run`). Where `left` (R,) counts each run's blocks still to go (the stepper's
    calls), the thread that finishes a run's last block makes the run's sums, and in a gradient
    call then its `update.after_gradient` (`update`: its arguments after lo, hi), as phase 1's
    `_expert_items` does. With `reuse` (the stepper's) a call without gradients (an adaptive
    trial) computes ∂/∂o as well, and a gradient call skips the objective where it skips the
    forward pass (as `_expert_items`)."""
    C0, C, Y, U, S1, S2, DY, log_lik = work
    w_in, w_rec, w_out, b_c, b_o, eps, u0_lane = net
    l_w_in, l_w_rec, l_w_out, l_b_c, l_b_o, l_eps, l_u0 = lane_grads
    S, LB = u0.shape[1], width(X)
    i = lo + claim(queue) if blocks else lo
    while i < hi:
        if blocks:
            for lane in range(i * LB, (i + 1) * LB):
                spread(lane, S, params, u0, net)
            if block_active(i, block_runs, active):
                fresh = block_active(i, block_runs, stale)
                if fresh:
                    forward_pass(X[i], w_in[i], w_rec[i], w_out[i], b_c[i], b_o[i], eps[i],
                                 u0_lane[i], bool(False),  # noqa: UP018
                                 C0[i], C[i], Y[i], U[i], S1[i], S2[i], sizes)
                if fresh or not (reuse and want_grad):
                    _softmax_objective(Y[i], targets[i], want_grad or reuse, DY[i], log_lik[i])
                if want_grad:
                    backward_pass(DY[i], X[i], C0[i], C[i], U[i], u0_lane[i], w_rec[i], w_out[i],
                                  eps[i], l_w_in[i], l_w_rec[i], l_w_out[i], l_b_c[i], l_b_o[i],
                                  l_eps[i], l_u0[i], sizes)
            if left.shape[0] > 0:  # the runs whose last block this was: their sums and update
                for r in range(block_runs[i, 0], block_runs[i, 1] + 1):
                    if done(left, r) == 1:
                        if active[r]:
                            _gating_run(r, params, work, lane_grads, grads, g_u0, targets,
                                        entropy, sigma_min, attraction, want_grad, net, out)
                        if want_grad:
                            after_gradient(r, r + 1, *update)
        elif active[i]:
            _gating_run(i, params, work, lane_grads, grads, g_u0, targets, entropy, sigma_min,
                        attraction, want_grad, net, out)
        i = lo + claim(queue) if blocks else i + 1


@njit(no_cpython_wrapper=True, **JIT)
def _gating_run(r, params, work, lane_grads, grads, g_u0, targets, entropy, sigma_min,
                attraction, want_grad, net, out):  # pragma: no cover
    """Run r after its blocks: out[:, r] (objective, Σ ĝ ln g, KL, E^g) and its gradients
    gathered from its lanes."""
    S, T, K = g_u0.shape[1], targets.shape[1], targets.shape[2]
    U, S1, S2, log_lik = work[3], work[4], work[5], work[7]
    total = lane_sum(log_lik, r * S, (r + 1) * S)
    out[1, r] = total
    out[2, r] = entropy[r] - total
    out[3, r] = out[2, r] / (S * T * K)
    out[0, r] = total + run_lanes(r, S, T, net[6], S1, S2, sigma_min * sigma_min, attraction,
                                  want_grad, lane_grads[6], g_u0)
    if want_grad:
        gather(r, S, params[5], lane_grads[:6], grads, U.shape[1] > 0)


class _Problem:
    """What both phases' problems share: the calls of `moex.kernels.Problem` around a phase's
    `_step`, with the parameters staged and the forward passes the lanes hold on record."""

    device = torch.device("cpu")
    STATS: tuple[str, ...] = ()
    KERNEL: tuple = ()  # (the compiled kernel, what the log calls it)
    SUMS: int | bool = 0  # the kernel's third argument for the runs' sums (`evaluate`)
    # the parameters that the objective after the forward pass reads besides the forward's
    # (phase 1's mixture: β, log σ); with them in the stepper's record a gradient step reuses an
    # accepted trial's objective and its ∂/∂o too (the kernels' `reuse`)
    AFTER_FORWARD: tuple[str, ...] = ()
    # the groups the kernel takes as (rows, first column) pairs (`rows_of`): the stepper hands
    # it the training loop's (R, P) buffers themselves, where the groups' views are strided
    # (R > 1) and would be staged (phase 1's β: a copy in and out of 20 000 numbers per run)
    ROWS: tuple[str, ...] = ()
    trials = 1  # adaptive-rate candidates per call: one (an accepted trial's pass is reused)

    def _call(self, params, grads, active, want_grad):
        p, g, lanes = self.staging.load(params), self.staging.outputs(grads), self.lanes
        active = np.ascontiguousarray(to_host(active))
        # a gradient step right after an accepted adaptive trial finds its forward pass done
        stale = self.forwarded.stale(p, active) if want_grad else active
        with first_use(*self.KERNEL):
            self._step(p, g, lanes, active, stale=stale, want_grad=want_grad)
        if want_grad:
            self.forwarded.forget()  # the next call is at other parameters (a step was taken)
        elif not self._stepper_record.size:  # the separate calls' adaptive trial: its passes
            self.forwarded.record(p, stale)  # on record for the gradient call after it
        # a stepper keeps a record of its own (`moex.kernels.cpu.step`), which this call's
        # passes void; and the training loop's last call (the trained parameters' value) needs
        # none: it recorded, and compiled the record's function on a first run, for nothing
        self._stepper_record[:] = False
        self.staging.store(grads, g)
        return lanes.stats(self.STATS)

    def value_and_grad(self, params: dict, grads: dict, active: np.ndarray) -> dict:
        """Objective statistics per run (R,); every gradient is written into `grads`."""
        return self._call(params, grads, active, True)

    def stepper(self, buffers: dict, columns: dict, fixed: dict, **settings) -> Stepper:
        """The whole training step with its arguments bound once (`moex.kernels.cpu.step`)."""
        stepper = Stepper(self, buffers, columns, fixed, **settings)
        self._stepper_record = stepper.current  # (the array, not the stepper: no reference cycle)
        return stepper

    def forget(self) -> None:
        """The inputs changed (fresh input noise): no lane holds a current forward pass."""
        self.forwarded.forget()
        self._stepper_record[:] = False  # the stepper's record of its lanes' forward pass

    def value(self, params: dict, active: np.ndarray) -> dict:
        """The same statistics without gradients (the adaptive-rate retry)."""
        return self._call(params, None, active, False)

    def _before(self, args: tuple) -> None:
        """What a step computes before its items (phase 1: σ²)."""

    def evaluate(self, args: tuple, share=threads.share) -> None:
        """One step of every active run (`kernel_args`): the items (chunks of series, blocks of
        lanes) taken by the threads one at a time (`shared`, through `share`: `threads.share`,
        or a stepper's `threads.Crew`), then every run's sums (one thread is enough), or with the
        stepper's `left` each run's sums (and in a gradient call its update) in the call, after
        the run's last item (`items_of_run`: the items that hold each run's lanes)."""
        self._before(args)
        left = args[-2]
        if left.size:
            np.copyto(left, self.items_of_run)
        share(*self.shared(args))
        if not left.size:
            self.KERNEL[0](0, self.shape[0], self.SUMS, *args)


class ExpertProblem(_Problem):
    """Phase 1 of R runs (Sec. 2.1.2, Eqs. 9-13): `value_and_grad` and `value` of ln L(D, θ)
    for all runs, one compiled call per thread each (`resample` has nothing to draw).

    Args:
        inputs, targets: (S, T, D) x_n and y_n = x_{n+τ}, or (R, S, T, D) when every run has
            data of its own (packed jobs).
        model: the `ModelConfig`; phase: the `ExpertPhaseConfig`; num_runs: R.
    """

    STATS = ("objective", "log_likelihood", "log_prior", "E")
    KERNEL = (_expert_items, "phase-1 kernel")
    SUMS = _RUNS  # (the kernel's stage that makes the runs' sums)
    AFTER_FORWARD = ("beta", "log_sigma")
    ROWS = ("beta",)

    def __init__(self, inputs, targets, model, phase, *, num_runs, device="cpu"):
        inputs, targets = to_host(inputs), to_host(targets)
        S, T, D = targets.shape[-3:]
        R, K, M = num_runs, model.num_experts, model.experts.context_size
        dtype = np.dtype(inputs.dtype)
        self.shape, self.model, self.phase = (R, S, T, K), model, phase
        self.lanes = Lanes(T, M, D, D, num_lanes=R * K * S, lanes_per_run=K * S, num_runs=R,
                           learn_tau=model.learn_time_constants, attraction=phase.attraction,
                           dtype=dtype)
        # lane (r·S + s)·K + k reads series s of run r
        x = np.broadcast_to(inputs, (R, S, T, D)).transpose(2, 3, 0, 1)
        self.inputs = in_lanes(np.broadcast_to(x[:, :, :, :, None], (T, D, R, S, K)).reshape(
            T, D, R * S * K))
        self.targets = np.ascontiguousarray(targets.reshape(-1, S, T, D))
        LB, NB = self.lanes.width, self.lanes.num_lanes // self.lanes.width
        # then the partial sums, σ², and the outputs y and ∂L/∂o by lane for the mixture: rows
        # of T' ≥ T steps, whole tiles of LB (`_by_lane`, `_by_step`)
        by_lane = (NB, D, LB, -(-T // LB) * LB)
        self.lanes.work += [np.zeros((R * S, 3 + K), dtype), np.zeros((R, K + 1), dtype),
                            zeros(by_lane, dtype), zeros(by_lane, dtype)]
        self.chunk = LB // math.gcd(K, LB)  # the fewest series whose lanes fill whole blocks
        self.staging = Staging({
            "w_in": (R, K, M, D), "w_rec": (R, K, M, M), "w_out": (R, K, D, M), "b_c": (R, K, M),
            "b_o": (R, K, D), "tau": (R, K, M), "log_sigma": (R, K), "u0": (R, S, K, M),
            "beta": (R, S, T, K)}, dtype)
        self.forwarded = Forwarded(self.lanes.block_runs, K * S, NET + ("u0",), LB)
        self._stepper_record = np.zeros(0, bool)
        self.queue = np.zeros(1, np.int64)  # the threads' next chunk (`threads.share`)
        self.items_of_run = np.zeros(R, np.int64)  # the chunks that hold series of each run
        for first in range(0, R * S, self.chunk):
            self.items_of_run[first // S:(min(first + self.chunk, R * S) - 1) // S + 1] += 1
        self.idle = idle(self)

    def _step(self, p, g, lanes, active, *, stale, want_grad):
        self.evaluate(self.kernel_args(p, g, want_grad, active, stale))

    def _before(self, args: tuple) -> None:
        """σ² of every run (`kernel_args`' order: log σ, then the floor and the prior's std)."""
        _variances(0, self.shape[0], args[2], *args[13:15], self.lanes.work[8])

    def shared(self, args: tuple) -> tuple:
        """`threads.share`'s arguments: the chunks of series (`_expert_items`)."""
        R, S = self.shape[:2]
        return _expert_items, -(-R * S // self.chunk), self.queue, _CHUNKS, *args

    def kernel_args(self, p, g, want_grad, active, stale, *, reuse=False,
                    finish=None) -> tuple:
        """`_expert_items`' arguments after its stage (`reuse`, `finish` = (left, update): the
        stepper's, see there; none: `idle`)."""
        lanes = self.lanes
        return (per_network(p, True), p["u0"], p["log_sigma"], rows_of(p["beta"]), lanes.net,
                tuple(lanes.work), lanes.lane_grads, per_network(g, True), g["u0"],
                g["log_sigma"], rows_of(g["beta"]), self.inputs, self.targets,
                float(self.model.sigma_min) ** 2, float(self.phase.gate_prior_std),
                bool(self.phase.attraction), want_grad, active, stale, bool(reuse),
                lanes.block_runs, self.chunk, lanes.out, lanes.sizes, self.queue,
                *(finish or self.idle))

    def resample(self, step: int) -> None:
        pass


class GatingProblem(_Problem):
    """Phase 2 of R runs (Sec. 2.1.2, Eqs. 14-16): ln L(D^g, θ^g) up to ln Z for all runs, one
    compiled call per thread each.

    Args:
        gate_targets: (R, S, T, K) ĝ_n; inputs: (S, T, D) x_n aligned with ĝ_n (D may be 0), or
            (R, S, T, D) per run.
        model: the `ModelConfig`; phase: the `GatingPhaseConfig`.
        seeds: one per run, for the input noise that `resample(step)` draws when
            `phase.input_noise_var` > 0 (`moex.kernels.noise`).
    """

    STATS = ("objective", "log_likelihood", "kl", "E_g")
    KERNEL = (gating_items, "phase-2 kernel")
    SUMS = False  # (`gating_items` over runs, not blocks: the runs' sums)

    def __init__(self, gate_targets, inputs, model, phase, *, seeds, device="cpu"):
        gate_targets, inputs = to_host(gate_targets), to_host(inputs)
        R, S, T, K = gate_targets.shape
        D, H, delay = inputs.shape[-1], model.gating.context_size, model.delay
        T_g = T - delay
        dtype = np.dtype(gate_targets.dtype)
        self.shape, self.model, self.phase = (R, S, T_g, K), model, phase
        self.lanes = Lanes(T_g, H, K + D, K, num_lanes=R * S, lanes_per_run=S, num_runs=R,
                           learn_tau=model.learn_time_constants, attraction=phase.attraction,
                           dtype=dtype)
        ghat = gate_targets
        x = np.broadcast_to(inputs, (R, S, T, D))
        # lane r·S + s reads [ĝ_n, x_n] of run r, series s and is fitted to ĝ_{n+τ} (Eq. 5)
        feed = np.concatenate([ghat[:, :, :T_g], x[:, :, :T_g]], -1)  # (R, S, T_g, K + D)
        self.inputs = in_lanes(feed.transpose(2, 3, 0, 1).reshape(T_g, K + D, R * S))
        self.clean, self.seeds = self.inputs.copy(), seeds
        targets = ghat[:, :, delay:]
        self.targets = in_lanes(targets.transpose(2, 3, 0, 1).reshape(T_g, K, R * S))
        with np.errstate(divide="ignore", invalid="ignore"):
            self.entropy = np.where(targets > 0, targets * np.log(targets), 0.0).sum((1, 2, 3))
        LB = self.lanes.width
        self.lanes.work.append(np.zeros((self.lanes.num_lanes // LB, LB), dtype))
        self.staging = Staging({
            "w_in": (R, H, K + D), "w_rec": (R, H, H), "w_out": (R, K, H), "b_c": (R, H),
            "b_o": (R, K), "tau": (R, H), "u0": (R, S, H)}, dtype)
        self.forwarded = Forwarded(self.lanes.block_runs, S, NET + ("u0",), LB)
        self._stepper_record = np.zeros(0, bool)
        self.queue = np.zeros(1, np.int64)  # the threads' next block (`threads.share`)
        self.items_of_run = np.zeros(R, np.int64)  # the blocks that hold lanes of each run
        for first, last in self.lanes.block_runs:
            self.items_of_run[first:last + 1] += 1
        self.idle = idle(self)

    def _step(self, p, g, lanes, active, *, stale, want_grad):
        self.evaluate(self.kernel_args(p, g, want_grad, active, stale))

    def shared(self, args: tuple) -> tuple:
        """`threads.share`'s arguments: the blocks of lanes (`gating_items`)."""
        return gating_items, self.lanes.net[0].shape[0], self.queue, True, *args

    def kernel_args(self, p, g, want_grad, active, stale, *, reuse=False,
                    finish=None) -> tuple:
        """`gating_items`' arguments after its stage (`reuse`, `finish` = (left, update): the
        stepper's, see there; none: `idle`)."""
        lanes = self.lanes
        return (per_network(p, False), p["u0"][:, :, None], lanes.net, tuple(lanes.work),
                lanes.lane_grads, per_network(g, False), g["u0"][:, :, None], self.inputs,
                self.targets, self.entropy, float(self.model.sigma_min),
                bool(self.phase.attraction), want_grad, active, stale, bool(reuse),
                lanes.block_runs, lanes.out, lanes.sizes, self.queue, *(finish or self.idle))

    def resample(self, step: int) -> None:
        """Fresh input noise on x_n for this training step (nothing without noise)."""
        if self.phase.input_noise_var <= 0:
            return
        self.forget()
        R, S, T_g, K = self.shape
        noisy_inputs(self.inputs, self.clean, self.seeds, step, self.phase.input_noise_var, S=S,
                     T_full=T_g + self.model.delay, K=K)  # (entries numbered over all of x_n)
