"""Laws of the Lyapunov estimator, through `benettin`, the loop the mixture's exponents use
(`moex.closed_loop.closed_loop_lyapunov`); the closed-loop kernels' own tangent maps are held to
the same laws at fixed points in tests/test_kernels.py."""

import math

import numpy as np
import pandas as pd
import pytest
import torch

from moex.errors import Interrupted
from moex.metrics.lyapunov import (
    CHAOTIC,
    NOT_CHAOTIC,
    UNDETERMINED,
    benettin,
    chaos_label,
    chaos_labels,
    initial_tangents,
    lyapunov_exponents,
    standard_error,
)


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
    lam = benettin(advance, tangents, 7, transient=2, chunk=3)
    assert calls == [(2, False, 0), (3, True, 0), (3, True, 3), (1, True, 6)]
    torch.testing.assert_close(lam, torch.full((1,), math.log(2)))
    with pytest.raises(Interrupted):
        benettin(advance, tangents, 7, transient=2, chunk=3, stop=lambda: True)


def _samples(step, x0, steps, transient=200):
    """Each initial state's own λ_max (numpy) and the label of their mean with its error."""
    lam = lyapunov_exponents(step, x0, steps, transient=transient)[..., 0].numpy()
    return lam, chaos_label(lam.mean(), standard_error(lam), steps)


def test_the_chaos_label_calls_the_logistic_map_chaotic():
    x0 = torch.rand(16, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lam, label = _samples(lambda x: 4 * x * (1 - x), x0 * 0.8 + 0.1, 2000)
    assert label == CHAOTIC and abs(lam.mean() - math.log(2)) < 0.02


@pytest.mark.parametrize("wobble", [0.0, 0.2])
def test_a_limit_cycle_is_never_chaotic(wobble):
    """An attracting circle (r -> r + 0.5 (1 - r)) travelled by a rotation, exact (λ_max = 0 up
    to rounding) or with an uneven speed (θ -> θ + 1 + 0.2 sin θ): its λ_max estimates straddle
    0 by far less than their resolution, so the label is never `chaotic`, at any length."""
    def circle(z):
        r, theta = z.norm(dim=-1, keepdim=True), torch.atan2(z[..., 1:], z[..., :1])
        r, theta = r + 0.5 * (1 - r), theta + 1.0 + wobble * torch.sin(theta)
        return torch.cat([r * torch.cos(theta), r * torch.sin(theta)], -1)

    g = torch.Generator().manual_seed(3)
    for steps in (500, 2000):
        z0 = torch.randn(12, 2, generator=g, dtype=torch.float64)
        lam, label = _samples(circle, z0, steps)
        assert abs(lam.mean()) < 1.0 / steps and label != CHAOTIC


def test_the_label_follows_the_error_not_the_sign():
    """The issue's limit cycle: +7e-6 within about one standard error is undetermined, not
    chaotic; a contracting map is not chaotic; one sample has no error and decides nothing."""
    assert chaos_label(7e-6, 6.5e-6, 100000) == UNDETERMINED
    assert chaos_label(4.1e-5, 1e-6, 100000) == CHAOTIC  # 41 s.e. and 4 resolutions above 0
    assert chaos_label(4.1e-6, 1e-7, 100000) == UNDETERMINED  # below 1/steps: not resolved
    assert chaos_label(-7.1e-5, 3e-5, 100000) == NOT_CHAOTIC
    assert chaos_label(0.5, float("nan"), 100000) == UNDETERMINED
    assert chaos_label(float("nan"), 0.1, 100000) == ""
    lam, label = _samples(lambda x: 0.5 * x + 0.1, torch.rand(4, 1, dtype=torch.float64), 300)
    assert label == NOT_CHAOTIC and np.allclose(lam, math.log(0.5))


def test_older_tables_are_labelled_from_their_error_columns():
    frame = pd.DataFrame({"max_lyapunov": [0.01, 1e-6, -0.01, np.nan],
                          "max_lyapunov_se": [1e-4, 1e-6, 1e-4, np.nan],
                          "lyapunov_steps": [100000, 100000, 100000, np.nan]})
    assert chaos_labels(frame).tolist() == [CHAOTIC, UNDETERMINED, NOT_CHAOTIC, ""]
    assert chaos_labels(frame.drop(columns="max_lyapunov_se")).tolist()[:3] == [UNDETERMINED] * 3
    # a table that gained the column: written labels kept, the older rows computed
    mixed = frame.assign(chaos=[np.nan, NOT_CHAOTIC, np.nan, np.nan])
    assert chaos_labels(mixed).tolist() == [CHAOTIC, NOT_CHAOTIC, NOT_CHAOTIC, ""]
