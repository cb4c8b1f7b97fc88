"""The training loop's momentum step (`moex.kernels.reference.momentum_step`, `apply_step`) as
one compiled call per thread over the runs: a run's row of the (R, P) buffers is read and
written in two passes (the finiteness checks need the whole row first) instead of a dozen
PyTorch operators, each a pass over every run. Each operation rounds as the reference's does
(no fused multiply-add, float32 steps scaled in float64 as PyTorch does), so the bits are the
reference's; and no fast-math flag, since the checks look for NaN and infinity (`nnan`/`ninf`
would let LLVM assume there are none)."""

import numpy as np
from numba import njit

from moex.kernels.cpu import threads
from moex.kernels.cpu.lanes import record_runs, to_host

JIT = dict(nogil=True, fastmath=False, error_model="numpy", cache=True, no_cfunc_wrapper=True)
# fastmath=False said outright: a function compiled without the option inherits its caller's,
# and both phase kernels (fast-math: `simd.FASTMATH`) call `after_gradient` for each run
# (`phases._expert_items`, `gating_items`): inherited, `nnan`/`ninf` made its finiteness checks
# pass a NaN (a scratch test, numba 0.68: and the Python-called function then gave the same
# wrong answer)
# The helpers the stage functions call (`_finite`, `_steps`, `_trials`, `_trial_point`, and
# `lanes.record_runs`) are inlined by numba into their callers (each still callable
# from Python): a function of its own costs a first run a compile pipeline of its own (wrappers,
# optimisation, machine code). The stage functions' first compile 2.8-2.95 s instead of
# 3.6-3.75 (Ice Lake VM, 2026-12-07, the trees in turn); the same bits. `_apply`, called from
# two stage functions, stays a function of its own (inlined into both: no faster to compile),
# without the wrapper Python would call it through; no C-callable wrappers (`simd.JIT`).


@njit(inline="always", **JIT)
def _finite(row) -> bool:
    """Whether every entry of `row` is finite: a check of all of them ANDed, which LLVM
    vectorises (a loop that leaves at the first non-finite entry stays scalar: 4-8x slower)."""
    ok = True
    for p in range(row.shape[0]):
        ok &= np.isfinite(row[p])
    return ok


@njit(no_cpython_wrapper=True, **JIT)
def _apply(r, theta, delta, velocity, frozen, paper_form, tau_start, tau_end) -> bool:
    """Run r's step taken (frozen: Δθ zeroed first), τ's columns clamped at 1; whether the clamp
    moved any of them (θ is then not θ + Δθ)."""
    zero = delta.dtype.type(0.0)
    clamped = False
    for p in range(theta.shape[1]):
        if frozen:
            delta[r, p] = zero
        theta[r, p] += delta[r, p]
        if velocity is None:  # (the paper form: Δθ_prev is `delta` itself, `momentum_buffer`)
            pass
        elif paper_form:
            velocity[r, p] = delta[r, p]
        elif frozen:
            velocity[r, p] = zero
    for p in range(tau_start, tau_end):
        if theta[r, p] < 1.0:  # (NaN stays NaN, as torch.clamp_ leaves it)
            theta[r, p] = 1.0
            clamped = True
    return clamped


@njit(inline="always", **JIT)
def _steps(lo, hi, theta, grad, velocity, delta, rate, lr_scale, objective, failed, momentum,
           paper_form, apply, tau_start, tau_end):
    """Runs lo..hi-1: their Δθ, and with `apply` the step taken."""
    zero = grad.dtype.type(0.0)
    for r in range(lo, hi):
        bad = failed[r] or not (np.isfinite(objective[r]) and _finite(grad[r]))
        failed[r] = bad
        scale = lr_scale[r]
        for p in range(grad.shape[1]):
            if bad:
                grad[r, p] = zero
            if velocity is None:  # the paper form, Δθ_prev read in `delta` (`momentum_buffer`)
                kept = delta[r, p] * momentum
                step = grad[r, p] * rate[p]
                delta[r, p] = step * scale
                delta[r, p] += kept
            elif paper_form:
                kept = velocity[r, p] * momentum
                step = grad[r, p] * rate[p]
                delta[r, p] = step * scale  # (float64, then rounded to the buffer's type)
                delta[r, p] += kept
            else:
                velocity[r, p] = velocity[r, p] * momentum
                velocity[r, p] += grad[r, p]
                delta[r, p] = velocity[r, p] * rate[p] * scale
        if apply:
            if not bad:  # (ANDed, as in `_finite`)
                ok = True
                for p in range(grad.shape[1]):
                    ok &= np.isfinite(theta[r, p] + delta[r, p])
                bad = not ok
            failed[r] = bad
            _apply(r, theta, delta, velocity, bad, paper_form, tau_start, tau_end)


