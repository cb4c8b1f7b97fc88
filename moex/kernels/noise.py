"""The input noise of phase 2 (`train.gating.input_noise_var`): the same draws, bit for bit, on
every backend, the GPU's drawn on the device (`moex.kernels.gpu.noise`).

Noise entry i of run r at training step n (i the flat index into the run's (S, T, D) inputs) is a
counter-based draw: no generator state, so any entry can be drawn alone, in any order, on any
device. With SplitMix64's mixing function `mix` (a bijection of 64-bit words) and its constant G:

    key_{r,n} = mix(mix(seed_r) + n·G),    h_j = mix(key_{r,n} + j·G)  for j = 2i + 1, 2i + 2
    u = (⌊h_{2i+1} / 2^11⌋ + 1) / 2^53 ∈ (0, 1],  w = (h_{2i+2} mod 2^53) / 2^53 ∈ [0, 1)
    z = ±√(−2 ln u) · (cos ψ or sin ψ),  ψ = w·π/4,  sign and choice from h_{2i+2}'s top bits

which is Box-Muller's z = √(−2 ln u) cos 2πv with the angle folded into [0, π/4) by cos's
symmetries (the same distribution, exactly). ln, cos and sin are written out with +, −, ×, ÷
and √ only (IEEE operations, rounded alike on a CPU and a GPU, and no fused multiply-adds):
ln u = e·ln 2 + 2 atanh((m−1)/(m+1)) with u = m·2^e, m ∈ [√½, √2), found with integer shifts;
cos and sin by their Taylor series to ψ^16 and ψ^17 (below 3e-18 at ψ = π/4). The noise is
σ·z with σ = √variance, computed in float64 and rounded once to the inputs' precision.
"""

import math

import numpy as np
from numba import njit

U64 = np.uint64
G = U64(0x9E3779B97F4A7C15)  # 2^64 / golden ratio, odd: j·G visits every word
C1, C2 = U64(0xBF58476D1CE4E5B9), U64(0x94D049BB133111EB)
M53 = U64((1 << 53) - 1)
LN2_HI, LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10  # e·LN2_HI exact
SQRT2 = 1.4142135623730951
# 2/(2k+1): ln m = f·Σ_k (2/(2k+1)) f^{2k}, |f| ≤ 0.1716; Taylor coefficients of cos and sin
LOG = tuple(2.0 / (2 * k + 1) for k in range(12))
COS = tuple((-1) ** k / math.factorial(2 * k) for k in range(9))
SIN = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(9))
# no fast-math flags (nothing that could change a result's bits); error_model="numpy": no
# ZeroDivisionError branch on float division, which would keep `_fill`'s loop from vectorising
NOISE_JIT = dict(error_model="numpy", cache=True)


def _mix(z):
    """SplitMix64's output function (Steele, Lea & Flood 2014) of uint64 words (NumPy arrays
    here; compiled as `mix`)."""
    z = (z ^ (z >> U64(30))) * C1
    z = (z ^ (z >> U64(27))) * C2
    return z ^ (z >> U64(31))


mix = njit(inline="always", **NOISE_JIT)(_mix)


@njit(inline="always", **NOISE_JIT)
def _poly(c, x):  # pragma: no cover (compiled)
    """Σ_k c[k] x^k by Horner's rule (unrolled: `c` is a tuple)."""
    acc = c[len(c) - 1]
    for k in range(len(c) - 2, -1, -1):
        acc = acc * x + c[k]
    return acc


@njit(inline="always", **NOISE_JIT)
def normal(key, i):  # pragma: no cover (compiled)
    """Standard normal number i of the stream `key` (the module's formulas)."""
    h1 = mix(key + (U64(2) * i + U64(1)) * G)
    h2 = mix(key + (U64(2) * i + U64(2)) * G)
    k = (h1 >> U64(11)) + U64(1)  # u = k / 2^53, k in [1, 2^53]
    lead = U64(0)  # k shifted up until its top bit is bit 63: u = m·2^(10 - lead), m ∈ [1, 2)
    for shift in (32, 16, 8, 4, 2, 1):
        small = k < (U64(1) << U64(64 - shift))
        k = (k << U64(shift)) if small else k
        lead = lead + (U64(shift) if small else U64(0))
    m = np.float64(k >> U64(11)) * 2.0 ** -52
    e = 10.0 - np.float64(lead)
    big = m > SQRT2
    m = m * 0.5 if big else m
    e = e + 1.0 if big else e
    f = (m - 1.0) / (m + 1.0)
    ln_u = e * LN2_HI + (e * LN2_LO + f * _poly(LOG, f * f))
    radius = math.sqrt(-2.0 * ln_u)
    psi = np.float64(h2 & M53) * 2.0 ** -53 * (math.pi / 4)
    trig = psi * _poly(SIN, psi * psi) if (h2 >> U64(62)) & U64(1) else _poly(COS, psi * psi)
    return -radius * trig if h2 >> U64(63) else radius * trig


@njit(**NOISE_JIT)
def _fill(keys, scale, out):  # pragma: no cover (compiled)
    """out[r, i] = σ·z_i of stream keys[r], rounded to out's precision."""
    for r in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[r, i] = normal(keys[r], U64(i)) * scale


def seed_words(seeds: list[int]) -> np.ndarray:
    """mix(seed_r) of each run, seeds taken modulo 2^64 (the gpu backend keeps them on the
    device and forms each step's keys there)."""
    return _mix(np.array([seed % (1 << 64) for seed in seeds], dtype=U64))


def stream_keys(seeds: list[int], step: int) -> np.ndarray:
    """key_{r,n} of each run's seed at training step n."""
    return _mix(seed_words(seeds) + np.array([step], dtype=U64) * G)  # arrays: wrap silently


def input_noise(seeds: list[int], step: int, shape: tuple, variance: float, dtype) -> np.ndarray:
    """(R, *shape) Gaussian noise of `variance` for training step `step`, run r drawn from
    (seeds[r], step) alone: a run sees the same noise batched or alone, fresh or resumed.
    `dtype`: a numpy or a torch dtype, that of the result (drawn and scaled in float64, then
    rounded once)."""
    name = str(dtype)
    dtype = np.dtype(name.removeprefix("torch.") if name.startswith("torch.") else dtype)
    keys = stream_keys(seeds, step)
    out = np.empty((len(seeds), math.prod(shape)), dtype=dtype)
    _fill(keys, math.sqrt(variance), out)
    return out.reshape(len(seeds), *shape)
