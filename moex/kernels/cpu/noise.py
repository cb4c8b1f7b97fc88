"""Phase 2's input noise added to the gating RNN's inputs in their lanes: `moex.kernels.noise`'s
draws (the same bits as every backend's), formed where they are stored, blocks of lanes over the
kernels' threads (it was drawn by run into an array, then transposed, padded and added: 6.4 ms a
step at 30 networks of Table 2's sizes on one core, most of it the copies)."""

import math

import numpy as np
from numba import njit

from moex.kernels.cpu import threads
from moex.kernels.cpu.simd import typed
from moex.kernels.noise import U64, normal, stream_keys

# nogil for the threads; no fast-math flags (`nsz` could flip a zero's sign), as `update.JIT`
JIT = dict(nogil=True, error_model="numpy", cache=True, no_cfunc_wrapper=True)


@njit(**JIT)
def add_noise(lo, hi, keys, scale, clean, inputs, S, T_full, K):  # pragma: no cover (compiled)
    """Blocks lo..hi-1 of `inputs` (NB, T, K + D, LB): the noise columns K.. = `clean`'s + σ·z,
    lane r·S + s drawing entries (s·T_full + t)·D + d of run r's stream `keys[r]` (rounded to the
    inputs' precision before it is added, as `input_noise`'s array was); padding lanes left. A
    lane's T·D draws are one contiguous loop (vectorised), then added where the lane's entries
    lie (a stride of K + D blocks of lanes)."""
    T, LB, lanes, D = inputs.shape[1], inputs.shape[3], len(keys) * S, inputs.shape[2] - K
    z = np.empty(T * D)
    for b in range(lo, hi):
        for lane in range(min(LB, lanes - b * LB)):
            r, s = divmod(b * LB + lane, S)
            key, first = keys[r], U64(s * T_full * D)
            for j in range(T * D):
                z[j] = normal(key, first + U64(j)) * scale
            for t in range(T):
                for d in range(D):
                    inputs[b, t, K + d, lane] = (clean[b, t, K + d, lane]
                                                 + typed(inputs, z[t * D + d]))


def noisy_inputs(inputs, clean, seeds: list[int], step: int, variance: float, *, S: int,
                 T_full: int, K: int) -> None:
    """`inputs`' noise columns := `clean`'s + the input noise of training step `step`."""
    keys = stream_keys(seeds, step)
    entries = len(seeds) * S * inputs.shape[1] * (inputs.shape[2] - K)
    threads.by_size(entries)(add_noise, inputs.shape[0], keys, math.sqrt(variance), clean,
                             inputs, S, T_full, K)
