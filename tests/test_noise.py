"""Phase 2's input noise (`moex.kernels.noise`): standard normal draws (moments and the
Kolmogorov-Smirnov distance within their sampling error), the written-out ln, cos and sin within
a few ulp of libm's, streams of other seeds and steps uncorrelated, and the device's draws
(`moex.kernels.gpu.noise`: CUDA where there is one, else Triton's interpreter) the CPU's bits."""

import math

import numpy as np
import pytest
import torch

from moex.kernels import available
from moex.kernels.noise import M53, G, _mix, input_noise, stream_keys

N = 200_000


def test_the_draws_are_standard_normal_within_their_sampling_error():
    z = input_noise([11, 12], 3, (N // 2,), 1.0, np.float64).ravel()
    n = len(z)
    centred = z - z.mean()
    var = (centred ** 2).mean()
    skew, kurt = (centred ** 3).mean() / var ** 1.5, (centred ** 4).mean() / var ** 2
    # standard errors of a normal sample's mean, variance, skewness and kurtosis
    assert abs(z.mean()) < 4 / math.sqrt(n)
    assert abs(var - 1) < 4 * math.sqrt(2 / n)
    assert abs(skew) < 4 * math.sqrt(6 / n) and abs(kurt - 3) < 4 * math.sqrt(24 / n)
    phi = 0.5 * (1 + np.vectorize(math.erf)(np.sort(z) / math.sqrt(2)))
    distance = max((np.arange(1, n + 1) / n - phi).max(), (phi - np.arange(n) / n).max())
    assert distance < 1.63 / math.sqrt(n)  # Kolmogorov-Smirnov at the 1 % level
    tail = np.abs(z) > 4  # P(|z| > 4) = 6.3e-5: the tails are there, not cut off
    assert 0 < tail.sum() < 4 * 6.3e-5 * n and np.abs(z).max() < 7


def test_the_written_out_log_cos_and_sin_are_within_a_few_ulp_of_libms():
    """z from the same 64-bit words with NumPy's ln, cos and sin, entry by entry."""
    key = stream_keys([5], 2)[0]
    i = np.arange(N, dtype=np.uint64)
    with np.errstate(over="ignore"):
        h1, h2 = (_mix(key + (np.uint64(2) * i + np.uint64(j)) * G) for j in (1, 2))
    u = ((h1 >> np.uint64(11)) + np.uint64(1)).astype(np.float64) * 2.0 ** -53
    psi = (h2 & M53).astype(np.float64) * 2.0 ** -53 * (math.pi / 4)
    trig = np.where((h2 >> np.uint64(62)) & np.uint64(1), np.sin(psi), np.cos(psi))
    libm = np.sqrt(-2 * np.log(u)) * trig * np.where(h2 >> np.uint64(63), -1, 1)
    z = input_noise([5], 2, (N,), 1.0, np.float64)[0]
    assert np.all(np.abs(z - libm) <= 4 * np.spacing(np.abs(libm)) + 1e-300)
    assert np.any(z != 0) and np.sign(z).sum() != len(z)


def test_streams_of_other_seeds_and_steps_are_uncorrelated_and_each_run_its_own():
    a, b, c = (input_noise([seed], step, (N,), 1.0, np.float64)[0]
               for seed, step in ((1, 0), (1, 1), (2, 0)))
    for x, y in ((a, b), (a, c), (a[1:], a[:-1])):  # and one stream with itself one entry on
        assert abs(np.corrcoef(x, y)[0, 1]) < 4 / math.sqrt(N)
    both = input_noise([1, 2], 0, (N,), 1.0, np.float64)
    assert np.array_equal(both[0], a) and np.array_equal(both[1], c)
    big = input_noise([(1 << 64) + 6, -3], 0, (3,), 1.0, np.float64)  # seeds modulo 2^64
    assert np.array_equal(big, input_noise([6, (1 << 64) - 3], 0, (3,), 1.0, np.float64))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_the_gpu_backend_draws_the_cpus_bits_into_the_noise_columns_only(dtype):
    """On the device (`benchmarks/gpu_session.sh` runs it on CUDA): runs of S series of
    T_FULL steps of which the first T are fed (the gating RNN's inputs), tiles that do not
    divide the entries, seeds beyond 2^63."""
    gpu, why = available("gpu")
    if gpu is None:
        pytest.skip(why)
    from moex.kernels.gpu.noise import BLOCK, DeviceNoise

    R, S, T_FULL, T, D, K = 3, 2, 203, 200, 2, 3
    assert (T * D) % BLOCK
    seeds, step, variance = [5, (1 << 63) + 11, 0], 7, 0.01
    clean = torch.randn(R * S, T, K + D, dtype=torch.float64,
                        generator=torch.Generator().manual_seed(0)).to(dtype)
    X = clean.clone().to(gpu.device)
    DeviceNoise(seeds, variance, S=S, T_FULL=T_FULL, device=gpu.device).add(
        X, X.clone(), step, K=K)
    noise = input_noise(seeds, step, (S, T_FULL, D), variance, dtype)[:, :, :T]
    want = clean.clone()
    want[:, :, K:] += torch.as_tensor(noise.reshape(R * S, T, D))
    assert torch.equal(X.cpu(), want)


@pytest.mark.parametrize("dtype", [np.float64, np.float32], ids=["float64", "float32"])
def test_the_cpu_backend_adds_the_same_bits_in_its_lanes_on_any_number_of_threads(dtype):
    """`moex.kernels.cpu.noise.noisy_inputs`: the lanes' noise columns are the clean inputs plus
    `input_noise`'s array laid out in lanes (lane r·S + s), bit for bit, on one thread and on
    two (blocks shared out above `SPLIT` entries); the other columns and the padding lanes keep
    their values."""
    import numba

    from moex.kernels.cpu.lanes import in_lanes
    from moex.kernels.cpu.noise import noisy_inputs
    from moex.kernels.cpu.threads import SPLIT

    R, S, T_FULL, T, D, K = 7, 5, 1001, 1000, 2, 3  # 35 lanes: the last block part padding
    assert R * S * T * D >= SPLIT
    seeds, step, variance = [3, 1 << 63, 9, 10, 11, 12, 13], 4, 0.01
    x = np.random.default_rng(0).normal(size=(T, K + D, R * S)).astype(dtype)
    clean = in_lanes(x)
    noise = input_noise(seeds, step, (S, T_FULL, D), variance, dtype)[:, :, :T]
    want = in_lanes(x + np.concatenate([np.zeros((T, K, R * S), dtype), noise.transpose(
        2, 3, 0, 1).reshape(T, D, R * S)], 1))
    saved = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            inputs = clean.copy()
            noisy_inputs(inputs, clean, seeds, step, variance, S=S, T_full=T_FULL, K=K)
            assert np.array_equal(inputs, want), threads
    finally:
        numba.set_num_threads(saved)
