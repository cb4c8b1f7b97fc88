"""Phase 2's input noise drawn on the device: `moex.kernels.noise`'s draws, bit for bit, added to
the clean inputs in one launch per training step (nothing drawn on the host or copied to the
device: each run's seed word stays on the device, the step is an argument). Compiled without
fused multiply-adds, with IEEE-rounded division and square root, as the CPU computes them."""

import math

import numpy as np
import torch
import triton
import triton.language as tl

from moex.kernels import noise
from moex.kernels.gpu.lanes import launched

BLOCK = 256  # noise entries per program
# Horner's coefficients of ln, cos and sin (`moex.kernels.noise`), one row each, and its other
# float64 constants, on the device (a Python float in a Triton kernel may be rounded to float32)
CONSTANTS = (noise.LN2_HI, noise.LN2_LO, noise.SQRT2, 2.0 ** -52, 2.0 ** -53, math.pi / 4)
COEFFICIENTS = np.array([noise.LOG, noise.COS + (0.0,) * 3, noise.SIN + (0.0,) * 3,
                         CONSTANTS + (0.0,) * 6])


@triton.jit
def _mix(z):
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9
    z = (z ^ (z >> 27)) * 0x94D049BB133111EB
    return z ^ (z >> 31)


@triton.jit
def _shift_up(k, lead, SHIFT: tl.constexpr):
    """One step of moving k's top bit to bit 63 (`noise.normal`'s loop)."""
    small = k < (1 << (64 - SHIFT))
    return tl.where(small, k << SHIFT, k), tl.where(small, lead + SHIFT, lead)


@triton.jit
def _horner(COEF, row: tl.constexpr, N: tl.constexpr, x):
    acc = tl.load(COEF + row * 12 + N - 1) + 0.0 * x
    for k in tl.static_range(N - 2, -1, -1):
        acc = acc * x + tl.load(COEF + row * 12 + k)
    return acc


@triton.jit
def _constant(COEF, k: tl.constexpr):
    return tl.load(COEF + 3 * 12 + k)


@triton.jit
def _normal(key, i, COEF):
    """`moex.kernels.noise.normal`, written again in Triton."""
    g = 0x9E3779B97F4A7C15
    h1 = _mix(key + (2 * i + 1) * g)
    h2 = _mix(key + (2 * i + 2) * g)
    k = (h1 >> 11) + 1
    lead = tl.zeros_like(k)
    k, lead = _shift_up(k, lead, 32)
    k, lead = _shift_up(k, lead, 16)
    k, lead = _shift_up(k, lead, 8)
    k, lead = _shift_up(k, lead, 4)
    k, lead = _shift_up(k, lead, 2)
    k, lead = _shift_up(k, lead, 1)
    m = (k >> 11).to(tl.float64) * _constant(COEF, 3)
    e = 10.0 - lead.to(tl.float64)
    big = m > _constant(COEF, 2)
    m = tl.where(big, m * 0.5, m)
    e = tl.where(big, e + 1.0, e)
    f = (m - 1.0) / (m + 1.0)  # float64: div.rn, IEEE-rounded
    ln_u = e * _constant(COEF, 0) + (e * _constant(COEF, 1) + f * _horner(COEF, 0, 12, f * f))
    radius = tl.sqrt(-2.0 * ln_u)  # float64: sqrt.rn, IEEE-rounded
    psi = (h2 & 0x1FFFFFFFFFFFFF).to(tl.float64) * _constant(COEF, 4) * _constant(COEF, 5)
    p2 = psi * psi
    trig = tl.where(((h2 >> 62) & 1) != 0, psi * _horner(COEF, 2, 9, p2),
                    _horner(COEF, 1, 9, p2))
    return tl.where((h2 >> 63) != 0, -radius * trig, radius * trig)


@triton.jit(do_not_specialize=["step"])  # (an int 1 would be a constant without `.to`)
def noise_kernel(X, CLEAN, WORDS, SCALE, COEF, step, S, T, T_FULL, D, C, K, TILES,
                 BLOCK: tl.constexpr):
    """Program (r·S + s)·TILES + tile: X[r·S + s, t, K + d] = CLEAN[...] + σ·z_i for the tile's
    BLOCK entries (t, d) of the series' first T steps, i = (s·T_FULL + t)·D + d."""
    pid = tl.program_id(0)
    row, tile = pid // TILES, pid % TILES
    r, s = row // S, row % S
    j = tile * BLOCK + tl.arange(0, BLOCK)
    ok = j < T * D
    t, d = j // D, j % D
    i = ((s.to(tl.int64) * T_FULL + t) * D + d).to(tl.uint64)
    word = tl.load(WORDS + r).to(tl.uint64, bitcast=True)
    key = _mix(word + step.to(tl.uint64) * 0x9E3779B97F4A7C15)
    z = _normal(key, i, COEF) * tl.load(SCALE)
    at = row.to(tl.int64) * T * C + t * C + K + d
    x = tl.load(CLEAN + at, mask=ok, other=0.0)
    tl.store(X + at, x + z.to(x.dtype), mask=ok)


class DeviceNoise:
    """`add(X, clean, step)`: X[:, :T, K:] = clean[:, :T, K:] + the noise of training step `step`
    for R runs of S series (X and clean (R·S, T, C), C = K + D), series of T_FULL steps."""

    def __init__(self, seeds: list[int], variance: float, *, S: int, T_FULL: int, device):
        self.S, self.T_FULL, self.R = S, T_FULL, len(seeds)
        self.words = torch.as_tensor(noise.seed_words(seeds).view(np.int64), device=device)
        self.scale = torch.tensor([math.sqrt(variance)], dtype=torch.float64, device=device)
        self.coef = torch.as_tensor(COEFFICIENTS, dtype=torch.float64, device=device)

    def add(self, X: torch.Tensor, clean: torch.Tensor, step: int, *, K: int) -> None:
        _, T, C = X.shape
        tiles = triton.cdiv(T * (C - K), BLOCK)
        launched("noise_kernel", noise_kernel[(self.R * self.S * tiles,)](
            X, clean, self.words, self.scale, self.coef, step, self.S, T, self.T_FULL, C - K, C,
            K, tiles, BLOCK=BLOCK, enable_fp_fusion=False))
