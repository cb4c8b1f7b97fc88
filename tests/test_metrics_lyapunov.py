"""Laws of the Lyapunov estimator, through `benettin`, the loop the mixture's exponents use
(`moex.closed_loop.closed_loop_lyapunov`); the closed-loop kernels' own tangent maps are held to
the same laws at fixed points in tests/test_kernels.py."""

import math

import pytest
import torch

from moex.errors import Interrupted
from moex.metrics.lyapunov import benettin, initial_tangents, lyapunov_exponents


def test_logistic_map_r4_gives_ln2(samples=64, steps=2500):
    x0 = torch.rand(samples, 1, generator=torch.Generator().manual_seed(0),
                    dtype=torch.float64) * 0.8 + 0.1
    lam = lyapunov_exponents(lambda x: 4 * x * (1 - x), x0, steps, transient=100)
    assert abs(lam.mean().item() - math.log(2)) < 0.01


def test_henon_spectrum():
    """Hénon map a = 1.4, b = 0.3: λ_1 ≈ 0.419 (the literature's value), and λ_1 + λ_2 = ln b
    exactly, since |det J| = b at every point."""
    def henon(z):
        x, y = z[..., :1], z[..., 1:]
        return torch.cat([1 - 1.4 * x * x + y, 0.3 * x], -1)

    g = torch.Generator().manual_seed(0)
    z0 = (torch.rand(32, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2
    lam = lyapunov_exponents(henon, z0, 600, num_exponents=2, transient=100, generator=g)
    torch.testing.assert_close(lam.sum(-1), torch.full((32,), math.log(0.3), dtype=torch.float64))
    assert abs(lam[:, 0].mean().item() - 0.419) < 0.015  # 32 trajectories: standard error 0.003


def test_linear_map_gives_log_abs_a():
    for a in (0.5, -1.7, 3.0):
        lam = lyapunov_exponents(lambda x, a=a: a * x, torch.ones(3, 1), 200)[..., 0]
        torch.testing.assert_close(lam, torch.full((3,), math.log(abs(a))))


def test_spectrum_of_a_diagonal_linear_map():
    A = torch.diag(torch.tensor([2.0, 0.5, -0.25]))
    lam = lyapunov_exponents(lambda x: x @ A.T, torch.ones(2, 3), 100, num_exponents=3,
                             transient=30, reorth_every=5)
    torch.testing.assert_close(lam, torch.log(torch.tensor([2.0, 0.5, 0.25])).expand(2, 3))


def test_contracting_rnn_is_negative(M=6):
    g = torch.Generator().manual_seed(1)
    W = torch.randn(M, M, generator=g) * 0.3 / math.sqrt(M)
    lam = lyapunov_exponents(lambda u: 0.8 * u + 0.2 * torch.tanh(u) @ W.T,
                             torch.randn(4, M, generator=g), 500, transient=100)
    assert (lam < 0).all()


def test_benettin_counts_the_steps_after_the_transient_in_chunks():
    """A map that doubles every step: chunks of 3 over 2 + 7 steps are called with the sizes and
    flags the loop promises, and the average is ln 2; a stop request raises `Interrupted`."""
    calls = []

    def advance(tangents, size, counted, done):
        calls.append((size, counted, done))
        return tangents, torch.full((1,), size * math.log(2))

    tangents = initial_tangents(torch.zeros(1, 1), 1)
    lam = benettin(advance, tangents, 7, 2, 3)
    assert calls == [(2, False, 0), (3, True, 0), (3, True, 3), (1, True, 6)]
    torch.testing.assert_close(lam, torch.full((1,), math.log(2)))
    with pytest.raises(Interrupted):
        benettin(advance, tangents, 7, 2, 3, should_stop=lambda: True)
