"""The training loop's momentum step (`moex.kernels.reference.momentum_step`, `apply_step`) as one
launch, a program per run over its row of the (R, P) buffers (instead of a dozen PyTorch
operators, each a launch and a pass over every run). Compiled without fused multiply-adds, and
with float32 steps scaled in float64 as PyTorch does: the bits are the reference's."""

import torch
import triton
import triton.language as tl

from moex.kernels.gpu.lanes import launch
from moex.kernels.gpu.rnn import device

BP = 1024  # entries of a row per tile
_CONSTANTS: dict = {}  # (η, dtype, device) -> η as a device scalar, made once


@device
def _nonfinite(x):
    return (x - x) != 0  # NaN and ±inf (x - x is NaN), finite x: 0


@triton.jit
def momentum_kernel(THETA, GRAD, VELOCITY, DELTA, RATE, LR_SCALE, OBJECTIVE, FAILED, MOMENTUM,
                    P, TAU_START, TAU_END, PAPER: tl.constexpr, APPLY: tl.constexpr,
                    FROZEN_ONLY: tl.constexpr, BP: tl.constexpr):
    """Run r = program: its Δθ (unless FROZEN_ONLY: `apply_step`, FAILED then the frozen runs)
    and, with APPLY, the step taken; FAILED[r] updated."""
    r = tl.program_id(0).to(tl.int64)
    row, cols = r * P, tl.arange(0, BP)
    bad = tl.load(FAILED + r + 0 * cols) != 0  # (BP,) alike: the interpreter masks by vectors
    if not FROZEN_ONLY:
        bad = bad | _nonfinite(tl.load(OBJECTIVE + r + 0 * cols))
        count = tl.zeros((BP,), dtype=tl.int32)
        for start in range(0, P, BP):
            c = start + cols
            count += _nonfinite(tl.load(GRAD + row + c, mask=c < P, other=0.0)).to(tl.int32)
        bad = bad | ((tl.sum(count, axis=0) + 0 * cols) > 0)
        momentum, scale = tl.load(MOMENTUM), tl.load(LR_SCALE + r)
        count = tl.zeros((BP,), dtype=tl.int32)
        for start in range(0, P, BP):
            c = start + cols
            ok = c < P
            g = tl.load(GRAD + row + c, mask=ok, other=0.0)
            g = tl.where(bad, 0.0, g)
            tl.store(GRAD + row + c, g, mask=ok & bad)
            v = tl.load(VELOCITY + row + c, mask=ok, other=0.0)
            rate = tl.load(RATE + c, mask=ok, other=0.0)
            if PAPER:
                kept = v * momentum
                d = ((g * rate).to(tl.float64) * scale).to(g.dtype) + kept
            else:
                v = v * momentum + g
                tl.store(VELOCITY + row + c, v, mask=ok)
                d = ((v * rate).to(tl.float64) * scale).to(g.dtype)
            tl.store(DELTA + row + c, d, mask=ok)
            if APPLY:
                t = tl.load(THETA + row + c, mask=ok, other=0.0)
                count += _nonfinite(t + d).to(tl.int32)
        if APPLY:
            bad = bad | ((tl.sum(count, axis=0) + 0 * cols) > 0)
        tl.store(FAILED + r + 0 * cols, bad, mask=cols == 0)
    if APPLY or FROZEN_ONLY:
        for start in range(0, P, BP):
            c = start + cols
            ok = c < P
            d = tl.where(bad, 0.0, tl.load(DELTA + row + c, mask=ok, other=0.0))
            tl.store(DELTA + row + c, d, mask=ok)
            t = tl.load(THETA + row + c, mask=ok, other=0.0) + d
            t = tl.where((c >= TAU_START) & (c < TAU_END) & (t < 1.0), 1.0, t)
            tl.store(THETA + row + c, t, mask=ok)
            if PAPER:
                tl.store(VELOCITY + row + c, d, mask=ok)
            else:
                tl.store(VELOCITY + row + c, tl.zeros((BP,), dtype=d.dtype), mask=ok & bad)


def _launch(theta, grad, velocity, delta, *, rate, lr_scale, objective, failed, momentum,
            paper_form, apply, frozen_only, tau):
    R, P = theta.shape
    key = (momentum, theta.dtype, theta.device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor([momentum], dtype=theta.dtype, device=theta.device)
    start, end = tau or (0, 0)
    launch(momentum_kernel, R, theta, grad, velocity, delta, rate, lr_scale, objective, failed,
           _CONSTANTS[key], P, start, end, PAPER=bool(paper_form), APPLY=bool(apply),
           FROZEN_ONLY=frozen_only, BP=BP, enable_fp_fusion=False)


def momentum_step(theta, grad, velocity, delta, *, rate, lr_scale, objective, failed,
                  momentum: float, paper_form: bool, apply: bool, tau=None) -> None:
    """`moex.kernels.reference.momentum_step`, bit for bit, in one launch."""
    _launch(theta, grad, velocity, delta, rate=rate, lr_scale=lr_scale, objective=objective,
            failed=failed, momentum=momentum, paper_form=paper_form, apply=apply,
            frozen_only=False, tau=tau)


def apply_step(theta, delta, velocity, frozen, *, paper_form: bool, tau=None) -> None:
    """`moex.kernels.reference.apply_step`, bit for bit, in one launch (`frozen` is read only)."""
    _launch(theta, delta, velocity, delta, rate=delta, lr_scale=delta, objective=delta,
            failed=frozen, momentum=0.0, paper_form=paper_form, apply=False, frozen_only=True,
            tau=tau)