@njit(**JIT)
def apply_runs(lo, hi, theta, delta, velocity, frozen, paper_form, tau_start, tau_end):
    for r in range(lo, hi):
        _apply(r, theta, delta, velocity, frozen[r], paper_form, tau_start, tau_end)


@njit(inline="always", **JIT)
def _trials(lo, hi, delta, values, base, pending, lr_scale, retries, decrease, decrease_cast,
            increase, max_ratio):
    """Runs lo..hi-1 of one adaptive-rate trial (`reference.adaptive_trial`'s operations)."""
    for r in range(lo, hi):
        if not pending[r]:
            continue
        ratio = values[r] / base[r]
        if ratio <= max_ratio:  # (NaN fails too)
            pending[r] = False
            if ratio < 1.0:
                lr_scale[r] = lr_scale[r] * increase
            continue
        lr_scale[r] = lr_scale[r] * decrease
        retries[r] += 1
        for p in range(delta.shape[1]):
            delta[r, p] = delta[r, p] * decrease_cast


@njit(inline="always", **JIT)
def _trial_point(r, theta, delta, scratch):
    """Run r's θ + Δθ, the point its next trial evaluates (the separate calls' torch.add)."""
    for p in range(theta.shape[1]):
        scratch[r, p] = theta[r, p] + delta[r, p]


@njit(**JIT)
def before_gradient(lo, hi, current, failed, active, stale):
    """Runs lo..hi-1 before the gradient at θ: active, the runs not failed; stale, those the
    phase kernel runs forward: the active ones whose lanes do not hold the forward pass at θ
    (`current`, which `after_trials` leaves set only where θ is the accepted trial's point)."""
    for r in range(lo, hi):
        active[r] = not failed[r]
        stale[r] = active[r] and not current[r]


@njit(**JIT)
def after_gradient(lo, hi, sources, columns, stats, out, current, theta, grad, velocity, delta,
                   scratch, rate, lr_scale, failed, pending, retries, momentum, paper_form,
                   adaptive, max_retries, tau_start, tau_end):
    """Runs lo..hi-1: the gradients the kernel wrote elsewhere copied into `grad` (each (R, n)
    array of `sources` into the columns from its `columns` entry on), the statistics at θ kept,
    the step Δθ (taken at a fixed rate); with the adaptive rate every run not failed pending,
    and where max_retries > 0 its first trial's point θ + Δθ in `scratch` and its retries 0."""
    for r in range(lo, hi):  # (loops written out: array expressions took a first run seconds)
        for g in range(len(sources)):
            row, first = sources[g][r], columns[g]
            for j in range(row.shape[0]):
                grad[r, first + j] = row[j]
        for i in range(stats.shape[0]):
            stats[i, r] = out[i, r]
        current[r] = False  # the step changes θ: no lane holds its forward pass
    _steps(lo, hi, theta, grad, velocity, delta, rate, lr_scale, stats[0], failed, momentum,
           paper_form, not adaptive, tau_start, tau_end)
    if adaptive:
        for r in range(lo, hi):  # (max_retries = 0: every run pending, frozen after no trial)
            pending[r] = not failed[r]
            if max_retries > 0:
                retries[r] = 0
                _trial_point(r, theta, delta, scratch)


@njit(**JIT)
def after_trial(lo, hi, now, current, block_runs, first_block, last_block, reuse, theta, delta,
                scratch, values, base, pending, lr_scale, retries, decrease, decrease_cast,
                increase, max_ratio):
    """Runs lo..hi-1: the lanes of those evaluated (pending) hold θ + Δθ's forward pass (`now`,
    the bits of `scratch`, which are the record itself: `lanes.record_runs` with `then` None);
    the trial judged (`_trials`); the runs still pending have their next trial's point in
    `scratch`, and their lanes are no longer current (their row of the record changed)."""
    if reuse:
        record_runs(lo, hi, now, None, pending, block_runs, first_block, last_block, current)
    _trials(lo, hi, delta, values, base, pending, lr_scale, retries, decrease, decrease_cast,
            increase, max_ratio)
    for r in range(lo, hi):
        if pending[r]:
            current[r] = False
            _trial_point(r, theta, delta, scratch)


@njit(**JIT)
def after_trials(lo, hi, theta, delta, velocity, pending, failed, current, paper_form,
                 tau_start, tau_end):
    """Runs lo..hi-1 after the adaptive rate's trials: each run's step taken, a run still
    rejected (pending) or failed frozen (`apply_runs` with frozen = pending | failed). A run that
    took its step is at its accepted trial's point θ + Δθ, bit for bit (the same addition of the
    same numbers: `_trial_point`'s), so its lanes stay current, unless τ's clamp moved θ; a
    frozen run (θ unchanged) is no longer current."""
    for r in range(lo, hi):
        frozen = pending[r] or failed[r]
        clamped = _apply(r, theta, delta, velocity, frozen, paper_form, tau_start, tau_end)
        current[r] = current[r] and not (frozen or clamped)


def adaptive_trial(delta, values, base, pending, lr_scale, *, retries, decrease: float,
                   increase: float, max_ratio: float) -> bool:
    """`moex.kernels.reference.adaptive_trial`, bit for bit: a rejecting run's Δθ times α_dec
    rounded to Δθ's type, r compared with r_th in the values' type, as PyTorch does."""
    arrays = [to_host(x) for x in (delta, values, base, pending, lr_scale, retries)]
    kind = arrays[0].dtype.type
    threads.over(_trials, len(arrays[0]), *arrays, float(decrease), kind(decrease),
                 float(increase), arrays[1].dtype.type(max_ratio))
    return bool(arrays[3].any())


def momentum_step(theta, grad, velocity, delta, *, rate, lr_scale, objective, failed,
                  momentum: float, paper_form: bool, apply: bool, tau=None) -> None:
    """`moex.kernels.reference.momentum_step`, bit for bit."""
    arrays = [to_host(x) for x in (theta, grad, velocity, delta, rate, lr_scale, objective,
                                   failed)]
    arrays[2] = momentum_buffer(arrays[2], arrays[3], paper_form)
    threads.over(_steps, len(arrays[0]), *arrays, arrays[0].dtype.type(momentum),
                 bool(paper_form), bool(apply), *(tau or (0, 0)))


def apply_step(theta, delta, velocity, frozen, *, paper_form: bool, tau=None) -> None:
    """`moex.kernels.reference.apply_step`, bit for bit."""
    arrays = [to_host(x) for x in (theta, delta, velocity, frozen)]
    arrays[2] = momentum_buffer(arrays[2], arrays[1], paper_form)
    threads.over(apply_runs, len(arrays[0]), *arrays, bool(paper_form), *(tau or (0, 0)))


def momentum_buffer(velocity: np.ndarray, delta: np.ndarray, paper_form: bool):
    """The momentum buffer as the compiled functions take it: None where it is Δθ's own buffer
    (the training loop's paper form, `moex.train`), so that they read Δθ_prev in `delta` and
    write it once (with two names for one buffer, LLVM's vectorised loops would check them at
    run time, find them overlapping and take their scalar versions)."""
    return None if paper_form and np.shares_memory(velocity, delta) else velocity
